"""The documentation site (#32.3): ``mkdocs build --strict`` with zero warnings, every
page of docs/ in the navigation, and every public name in the API reference.

The site is built once, here, the way ``make docs`` builds it (mkdocs.yml), into a
scratch directory; the reference comes from the docstrings (mkdocstrings), and its
inventory (``objects.inv``, the identifiers the site documents) is read back."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import types
import typing
import zlib
from pathlib import Path

import pytest

yaml = pytest.importorskip("yaml")  # mkdocs's own dependency

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def nav_pages() -> list[str]:
    """The pages of mkdocs.yml's navigation, in order (paths under docs/)."""
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    out: list[str] = []

    def walk(node: object) -> None:
        if isinstance(node, str):
            out.append(node)
        elif isinstance(node, list):
            for item in node:
                walk(item)
        elif isinstance(node, dict):
            for value in node.values():
                walk(value)

    walk(config["nav"])
    return out


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", PYTHONPATH=str(ROOT))
    r = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    return out, r.stdout + r.stderr


def inventory(site_dir: Path) -> set[str]:
    """The identifiers of objects.inv (Sphinx inventory v2: four header lines, then
    zlib-compressed lines ``name domain:role priority uri dispname``)."""
    data = (site_dir / "objects.inv").read_bytes()
    start = 0
    for _ in range(4):
        start = data.index(b"\n", start) + 1
    return {line.split()[0] for line in zlib.decompress(data[start:]).decode().splitlines()}


def test_the_site_builds_with_no_warning(site: tuple[Path, str]) -> None:
    site_dir, log = site
    assert "WARNING" not in log, log
    assert (site_dir / "index.html").is_file()
    # the landing page is the README, its links into docs/ made relative to the site
    index = (site_dir / "index.html").read_text()
    assert "Set-up: two commands" in index and 'href="getting-started/"' in index


def test_every_page_is_in_the_navigation() -> None:
    pages = set(nav_pages())
    on_disk = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert on_disk - pages == set(), "pages missing from mkdocs.yml's nav"
    assert pages - on_disk == set(), "nav entries without a page"


def reference_modules() -> list[str]:
    return [Path(p).stem for p in nav_pages() if p.startswith("reference/")]


def test_every_public_module_has_a_reference_page() -> None:
    """A module or package of pyrtu with an ``__all__`` is public: it has a page; a
    deprecated path (tests/test_public_paths.py) has none."""
    from test_public_paths import DEPRECATED_FACES

    documented = set(reference_modules())
    assert documented & set(DEPRECATED_FACES) == set()
    public = {"pyrtu"}
    for path in sorted((ROOT / "pyrtu").rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if any(p.startswith("_") for p in parts) or parts[-1] == "__main__":
            continue
        name = ".".join(parts)
        is_package = path.name == "__init__.py"
        if (is_package or len(parts) == 2) and "__all__" in path.read_text():
            public.add(name)
    public -= set(DEPRECATED_FACES)
    assert public - documented == set()


def test_every_public_name_is_in_the_reference(site: tuple[Path, str]) -> None:
    site_dir, _log = site
    names = inventory(site_dir)
    missing = []
    for module_name in reference_modules():
        module = importlib.import_module(module_name)
        page = (DOCS / "reference" / f"{module_name}.md").read_text()
        for name in module.__all__:
            obj = getattr(module, name)
            if isinstance(obj, types.GenericAlias | types.UnionType | typing._GenericAlias):  # type: ignore[attr-defined]
                ok = f"`{name}`" in page  # a type alias: described on its page
            else:
                where = (
                    obj.__name__
                    if isinstance(obj, types.ModuleType)
                    else f"{getattr(obj, '__module__', '')}.{getattr(obj, '__qualname__', '')}"
                )
                ok = f"{module_name}.{name}" in names or where in names
            if not ok:
                missing.append(f"{module_name}.{name}")
    assert missing == []
