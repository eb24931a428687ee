"""``python -m sb3_detc.evaluate``: a saved model or policy evaluated with the package's protocol."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest
import torch as th
from stable_baselines3 import PPO

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc import MAPPOC, evaluate
from sb3_detc.evaluation import MODES, evaluate_policy_modes

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "benchmarks" / "studies" / "multiwalker_paper"
ENV_ID = "sb3_detc/LinearETC-v0"


def refused(argv: list[str], capsys: pytest.CaptureFixture) -> str:
    """The one line the command refuses ``argv`` with."""
    with pytest.raises(SystemExit) as stopped:
        evaluate.main(argv)
    assert stopped.value.code == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "Traceback" not in error, error
    return error


def test_a_shipped_policy_is_evaluated_as_its_study_did(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The env, its settings and the trigger come from the study; short episodes keep it fast."""
    out = tmp_path / "evaluation.json"
    policy = STUDY / "trials" / "mappoc_paper" / "seed0" / "policy.pt"
    evaluate.main([str(policy), "--episodes", "1", "--env-kwargs", "max_cycles=8", "--out", str(out)])
    printed = capsys.readouterr().out
    result = json.loads(out.read_text())
    assert result["seed"] == 10_000 and result["episodes"] == 1  # the study's evaluation seed
    assert result["options"] == "sampled"  # as the study evaluated the paper's policies
    learned_modes = [mode for mode in MODES if mode != "thresholded"]  # the study compared no fixed families
    assert list(result["modes"]) == learned_modes and result["modes"]["learned"]["length"] == [8]
    assert "broadcast_cost=0.25, max_cycles=8" in printed  # the study's settings, and the one given here
    for mode in learned_modes:
        assert f"  {mode}: control return" in printed  # a line as each mode finishes
        assert f"| {mode} | {result['metrics'].get(f'{mode}_return', result['metrics']['return']):.2f} |" in printed
    assert "| mode | return | control return | savings | package travel | fall rate |" in printed
    assert result["metrics"]["return"] < result["metrics"]["control_return"]  # broadcasts cost 0.25 each
    assert "option_state_information" in result["metrics"] and "bits" in printed
    # The baseline of the same study: its learned mode is the random trigger it trained with.
    baseline = STUDY / "trials" / "random_skip_paper" / "seed2" / "policy.pt"
    evaluate.main([str(baseline), "--episodes", "1", "--env-kwargs", "max_cycles=8", "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["options"] == "fixed trigger" and "mode" not in result["modes"]
    assert "the fixed trigger it trained with" in capsys.readouterr().out


def test_a_policy_of_a_study_with_fixed_families_is_compared_with_them(tmp_path: Path, capsys) -> None:
    """The study's families at the learned rate, and mu thresholded at it; ``--fixed-families`` chooses others."""
    out = tmp_path / "evaluation.json"
    policy = ROOT / "benchmarks" / "studies" / "linear_lqr_rate" / "trials" / "predicted_held_90" / "seed0"
    policy = policy / "policy.pt"
    evaluate.main([str(policy), "--episodes", "4", "--out", str(out)])
    printed = capsys.readouterr().out
    result = json.loads(out.read_text())
    assert list(result["fixed"]) == ["periodic", "periodic_staggered", "send_on_delta_max_age", "predictive"]
    assert "ThresholdedOptions(threshold=" in result["thresholded"]  # one threshold, or two mixed
    assert result["metrics"]["thresholded_savings"] == pytest.approx(result["metrics"]["savings"], abs=1e-12)
    assert "| thresholded |" in printed and f"mu thresholded at the learned rate: {result['thresholded']}" in printed
    difference = result["metrics"]["thresholded_minus_best_fixed_control_return"]
    best = result["best_fixed"]
    assert f"thresholded minus the best fixed family ({best}), same episodes: {difference:.2f}" in printed
    evaluate.main([str(policy), "--episodes", "4", "--fixed-families", "send_on_delta", "--out", str(out)])
    assert list(json.loads(out.read_text())["fixed"]) == ["send_on_delta"]
    evaluate.main([str(policy), "--episodes", "2", "--fixed-families", "--out", str(out)])
    result = json.loads(out.read_text())
    assert "fixed" not in result and "thresholded" not in result["modes"]
    with pytest.raises(SystemExit) as stopped:  # argparse's own refusal, with the usage
        evaluate.main(["--fixed-families", "sometimes", str(policy)])
    assert stopped.value.code == 2 and "--fixed-families: invalid choice: 'sometimes'" in capsys.readouterr().err


def test_a_saved_model_with_an_env_given_is_evaluated_with_the_protocol(tmp_path: Path) -> None:
    env_kwargs = {"n_agents": 2, "max_cycles": 12, "broadcast_cost": 1e-3}
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **env_kwargs), n_steps=16, policy_kwargs={"net_arch": [8]})
    model.save(tmp_path / "model.zip")
    out = tmp_path / "evaluation.json"
    command = [sys.executable, "-m", "sb3_detc.evaluate", str(tmp_path / "model.zip"), "--env", ENV_ID]
    command += ["--episodes", "3", "--seed", "40", "--out", str(out), "--sample-options"]
    command += ["--env-kwargs", "n_agents=2", "max_cycles=12", "broadcast_cost=1e-3"]
    subprocess.run(command, check=True, capture_output=True, text=True, cwd=ROOT)
    result = json.loads(out.read_text())
    assert result["episodes"] == 3 and result["seed"] == 40 and result["options"] == "sampled"
    # The same as the protocol run here on the env with these settings (the cost included), the options
    # sampled from mu too: the episodes' seeds seed them.
    policy = MAPPOC.load(tmp_path / "model.zip").policy
    expected = evaluate_policy_modes(policy, gym.make(ENV_ID, **env_kwargs), 3, 40, sample_options=True)
    assert set(result["metrics"]) == set(expected["metrics"])
    for metric, value in expected["metrics"].items():
        assert result["metrics"][metric] == pytest.approx(value, rel=1e-6), metric
    # A model of the baseline: its own options are the random trigger it trained with.
    evaluate.main([*command[3:], "--skip-prob", "1.0"])
    assert json.loads(out.read_text())["metrics"]["savings"] == 1.0


def test_a_video_of_one_episode(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    policy = STUDY / "trials" / "mappoc_paper" / "seed0" / "policy.pt"
    video = tmp_path / "videos" / "episode.mp4"
    evaluate.main([str(policy), "--episodes", "1", "--env-kwargs", "max_cycles=5", "--video", str(video)])
    assert video.stat().st_size > 1000 and str(video) in capsys.readouterr().out
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID), n_steps=16, policy_kwargs={"net_arch": [8]})
    model.save(tmp_path / "model.zip")
    argv = [str(tmp_path / "model.zip"), "--env", ENV_ID, "--episodes", "1", "--video", str(video)]
    assert f"{ENV_ID} does not render" in refused(argv, capsys)


def test_what_is_not_a_saved_model_or_policy_is_refused_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("not a model")
    assert "notes.txt is not a saved MAPPOC model (.zip) or policy (policy.pt)" in refused([str(text)], capsys)
    assert "no such file" in refused([str(tmp_path / "missing.zip")], capsys)
    PPO("MlpPolicy", "CartPole-v1", n_steps=16).save(tmp_path / "ppo.zip")
    assert "ppo.zip is a model of another algorithm" in refused([str(tmp_path / "ppo.zip")], capsys)
    th.save({"weights": th.zeros(2)}, tmp_path / "tensors.pt")
    assert "tensors.pt is not a saved MAPPOC model" in refused([str(tmp_path / "tensors.pt")], capsys)
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID), n_steps=16, policy_kwargs={"net_arch": [8]})
    model.save(tmp_path / "model.zip")
    assert "cannot tell the env" in refused([str(tmp_path / "model.zip")], capsys)  # no run or study around it
    model.policy.save(str(tmp_path / "policy.pt"))
    assert "cannot tell the env" in refused([str(tmp_path / "policy.pt")], capsys)
    argv = [str(tmp_path / "model.zip"), "--env", ENV_ID]
    assert "--env-kwargs takes key=value" in refused([*argv, "--env-kwargs", "n_agents"], capsys)
    assert "--episodes must be >= 1" in refused([*argv, "--episodes", "0"], capsys)
    assert "unknown" in refused([str(tmp_path / "model.zip"), "--env", "sb3_detc/Nothing-v0"], capsys).lower()
