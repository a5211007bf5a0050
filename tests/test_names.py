"""One name per concept (docs/DESIGN.md, "Glossary"): no two classes of pyrtu share a
name unless they are one concept's twins (the C backend and its pure-Python twin, a
contract and its implementations), and no module is imported under a one-letter alias.

A new duplicate fails until it is renamed or, being a twin (or one concept in each
drive's profile), listed.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "pyrtu"

#: class name -> the modules that define it, each module's class one concept's twin
TWINS: dict[str, set[str]] = {
    # the backends: the C binding and its pure-Python twin
    "_Core": {"core/_cext.py", "core/_pure/__init__.py"},
    "_MbapCore": {"core/_cext.py", "core/_pure/__init__.py"},
    # the xfer step: its contract (drivers/xfer.py) and its two implementations
    "XferRunner": {"drivers/xfer.py", "drivers/_cxfer.py", "drivers/_pyxfer.py"},
    "AsyncXferRunner": {"drivers/xfer.py", "drivers/_cxfer.py", "drivers/_pyxfer.py"},
    "TcpXferRunner": {"drivers/xfer.py", "drivers/_cxfer.py", "drivers/_pyxfer.py"},
    "TcpScanner": {"drivers/xfer.py", "drivers/_cxfer.py", "drivers/_pyxfer.py"},
}
#: one concept in each of the drives' own profiles (the drive's vocabulary, from its
#: manual): the same name for the same concept, one class per drive
PER_DRIVE: dict[str, set[str]] = {
    # a drive's command word (the CLI's command is a Subcommand)
    "Command": {"devices/bonfiglioli.py", "devices/cv100.py"},
}


def _python_files(*folders: str) -> list[Path]:
    return sorted(
        p
        for folder in folders
        for p in (ROOT / folder).rglob("*.py")
        if "__pycache__" not in p.parts
    )


def test_no_two_classes_share_a_name() -> None:
    defined: dict[str, set[str]] = defaultdict(set)
    for path in _python_files("pyrtu"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.ClassDef):
                defined[node.name].add(path.relative_to(PACKAGE).as_posix())
    shared = {name: homes for name, homes in defined.items() if len(homes) > 1}
    assert len(defined) > 100  # the tree was read
    unexpected = {
        name: sorted(homes)
        for name, homes in shared.items()
        if homes != TWINS.get(name) and homes != PER_DRIVE.get(name)
    }
    assert not unexpected, f"one name for two classes: {unexpected}"
    gone = sorted((set(TWINS) | set(PER_DRIVE)) - set(shared))
    assert not gone, f"listed duplicates that are gone (take them off the list): {gone}"


def test_no_one_letter_module_alias() -> None:
    found = []
    for path in _python_files("pyrtu", "tests", "bench", "fuzz", "mutate"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for alias in node.names:
                    if alias.asname is not None and len(alias.asname) == 1:
                        where = f"{path.relative_to(ROOT)}:{node.lineno}"
                        found.append(f"{where}: {alias.name} as {alias.asname}")
    assert not found, found
