"""setup.cfg against the code: every package that ``install_requires`` lists is one that sb3_detc imports."""

from __future__ import annotations

import ast
import configparser
import functools
import importlib.metadata
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def install_requires() -> list[str]:
    """The distribution names in setup.cfg's ``install_requires`` (versions and extras left out)."""
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    lines = [line.strip() for line in config["options"]["install_requires"].splitlines()]
    return [re.match(r"[A-Za-z0-9_.-]+", line).group() for line in lines if line]


@functools.cache
def imported_modules(folder: Path) -> frozenset[str]:
    """The top-level names of every absolute import in the Python files under a folder (in functions as well)."""
    names = set()
    for path in folder.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                names |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return frozenset(names)


def normalised(name: str) -> str:
    """A distribution name as the packaging standards compare it (PEP 503)."""
    return re.sub(r"[-_.]+", "-", name).lower()


@functools.cache
def installed_modules() -> dict[str, set[str]]:
    """Installed distribution (normalised name) -> the importable top-level names it provides."""
    modules: dict[str, set[str]] = {}
    for module, distributions in importlib.metadata.packages_distributions().items():
        for distribution in distributions:
            modules.setdefault(normalised(distribution), set()).add(module)
    return modules


def test_imports_are_found_in_functions_and_relative_ones_are_left_out(tmp_path: Path) -> None:
    lines = [
        "import numpy as np",
        "from . import sibling",
        "def later():",
        "    from ray import tune",
        "    import scipy.linalg",
    ]
    (tmp_path / "module.py").write_text("\n".join(lines) + "\n")
    assert imported_modules(tmp_path) == {"numpy", "ray", "scipy"}


@pytest.mark.parametrize("requirement", install_requires())
def test_every_required_package_is_imported_by_the_package(requirement: str) -> None:
    modules = installed_modules().get(normalised(requirement), set())
    assert modules, f"{requirement} (install_requires) is not installed here"
    assert modules & imported_modules(ROOT / "sb3_detc"), (
        f"sb3_detc imports none of {sorted(modules)}: move {requirement} to the extra that uses it"
    )
