"""MkDocs hooks of the pyrtu site.  Two pages carry files that live outside docs/:
the landing page is README.md (docs/index.md says so), the benchmarks page includes
bench/RESULTS.md.  Their text is read here, and links are made to work on the site:
the README's links into docs/ become relative to the site, and a link to a file the
site carries under another name (bench/RESULTS.md, README.md) goes to its page."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
#: file outside docs/ -> the page that carries it
CARRIED = {"bench/RESULTS.md": "benchmarks.md", "README.md": "index.md"}
_INCLUDE = re.compile(r"^<!-- include: (\S+) -->$", re.M)


def on_page_markdown(markdown: str, page: Any, **_: Any) -> str:
    markdown = _INCLUDE.sub(lambda m: (ROOT / m.group(1)).read_text(), markdown)
    if page.file.src_uri == "index.md":
        markdown = markdown.replace("](docs/", "](")
    prefix = "../" * page.file.src_uri.count("/")
    pattern = r"\]\((?:\.\./)*(" + "|".join(re.escape(k) for k in CARRIED) + r")(#[\w-]+)?\)"

    def carried(m: re.Match[str]) -> str:
        return f"]({prefix}{CARRIED[m.group(1)]}{m.group(2) or ''})"

    return re.sub(pattern, carried, markdown)
