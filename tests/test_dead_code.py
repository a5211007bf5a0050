"""No dead code in the private layers, and no benchmark-only code in the shipped core.

A private module (``pyrtu/_*.py``, ``pyrtu/core/_pure/``) has no users outside the
project, so a function, class or method of one that nothing in pyrtu/, tests/ or
bench/ names is dead: it only misleads a reader (``_mbap.decode_header`` and
``ClientProtocol.wait_limit`` were such, issue 18).
"""

from __future__ import annotations

import ast
import os
from pathlib import Path

import pytest

import pyrtu

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "pyrtu"


def _private_modules() -> list[Path]:
    return sorted(PACKAGE.glob("_*.py")) + sorted((PACKAGE / "_pure").glob("*.py"))


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
        if name not in used
    ]
    assert unused == [], f"defined but never used: {unused}"


def test_shipped_core_has_no_benchmark_only_function() -> None:
    """The empty functions bench/bench_crc.py measures as the floor of a cffi call
    live in a module the benchmark compiles itself, not in pyrtu.core._rtu_core."""
    if "c" not in pyrtu.available_backends():
        if os.environ.get("PYRTU_REQUIRE_C") == "1":
            pytest.fail("PYRTU_REQUIRE_C=1 but the C core is not built")
        pytest.skip("the C core is not built here")
    from pyrtu.core._rtu_core import lib

    assert [name for name in dir(lib) if "noop" in name] == []
