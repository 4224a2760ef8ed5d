"""Lay out the installed package as one folder of links, for tools that find modules by path.

``pyproject.toml`` maps folders to import names (``services/X`` is ``lelsonar.X``); import-linter and
mypy walk folders and know nothing of that map.  ``python tools/package_tree.py DIR`` makes
``DIR/lelsonar`` whose entries link to the real folders and files, so both see every module once under
its import name.
"""

from __future__ import annotations

import shutil
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def build(target: Path) -> Path:
    """Make ``target/lelsonar`` from ``[tool.setuptools] package-dir``; return ``target``."""
    package_dir = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    top = target / "lelsonar"
    if top.exists():
        shutil.rmtree(top)
    top.mkdir(parents=True)
    for entry in (ROOT / package_dir["lelsonar"]).iterdir():
        if entry.name != "__pycache__":
            (top / entry.name).symlink_to(entry)
    for name, folder in package_dir.items():
        if name != "lelsonar":
            link = top.joinpath(*name.split(".")[1:])
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to(ROOT / folder)
    return target


if __name__ == "__main__":
    print(build(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "build" / "package-tree"))
