"""Every code example of README.md and docs/*.md runs as a test, so the docs cannot
drift from the code.

The blocks are taken from the Markdown as they are.  What a block needs that a
reader brings (a bus with drives, the ports of their adapters) is given by the
test, never written into the block: an HTML comment right before the fence says
what (readers of the rendered Markdown do not see it)::

    <!-- doctest: setup=drives -->

Directives (space-separated, ``key=value`` or a bare word):

``setup=drives``
    a virtual bus (19200 baud, drops opened 8N1) at the bus directory of the
    README's session, ``/tmp/bus``, with the session's simulators on it: a WEG
    CFW701 at address 1 on drop1 (stopped), a Bonfiglioli ACU at 3 on drop2 and a
    CV100 at 5 on drop3 (stopped); drop0 is the master's, drop4 a spare.  A second
    bus, ``/tmp/bus2``, has a CFW701 at address 1 on drop1.  The test makes both in
    a temporary directory and puts its path where the block says ``/tmp/bus``
    (the one substitution: a reader picks their own directory).
``setup=gateway``
    ``setup=drives`` plus ``pyrtu gateway`` in front of ``/tmp/bus``: Modbus TCP
    and RTU over TCP listeners, put where the block names ``192.168.1.20`` (TCP,
    port 502) and ``10.0.0.5:4001`` (RTU over TCP), the addresses of the reader's
    gateway or device server.
``setup=dir``
    only the temporary directory for ``/tmp/bus``: the block makes its bus and
    drives itself (the README's session).
``reference``
    an API summary (signatures, not a program): every ``Name(...)`` it shows must
    exist and take the keywords it shows (checked with `inspect.signature`).
``sequel``
    run after the block before it in the same file, in the same interpreter (it
    goes on with the names that block made).
``file=NAME``
    (on a block of another language, e.g. ``toml``) the block is a file the
    examples after it read: written as NAME into their directory first.

Without a directive a ``python`` block runs as written in a fresh interpreter, in
a temporary directory shared by the blocks of one file (``bus.cap`` written by one
block is read by the next); it must end by itself (an example that never ends
fails).  A ``console`` block's ``$ pyrtu ...`` lines are parsed by the real
argument parser (every flag and value accepted); with ``setup=dir`` they are
also run, in order (``&``: in the background, stopped at the end), each ending
with the exit status the block shows (``echo "exit $?"``, else 0) and printing
the lines it shows, compared with the numbers and spacing left out (``...``
elides lines).
"""

from __future__ import annotations

import ast
import contextlib
import inspect
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from pyrtu.vbus import VirtualBus

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RUN_TIMEOUT = 90.0
BUS = "/tmp/bus"

_FENCE = re.compile(r"^(`{3,})\s*([\w+-]*)\s*$")
_DIRECTIVE = re.compile(r"^<!--\s*doctest:(.*?)-->\s*$")


@dataclass
class Block:
    path: Path
    line: int  # of the opening fence, 1-based
    lang: str
    code: str
    directives: dict[str, str] = field(default_factory=dict)

    @property
    def id(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def blocks_of(path: Path) -> list[Block]:
    """The fenced code blocks of ``path`` with the directives just before them."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out: list[Block] = []
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, lang = m.group(1), m.group(2).lower()
        body: list[str] = []
        j = i + 1
        while j < len(lines) and lines[j].strip() != fence:
            body.append(lines[j])
            j += 1
        directives: dict[str, str] = {}
        k = i - 1
        while k >= 0 and not lines[k].strip():
            k -= 1
        d = _DIRECTIVE.match(lines[k].strip()) if k >= 0 else None
        if d:
            for word in d.group(1).split():
                key, _, value = word.partition("=")
                directives[key] = value
        out.append(Block(path, i + 1, lang, "\n".join(body) + "\n", directives))
        i = j + 1
    return out


ALL = [b for p in DOCS for b in blocks_of(p)]
PYTHON = [b for b in ALL if b.lang == "python"]
CONSOLE = [b for b in ALL if b.lang == "console"]


def test_the_examples_are_found() -> None:
    """The extractor sees the documents' blocks (a broken fence would hide them)."""
    names = {b.path.name for b in PYTHON}
    assert {"README.md", "vbus.md"} <= names
    assert len(PYTHON) >= 10 and len(CONSOLE) >= 3
    for b in ALL:
        unknown = set(b.directives) - {"setup", "reference", "sequel", "file"}
        assert not unknown, f"{b.id}: unknown doctest directive {sorted(unknown)}"
        assert b.directives.get("setup", "drives") in ("drives", "gateway", "dir"), b.id


# -- the context: virtual buses with the README session's drives --------------------------------


@dataclass
class Drives:
    """The ``setup=drives`` context (see the module docstring)."""

    root: Path
    buses: list[VirtualBus]
    procs: list[subprocess.Popen[str]]
    subst: dict[str, str]

    def apply(self, text: str) -> str:
        for old, new in self.subst.items():
            text = text.replace(old, new)
        return text


def _pyrtu_bg(*args: object, ready: str) -> tuple[subprocess.Popen[str], str]:
    """``python -m pyrtu ARGS`` in the background, once its stderr says ``ready``
    (the process and that line)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", *map(str, args)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    line = proc.stderr.readline()
    assert ready in line, line + (proc.stderr.read() if proc.poll() is not None else "")
    return proc, line


def _stop(procs: list[subprocess.Popen[str]]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.communicate()


@contextlib.contextmanager
def drives(tmp: Path, setup: str = "drives") -> Iterator[Drives]:
    root = tmp / "doc"
    root.mkdir()
    if setup == "dir":
        yield Drives(root, [], [], {BUS: str(root / "bus")})
        return
    gateway = setup == "gateway"
    buses = [
        VirtualBus(5, baudrate=19200, parity="N", directory=str(root / "bus")),
        VirtualBus(2, baudrate=19200, parity="N", directory=str(root / "bus2")),
    ]
    procs: list[subprocess.Popen[str]] = []
    try:
        for bus in buses:
            bus.start()
        b1, b2 = (str(root / "bus"), str(root / "bus2"))
        for args in (
            ("cfw701", f"{b1}/drop1", "-a", 1, "--state", "stopped"),
            ("acu", f"{b1}/drop2", "-a", 3),
            ("cv100", f"{b1}/drop3", "-a", 5, "--state", "stopped"),
            ("cfw701", f"{b2}/drop1", "-a", 1),
        ):
            device, port, *rest = args
            sim, _ = _pyrtu_bg("simulate", device, "--port", port, "-P", "N", *rest,
                               ready="address")  # fmt: skip
            procs.append(sim)
        subst = {BUS: b1}
        if gateway:
            gw, line = _pyrtu_bg(
                "gateway", "--listen", "127.0.0.1:0", "--listen-rtu", "127.0.0.1:0",
                "--port", f"{b1}/drop0", "--parity", "N", "--timeout", "0.5",
                ready="listening",
            )  # fmt: skip
            procs.append(gw)
            subst.update(_gateway_addresses(line))
        yield Drives(root, buses, procs, subst)
    finally:
        _stop(procs)
        for bus in buses:
            bus.close()


def _gateway_addresses(ready: str) -> dict[str, str]:
    """Where the block's gateway addresses go: the ports the gateway bound (from its
    "listening on HOST:PORT (RTU over TCP on HOST:PORT)" line)."""
    m = re.search(r"listening on (\S+?:\d+) \(RTU over TCP on (\S+?:\d+)\)", ready)
    assert m, ready
    tcp, rtu = m.groups()
    return {"192.168.1.20:502": tcp, "192.168.1.20": tcp, "10.0.0.5:4001": rtu}


# -- python blocks --------------------------------------------------------------------------------


def _run_python(code: str, cwd: Path, what: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", code],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert proc.returncode == 0, f"{what} failed:\n{proc.stderr[-3000:]}"


def _file_dir(tmp_path_factory: pytest.TempPathFactory, block: Block) -> Path:
    """The temporary directory the blocks of ``block``'s file share."""
    base = tmp_path_factory.getbasetemp() / "docs-cwd" / block.path.name
    base.mkdir(parents=True, exist_ok=True)
    return base


def _program(block: Block) -> str:
    """The block, after the blocks it is a sequel of."""
    i = PYTHON.index(block)
    parts = [block.code]
    while "sequel" in PYTHON[i].directives:
        i -= 1
        assert i >= 0 and PYTHON[i].path == block.path, f"{block.id}: sequel of nothing"
        parts.insert(0, PYTHON[i].code)
    return "\n".join(parts)


def _write_files(block: Block, cwd: Path, ctx: Drives | None) -> None:
    """The ``file=NAME`` blocks before ``block`` in its file, written into ``cwd``."""
    for b in ALL:
        if b.path == block.path and b.line < block.line and "file" in b.directives:
            text = ctx.apply(b.code) if ctx is not None else b.code
            (cwd / b.directives["file"]).write_text(text)


@pytest.mark.parametrize("block", [b for b in PYTHON if "reference" not in b.directives],
                         ids=lambda b: b.id)  # fmt: skip
def test_python_example_runs(
    block: Block, tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    code = _program(block)
    ast.parse(code, filename=block.id)  # a syntax error is reported as such
    cwd = _file_dir(tmp_path_factory, block)
    setup = block.directives.get("setup")
    if setup is None:
        _write_files(block, cwd, None)
        _run_python(code, cwd, block.id)
        return
    with drives(tmp_path, setup) as ctx:
        _write_files(block, cwd, ctx)
        _run_python(ctx.apply(code), cwd, block.id)


# -- reference blocks: the signatures they show exist ---------------------------------------------

_CALL = re.compile(r"^\s*(?:[a-z_][\w.]*\s*=\s*)?((?:[A-Za-z_]\w*\.)*[A-Z]\w*)\(", re.M)
_KEYWORD = re.compile(r"[(,\s\[]([a-z_]\w*)=")


def _resolve(name: str) -> object | None:
    import pyrtu
    import pyrtu.drivers.aio
    import pyrtu.vbus

    spaces = [pyrtu, pyrtu.drivers.aio, pyrtu.vbus]
    parts = name.split(".")
    if parts[0] == "pyrtu":
        parts = parts[1:]
    for space in spaces:
        obj: object = space
        try:
            for part in parts:
                obj = getattr(obj, part)
        except AttributeError:
            continue
        return obj
    return None


def _calls(code: str) -> Iterator[tuple[str, str]]:
    """``(name, argument text)`` of each top-level call ``Name(...)`` of the block."""
    for m in _CALL.finditer(code):
        depth, i = 1, m.end()
        while i < len(code) and depth:
            depth += {"(": 1, ")": -1}.get(code[i], 0)
            i += 1
        yield m.group(1), code[m.end() : i - 1]


@pytest.mark.parametrize("block", [b for b in PYTHON if "reference" in b.directives],
                         ids=lambda b: b.id)  # fmt: skip
def test_reference_signatures_exist(block: Block) -> None:
    checked = 0
    assert "setup" not in block.directives, f"{block.id}: a reference block is not run"
    for name, args in _calls(block.code):
        obj = _resolve(name)
        assert obj is not None, f"{block.id}: {name} does not exist"
        params = inspect.signature(obj).parameters  # type: ignore[arg-type]
        takes_any = any(p.kind is p.VAR_KEYWORD for p in params.values())
        for kw in _KEYWORD.findall(" " + args):
            assert kw in params or takes_any, f"{block.id}: {name} has no keyword {kw!r}"
            checked += 1
    assert checked, f"{block.id}: a reference block with no signature to check"


# -- console blocks -------------------------------------------------------------------------------


@dataclass
class Command:
    argv: list[str]
    background: bool
    exit_code: int
    shown: list[str]  # the output lines the block shows after it


def commands_of(block: Block) -> list[Command]:
    out: list[Command] = []
    for raw in block.code.splitlines():
        if raw.startswith("$ "):
            text = raw[2:].strip()
            code = 0
            m = re.search(r';\s*echo "exit \$\?"$', text)
            if m:
                text = text[: m.start()]
            background = text.endswith("&")
            text = text.rstrip("&").strip()
            if "|" in text:
                text = text.split("|")[0].strip()
            out.append(Command(shlex.split(text), background, code, []))
        elif out:
            m = re.fullmatch(r"exit (\d+)", raw.strip())
            if m:
                out[-1].exit_code = int(m.group(1))
            else:
                out[-1].shown.append(raw)
    return [c for c in out if c.argv and c.argv[0] == "pyrtu"]


@pytest.mark.parametrize("block", CONSOLE, ids=lambda b: b.id)
def test_console_commands_parse(block: Block) -> None:
    """Every ``$ pyrtu ...`` line is a command line the parser accepts."""
    from pyrtu.cli import build_parser, poll_config

    commands = commands_of(block)
    assert commands, f"{block.id}: no pyrtu command"
    for c in commands:
        argv = c.argv[1:]
        if poll_config.wants(argv):
            poll_config.build_parser().parse_args(argv[argv.index("poll") + 1 :])
            continue
        try:
            build_parser().parse_args(argv)
        except SystemExit as exc:
            pytest.fail(f"{block.id}: `{' '.join(c.argv)}` is refused (exit {exc.code})")


def _shape(line: str) -> str:
    """A line with its numbers and spacing left out (timings and ids vary)."""
    line = re.sub(r"/tmp/[\w./-]+", "PATH", line)
    line = re.sub(r"0x[0-9A-Fa-f]+|\d+(\.\d+)?", "#", line)
    return " ".join(line.split())


@pytest.mark.parametrize("block", [b for b in CONSOLE if "setup" in b.directives],
                         ids=lambda b: b.id)  # fmt: skip
def test_console_session_runs(block: Block, tmp_path: Path) -> None:
    with drives(tmp_path, block.directives["setup"]) as ctx:
        background: list[subprocess.Popen[str]] = []
        try:
            for c in commands_of(block):
                argv = [sys.executable, "-m", "pyrtu", *(ctx.apply(a) for a in c.argv[1:])]
                if c.background:
                    background.append(_start_background(argv))
                    continue
                r = subprocess.run(argv, cwd=ctx.root, capture_output=True, text=True,
                                   timeout=RUN_TIMEOUT)  # fmt: skip
                what = f"{block.id}: `{' '.join(c.argv)}`"
                assert r.returncode == c.exit_code, f"{what}: exit {r.returncode}\n{r.stderr}"
                got = [_shape(x) for x in (r.stdout + r.stderr).splitlines()]
                at = 0
                for shown in c.shown:
                    if shown.strip() in ("...", ""):
                        continue
                    want = _shape(ctx.apply(shown))
                    assert want in got[at:], f"{what}: not printed: {shown!r}\ngot: {got}"
                    at = got.index(want, at) + 1
        finally:
            _stop(background)


def _start_background(argv: list[str]) -> subprocess.Popen[str]:
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)  # fmt: skip
    deadline = time.monotonic() + 10
    assert proc.stderr is not None
    proc.stderr.readline()  # the ready line of vbus or simulate
    assert proc.poll() is None or time.monotonic() < deadline
    return proc
