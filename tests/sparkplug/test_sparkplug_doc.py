"""docs/sparkplug.md's conformance table: every test it names exists, every row
is a tck-id of chapters 4-6 once, and the counts it states are the table's."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent
DOC = ROOT / "docs" / "sparkplug.md"
HERE = Path(__file__).resolve().parent


def _rows() -> list[list[str]]:
    rows = []
    for line in DOC.read_text(encoding="utf-8").splitlines():
        if line.startswith("| ") and "`tck-id-" in line:
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]
            rows.append(cells)
    return rows


def _tests() -> set[str]:
    names = set()
    for path in HERE.glob("test_*.py"):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.FunctionDef) and node.name.startswith("test_"):
                names.add(node.name)
    return names


def test_every_test_the_table_names_exists() -> None:
    tests = _tests()
    rows = _rows()
    assert len(rows) > 200  # chapters 4-6 hold 274 tck-id statements
    named = {t for r in rows for t in re.findall(r"`(test_\w+)`", r[3])}
    assert named and named <= tests, sorted(named - tests)


def test_each_tck_id_once_and_the_stated_counts_are_the_table_s() -> None:
    rows = _rows()
    ids = [re.search(r"`(tck-id-[\w-]+)`", r[1]).group(1) for r in rows]  # type: ignore[union-attr]
    assert len(ids) == len(set(ids))
    assert {r[0] for r in rows} == {"4", "5", "6"}
    covered = sum(1 for r in rows if "`test_" in r[3])
    by_construction = sum(1 for r in rows if r[3].startswith("by construction"))
    for r in rows:  # each row: tests, or a reason why not
        assert "`test_" in r[3] or r[3].startswith(("n/a: ", "by construction")), r
    text = DOC.read_text(encoding="utf-8")
    stated = re.search(
        r"\*\*(\d+) of (\d+)\s+applicable statements are checked by a test\*\*", text
    )
    assert stated is not None
    assert (int(stated.group(1)), int(stated.group(2))) == (covered, covered + by_construction)
    assert f"({len(rows)} statements in all" in text
