"""The folders of pyrtu are its layers: each imports only from the layers below it.

docs/DESIGN.md ("The tree") lists them.  Every import of every module counts,
the deferred ones inside functions and TYPE_CHECKING blocks included, so that a
newcomer can trust `ls pyrtu/` as the map of what depends on what.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "pyrtu"

CORE = {"core"}
PDU = CORE | {"pdu"}
PROTOCOL = PDU | {"protocol"}
TRANSPORTS = PROTOCOL | {"drivers", "tcp"}
#: the folders each folder may import from (itself included)
ALLOWED: dict[str, set[str]] = {
    "core": CORE,
    "pdu": PDU,
    "protocol": PROTOCOL,
    "drivers": TRANSPORTS,
    "tcp": TRANSPORTS,
    "vbus": TRANSPORTS | {"vbus"},
    "devices": TRANSPORTS | {"devices"},
    "compat": PDU | {"compat"},
    "security": PDU | {"security"},
    "gateway": TRANSPORTS | {"security", "gateway"},
    "poller": TRANSPORTS | {"security", "devices", "poller"},
    "outbox": TRANSPORTS | {"devices", "poller", "outbox"},
    "bridge": TRANSPORTS | {"devices", "poller", "outbox", "bridge"},
    "sparkplug": TRANSPORTS | {"devices", "poller", "outbox", "bridge", "sparkplug"},
    "bench": TRANSPORTS | {"vbus", "bench"},
    "metrics": TRANSPORTS
    | {"security", "gateway", "poller", "outbox", "bridge", "sparkplug", "metrics"},
}
#: modules that stand above their folder's layer (module path -> what it may import):
#: the TCP server is the gateway's machinery with an application as its one bus, while
#: the gateway's connections use tcp/sockets.py, so it sits above gateway/ (alone of tcp/)
ABOVE: dict[str, set[str]] = {
    "tcp/server.py": TRANSPORTS | {"security", "gateway"},
}
#: the root modules (the package's face) and their homes
FACES = {
    "aio": "drivers",
    "ascii": "core",
    "data": "pdu",
    "errors": "pdu",
    "functions": "pdu",
    "line": "core",
    "rules": "core",
    "timing": "core",
    "tcp_server": "tcp",
}


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def _folder_of(path: Path) -> str:
    rel = path.relative_to(PACKAGE).parts
    return rel[0] if len(rel) > 1 else rel[0][: -len(".py")]


def _imported(path: Path) -> set[str]:
    """The pyrtu modules ``path`` imports (absolute dotted names), wherever the import stands."""
    rel = path.relative_to(PACKAGE.parent).with_suffix("").parts
    package = list(rel if rel[-1] == "__init__" else rel[:-1])
    if package[-1] == "__init__":
        package = package[:-1]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "pyrtu"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module.split(".")[0] != "pyrtu":
                continue
            found.add(module)
            found |= {f"{module}.{a.name}" for a in node.names}  # (names may be modules)
    return found


def _folder_of_module(name: str) -> str | None:
    parts = name.split(".")
    if len(parts) < 2:
        return None  # the package root
    if (PACKAGE / parts[1]).is_dir():
        return parts[1]
    if (PACKAGE / f"{parts[1]}.py").is_file():
        return parts[1]
    return None  # a name inside a module (from pyrtu.x import name)


def test_every_folder_is_a_known_layer() -> None:
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders - {"cli"} == set(ALLOWED), (
        "a new folder needs its place in ALLOWED and DESIGN.md"
    )


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_down_the_layers(path: Path) -> None:
    folder = _folder_of(path)
    if folder in ("cli", "__init__", "__main__", "_version", "_startup"):
        return  # the commands and the package's face use every layer
    allowed = ABOVE.get(path.relative_to(PACKAGE).as_posix())
    if allowed is None:
        allowed = ALLOWED.get(folder) or ALLOWED[FACES[folder]]
    wrong = set()
    for name in _imported(path):
        target = _folder_of_module(name)
        if target is None or target in allowed:
            continue
        if target in FACES:
            wrong.add(f"{name} (a public face: import its home, pyrtu.{FACES[target]})")
        elif target not in ("_version",):
            wrong.add(name)
    assert not wrong, f"{path.relative_to(PACKAGE)} ({folder}) imports {sorted(wrong)}"


def test_faces_re_export_their_home_only() -> None:
    """A root module imports its home only (a deprecated one: the warning helper too)."""
    helper = {
        "pyrtu.core._deprecated",
        "pyrtu.core._deprecated.renamed",
        "pyrtu.core._deprecated.moved",
    }
    for face, home in FACES.items():
        names = _imported(PACKAGE / f"{face}.py") - helper
        imported = {_folder_of_module(n) for n in names}
        assert imported <= {home}, (face, imported)
