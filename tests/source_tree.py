"""The checkout's Python modules under their import names, from pyproject.toml's package-dir map.

The top-level folders are the packages of the one ``embedrl`` namespace (``train/`` is ``embedrl.train``);
tools that find modules by folder name (mypy, an import-graph reader) are handed this map instead.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def package_dirs() -> dict[str, Path]:
    """Package name -> its folder, as pyproject.toml maps them (``embedrl.train`` -> ``train/``)."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    return {name: REPO / folder for name, folder in config["tool"]["setuptools"]["package-dir"].items()}


def _name(package: str, root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join([package, *parts])


def modules(with_tests: bool = True) -> dict[str, Path]:
    """Every Python module of the checkout, import name -> file (the tests as ``tests.*`` when asked)."""
    roots = dict(package_dirs())
    found: dict[str, Path] = {}
    for package, root in roots.items():
        inner = [other for other in roots.values() if other != root and other.is_relative_to(root)]
        for path in sorted(root.rglob("*.py")):
            if not any(path.is_relative_to(other) for other in inner):
                found[_name(package, root, path)] = path
    if with_tests:
        for path in sorted((REPO / "tests").rglob("*.py")):
            found[_name("tests", REPO / "tests", path)] = path
    return found
