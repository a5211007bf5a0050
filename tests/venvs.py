"""Fresh virtual environments without an index: what they need copied from this one.

A wheel install is the wheel's files unpacked into site-packages plus its .dist-info;
copying an installed distribution's files is that install again, with no index and no
network.  Used by tests/test_packaging.py and bench/bench_install.py.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name


def closure(names: list[str]) -> list[metadata.Distribution]:
    """The installed distributions of `names` and of what they require, transitively."""
    found: dict[str, metadata.Distribution] = {}
    todo = [Requirement(n) for n in names]
    while todo:
        req = todo.pop()
        key = canonicalize_name(req.name)
        if key in found or (req.marker is not None and not req.marker.evaluate({"extra": ""})):
            continue
        dist = metadata.distribution(req.name)  # PackageNotFoundError: `make setup` missed it
        assert dist.version in req.specifier, f"{req}: {dist.version} installed"
        found[key] = dist
        todo += [Requirement(r) for r in dist.requires or ()]
    return list(found.values())


def install_copy(dist: metadata.Distribution, site: Path) -> None:
    """Install `dist` into `site` from its files in this environment (as pip laid them
    out).  Console scripts (outside site-packages) are left out."""
    for rel in dist.files or ():
        if ".." in rel.parts or rel.suffix == ".pyc":
            continue
        dest = site / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(str(dist.locate_file(rel)), dest)


def venv_with(base: Path, names: list[str]) -> Path:
    """A fresh venv under `base` holding pip and `names` with what they require, copied
    from this environment; its python.  Nothing else: not the system interpreter's
    packages, nor the setuptools a Python 3.11 venv would bring."""
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = Path(
        subprocess.run(
            [str(py), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    assert site.is_relative_to(venv), site
    for dist in closure([*names, "pip"]):
        install_copy(dist, site)
    return py
