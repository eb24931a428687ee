"""Shared test settings."""

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

#: The repository's root.
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    """Small networks on a small machine: one thread is fastest and avoids oversubscription."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def run_benchmark() -> Callable[..., subprocess.CompletedProcess]:
    """Run a script of ``benchmarks/`` as a user does, in the repository's root with this checkout's package.

    The returned function takes the script's name, its arguments and ``check`` (raise if the
    script fails, default False), and returns the finished process with its output as text.
    """
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}

    def run(script: str, *arguments: str, check: bool = False) -> subprocess.CompletedProcess:
        command = [sys.executable, str(ROOT / "benchmarks" / script), *arguments]
        return subprocess.run(command, check=check, capture_output=True, text=True, cwd=ROOT, env=env)

    return run
