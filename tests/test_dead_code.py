"""No dead code in the private layers, and no benchmark-only code in the shipped core.

A private module (any ``_*.py`` under pyrtu/, and every module of a private package
such as ``pyrtu/core/_pure/``) has no users outside the project, so a function,
class or method of one that nothing in pyrtu/, tests/ or bench/ names is dead: it
only misleads a reader (``_mbap.decode_header`` and ``ClientProtocol.wait_limit``
were such, issue 18; ``_cvbus.wake_estimate_ns`` and its C function, issue 28).
Likewise a C function of the cffi declarations (pyrtu/core/_cdef.h) that neither
Python names nor any C code calls.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

from c_core import need_c

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "pyrtu"


#: the private modules there are at least (44 when this was written): fewer means the
#: search no longer finds the tree (it once globbed paths that had moved away)
MIN_PRIVATE_MODULES = 35
#: methods the framework calls, not the project (asyncio.Protocol's callbacks)
#: (and asyncio.DatagramProtocol's)
CALLBACKS = {
    "connection_made",
    "eof_received",
    "pause_writing",
    "resume_writing",
    "datagram_received",
    "error_received",
}


def _private_modules() -> list[Path]:
    """Every ``_name.py`` under pyrtu/ (not dunder files) and every module of a
    private package (a folder named ``_name``)."""
    found = set()
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE).parts
        private_file = path.name.startswith("_") and not path.name.startswith("__")
        if private_file or any(p.startswith("_") and not p.startswith("__") for p in parts[:-1]):
            found.add(path)
    return sorted(found)


def test_the_search_finds_the_tree() -> None:
    modules = _private_modules()
    assert len(modules) >= MIN_PRIVATE_MODULES, [str(m.relative_to(ROOT)) for m in modules]
    names = {str(m.relative_to(PACKAGE)) for m in modules}
    assert {"core/_pure/framer.py", "vbus/_cvbus.py", "outbox/_format.py"} <= names


def _names_used() -> set[str]:
    """Every name read, every attribute taken and every name imported, in pyrtu/,
    tests/ and bench/ (a definition is none of these)."""
    used: set[str] = set()
    for folder in ("pyrtu", "tests", "bench"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Attribute):
                    used.add(node.attr)
                elif isinstance(node, ast.Name):
                    used.add(node.id)
                elif isinstance(node, ast.alias):
                    used.add(node.name.rsplit(".", 1)[-1])
    return used


def _definitions(path: Path) -> list[str]:
    """Top-level functions and classes, and the methods of those classes (not the
    dunder methods, which Python calls itself)."""
    defs: list[str] = []
    funcs = (ast.FunctionDef, ast.AsyncFunctionDef)
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, funcs):
            if not node.name.startswith("__"):  # a module's __getattr__: Python calls it
                defs.append(node.name)
        elif isinstance(node, ast.ClassDef):
            defs.append(node.name)
            defs += [
                m.name for m in node.body if isinstance(m, funcs) and not m.name.startswith("__")
            ]
    return defs


def test_private_modules_define_nothing_unused() -> None:
    used = _names_used()
    unused = [
        f"{path.relative_to(ROOT)}: {name}"
        for path in _private_modules()
        for name in _definitions(path)
        if name not in used and name not in CALLBACKS
    ]
    assert unused == [], f"defined but never used: {unused}"


def test_shipped_core_has_no_benchmark_only_function() -> None:
    """The empty functions bench/bench_crc.py measures as the floor of a cffi call
    live in a module the benchmark compiles itself, not in pyrtu.core._rtu_core."""
    need_c()
    from pyrtu.core._rtu_core import lib

    assert [name for name in dir(lib) if "noop" in name] == []


def _c_calls() -> set[str]:
    """The functions C code (csrc/, fuzz/) calls: every ``name(`` but a definition's
    (a line at column 0 whose first ``name(`` it is) and a declaration's (headers)."""
    calls: set[str] = set()
    for path in [*(ROOT / "csrc").rglob("*.c"), *(ROOT / "fuzz").glob("*.c")]:
        text = re.sub(r"/\*.*?\*/", "", path.read_text(encoding="utf-8"), flags=re.S)
        for line in text.splitlines():
            found = re.findall(r"\b(\w+)\s*\(", line)
            if line[:1].isalpha() and found:
                found = found[1:]  # the function this line defines
            calls.update(found)
    return calls


def test_cffi_declarations_have_a_caller() -> None:
    text = (PACKAGE / "core" / "_cdef.h").read_text(encoding="utf-8")
    declared = re.findall(r"\b(rtu_\w+)\s*\(", re.sub(r"/\*.*?\*/", "", text, flags=re.S))
    assert len(declared) >= 50, declared  # the search finds the declarations
    used, calls = _names_used(), _c_calls()
    assert [n for n in declared if n not in used and n not in calls] == []
