"""bench/RESULTS.md's sections: a benchmark's section replaced where it stands."""

from __future__ import annotations

from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


def write_section(heading: str, text: str, results: Path = RESULTS) -> None:
    """The section under ``heading`` (up to the next ``## ``) replaced by ``text`` where
    it is, or ``text`` added at the end."""
    old = results.read_text()
    i = old.find(heading)
    if i < 0:
        results.write_text(old.rstrip("\n") + "\n\n" + text)
        return
    j = old.find("\n## ", i + len(heading))
    rest = old[j + 1 :] if j >= 0 else ""
    results.write_text(old[:i] + text.rstrip("\n") + "\n" + ("\n" + rest if rest else ""))
