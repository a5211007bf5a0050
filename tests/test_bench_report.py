"""bench/RESULTS.md is a report of one run of bench/report.py, and nothing else.

Checked without running a benchmark: the committed RESULTS.md is exactly what the
generator (bench/report_render.py) writes from the committed run (bench/results/);
every section names its command and its date; every target's figure comes from a
section that ran in that run; every benchmark bench/README.md lists is one the
generator runs; and the CRC target divides like by like, judged at its boundary.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "bench"
sys.path.insert(0, str(BENCH))

import report  # noqa: E402
import report_render  # noqa: E402

RESULTS = BENCH / "RESULTS.md"


def sections(text: str) -> dict[str, str]:
    """The ``## `` sections of ``text``, by title."""
    parts = re.split(r"^## ", text, flags=re.M)[1:]
    return {p.split("\n", 1)[0]: p.split("\n", 1)[1] for p in parts}


def test_results_md_is_what_the_generator_writes_from_the_committed_run() -> None:
    assert RESULTS.read_text() == report_render.render_dir(report.RAW), (
        "bench/RESULTS.md differs from what bench/report.py writes from bench/results/: "
        "do not edit it by hand; run `python bench/report.py --render` (or `make bench`)"
    )


def test_every_section_names_its_command_and_its_date() -> None:
    found = sections(RESULTS.read_text())
    titles = [s.title for s in report_render.SECTIONS]
    assert list(found) == ["Targets", *titles]
    for title in titles:
        body = found[title]
        assert re.search(r"^Command: (`python [^`]+`|not run)$", body, re.M), title
        date = re.search(r"^Date: (.*)$", body, re.M)
        assert date is not None, title
        assert re.match(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC, ", date[1]) or date[1] == (
            f"{report_render.NOT_MEASURED}."
        ), (title, date[1])


def test_the_header_names_the_machine_and_its_load() -> None:
    head = RESULTS.read_text().split("\n## ", 1)[0]
    for label in ("CPU:", "kernel:", "Python ", "gcc:", "load average (1, 5, 15 min):"):
        assert label in head, label


def test_every_target_figure_comes_from_a_section_of_the_same_run_that_ran() -> None:
    text = RESULTS.read_text()
    found = sections(text)
    anchors = {report_render.anchor(title): title for title in found}
    rows = [
        line
        for line in found["Targets"].splitlines()
        if line.startswith("| ") and "---" not in line
    ][1:]  # the header row
    assert len(rows) == sum(len(s.target_texts) for s in report_render.SECTIONS)
    for row in rows:
        target, figure, met, link = (cell.strip() for cell in row.strip("|").split(" | "))
        title = anchors[re.fullmatch(r"\[.*\]\(#(.*)\)", link)[1]]  # type: ignore[index]
        ran = "Command: `python " in found[title] and "The benchmark failed" not in found[title]
        if figure == report_render.NOT_MEASURED:
            assert met == "-", target
        else:
            assert ran, f"{target}: a figure, but its section {title!r} did not run"
            assert met in ("met", "not met", "reported") or met.startswith(("met ", "not met ")), (
                met
            )


def test_every_benchmark_of_the_readme_is_run_by_the_generator() -> None:
    readme = (BENCH / "README.md").read_text()
    listed = readme.split("## Benchmarks", 1)[1].split("\n## ", 1)[0]
    scripts = set(re.findall(r"^\| `([a-z_]+\.py)`", listed, re.M))
    run = {
        arg.rsplit("/", 1)[-1] for b in report.BENCHMARKS for arg in b.argv if arg.endswith(".py")
    }
    assert scripts, "bench/README.md lists no benchmark"
    assert scripts - {"report.py"} <= run, scripts - run
    assert {s.name for s in report_render.SECTIONS} == set(report.BY_NAME)


def _crc_run(crc_ns: float, builtin_ns: float, cffi_ns: float) -> dict[str, Any]:
    def row(name: str, ns: float) -> dict[str, Any]:
        return {
            "name": f"{name}[8 B]",
            "group": "crc16 8 B",
            "stats": {"median": ns * 1e-9},
            "extra_info": {"bytes": 8},
        }

    rows = [
        row("test_c_crc16", crc_ns),
        row("test_builtin_noop", builtin_ns),
        row("test_c_noop_same_arguments", cffi_ns),
    ]
    return {"benchmarks": rows}


@pytest.mark.parametrize(("crc_ns", "verdict"), [(130.0, "met"), (131.0, "not met")])
def test_the_crc_builtin_is_judged_against_an_empty_builtin_call_at_the_bound(
    crc_ns: float, verdict: str
) -> None:
    """1.3x of an empty builtin call is met, 1.31x is not; the empty cffi call (three
    times slower here) never enters the ratio."""
    small, _large = report_render.crc_targets(_crc_run(crc_ns, 100.0, 300.0))
    assert small == (
        f"{crc_ns:.0f} ns against 100 ns for an empty builtin call: **{crc_ns / 100:.2f}x**",
        verdict,
    )


def test_a_benchmark_that_did_not_run_leaves_its_targets_not_measured(tmp_path: Path) -> None:
    machine = json.loads((report.RAW / "machine.json").read_text())
    (tmp_path / "machine.json").write_text(json.dumps(machine))
    failed = {
        "name": "core", "command": "python -m pytest bench/bench_core.py",
        "started": "2026-01-01 00:00 UTC", "duration_s": 1.0, "load_before": [0, 0, 0],
        "load_after": [0, 0, 0], "error": "exit status 1", "log_tail": ["boom"], "data": None,
    }  # fmt: skip
    (tmp_path / "core.json").write_text(json.dumps(failed))
    text = report_render.render_dir(tmp_path)
    rows = [line for line in text.splitlines() if line.startswith("| ") and "](#" in line]
    assert rows and all(f"| {report_render.NOT_MEASURED} | - |" in line for line in rows)
    assert "The benchmark failed (exit status 1)" in sections(text)["Framer and stream parser"]


SCRIPTS = sorted(
    p.relative_to(ROOT).as_posix()
    for p in [*BENCH.glob("*.py"), *BENCH.glob("investigations/*.py")]
    if "argparse" in p.read_text()
)


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_bench_script_answers_help(script: str) -> None:
    """``--help`` prints the usage and exits 0 (argparse formats help texts with ``%``:
    one unescaped in a help text made ``--help`` a traceback)."""
    done = subprocess.run(
        [sys.executable, script, "--help"], cwd=ROOT, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("usage:"), done.stdout[:200]
