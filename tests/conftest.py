"""Shared test settings."""

import sys
from pathlib import Path

import pytest
import torch

# The benchmark scripts import their sibling modules (``resumable``) as they do when run as scripts.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    """Small networks on a small machine: one thread is fastest and avoids oversubscription."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
