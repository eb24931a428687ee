"""``benchmarks/broadcast_synchrony.py``: do the agents of a trigger broadcast together, apart or independently?"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

SCRIPT = "broadcast_synchrony.py"


@pytest.fixture(scope="module")
def script(benchmark_module):
    """The benchmark script as a module."""
    return benchmark_module(SCRIPT)


def test_schedules_in_phase_and_staggered_are_the_extremes(script) -> None:
    in_phase = np.tile([[1, 1, 1], [0, 0, 0], [0, 0, 0]], (4, 1))  # every third step, all together
    staggered = np.tile(np.eye(3, dtype=int), (4, 1))  # every third step, one after another
    assert script.synchrony(in_phase)["together"] == 1.0 and script.synchrony(staggered)["together"] == 0.0
    for options in (in_phase, staggered):  # both at a third: 1 - (2/3)^2 if they were independent
        result = script.synchrony(options)
        assert result["rates"] == pytest.approx([1 / 3] * 3) and result["independent"] == pytest.approx(5 / 9)


def test_broadcasts_together_and_independent_timing_by_hand(script) -> None:
    options = np.array([[1, 1, 0], [1, 0, 0], [0, 0, 0], [0, 1, 1]])  # 5 broadcasts, 4 with another's
    result = script.synchrony(options)
    assert result["together"] == pytest.approx(4 / 5)
    rates = [0.5, 0.5, 0.25]  # agent 0 alone with probability 0.5 * 0.75; 1 the same; 2: 0.5 * 0.5
    alone = [0.5 * 0.75, 0.5 * 0.75, 0.5 * 0.5]
    counts = [2, 2, 1]
    assert result["rates"] == pytest.approx(rates)
    assert result["independent"] == pytest.approx(sum((1 - a) * c for a, c in zip(alone, counts, strict=True)) / 5)
    assert np.isnan(script.synchrony(np.zeros((5, 3)))["together"])


def test_saved_policies_run_in_their_studys_env(tmp_path: Path, run_benchmark) -> None:
    policy = "benchmarks/studies/linear_lqr_rate/trials/target_90/seed0/policy.pt"
    out = tmp_path / "rows.json"
    done = run_benchmark(SCRIPT, policy, policy, "--episodes", "2", "--out", str(out), check=True)
    first, second = json.loads(out.read_text())
    assert first == second and done.stdout.count("| policy.pt |") == 2  # seeded: the same options twice
    assert len(first["rates"]) == 3 and 0 < first["together"] < 1
