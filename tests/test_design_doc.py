"""docs/DESIGN.md is the map of the tree: it names no path that does not exist, and
it leaves out no package folder, C source or fuzz harness.

The layer rule it states (the table under "### The layer rule") is the one
`tests/test_layers.py` enforces, read from its `ALLOWED` table, so that the two cannot
drift apart.
"""

from __future__ import annotations

import re
from pathlib import Path

from test_layers import ABOVE, ALLOWED

ROOT = Path(__file__).resolve().parent.parent
DESIGN = ROOT / "docs" / "DESIGN.md"
PACKAGE = ROOT / "pyrtu"

#: a backticked token that names a file or folder of the tree
_PATH = re.compile(r"`([\w./-]+(?:\.(?:py|c|h|md|toml|sh|pyi)|/))`")
_SUFFIXES = (".py", ".c", ".h", ".md", ".toml", ".sh", ".pyi")


def _text() -> str:
    return DESIGN.read_text(encoding="utf-8")


def _tree_rows() -> dict[str, str]:
    """The rows of "## The tree": folder (without its slash) -> the row's text."""
    section = _text().split("## The tree", 1)[1].split("\n## ", 1)[0]
    section = section.split("### The layer rule", 1)[0]
    rows = {}
    for line in section.splitlines():
        m = re.match(r"\|\s*`([\w]+)/`\s*\|", line)
        if m:
            rows[m.group(1)] = line
    return rows


def _exists(token: str, folder: str | None = None) -> bool:
    token = token.rstrip("/")
    bases = [ROOT, PACKAGE]
    if folder is not None:
        bases.insert(0, PACKAGE / folder)
    if any((base / token).exists() for base in bases):
        return True
    if "/" not in token:  # a bare file name: somewhere in the package or the C core
        return any(p.name == token for p in [*PACKAGE.rglob(token), *(ROOT / "csrc").rglob(token)])
    return False


def test_every_path_design_md_names_exists() -> None:
    missing = sorted({t for t in _PATH.findall(_text()) if not _exists(t)})
    assert not missing, f"docs/DESIGN.md names paths that do not exist: {missing}"


def test_every_file_a_tree_row_names_is_in_that_folder() -> None:
    wrong = []
    for folder, row in _tree_rows().items():
        for token in _PATH.findall(row):
            if token.rstrip("/") == folder:
                continue
            if not _exists(token, folder) or (
                "/" not in token.rstrip("/") and not (PACKAGE / folder / token).exists()
            ):
                wrong.append(f"{folder}/ names {token}")
    assert not wrong, wrong


def test_every_package_folder_has_a_row() -> None:
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == set(_tree_rows()), (
        f"folders without a row: {sorted(folders - set(_tree_rows()))}; "
        f"rows without a folder: {sorted(set(_tree_rows()) - folders)}"
    )


def test_every_module_of_a_folder_is_named_in_its_row() -> None:
    """A module a newcomer finds with `ls` is on the map (the package's `__init__.py` aside)."""
    missing = []
    for folder, row in _tree_rows().items():
        named = set(_PATH.findall(row))
        for path in sorted((PACKAGE / folder).glob("*.py")):
            if path.name == "__init__.py":
                continue
            if path.name not in named and f"{folder}/{path.name}" not in named:
                missing.append(f"{folder}/{path.name}")
    assert not missing, f"modules missing from DESIGN.md's tree: {missing}"


def test_every_c_source_and_fuzz_harness_is_named() -> None:
    text = _text()
    sources = [
        p.relative_to(ROOT).as_posix()
        for pattern in ("csrc/*.c", "csrc/*.h", "csrc/python/*.c", "fuzz/fuzz_*.c", "fuzz/*.py")
        for p in sorted(ROOT.glob(pattern))
    ]
    missing = [s for s in sources if f"`{s}`" not in text]
    assert not missing, f"C sources and fuzz harnesses missing from DESIGN.md: {missing}"


def test_the_layer_rule_is_the_one_test_layers_enforces() -> None:
    section = _text().split("### The layer rule", 1)[1].split("\n#", 1)[0]
    stated: dict[str, set[str]] = {}
    for line in section.splitlines():
        m = re.match(r"\|\s*`(\w+/|\w+/\w+\.py)`\s*\|(.*)\|\s*$", line)
        if m:
            stated[m.group(1).rstrip("/")] = set(re.findall(r"`(\w+)/`", m.group(2)))
    enforced = {**ALLOWED, **ABOVE}
    differ = {
        k: (sorted(stated.get(k, ())), sorted(enforced.get(k, ())))
        for k in set(stated) | set(enforced)
        if stated.get(k) != enforced.get(k)
    }
    assert not differ, f"DESIGN.md's layer table against test_layers.ALLOWED: {differ}"


def test_the_checks_read_something() -> None:
    """The checks above would pass on an empty document: they must have read the map."""
    assert len(_tree_rows()) >= 10
    assert len(_PATH.findall(_text())) >= 50
