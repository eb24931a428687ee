"""``benchmarks/multiwalker_trigger_for_controller.py``: policies over options for a study's frozen controllers."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_detc import MAPPOC
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.triggers import PeriodicTrigger

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


def test_progress_reports_every_given_rollout_with_the_last_rollouts_savings(capsys) -> None:
    import multiwalker_trigger_for_controller as script

    env = make_vec_env("sb3_detc/LinearETC-v0", n_envs=1, env_kwargs={"n_agents": 2, "max_cycles": 20})
    model = MAPPOC("MlpHybridPolicy", env, n_steps=8, batch_size=8, n_epochs=1, seed=0)
    model.set_fixed_trigger(PeriodicTrigger(4))  # a message every 4th step: savings 0.75 in every rollout
    model.learn(8 * 5, callback=script.Progress("tiny", every=2))
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(",")[0] for line in lines] == ["tiny: 16 steps", "tiny: 32 steps"]
    assert all("savings in the last rollout 0.750" in line for line in lines)
