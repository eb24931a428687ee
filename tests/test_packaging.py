"""The package builds without packaging warnings, ships its data files and states one version everywhere."""

from __future__ import annotations

import configparser
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import sb3_detc

ROOT = Path(__file__).resolve().parents[1]


def test_the_wheel_builds_without_packaging_warnings_and_ships_the_data_files(tmp_path) -> None:
    command = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-v", str(ROOT)]
    result = subprocess.run(
        [*command, "-w", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    output = result.stdout + result.stderr
    for warning in ("BuildBackendWarning", "SetuptoolsDeprecationWarning", "absent from the `packages` configuration"):
        assert warning not in output, output
    (wheel,) = tmp_path.glob("sb3_detc-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {f"sb3_detc/{path.relative_to(ROOT / 'sb3_detc')}" for path in (ROOT / "sb3_detc").glob("*/*.yml")}
    assert {"sb3_detc/hyperparams/mappoc.yml", "sb3_detc/studies/multiwalker_paper.yml"} <= shipped <= names


def test_the_editable_install_prints_no_packaging_warnings(tmp_path) -> None:
    """``make install`` installs in editable mode: setuptools' editable notices are warnings that pip shows."""
    command = [sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--ignore-installed"]
    command += ["-e", str(ROOT)]  # into a folder of its own: the installed package stays as it is
    result = subprocess.run([*command, "--prefix", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    output = result.stdout + result.stderr
    for warning in ("BuildBackendWarning", "SetuptoolsDeprecationWarning", "Editable installation."):
        assert warning not in output, output


def test_the_version_is_the_top_release_of_the_changelog_of_setup_cfg_and_of_the_citation() -> None:
    releases = re.findall(
        r"^## Release (\S+) \((unreleased|\d{4}-\d{2}-\d{2})\)$", (ROOT / "CHANGELOG.md").read_text(), re.M
    )
    assert releases, "CHANGELOG.md has no '## Release X.Y.Z (date)' heading"
    assert releases[0][0] == sb3_detc.__version__
    setup = configparser.ConfigParser()
    setup.read(ROOT / "setup.cfg")
    assert setup["metadata"]["version"] in ("attr: sb3_detc.__version__", sb3_detc.__version__)
    citation = re.search(r"^version: (\S+)$", (ROOT / "CITATION.cff").read_text(), re.M)
    assert citation is not None and citation.group(1) == sb3_detc.__version__
