"""Every pyrtu module imports on its own in a fresh interpreter: no import cycles.

A module that is first in a cycle fails (or sees a half-initialised partner) when it
is the first thing imported; importing each module alone, first, in its own
interpreter catches that.  The leaf modules import nothing of pyrtu at all.
"""

from __future__ import annotations

import pkgutil
import subprocess
import sys

import pytest

import pyrtu

MODULES = sorted(
    m.name
    for m in pkgutil.walk_packages(pyrtu.__path__, "pyrtu.")
    if "_build_core" not in m.name and not m.name.endswith("__main__")
)
LEAVES = ("pyrtu.pdu.functions", "pyrtu.core._errtypes")
# the low layers import leaves only
LOW = ("pyrtu.core.timing", "pyrtu.core.rules")

_PROBE = """
import importlib, sys
importlib.import_module(sys.argv[1])
"""


def _module_graph(deferred: bool = False) -> dict[str, set[str]]:
    """pyrtu module -> the pyrtu modules it imports at module level (``deferred``: also
    inside functions).  ``from P import x`` depends on P.x when that is a module, else
    on P (x is an attribute of P)."""
    import ast
    import pathlib

    root = pathlib.Path(pyrtu.__path__[0])
    files: dict[str, pathlib.Path] = {}
    for path in root.rglob("*.py"):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        files[".".join(parts)] = path
    graph: dict[str, set[str]] = {}
    for mod, path in files.items():
        pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
        deps: set[str] = set()
        tree = ast.parse(path.read_text())
        nodes = list(ast.walk(tree)) if deferred else tree.body
        for node in nodes:
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    deps.add(sub if sub in files else target)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
        graph[mod] = {d for d in deps if d in files and d != mod}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    state: dict[str, int] = {}
    found: list[list[str]] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                found.append([*stack[stack.index(d) :], d])
            elif d not in state:
                visit(d, stack)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
    return found


@pytest.mark.parametrize("name", MODULES)
def test_module_imports_alone(name: str) -> None:
    done = subprocess.run(
        [sys.executable, "-c", _PROBE, name], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr


def test_no_module_level_import_cycles() -> None:
    """Module-level imports between pyrtu modules form no cycle.  A package's
    ``__init__`` importing its own submodules is the one exception Python allows (the
    package is always initialised first), so edges into a package root from inside
    it are left out."""
    graph = _module_graph()
    assert "pyrtu.pdu.functions" in graph and "pyrtu.pdu.errors" in graph
    inner = {m: {d for d in ds if not m.startswith(d + ".")} for m, ds in graph.items()}
    assert _cycles(inner) == []


def test_no_deferred_import_cycles_in_the_layers() -> None:
    """Counting imports inside functions too (a deferred import is how a cycle hides,
    as errors <-> _pdu_base did), the core layers form no cycle."""
    graph = _module_graph(deferred=True)
    core = {
        m
        for m in graph
        if not m.startswith(("pyrtu.cli", "pyrtu.devices", "pyrtu.vbus"))
        and m not in ("pyrtu", "pyrtu.cli", "pyrtu.cli.demo", "pyrtu.__main__")
    }
    inner = {m: {d for d in graph[m] if d in core and not m.startswith(d + ".")} for m in core}
    assert _cycles(inner) == []
    assert "pyrtu.pdu.base" not in graph["pyrtu.pdu.errors"]


@pytest.mark.parametrize("name", LEAVES)
def test_leaf_modules_import_nothing_of_pyrtu(name: str) -> None:
    code = (
        "import sys, importlib.util, pathlib\n"
        f"spec = importlib.util.find_spec({name!r})\n"
        "src = pathlib.Path(spec.origin).read_text()\n"
        "import ast\n"
        "bad = [n for n in ast.walk(ast.parse(src)) if isinstance(n, ast.ImportFrom) and n.level]\n"
        "print(len(bad))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == "0", done.stderr


def test_no_function_imports_the_package_root() -> None:
    """Layers reach the backend through pyrtu.core._backend, never ``import pyrtu`` inside a
    function (which is how cycles hide)."""
    import ast
    import pathlib

    offenders = []
    for path in pathlib.Path(pyrtu.__path__[0]).rglob("*.py"):
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.Import) and any(a.name == "pyrtu" for a in node.names):
                    offenders.append(f"{path.name}:{node.lineno}")
                if isinstance(node, ast.ImportFrom) and node.level >= 1 and node.module is None:
                    names = {a.name for a in node.names}
                    if path.parent.name == "pyrtu" and names & {"backend", "BACKEND"}:
                        offenders.append(f"{path.name}:{node.lineno}")
    assert offenders == [], offenders


@pytest.mark.parametrize("name", LOW)
def test_low_layers_import_only_leaves(name: str) -> None:
    graph = _module_graph(deferred=True)
    assert graph[name] <= set(LEAVES), graph[name]
