"""Mutation testing of pyrtu: which fault in the code would no test notice?

Two kinds of mutants, both run in a copy of the tree (build/mutate/), never in it:

* **generated** (`make mutate`): cosmic-ray (PyPI) makes every mutant of the
  operators in `OPERATORS` (realistic faults: a boundary moved, a condition negated,
  an operator or a constant changed, a loop skipped) in each module of
  `mutate/targets.toml`, and runs that target's test files against each one.  A
  mutant no test kills "survives"; `mutate/equivalent.toml` lists the survivors that
  change no behaviour, each with its reason.  The report (killed, survived,
  equivalent, the score, every survivor with its line) goes to docs/MUTATION.md.
* **hand-written** (`make mutate-faults`, run by CI): the faults of
  `mutate/faults.toml`, Python and C (cosmic-ray does not reach C: a C fault is
  applied to csrc/, the core rebuilt, and the named tests run on it).  Each must be
  killed by the tests it names; one that survives fails the run.

    python mutate/run.py faults                 # every hand-written fault (CI)
    python mutate/run.py generated [TARGET ...] # cosmic-ray over the targets (all)
    python mutate/run.py generated --jobs 2     # targets in parallel, a tree copy each
    python mutate/run.py generated --survivors plan  # re-judge only the last survivors
    python mutate/run.py generated --rest plan --budget 20  # judge more of them
    python mutate/run.py listed server          # re-judge the survivors the page lists
    python mutate/run.py report plan            # docs/MUTATION.md from the last run

`--budget MINUTES` bounds each module's run: cosmic-ray takes the mutants in random
order, so the ones judged when the time is up are a random sample; the report says
how many were not run (and `--survivors` later judges the survivors of the sample).

A mutant inside an annotation is not run (`_annotation_spans`: every target module
has `from __future__ import annotations`, so an annotation is a string nothing
evaluates).  A run that cosmic-ray stopped at the target's timeout counts as
incompetent, not killed (a loaded machine makes a slow run, no kill).

`--survivors` reuses a target's last session: the killed mutants stay killed, and
only the survivors (and the runs that timed out) run again against the current
tests/ (copied anew).  `--rest`
reuses it too: the verdicts stay, and the mutants a budget left unjudged run (a
further sample, within the budget), so that a target's figure grows to cover most
mutants run by run (run `--survivors` first: a survivor stays one until then).  That is
sound only when the mutated modules are unchanged and the target's test files only
grew since the session; the run checks both and refuses otherwise.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parent.parent
HERE = ROOT / "mutate"
WORK = ROOT / "build" / "mutate"
REPORT = ROOT / "docs" / "MUTATION.md"

#: the tree a test run needs (copied; the .venv stays where it is)
TREE = (
    "pyrtu",
    "tests",
    "csrc",
    "docs",
    "bench",
    "fuzz",
    "setup.py",
    "pyproject.toml",
    "MANIFEST.in",
    "README.md",
    "LICENSE",
    "Makefile",
)

#: cosmic-ray's operators kept: faults a person makes.  Left out: swaps that no one
#: writes by mistake (``+`` to ``**`` or ``^``, ``<`` to ``is``), and the operators
#: that rewrite names, decorators and exception types.
OPERATORS = tuple(
    f"core/{name}"
    for name in (
        # a boundary moved, a comparison negated or turned
        *(
            f"ReplaceComparisonOperator_{a}_{b}"
            for a, b in (
                ("Lt", "LtE"),
                ("LtE", "Lt"),
                ("Gt", "GtE"),
                ("GtE", "Gt"),
                ("Lt", "GtE"),
                ("GtE", "Lt"),
                ("Gt", "LtE"),
                ("LtE", "Gt"),
                ("Lt", "Gt"),
                ("Gt", "Lt"),
                ("LtE", "GtE"),
                ("GtE", "LtE"),
                ("Eq", "NotEq"),
                ("NotEq", "Eq"),
                ("Is", "IsNot"),
                ("IsNot", "Is"),
            )
        ),
        # arithmetic and bit operations swapped for their mirror
        *(
            f"ReplaceBinaryOperator_{a}_{b}"
            for a, b in (
                ("Add", "Sub"),
                ("Sub", "Add"),
                ("Mul", "Div"),
                ("Div", "Mul"),
                ("FloorDiv", "Div"),
                ("Mul", "Add"),
                ("Mod", "FloorDiv"),
                ("BitAnd", "BitOr"),
                ("BitOr", "BitAnd"),
                ("BitXor", "BitOr"),
                ("LShift", "RShift"),
                ("RShift", "LShift"),
            )
        ),
        "ReplaceUnaryOperator_USub_UAdd",
        "ReplaceUnaryOperator_Delete_Not",
        "AddNot",
        "ReplaceAndWithOr",
        "ReplaceOrWithAnd",
        "ReplaceTrueWithFalse",
        "ReplaceFalseWithTrue",
        "ReplaceBreakWithContinue",
        "ReplaceContinueWithBreak",
        "ZeroIterationForLoop",
        "NumberReplacer",
    )
)


def _copy_tree(dest: Path) -> None:
    """The tree, with the built extension modules, at `dest` (made anew)."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", ".hypothesis", "build")
    for name in TREE:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=ignore)
        elif src.exists():
            shutil.copy2(src, dest / name)
    built = list((ROOT / "pyrtu").rglob("*.so"))
    if not built:
        sys.exit("mutate: the C core is not built (make setup first)")
    for so in built:  # copytree took them; say so if one is missing
        assert (dest / so.relative_to(ROOT)).exists(), so


def _env(tree: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree)
    env["PYRTU_REQUIRE_C"] = "1"
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def _pytest(tests: list[str]) -> list[str]:
    return [
        sys.executable,
        "-m",
        "pytest",
        "-x",
        "-q",
        "-p",
        "no:cacheprovider",
        # hypothesis works without its pytest plugin, whose import (2 s on a loaded
        # machine) is most of a short run: a test file that uses it imports it
        "-p",
        "no:hypothesispytest",
        "-p",
        "no:benchmark",
        "-m",
        "not rss",
        *tests,
    ]


# --------------------------------------------------------------------------- faults


@dataclass
class Fault:
    name: str
    file: str
    old: str
    new: str
    tests: list[str]
    why: str = ""


def _faults() -> list[Fault]:
    data = tomllib.loads((HERE / "faults.toml").read_text())
    return [Fault(**f) for f in data["fault"]]


def _build_core(tree: Path) -> None:
    subprocess.run(
        [sys.executable, "setup.py", "-q", "build_ext", "--inplace", "--force"],
        cwd=tree,
        env=_env(tree) | {"PYRTU_REQUIRE_C": "1"},
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )


def run_faults(names: list[str]) -> int:
    faults = [f for f in _faults() if not names or f.name in names]
    tree = WORK / "faults"
    _copy_tree(tree)
    built = {so: so.read_bytes() for so in (tree / "pyrtu").rglob("*.so")}
    survived = []
    for fault in faults:
        path = tree / fault.file
        original = path.read_text()
        if original.count(fault.old) != 1:
            print(
                f"FAULT NOT APPLIED  {fault.name}: `old` is found "
                f"{original.count(fault.old)} times in {fault.file} (it must be once)"
            )
            survived.append(fault.name)
            continue
        path.write_text(original.replace(fault.old, fault.new))
        try:
            if fault.file.startswith("csrc/"):
                _build_core(tree)
            t0 = time.monotonic()
            run = subprocess.run(
                _pytest(fault.tests),
                cwd=tree,
                env=_env(tree),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            took = time.monotonic() - t0
            if run.returncode == 1:  # tests ran and failed: killed
                first = next(
                    (line for line in run.stdout.splitlines() if line.startswith("FAILED")), ""
                )
                print(f"killed   {fault.name} ({took:.0f} s) {first[:150]}")
            else:  # 0: survived; other codes: the run itself broke, which proves nothing
                print(f"SURVIVED {fault.name} (pytest exit {run.returncode})")
                print("\n".join(run.stdout.splitlines()[-15:]))
                survived.append(fault.name)
        finally:
            path.write_text(original)
            for so, data in built.items():  # the core as built from the true sources
                so.write_bytes(data)
    print(
        f"{len(faults) - len(survived)} killed, {len(survived)} survived "
        f"of {len(faults)} hand-written faults"
    )
    return 1 if survived else 0


# --------------------------------------------------------------------------- generated


@dataclass
class Target:
    name: str
    modules: list[str]
    tests: list[str]
    timeout: float = 120.0
    results: list[dict[str, object]] = field(default_factory=list)


def _targets() -> list[Target]:
    data = tomllib.loads((HERE / "targets.toml").read_text())
    return [Target(name=name, **spec) for name, spec in data["target"].items()]


def _equivalents() -> list[dict[str, object]]:
    return list(tomllib.loads((HERE / "equivalent.toml").read_text()).get("equivalent", []))


def _survivors_again(tree: Path, target: Target, rest: bool = False) -> None:
    """The tree copied anew, the last session's survivors pending again.

    Refused (SystemExit) unless every mutated module is the one the session mutated
    and the session's test files are all among the target's test files now: then a
    mutant the session killed is still killed, and only the survivors need a run.
    With ``rest``, the verdicts all stay, and the mutants not judged yet are pending.
    """
    import sqlite3

    sessions = {f.name: f.read_bytes() for f in tree.glob("cr-*")}
    mutated = {m: (tree / m).read_bytes() for m in target.modules if (tree / m).exists()}
    _copy_tree(tree)
    for name, data in sessions.items():
        (tree / name).write_bytes(data)
    for module in target.modules:
        stem = module.replace("/", "_").removesuffix(".py")
        config = tree / f"cr-{stem}.toml"
        session = tree / f"cr-{stem}.sqlite"
        if not session.exists():  # a run stopped before this module began: no
            continue  # survivor to judge again; with `rest`, all of it is the rest
        if mutated.get(module) != (ROOT / module).read_bytes():
            raise SystemExit(
                f"mutate: {target.name}: {module} changed since the session; run it in full"
            )
        command = tomllib.loads(config.read_text())["cosmic-ray"]["test-command"]
        before = {arg for arg in shlex.split(command) if arg.startswith("tests/")}
        if not before <= set(target.tests):
            raise SystemExit(
                f"mutate: {target.name}: the session's tests {sorted(before - set(target.tests))}"
                " are no longer the target's; run it in full"
            )
    for session in sorted(tree.glob("cr-*.sqlite")):  # all checked: now re-open them
        with sqlite3.connect(session) as db:
            # the mutants a budget left unjudged stay so (not a new sample): parked
            # until the survivors are judged (`_unpark`); with `rest` only they run
            if rest:
                continue
            db.execute(
                "INSERT INTO work_results (job_id, worker_outcome, output) SELECT job_id,"
                " 'SKIPPED', ? FROM work_items WHERE job_id NOT IN"
                " (SELECT job_id FROM work_results)",
                (_PARKED,),
            )
            # the survivors, and the runs that timed out (under load: judged again);
            # not the survivors mutate/equivalent.toml explains (no test can kill one)
            equivalents = _equivalents()
            again = [
                job
                for job, module, operator, occurrence, row, col, definition, diff in db.execute(
                    "SELECT r.job_id, m.module_path, m.operator_name, m.occurrence,"
                    " m.start_pos_row, m.start_pos_col, m.definition_name, r.diff"
                    " FROM work_results r"
                    " JOIN mutation_specs m USING (job_id) WHERE r.test_outcome = 'SURVIVED'"
                )
                if not any(
                    _is(
                        e,
                        {
                            "module_path": module,
                            "operator_name": operator,
                            "occurrence": occurrence,
                            "start_pos": [row, col],
                            "definition_name": definition,
                        },
                        _line(tree, module, row),
                        diff or "",
                    )
                    for e in equivalents
                )
            ]
            db.executemany("DELETE FROM work_results WHERE job_id = ?", [(j,) for j in again])
            db.execute("DELETE FROM work_results WHERE output = ?", (_TIMEOUT,))


#: cosmic-ray's output for a test run it stopped at the target's timeout (it counts
#: it as killed; here it is incompetent: on a loaded machine a slow run is no kill)
_TIMEOUT = "timeout"

_PARKED = "not run: parked while the survivors are judged again"


def _unpark(session: Path) -> None:
    import sqlite3

    with sqlite3.connect(session) as db:
        db.execute("DELETE FROM work_results WHERE output = ?", (_PARKED,))


def _dump(cr: Path, tree: Path, session: Path) -> str:
    """cosmic-ray's JSON lines of ``session``: each mutant and its verdict."""
    return subprocess.run(
        [cr, "dump", session.name],
        cwd=tree,
        check=True,
        env=_env(tree),
        stdout=subprocess.PIPE,
        text=True,
    ).stdout


#: set when the run is stopped (Ctrl-C, SIGTERM): every target's `_exec` stops its
#: cosmic-ray and puts its module back, whichever thread it runs on (--jobs)
_STOPPING = threading.Event()


def _exec(cr: Path, tree: Path, config: Path, session: Path, module: str, budget: float) -> None:
    """`cosmic-ray exec`, stopped after `budget` minutes (0: none) or when the run is
    stopped (`_STOPPING`), with the mutated module put back as it was (cosmic-ray
    mutates it on disk); the mutants not yet run stay pending in the session, for
    `--rest`."""
    original = (tree / module).read_bytes()
    proc = subprocess.Popen(
        [cr, "exec", config.name, session.name], cwd=tree, env=_env(tree), start_new_session=True
    )
    deadline = time.monotonic() + budget * 60 if budget else None
    while True:
        try:
            code = proc.wait(timeout=1.0)
            break
        except subprocess.TimeoutExpired:
            late = deadline is not None and time.monotonic() >= deadline
            if not (late or _STOPPING.is_set()):
                continue
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        _stop_test_runs(tree)
        (tree / module).write_bytes(original)
        if _STOPPING.is_set():
            raise SystemExit(f"mutate: {module}: stopped; `--rest` judges what is left")
        print(f"mutate: {module}: stopped after {budget:g} min; the rest is not run")
        return
    if code != 0:
        raise SystemExit(f"mutate: cosmic-ray exec failed on {module} (exit {code})")


def _stop_test_runs(tree: Path) -> None:
    """Stop the test run cosmic-ray left in ``tree``: it starts each in a session of
    its own (to kill it at the timeout), which stopping cosmic-ray leaves running (a
    mutant that hangs would run on unsupervised).  Linux: every process whose working
    directory is the tree, with its process group."""
    root = tree.resolve()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if Path(os.readlink(entry / "cwd")) == root:
                os.killpg(os.getpgid(int(entry.name)), signal.SIGKILL)
        except OSError:  # gone meanwhile, or not ours to read
            continue


_IN_ANNOTATION = "in an annotation, never evaluated"


def _annotation_spans(path: Path) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """Where the annotations of the module at `path` are, as ((line, column), (line,
    column)) spans in characters, when it never evaluates them: with `from __future__
    import annotations` an annotation is a string, and nothing in pyrtu evaluates one
    (no get_type_hints), so a mutant inside it (`int | None` to `int & None`) changes
    nothing.  Empty for a module without that import (its annotations run)."""
    source = path.read_text()
    module = ast.parse(source)
    if not any(
        isinstance(node, ast.ImportFrom)
        and node.module == "__future__"
        and any(alias.name == "annotations" for alias in node.names)
        for node in module.body
    ):
        return []
    lines = source.splitlines()

    def column(line: int, offset: int) -> int:  # ast counts UTF-8 bytes, cosmic-ray characters
        return len(lines[line - 1].encode()[:offset].decode(errors="ignore"))

    spans = []
    for node in ast.walk(module):
        found: list[ast.expr | None] = []
        if isinstance(node, ast.arg):
            found.append(node.annotation)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            found.append(node.returns)
        elif isinstance(node, ast.AnnAssign):
            found.append(node.annotation)
        for expr in found:
            if expr is not None and expr.end_lineno is not None and expr.end_col_offset is not None:
                spans.append(
                    (
                        (expr.lineno, column(expr.lineno, expr.col_offset)),
                        (expr.end_lineno, column(expr.end_lineno, expr.end_col_offset)),
                    )
                )
    return spans


def _inside(spans: list[tuple[tuple[int, int], tuple[int, int]]], pos: tuple[int, int]) -> bool:
    return any(start <= tuple(pos) < end for start, end in spans)


def _baseline(tree: Path, target: Target) -> None:
    """The tests pass on the true code (else every mutant is "killed"): SystemExit if not."""
    base = subprocess.run(
        _pytest(target.tests),
        cwd=tree,
        env=_env(tree),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    if base.returncode != 0 or " passed" not in base.stdout.splitlines()[-1]:
        raise SystemExit(
            f"mutate: {target.name}: the tests fail on the true code:\n"
            + "\n".join(base.stdout.splitlines()[-20:])
        )


def _run_target(
    target: Target, survivors: bool = False, budget: float = 0.0, rest: bool = False
) -> Path:
    """cosmic-ray over one target in a tree copy of its own; the session's JSON dump.

    With `survivors`, the last session's survivors only (see `_survivors_again`);
    with `rest`, its mutants not judged yet; with `budget`, at most that many
    minutes a module (see `_exec`).
    """
    from cosmic_ray.work_db import WorkDB, use_db  # the tool, installed by make mutate
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    tree = WORK / f"tree-{target.name}"
    if survivors or rest:
        _survivors_again(tree, target, rest)
    else:
        _copy_tree(tree)
    out = WORK / f"{target.name}.jsonl"
    out.write_text("")
    for module in target.modules:
        stem = module.replace("/", "_").removesuffix(".py")
        config = tree / f"cr-{stem}.toml"
        session = tree / f"cr-{stem}.sqlite"
        if survivors and not session.exists():
            continue  # a module the stopped run never began: `--rest` runs it
        command = shlex.join(_pytest(target.tests))
        _baseline(tree, target)
        config.write_text(
            "[cosmic-ray]\n"
            f'module-path = "{module}"\n'
            f"timeout = {target.timeout}\n"
            "excluded-modules = []\n"
            f"test-command = {json.dumps(command)}\n"
            '[cosmic-ray.distributor]\nname = "local"\n'
        )
        cr = Path(sys.executable).with_name("cosmic-ray")
        if not (survivors or rest) or (rest and not session.exists()):
            subprocess.run(
                [cr, "init", config.name, session.name], cwd=tree, check=True, env=_env(tree)
            )
            spans = _annotation_spans(tree / module)
            with use_db(str(session), WorkDB.Mode.open) as db:
                items = list(db.pending_work_items)
                for skip, why in (
                    (
                        [i.job_id for i in items if i.mutations[0].operator_name not in OPERATORS],
                        "operator not kept",
                    ),
                    (
                        [
                            i.job_id
                            for i in items
                            if i.mutations[0].operator_name in OPERATORS
                            and _inside(spans, i.mutations[0].start_pos)
                        ],
                        _IN_ANNOTATION,
                    ),
                ):
                    db.set_multiple_results(
                        skip, WorkResult(output=why, worker_outcome=WorkerOutcome.SKIPPED)
                    )
        _exec(cr, tree, config, session, module, budget)
        if survivors:
            _unpark(session)
        dump = _dump(cr, tree, session)
        with out.open("a") as f:
            f.write(dump)
    return out


def _line(tree: Path, module: str, line: int) -> str:
    try:
        return (tree / module).read_text().splitlines()[line - 1].strip()
    except (OSError, IndexError):
        return ""


@dataclass
class Summary:
    target: str
    counts: dict[str, int]
    survivors: list[str]

    @property
    def score(self) -> float:
        judged = self.counts["killed"] + self.counts["survived"]
        return self.counts["killed"] / judged if judged else 0.0


def _is(entry: dict[str, object], mutation: dict[str, object], text: str, diff: str) -> bool:
    """Whether an entry of mutate/equivalent.toml names this mutant: its module,
    operator and line's text, and where the line alone is ambiguous (the same text in
    two functions, two operators of a kind on one line, a number moved up or down)
    the optional `definition` (the enclosing function, cosmic-ray's
    definition_name), `column` (where the mutated token starts), `occurrence`
    (cosmic-ray's count of the operator's sites in the module) and `mutated` (the
    line as the mutant has it)."""
    start = mutation["start_pos"]
    assert isinstance(start, list)
    mutated = [
        line[1:].strip()
        for line in diff.splitlines()
        if line.startswith("+") and not line.startswith("+++")
    ]
    return (
        entry["module"] == mutation["module_path"]
        and entry["operator"] == mutation["operator_name"]
        and str(entry["line"]).strip() == text
        and entry.get("definition", mutation["definition_name"]) == mutation["definition_name"]
        and entry.get("column", start[1]) == start[1]
        and entry.get("occurrence", mutation["occurrence"]) == mutation["occurrence"]
        and ("mutated" not in entry or [str(entry["mutated"]).strip()] == mutated)
    )


def _summarise(target: Target) -> Summary:
    tree = WORK / f"tree-{target.name}"
    equivalents = _equivalents()
    counts = {"killed": 0, "survived": 0, "equivalent": 0, "incompetent": 0, "not run": 0}
    survivors = []
    for raw in (WORK / f"{target.name}.jsonl").read_text().splitlines():
        item, result = json.loads(raw)
        if result is None:  # pending: the run was stopped by its budget
            counts["not run"] += 1
            continue
        if result["worker_outcome"] == "skipped":
            continue
        mutation = item["mutations"][0]
        module = mutation["module_path"]
        line = mutation["start_pos"][0]
        text = _line(tree, module, line)
        outcome = result["test_outcome"]
        if result["worker_outcome"] in ("exception", "abnormal") or result["output"] == _TIMEOUT:
            outcome = "incompetent"
        if outcome == "survived":
            match = next(
                (e for e in equivalents if _is(e, mutation, text, result.get("diff") or "")),
                None,
            )
            if match is not None:
                counts["equivalent"] += 1
                continue
            survivors.append(
                f"`{module}:{line}` {mutation['operator_name']}"
                f" (#{mutation['occurrence']}): `{text}`"
            )
        counts[outcome] = counts.get(outcome, 0) + 1
    return Summary(target.name, counts, survivors)


def run_generated(
    names: list[str], jobs: int, survivors: bool = False, budget: float = 0.0, rest: bool = False
) -> int:
    import concurrent.futures

    targets = [t for t in _targets() if not names or t.name in names]
    with concurrent.futures.ThreadPoolExecutor(max_workers=jobs) as pool:
        list(pool.map(lambda t: _run_target(t, survivors, budget, rest), targets))
    return report([t.name for t in targets])


_LISTED = re.compile(
    r"^- `(?P<module>[^:`]+):(?P<line>\d+)` (?P<operator>\S+) \(#(?P<occurrence>\d+)\): "
    r"`(?P<text>.*)`$"
)


def run_listed(names: list[str]) -> int:
    """Judge again the survivors docs/MUTATION.md lists for targets whose session is
    gone (a run on another machine): each is made anew by cosmic-ray (module,
    operator, occurrence; refused unless its line still reads as listed) and run
    against the tests as they are now.  The row keeps the sample's other figures: a
    survivor now killed moves to killed, one mutate/equivalent.toml explains to
    equivalent."""
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    text = REPORT.read_text()
    summaries = []
    for target in [t for t in _targets() if t.name in names]:
        row = next(line for line in text.splitlines() if line.startswith(f"| `{target.name}` |"))
        cells = [c.strip() for c in row.split("|")[2:7]]
        counts = dict(zip(("killed", "survived", "equivalent", "incompetent", "not run"),
                          map(int, cells), strict=True))  # fmt: skip
        section = text.split(f"### `{target.name}`\n", 1)[1].split("\n### ", 1)[0]
        listed = [m.groupdict() for m in map(_LISTED.match, section.splitlines()) if m]
        tree = WORK / f"tree-{target.name}-listed"
        _copy_tree(tree)
        _baseline(tree, target)
        cr = Path(sys.executable).with_name("cosmic-ray")
        judged: list[dict[str, object]] = []
        for module in sorted({str(x["module"]) for x in listed}):
            mine = [x for x in listed if x["module"] == module]
            for x in mine:
                if _line(tree, module, int(x["line"])) != x["text"]:
                    raise SystemExit(f"mutate: {module}:{x['line']} changed since the run")
            stem = module.replace("/", "_").removesuffix(".py")
            config, session = tree / f"cr-{stem}.toml", tree / f"cr-{stem}.sqlite"
            command = json.dumps(shlex.join(_pytest(target.tests)))
            config.write_text(
                f'[cosmic-ray]\nmodule-path = "{module}"\ntimeout = {target.timeout}\n'
                f"excluded-modules = []\ntest-command = {command}\n"
                '[cosmic-ray.distributor]\nname = "local"\n'
            )
            subprocess.run(
                [cr, "init", config.name, session.name], cwd=tree, check=True, env=_env(tree)
            )
            wanted = {(x["operator"], int(x["occurrence"])) for x in mine}
            with use_db(str(session), WorkDB.Mode.open) as db:
                other = [
                    i.job_id
                    for i in db.pending_work_items
                    if (i.mutations[0].operator_name, i.mutations[0].occurrence) not in wanted
                ]
                db.set_multiple_results(
                    other, WorkResult(output="not listed", worker_outcome=WorkerOutcome.SKIPPED)
                )
            _exec(cr, tree, config, session, module, 0)
            dump = _dump(cr, tree, session)
            judged += [json.loads(line) for line in dump.splitlines()]
        equivalents = _equivalents()
        survivors = []
        for item, result in judged:
            if result is None or result["worker_outcome"] == "skipped":
                continue
            mutation = item["mutations"][0]
            line_text = _line(tree, mutation["module_path"], mutation["start_pos"][0])
            counts["survived"] -= 1
            if (
                result["worker_outcome"] in ("exception", "abnormal")
                or result["output"] == _TIMEOUT
            ):
                counts["incompetent"] += 1
            elif result["test_outcome"] == "killed":
                counts["killed"] += 1
            elif any(_is(e, mutation, line_text, result.get("diff") or "") for e in equivalents):
                counts["equivalent"] += 1
            else:
                counts["survived"] += 1
                survivors.append(
                    f"`{mutation['module_path']}:{mutation['start_pos'][0]}` "
                    f"{mutation['operator_name']} (#{mutation['occurrence']}): `{line_text}`"
                )
        summaries.append(Summary(target.name, counts, survivors))
    _write_report(summaries, note="survivors re-judged")
    return 0


def report(names: list[str]) -> int:
    """docs/MUTATION.md from the targets' last runs (build/mutate/), with
    mutate/equivalent.toml as it is now."""
    targets = [t for t in _targets() if not names or t.name in names]
    missing = [t.name for t in targets if not (WORK / f"{t.name}.jsonl").exists()]
    if missing:
        raise SystemExit(f"mutate: no run to report for {', '.join(missing)}")
    summaries = [_summarise(t) for t in targets]
    _write_report(summaries)
    for s in summaries:
        c = s.counts
        print(
            f"{s.target}: {c['killed']} killed, {c['survived']} survived, "
            f"{c['equivalent']} equivalent, {c['incompetent']} incompetent, "
            f"{c['not run']} not run: score {100 * s.score:.1f} %"
        )
    return 0


def _write_report(summaries: list[Summary], note: str = "") -> None:
    """docs/MUTATION.md: the figures of the targets run now; other targets' rows kept."""
    stamp = time.strftime("%Y-%m-%d", time.gmtime()) + (f" ({note})" if note else "")
    rows = {}
    sections = {}
    if REPORT.exists():
        text = REPORT.read_text()
        for block in text.split("\n### ")[1:]:
            name = block.split("\n", 1)[0].strip("` ")
            sections[name] = "### " + block.rstrip() + "\n"
        for line in text.splitlines():
            if line.startswith("| `") and "|" in line[3:]:
                rows[line.split("`")[1]] = line
    for s in summaries:
        c = s.counts
        rows[s.target] = (
            f"| `{s.target}` | {c['killed']} | {c['survived']} | "
            f"{c['equivalent']} | {c['incompetent']} | {c['not run']} | {100 * s.score:.1f} % "
            f"| {stamp} |"
        )
        survivors = s.survivors or ["none"]
        sections[s.target] = f"### `{s.target}`\n\n" + "\n".join(f"- {x}" for x in survivors) + "\n"

    head = (HERE / "REPORT_HEAD.md").read_text()
    table = (
        "| target | killed | survived | equivalent | incompetent | not run | score | run |\n"
        "|---|---|---|---|---|---|---|---|\n" + "\n".join(rows[k] for k in sorted(rows))
    )
    body = "\n".join(sections[k] for k in sorted(sections))
    REPORT.write_text(f"{head}\n{table}\n\n## Survivors\n\n{body}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="kind", required=True)
    faults = sub.add_parser("faults", help="the hand-written faults (mutate/faults.toml)")
    faults.add_argument("names", nargs="*")
    generated = sub.add_parser("generated", help="cosmic-ray over mutate/targets.toml")
    generated.add_argument("names", nargs="*")
    generated.add_argument("--jobs", type=int, default=1)
    generated.add_argument(
        "--survivors",
        action="store_true",
        help="re-judge only the last session's survivors (modules unchanged, tests only grown)",
    )
    generated.add_argument(
        "--rest",
        action="store_true",
        help="judge the mutants the last session's budget left unjudged (its verdicts kept)",
    )
    generated.add_argument(
        "--budget",
        type=float,
        default=0.0,
        metavar="MINUTES",
        help="stop each module's run after MINUTES: a random sample of its mutants is judged",
    )
    listed = sub.add_parser(
        "listed", help="judge again the survivors docs/MUTATION.md lists (no session needed)"
    )
    listed.add_argument("names", nargs="+")
    again = sub.add_parser("report", help="docs/MUTATION.md from the targets' last runs")
    again.add_argument("names", nargs="*")
    args = parser.parse_args()

    # Ctrl-C or SIGTERM: each target's cosmic-ray is stopped and its mutated module put
    # back (`_exec`), so that `--rest` can go on from the sessions
    def stopping(signum: int, frame: object) -> None:
        _STOPPING.set()

    signal.signal(signal.SIGINT, stopping)
    signal.signal(signal.SIGTERM, stopping)
    if args.kind == "faults":
        return run_faults(args.names)
    if args.kind == "report":
        return report(args.names)
    if args.kind == "listed":
        return run_listed(args.names)
    if args.rest and args.survivors:
        parser.error("--rest and --survivors are two runs: --survivors first")
    return run_generated(args.names, args.jobs, args.survivors, args.budget, args.rest)


if __name__ == "__main__":
    sys.exit(main())
