"""Benchmark scripts: bad input is a one-line usage error (`evaluate_run.py` and others)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "evaluate_run.py"


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--episodes", "0"], "--episodes must be >= 1"),
        (["--checkpoints"], "no checkpoints rl_model_<steps>_steps.zip"),
        ([], "no saved model"),
    ],
)
def test_bad_input_is_a_usage_error(tmp_path: Path, arguments: list[str], message: str) -> None:
    command = [sys.executable, str(SCRIPT), str(tmp_path), "--env", "sb3_detc/LinearETC-v0", *arguments]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr
    missing = subprocess.run([*command[:2], str(tmp_path / "none"), *command[3:]], capture_output=True, text=True)
    assert missing.returncode == 2 and ("no run folder" in missing.stderr or "--episodes" in missing.stderr)


@pytest.mark.parametrize(
    ("script", "arguments", "message"),
    [
        ("value_of_information.py", ["--steps", "100"], "--steps must be more than the 200 steps of burn-in"),
        ("linear_pareto.py", ["--episodes", "0"], "--episodes must be >= 1"),
    ],
)
def test_other_benchmarks_check_their_numbers_first(script: str, arguments: list[str], message: str) -> None:
    command = [sys.executable, str(ROOT / "benchmarks" / script), *arguments]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 2 and message in done.stderr
