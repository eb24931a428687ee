"""``benchmarks/paired_confirmation.py``: learned triggers against a family on more episodes, their noise counted."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sb3_detc.study.report import crossed_interval

SCRIPT = "paired_confirmation.py"
STUDY = "benchmarks/studies/linear_lqr_rate"
ARM = "predictive_imitated_90"


def test_an_arm_is_compared_on_new_episodes_and_its_results_are_read_again(run_benchmark, tmp_path: Path) -> None:
    out = tmp_path / "confirmation.json"
    arguments = ("--arms", ARM, "--episodes", "2", "--seed", "30000", "--cpus", "2", "--out", str(out))
    done = run_benchmark(SCRIPT, STUDY, *arguments, check=True)
    assert "5 trials, 5 to evaluate on 2 episodes" in done.stdout
    report = json.loads(out.read_text())["arms"][ARM]
    assert report["seeds"] == [f"seed{k}" for k in range(5)] and report["new"]["episodes"] == 2
    trials = Path(STUDY) / "trials" / ARM
    study = [json.loads((trials / f"seed{k}" / "evaluation.json").read_text())["metrics"] for k in range(5)]
    expected = [m["control_return"] - m["fixed_predictive_control_return"] for m in study]
    assert report["study"]["learned"]["per_seed"] == pytest.approx(expected, abs=1e-6)  # episodes rounded
    for k in range(5):
        new = json.loads((tmp_path / "confirmation" / ARM / f"seed{k}.json").read_text())
        assert len(new["modes"]["learned"]["control_return"]) == 2 and new["seed"] == 30000
        metrics = new["metrics"]
        gap = metrics["control_return"] - metrics["fixed_predictive_control_return"]
        assert report["new"]["learned"]["per_seed"][k] == pytest.approx(gap, abs=1e-6)
    gaps = [
        np.subtract(e["modes"]["learned"]["control_return"], e["modes"]["fixed_predictive"]["control_return"])
        for e in (json.loads((tmp_path / "confirmation" / ARM / f"seed{k}.json").read_text()) for k in range(5))
    ]
    assert report["new"]["learned"]["interval_seeds_and_episodes"] == list(crossed_interval(np.array(gaps)))
    again = run_benchmark(SCRIPT, STUDY, *arguments, check=True)
    assert "5 trials, 0 to evaluate" in again.stdout
    assert json.loads(out.read_text())["arms"][ARM] == report


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--arms", "nothing"], "not algorithms of benchmarks/studies/linear_lqr_rate: nothing"),
        (["--arms", ARM, "--family", "send_on_delta"], "does not compare 'send_on_delta'"),
        (["--arms", ARM, "--episodes", "1"], "--episodes must be at least 2"),
        (["--arms", ARM, "--cpus", "0"], "--cpus must be at least 1"),
    ],
)
def test_bad_input_is_a_usage_error(run_benchmark_here, tmp_path: Path, arguments: list[str], message: str) -> None:
    done = run_benchmark_here(SCRIPT, STUDY, *arguments, "--out", str(tmp_path / "x.json"))
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr
