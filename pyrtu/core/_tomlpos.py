"""Where a key stands in a TOML file (a leaf module): the line an error message names
(file:line: key), for every TOML file pyrtu reads (configurations, templates,
policies).  ``tomllib`` gives values, not positions."""

from __future__ import annotations

import re


def locate(text: str, table: str, key: str | None, array_index: int | None = None) -> int | None:
    """The line (1-based) of ``key`` in ``[table]`` (``array_index``: in the n-th
    ``[[table]]``), or of the header; an inline table's key is found on its line."""
    if array_index is None:
        header = re.compile(r"^\s*\[\s*" + re.escape(table) + r"\s*\]")
    else:
        header = re.compile(r"^\s*\[\[\s*" + re.escape(table) + r"\s*\]\]")
    lines = text.splitlines()
    seen = -1
    for n, line in enumerate(lines):
        if not header.match(line):
            continue
        seen += 1
        if array_index is not None and seen != array_index:
            continue
        if key is None:
            return n + 1
        first = key.split(".")[0]
        want = re.compile(r"^\s*" + re.escape(first) + r"\s*=")
        for m in range(n + 1, len(lines)):
            if lines[m].lstrip().startswith("["):
                break
            if want.match(lines[m]):
                return m + 1
        return n + 1
    return None


__all__ = ["locate"]
