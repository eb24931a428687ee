"""``benchmarks/multiwalker_trigger_for_controller.py``: policies over options for a study's frozen controllers."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch as th

from sb3_detc.mappoc.policies import MlpHybridPolicy

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "multiwalker_trigger_for_controller.py"
TRIAL = ROOT / "benchmarks" / "studies" / "linear" / "trials" / "ppo_random_skip" / "seed1"


def test_only_the_policies_over_options_change_and_the_protocol_evaluates_them(tmp_path: Path) -> None:
    out, saved = tmp_path / "rows.json", tmp_path / "policies"
    command = [sys.executable, str(SCRIPT), "benchmarks/studies/linear", "--algorithm", "ppo_random_skip"]
    command += ["--seeds", "1", "1", "--timesteps", "4096", "--warm-up", "2048", "--out", str(out)]
    command += ["--save-dir", str(saved)]
    printed = subprocess.run(command, check=True, capture_output=True, text=True, cwd=ROOT).stdout
    (row,) = json.loads(out.read_text())  # the seed given twice runs once
    before = MlpHybridPolicy.load(str(TRIAL / "policy.pt"), device="cpu")
    after = MlpHybridPolicy.load(str(saved / row["saved"]), device="cpu")
    for net, changed in (("pi", False), ("mu", True), ("q", True)):
        same = all(th.equal(a, b) for a, b in zip(before.net_parameters(net), after.net_parameters(net), strict=True))
        assert same != changed, net
    metrics = row["metrics"]
    assert row["seed"] == 1 and 0.0 < metrics["savings"] < 1.0 and row["periodic_nearest"]["period"] >= 1
    assert row["env_kwargs"] == {"broadcast_cost": 0.03}  # the entry's cost
    assert row["periodic_nearest"]["package_travel"] is None  # the linear env reports none
    # the trial's controller, unchanged: every step and never as in the study's own evaluation
    study = json.loads((TRIAL / "evaluation.json").read_text())["metrics"]
    for mode in ("periodic_control_return", "never_control_return"):
        assert abs(metrics[mode] - study[mode]) < 1e-6 * max(1.0, abs(study[mode])), mode
    assert "| 1 | " in printed
    again = subprocess.run(command, check=True, capture_output=True, text=True, cwd=ROOT).stdout
    assert "1 of 1 jobs already in" in again  # resumed, not trained again


def test_an_unfinished_algorithm_is_a_usage_error() -> None:
    command = [sys.executable, str(SCRIPT), "benchmarks/studies/linear", "--algorithm", "nothing"]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    assert (
        done.returncode == 2 and "no finished trial of 'nothing' (algorithms: mappoc, ppo_random_skip)" in done.stderr
    )


def test_the_periodic_trigger_nearest_in_savings() -> None:
    import multiwalker_trigger_for_controller as script  # benchmarks/, on the path in conftest.py

    assert [script.nearest_period(s) for s in (0.0, 0.3, 0.5, 0.84, 0.875, 0.9, 0.99)] == [1, 2, 2, 6, 8, 10, 100]
    assert script.nearest_period(1.0) is None
