"""``benchmarks/evaluate_saved_model.py``: a saved model evaluated with the study's protocol, from the command line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc import MAPPOC
from sb3_detc.study.trial import MODES, evaluate_policy_modes

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "evaluate_saved_model.py"
ENV_ID = "sb3_detc/LinearETC-v0"


def test_the_script_writes_the_study_protocol_of_a_saved_model(tmp_path: Path) -> None:
    env_kwargs = {"n_agents": 2, "max_cycles": 12, "broadcast_cost": 1e-3}
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **env_kwargs), n_steps=16, policy_kwargs={"net_arch": [8]})
    model.save(tmp_path / "model.zip")
    out = tmp_path / "evaluation.json"
    command = [sys.executable, str(SCRIPT), str(tmp_path / "model.zip"), "--env", ENV_ID, "--episodes", "3"]
    command += ["--seed", "40", "--out", str(out), "--env-kwargs", "n_agents=2", "max_cycles=12", "broadcast_cost=1e-3"]
    printed = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    result = json.loads(out.read_text())
    assert result["episodes"] == 3 and result["seed"] == 40 and set(result["modes"]) == set(MODES)
    assert all(len(mode["control_return"]) == 3 for mode in result["modes"].values())
    assert f"control_return: {result['metrics']['control_return']:.4g}" in printed
    # The same as the study's protocol run here on the env with these settings (the cost included),
    # the options sampled from mu too: the episodes' seeds seed them.
    expected = evaluate_policy_modes(MAPPOC.load(tmp_path / "model.zip").policy, gym.make(ENV_ID, **env_kwargs), 3, 40)
    assert set(result["metrics"]) == set(expected["metrics"])
    for metric, value in expected["metrics"].items():
        assert result["metrics"][metric] == pytest.approx(value, rel=1e-6), metric
    # A model of the baseline: its own options are the random trigger it trained with.
    subprocess.run([*command, "--skip-prob", "1.0"], check=True, capture_output=True)
    assert json.loads(out.read_text())["metrics"]["savings"] == 1.0


def test_the_script_rejects_settings_without_a_value(tmp_path: Path) -> None:
    command = [sys.executable, str(SCRIPT), str(tmp_path / "model.zip"), "--env", ENV_ID, "--out", str(tmp_path / "x")]
    done = subprocess.run([*command, "--env-kwargs", "n_agents"], capture_output=True, text=True)
    assert done.returncode == 2 and "key=value" in done.stderr
    done = subprocess.run([*command, "--episodes", "0"], capture_output=True, text=True)
    assert done.returncode == 2 and "--episodes must be >= 1" in done.stderr
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 2 and "no saved model" in done.stderr
