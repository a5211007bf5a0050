"""The examples of README.md and docs/*.md run as a reader runs them, so the docs
cannot drift from the code (#27.15).

One reader's session: README.md from top to bottom, then the pages of the
documentation site in the order of its navigation (mkdocs.yml),
in one scratch directory (the working directory and ``HOME``), with nothing the
documents do not set up themselves: no bus, drive, port or file is made by the test.
What a block needs comes from the blocks before it (the README starts its virtual bus,
its simulated drives and its gateway in ``console`` blocks, in the background with
``&``, and they keep running until the session ends, as in the reader's terminals).

What runs:

``console`` blocks
    a terminal transcript: every ``$ COMMAND`` line runs in ``bash`` (``pyrtu`` and
    ``python`` are the ones under test), in order.  A command ending in ``&`` runs in
    the background for the rest of the session; the lines shown under it are awaited
    in its output (its "ready" lines), and it must still run at the end of every later
    block.  Any other command must end by itself, with the status ``exit N`` shows
    after it (``; echo "exit $?"``), else 0, and print the lines shown under it, in
    that order (other lines may come between them; ``...`` stands for any lines, or
    for any text inside a line).
    Lines are compared with their numbers, ``/tmp/...`` paths and spacing left out
    (timings, ids and the reader's directory vary).
``python`` blocks
    saved and run as a script (``python example.py``), which must end by itself with
    status 0.  What the block shows is checked: a line whose comment is ``# prints:
    TEXT`` must print TEXT (in order; compared as the console lines are), and an
    expression statement whose comment starts with a Python literal (``# [256]``,
    ``# True``, ``# 2: the request and its response``: the literal, then the end
    of the comment or ``: ``) must have that value (floats to 6 digits; a list or
    tuple ending in ``...`` matches one that starts so).
``file=NAME`` (a directive, below)
    a block the reader saves as NAME (``points.toml``): written when it is reached.

Anything else is shown, not run: ``sh`` blocks are commands for the reader's own
machine (installing, hardware, a broker), ``toml``/text blocks without ``file=``.

The one substitution: ``/tmp/`` becomes the scratch directory's ``tmp/`` (a reader
picks their own directory), and the TCP ports ``5020``, ``5021`` and ``5022`` of
``127.0.0.1`` (``127.0.0.1:PORT``, and ``listener PORT 127.0.0.1`` in a
mosquitto.conf) become free ones (the reader's are free).

Directives: an HTML comment right before the fence (invisible in the rendered
Markdown), space-separated words::

    <!-- doctest: skip -->

``skip``
    a block a reader cannot run as it is: it needs hardware (``/dev/ttyUSB0``) or
    shows a command's form; say why in the text.
``reference``
    (python) an API summary: every ``Name(...)`` it shows must exist and take the
    keywords it shows (`inspect.signature`); not run.
``sequel``
    (python) runs in one script with the block before it (it goes on with the names
    that block made).
``file=NAME``
    as above.

Each block is one test, ``FILE:LINE`` of its opening fence; a failure names the
document's line.  A block runs after every block before it (selecting one block with
``-k`` runs those first).
"""

from __future__ import annotations

import ast
import inspect
import io
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
import tokenize
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _reading_order() -> list[Path]:
    """The README (the site's landing page), then the pages of mkdocs.yml's navigation
    in its order: the order a reader of the site follows.  (The benchmarks page and the
    API reference carry no examples of their own.)"""
    nav = (ROOT / "mkdocs.yml").read_text().split("\nnav:", 1)[1]
    pages = re.findall(r"^\s*- (?:[^:\n]+: )?(\S+\.md)\s*$", nav, re.M)
    skip = {"index.md", "benchmarks.md"}
    return [ROOT / "README.md"] + [
        ROOT / "docs" / p for p in pages if p not in skip and not p.startswith("reference/")
    ]


DOCS = _reading_order()
RUN_TIMEOUT = 90.0  # a command or script that has not ended by then never ends
READY_TIMEOUT = 20.0  # a background command's shown lines
TCP_PORTS = ("5020", "5021", "5022")
DIRECTIVES = {"skip", "reference", "sequel", "file"}

_ALARM = re.compile(r"warning|error|traceback", re.I)
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

    @property
    def runs(self) -> bool:
        if {"skip", "reference"} & set(self.directives):
            return False
        return self.lang in ("python", "console") or "file" in self.directives


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
RUN = [b for b in ALL if b.runs]


def test_the_examples_are_found() -> None:
    """The extractor sees the documents' blocks (a broken fence would hide them), and
    every directive is known."""
    names = {b.path.name for b in RUN if b.lang == "python"}
    assert {"README.md", "vbus.md"} <= names
    assert len([b for b in RUN if b.lang == "python"]) >= 10
    assert len([b for b in RUN if b.lang == "console"]) >= 4
    for b in ALL:
        unknown = set(b.directives) - DIRECTIVES
        assert not unknown, f"{b.id}: unknown doctest directive {sorted(unknown)}"
        if "file" in b.directives:
            assert b.directives["file"], f"{b.id}: file= names no file"


# -- what a block shows -----------------------------------------------------------------------


def _shape(line: str) -> str:
    """A line with its numbers, /tmp paths and spacing left out."""
    line = re.sub(r"/tmp/[\w./+-]+", "PATH", line)
    line = re.sub(r"0x[0-9A-Fa-f]+|\d+(\.\d+)?", "#", line)
    return " ".join(line.split())


def _missing(shown: list[tuple[int, str]], output: str) -> tuple[int, str] | None:
    """The first ``(line, text)`` of ``shown`` not found in ``output`` in order."""
    got = [_shape(x) for x in output.splitlines()]
    at = 0
    for number, text in shown:
        want = _shape(text)
        if not want or want == "...":
            continue
        # "..." inside a line stands for any text there
        pattern = re.compile(".*".join(re.escape(part) for part in want.split("...")))
        found = next((i for i in range(at, len(got)) if pattern.fullmatch(got[i])), None)
        if found is None:
            return number, text
        at = found + 1
    return None


def _literal(comment: str) -> str | None:
    """The Python literal a value comment starts with (then its end or ``: ``)."""
    ends = [len(comment)] + [m.start() for m in re.finditer(r": ", comment)]
    for end in sorted(ends, reverse=True):
        text = comment[:end].strip()
        if not text:
            continue
        try:
            ast.literal_eval(text)
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            continue
        return text
    return None


def _comments(code: str) -> dict[int, str]:
    """Line (1-based, in ``code``) -> its comment's text."""
    out: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(code).readline):
        if tok.type == tokenize.COMMENT:
            out[tok.start[0]] = tok.string[1:].strip()
    return out


def instrument(block: Block) -> tuple[str, list[tuple[int, str]], int]:
    """``block``'s code with its value comments turned into checks (``__doc_check(value,
    literal, document line)``, line numbers kept), the ``# prints:`` lines it shows
    (document line, text), and how many values it checks."""
    code = block.code
    lines = code.splitlines()
    comments = _comments(code)
    prints = [
        (block.line + n, text[len("prints:") :].strip())
        for n, text in sorted(comments.items())
        if text.startswith("prints:")
    ]
    checks = 0
    for node in ast.walk(ast.parse(code, filename=block.id)):
        if not isinstance(node, ast.Expr) or node.lineno != node.end_lineno:
            continue
        value = node.value
        inner = value.value if isinstance(value, ast.Await) else value
        if isinstance(inner, ast.Call) and getattr(inner.func, "id", "") == "print":
            continue
        comment = comments.get(node.lineno)
        literal = _literal(comment) if comment else None
        if literal is None:
            continue
        src = lines[node.lineno - 1]
        expr = src[node.col_offset : node.end_col_offset]
        rest = src[node.end_col_offset :].strip()
        if not rest.startswith("#") or src[: node.col_offset].strip():
            continue  # another statement on the line
        lines[node.lineno - 1] = (
            f"{src[: node.col_offset]}__doc_check({expr}, {literal!r}, "
            f"{str(block.path.relative_to(ROOT))!r}, {block.line + node.lineno})"
        )
        checks += 1
    return "\n".join(lines) + "\n", prints, checks


_CHECKER = """
import ast, builtins, math, runpy, sys

def _like(value, expected):
    if isinstance(expected, float) or (isinstance(value, float) and isinstance(expected, int)):
        return isinstance(value, (int, float)) and math.isclose(value, expected, rel_tol=1e-6)
    if isinstance(expected, (list, tuple)) and expected and expected[-1] is Ellipsis:
        head = expected[:-1]
        return (isinstance(value, (list, tuple)) and len(value) >= len(head)
                and all(_like(v, e) for v, e in zip(value, head)))
    if isinstance(expected, (list, tuple)):
        return (isinstance(value, (list, tuple)) and len(value) == len(expected)
                and all(_like(v, e) for v, e in zip(value, expected)))
    if isinstance(expected, dict):
        return (isinstance(value, dict) and value.keys() == expected.keys()
                and all(_like(value[k], e) for k, e in expected.items()))
    return type(value) is type(expected) and value == expected or (
        isinstance(value, int) and isinstance(expected, int) and value == expected)

def __doc_check(value, literal, doc, line):
    if not _like(value, ast.literal_eval(literal)):
        raise AssertionError(f"{doc}:{line}: the comment shows {literal}, the value is {value!r}")
    return value

builtins.__doc_check = __doc_check
sys.argv = [sys.argv[1]]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


# -- the reader's session ---------------------------------------------------------------------


def _free_port() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return str(s.getsockname()[1])


@dataclass
class Background:
    block: Block
    command: str
    proc: subprocess.Popen[bytes]
    log: Path
    seen: int = 0  # characters of the log looked at


class Session:
    """The scratch directory, the substitutions and the background commands."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.cwd = root / "work"
        self.cwd.mkdir()
        (root / "tmp").mkdir()
        self.logs = root / "logs"
        self.logs.mkdir()
        bin_dir = root / "bin"
        bin_dir.mkdir()
        for name, argv in (("pyrtu", f"{sys.executable} -m pyrtu"), ("python", sys.executable)):
            shim = bin_dir / name
            shim.write_text(f'#!/bin/sh\nexec {argv} "$@"\n')
            shim.chmod(0o755)
        self.subst = {"/tmp/": f"{root}/tmp/"}
        for port in TCP_PORTS:
            free = _free_port()
            self.subst[f"127.0.0.1:{port}"] = f"127.0.0.1:{free}"
            self.subst[f"listener {port} 127.0.0.1"] = f"listener {free} 127.0.0.1"
        self.env = {
            **os.environ,
            "HOME": str(root),
            "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
            "PYTHONPATH": os.pathsep.join(
                [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]
            ),
        }
        # as in the reader's shell: output as the programs buffer it (a background
        # command's lines must reach its file by themselves)
        self.env.pop("PYTHONUNBUFFERED", None)
        self.background: list[Background] = []
        self.done = 0  # blocks of RUN run so far
        self.failed: dict[str, str] = {}

    def apply(self, text: str) -> str:
        for old, new in self.subst.items():
            text = text.replace(old, new)
        return text

    def unapply(self, text: str) -> str:
        for old, new in self.subst.items():
            text = text.replace(new, old)
        return text

    # -- running blocks

    def run_through(self, block: Block) -> None:
        """Run the blocks before ``block`` not run yet, then ``block``."""
        target = RUN.index(block)
        while self.done <= target:
            b = RUN[self.done]
            self.done += 1
            try:
                self.run(b)
            except BaseException as exc:
                self.failed[b.id] = str(exc)
                if b is block:
                    raise
        if block.id in self.failed:  # run earlier, for a block after it
            pytest.fail(self.failed[block.id])

    def run(self, block: Block) -> None:
        if "file" in block.directives:
            (self.cwd / block.directives["file"]).write_text(self.apply(block.code))
        elif block.lang == "console":
            self._console(block)
        elif block.lang == "python":
            self._python(block)
        self._background_alive(block)

    def _background_alive(self, block: Block) -> None:
        """The background commands still run, and said nothing alarming meanwhile (a
        reader sees what they print in the terminal: a simulator's warning that another
        device answers at its address is a collision on the bus)."""
        for bg in self.background:
            text = bg.log.read_text(errors="replace")
            new, bg.seen = text[bg.seen :], len(text)
            alarming = [x for x in new.splitlines() if _ALARM.search(x)]
            if alarming:
                pytest.fail(
                    f"{block.id}: while it ran, `{bg.command}` (started in the background "
                    f"at {bg.block.id}) printed:\n" + "\n".join(alarming)
                )
            if bg.proc.poll() is not None:
                self.background.remove(bg)
                pytest.fail(
                    f"{bg.block.id}: `{bg.command}` (in the background) ended with "
                    f"status {bg.proc.returncode} by the end of {block.id}:\n"
                    + bg.log.read_text(errors="replace")[-3000:]
                )

    def _console(self, block: Block) -> None:
        for c in commands_of(block):
            line = self.apply(c.text)
            where = f"{block.path.relative_to(ROOT)}:{c.line}: `{c.text}`"
            if c.background:
                self._start(block, c, line, where)
                continue
            try:
                r = subprocess.run(["bash", "-c", line], cwd=self.cwd, env=self.env,
                                   capture_output=True, timeout=RUN_TIMEOUT)  # fmt: skip
            except subprocess.TimeoutExpired:
                pytest.fail(f"{where}: did not end within {RUN_TIMEOUT:.0f} s")
            out = self.unapply((r.stdout + r.stderr).decode(errors="replace"))
            assert r.returncode == c.exit_code, (
                f"{where}: exit {r.returncode}, the document shows {c.exit_code}\n{out[-3000:]}"
            )
            miss = _missing(c.shown, out)
            assert miss is None, (
                f"{block.path.relative_to(ROOT)}:{miss[0]}: not printed: {miss[1]!r}\n{out[-3000:]}"
            )

    def _start(self, block: Block, c: Command, line: str, where: str) -> None:
        log = self.logs / f"bg-{len(self.background)}.log"
        with log.open("wb") as sink:
            proc = subprocess.Popen(["bash", "-c", f"exec {line}"], cwd=self.cwd, env=self.env,
                                    stdout=sink, stderr=subprocess.STDOUT,
                                    start_new_session=True)  # fmt: skip
        bg = Background(block, c.text, proc, log)
        self.background.append(bg)
        deadline = time.monotonic() + READY_TIMEOUT
        while True:
            text = log.read_text(errors="replace")
            out = self.unapply(text)
            miss = _missing(c.shown, out)
            if miss is None and (c.shown or out or time.monotonic() > deadline - READY_TIMEOUT + 1):
                bg.seen = len(text)  # its ready lines
                return
            if proc.poll() is not None:
                pytest.fail(f"{where}: ended with status {proc.returncode}\n{out[-3000:]}")
            if time.monotonic() > deadline:
                assert miss is not None
                pytest.fail(
                    f"{block.path.relative_to(ROOT)}:{miss[0]}: not printed within "
                    f"{READY_TIMEOUT:.0f} s: {miss[1]!r}\n{out[-3000:]}"
                )
            time.sleep(0.05)

    def _python(self, block: Block) -> None:
        parts = [block]
        i = PYTHON.index(block)
        while "sequel" in PYTHON[i].directives:
            i -= 1
            assert i >= 0 and PYTHON[i].path == block.path, f"{block.id}: sequel of nothing"
            parts.insert(0, PYTHON[i])
        codes, prints = [], []
        for part in parts:
            code, shown, _ = instrument(part)
            codes.append(code)
            prints += shown
        script = self.cwd / "example.py"
        script.write_text(self.apply("\n".join(codes)))
        checker = self.logs / "check_example.py"
        checker.write_text(_CHECKER)
        try:
            r = subprocess.run([sys.executable, str(checker), str(script)], cwd=self.cwd,
                               env=self.env, capture_output=True, timeout=RUN_TIMEOUT)  # fmt: skip
        except subprocess.TimeoutExpired:
            pytest.fail(f"{block.id}: the example did not end within {RUN_TIMEOUT:.0f} s")
        out = self.unapply(r.stdout.decode(errors="replace"))
        err = self.unapply(r.stderr.decode(errors="replace"))
        assert r.returncode == 0, f"{block.id}: the example failed:\n{err[-3000:]}"
        miss = _missing([(n, t) for n, t in prints], out)
        assert miss is None, (
            f"{block.path.relative_to(ROOT)}:{miss[0]}: not printed: {miss[1]!r}\n{out[-3000:]}"
        )

    def close(self) -> None:
        for bg in self.background:
            if bg.proc.poll() is None:
                os.killpg(bg.proc.pid, signal.SIGINT)
        for bg in self.background:
            try:
                bg.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(bg.proc.pid, signal.SIGKILL)
                bg.proc.wait()


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Session]:
    s = Session(tmp_path_factory.mktemp("reader"))
    try:
        yield s
    finally:
        s.close()


@pytest.mark.parametrize("block", RUN, ids=lambda b: b.id)
def test_a_reader_runs_the_example(block: Block, session: Session) -> None:
    session.run_through(block)


# -- console commands -------------------------------------------------------------------------


@dataclass
class Command:
    line: int  # in the document
    text: str  # the command, without ``; echo "exit $?"`` and ``&``
    background: bool
    exit_code: int
    shown: list[tuple[int, str]]  # the output lines the block shows after it

    @property
    def argv(self) -> list[str]:
        """The first command's words (before a pipe or redirection)."""
        lexer = shlex.shlex(self.text, posix=True, punctuation_chars=True)
        lexer.whitespace_split = True
        out: list[str] = []
        for word in lexer:
            if set(word) <= set("|&;<>()"):
                break
            out.append(word)
        return out


def commands_of(block: Block) -> list[Command]:
    out: list[Command] = []
    for n, raw in enumerate(block.code.splitlines()):
        if raw.startswith("$ "):
            text = raw[2:].strip()
            m = re.search(r';\s*echo "exit \$\?"$', text)
            if m:
                text = text[: m.start()].strip()
            background = text.endswith("&")
            text = text.rstrip("&").strip()
            out.append(Command(block.line + 1 + n, text, background, 0, []))
        elif out:
            m = re.fullmatch(r"exit (\d+)", raw.strip())
            if m:
                out[-1].exit_code = int(m.group(1))
            else:
                out[-1].shown.append((block.line + 1 + n, raw))
    return out


@pytest.mark.parametrize("block", CONSOLE, ids=lambda b: b.id)
def test_console_commands_parse(block: Block) -> None:
    """Every ``$ pyrtu ...`` line is a command line the parser accepts (also in the
    blocks that are not run)."""
    from pyrtu.cli import build_parser, poll_config

    assert commands_of(block), f"{block.id}: no command"
    commands = [c for c in commands_of(block) if c.argv and c.argv[0] == "pyrtu"]
    for c in commands:
        argv = c.argv[1:]
        if poll_config.wants(argv):
            poll_config.build_parser().parse_args(argv[argv.index("poll") + 1 :])
            continue
        try:
            build_parser().parse_args(argv)
        except SystemExit as exc:
            pytest.fail(
                f"{block.path.relative_to(ROOT)}:{c.line}: `{c.text}` is refused (exit {exc.code})"
            )


# -- reference blocks: the signatures they show exist -----------------------------------------

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
    for name, args in _calls(block.code):
        obj = _resolve(name)
        assert obj is not None, f"{block.id}: {name} does not exist"
        params = inspect.signature(obj).parameters  # type: ignore[arg-type]
        takes_any = any(p.kind is p.VAR_KEYWORD for p in params.values())
        for kw in _KEYWORD.findall(" " + args):
            assert kw in params or takes_any, f"{block.id}: {name} has no keyword {kw!r}"
            checked += 1
    assert checked, f"{block.id}: a reference block with no signature to check"


# -- the dotted paths the documents name ------------------------------------------------------

_PATH = re.compile(r"\bpyrtu(?:\.[A-Za-z_]\w*)+")
_IMPORT = re.compile(r"\bimport (pyrtu(?:\.\w+)+)")


def test_documented_paths_work_after_import_pyrtu() -> None:
    """Every ``pyrtu.X.name`` the documents name resolves after ``import pyrtu`` alone
    (``pyrtu.data.encode_float32``), or after the ``import pyrtu.X.Y`` they show for it
    (``import pyrtu.compat.pymodbus``).  Checked in a fresh interpreter: nothing else
    imported first."""
    text = "\n".join(p.read_text(encoding="utf-8") for p in DOCS)
    paths = sorted(set(_PATH.findall(text)))
    imported = sorted(set(_IMPORT.findall(text)))

    def needs(path: str) -> list[str]:
        return [m for m in imported if path == m or path.startswith(m + ".")]

    groups: dict[tuple[str, ...], list[str]] = {}
    for path in paths:
        groups.setdefault(tuple(needs(path)), []).append(path)
    for imports, group in groups.items():
        probe = (
            "import importlib, pyrtu\n"
            f"for m in {list(imports)!r}:\n"
            "    importlib.import_module(m)\n"
            f"for path in {group!r}:\n"
            "    obj = pyrtu\n"
            "    try:\n"
            "        for part in path.split('.')[1:]:\n"
            "            obj = getattr(obj, part)\n"
            "    except AttributeError as exc:\n"
            "        print(f'{path}: {exc}')\n"
        )
        r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                           timeout=120, cwd=ROOT)  # fmt: skip
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip() == "", r.stdout
    assert "pyrtu.data.encode_float32" in paths
