"""``benchmarks/multiwalker_trigger_for_controller.py``: policies over options for a study's frozen controllers."""

from __future__ import annotations

import json
import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_detc.evaluation import evaluate_episodes
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.study.spec import load_folder_study

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = "multiwalker_trigger_for_controller.py"
TRIAL = ROOT / "benchmarks" / "studies" / "linear" / "trials" / "ppo_random_skip" / "seed1"


def test_only_the_policies_over_options_change_and_the_protocol_evaluates_them(tmp_path: Path, run_benchmark) -> None:
    out, saved = tmp_path / "rows.json", tmp_path / "policies"
    arguments = ["benchmarks/studies/linear", "--algorithm", "ppo_random_skip", "--seeds", "1", "1"]
    arguments += ["--timesteps", "4096", "--warm-up", "2048", "--out", str(out), "--save-dir", str(saved)]
    printed = run_benchmark(SCRIPT, *arguments, "--progress-every", "2", check=True).stdout
    (row,) = json.loads(out.read_text())  # the seed given twice runs once
    before = MlpHybridPolicy.load(str(TRIAL / "policy.pt"), device="cpu")
    after = MlpHybridPolicy.load(str(saved / row["saved"]), device="cpu")
    for net, changed in (("pi", False), ("mu", True), ("q", True)):
        same = all(th.equal(a, b) for a, b in zip(before.net_parameters(net), after.net_parameters(net), strict=True))
        assert same != changed, net
    metrics = row["metrics"]
    assert row["seed"] == 1 and 0.0 < metrics["savings"] < 1.0
    # a message every k-th step at the k whose savings 1 - 1/k lie nearest the learned savings
    nearest = min(range(1, 10_000), key=lambda k: abs(1 - 1 / k - metrics["savings"]))
    assert row["periodic_nearest"]["period"] == nearest
    assert row["env_kwargs"] == {"broadcast_cost": 0.03}  # the entry's cost
    assert row["periodic_nearest"]["package_travel"] is None  # the linear env reports none
    # the trial's controller, unchanged: every step and never as in the study's own evaluation
    study = json.loads((TRIAL / "evaluation.json").read_text())["metrics"]
    for mode in ("periodic_control_return", "never_control_return"):
        assert abs(metrics[mode] - study[mode]) < 1e-6 * max(1.0, abs(study[mode])), mode
    assert "| 1 | " in printed
    # progress every 2nd rollout (of 1024 steps) of each phase, with the savings of the last rollout
    progress = re.findall(r"^(.*): (\d+) steps, savings in the last rollout ([\d.]+), ", printed, re.MULTILINE)
    label = "ppo_random_skip seed 1"
    assert [(who, int(steps)) for who, steps, _ in progress] == [(f"{label}, critic alone", 2048), (label, 4096)]
    assert all(0.0 <= float(savings) <= 1.0 for *_, savings in progress)
    recent = re.findall(r"return of the last (\d+) episodes (-?[\d.]+), \d+ s$", printed, re.MULTILINE)
    assert len(recent) == 2 and all(1 <= int(n) <= 100 for n, _ in recent)  # episodes have ended by either line
    again = run_benchmark(SCRIPT, *arguments, check=True).stdout
    assert "1 of 1 jobs already in" in again  # resumed, not trained again


def test_an_unfinished_algorithm_is_a_usage_error(run_benchmark_here) -> None:
    done = run_benchmark_here(SCRIPT, "benchmarks/studies/linear", "--algorithm", "nothing")
    assert (
        done.returncode == 2 and "no finished trial of 'nothing' (algorithms: mappoc, ppo_random_skip)" in done.stderr
    )


def test_a_fresh_mu_reads_its_own_age_and_the_fixed_families_are_compared(tmp_path: Path, run_benchmark) -> None:
    out, saved = tmp_path / "rows.json", tmp_path / "policies"
    arguments = ["benchmarks/studies/linear", "--algorithm", "ppo_random_skip", "--seeds", "1", "--option-age-scale"]
    arguments += ["0.1", "--timesteps", "2048", "--warm-up", "1024", "--out", str(out), "--save-dir", str(saved)]
    # where the fresh mu starts may change with it (the entry's other policy settings may not)
    kwargs = "dict(net_arch=[64, 64], learn_log_std=True, critic='afterstate', age_scale=0.0, broadcast_prob_init=0.2)"
    arguments += ["--set", json.dumps({"policy_kwargs": kwargs})]
    done = run_benchmark(SCRIPT, *arguments, "--fixed-families", "send_on_delta", "send_on_delta_max_age", check=True)
    # the families' table: mu thresholded at the learned rate and every compared family per seed, and the
    # learned (and thresholded) minus the best
    assert (
        "| seed | learned | thresholded | send on delta | send on delta max age | learned minus best family "
        "| thresholded minus best family |"
    ) in done.stdout
    (row,) = json.loads(out.read_text())
    before = MlpHybridPolicy.load(str(TRIAL / "policy.pt"), device="cpu")
    after = MlpHybridPolicy.load(str(saved / row["saved"]), device="cpu")
    assert before.option_age_scale == 0.0 and after.option_age_scale == 0.1
    assert after.constructor_parameters()["broadcast_prob_init"] == 0.2
    # mu reads one input more (its age); the controls are the trial's over their common part
    (mu_in,) = {w.shape[1] for w in after.net_parameters("mu")[:1]}
    assert after.chains.specs["mu"].in_features == before.chains.specs["mu"].in_features + 1 <= mu_in
    for new, old in zip(after.net_parameters("pi"), before.net_parameters("pi"), strict=True):
        common = tuple(slice(0, min(a, b)) for a, b in zip(new.shape, old.shape, strict=True))
        assert th.equal(new[common], old[common])
    metrics = row["metrics"]
    # thresholds reach any savings (a period only 1 - 1/k): both families are compared at the learned rate
    for family in ("send_on_delta", "send_on_delta_max_age"):
        assert abs(metrics[f"fixed_{family}_savings"] - metrics["savings"]) <= 0.05, family
    assert abs(metrics["thresholded_savings"] - metrics["savings"]) <= 0.05
    assert metrics["best_fixed_control_return"] == max(
        metrics["fixed_send_on_delta_control_return"], metrics["fixed_send_on_delta_max_age_control_return"]
    )
    bad = run_benchmark(
        SCRIPT, "benchmarks/studies/linear", "--algorithm", "ppo_random_skip", "--option-age-scale", "0"
    )
    assert bad.returncode == 2 and "--option-age-scale must be a finite number > 0" in bad.stderr


def test_a_trigger_started_as_a_schedule_imitates_it_after_a_warm_up_under_it(tmp_path: Path, run_benchmark) -> None:
    out = tmp_path / "rows.json"
    arguments = ["benchmarks/studies/linear", "--algorithm", "ppo_random_skip", "--seeds", "1", "--option-age-scale"]
    arguments += ["0.1", "--start-period", "4", "--timesteps", "2048", "--warm-up", "1024", "--out", str(out)]
    kwargs = "dict(net_arch=[64, 64], learn_log_std=True, critic='afterstate', age_scale=0.0, broadcast_prob_init=0.5)"
    arguments += ["--set", json.dumps({"policy_kwargs": kwargs})]
    done = run_benchmark(SCRIPT, *arguments, "--progress-every", "1", check=True)
    # the warm-up's rollout under the schedule: a message every 4th step, whatever mu would have done
    first = re.search(r"critic alone: 1024 steps, savings in the last rollout ([\d.]+)", done.stdout)
    assert first is not None and abs(float(first.group(1)) - 0.75) < 0.01
    assert "mu imitated PeriodicTrigger(period=4" in done.stdout
    (row,) = json.loads(out.read_text())
    assert row["imitation_accuracy"] > 0.95
    # one update after the imitation: mu still broadcasts about every 4th step (it started at 1 in 2)
    assert abs(row["metrics"]["savings"] - 0.75) < 0.1
    bad = run_benchmark(SCRIPT, "benchmarks/studies/linear", "--algorithm", "ppo_random_skip", "--start-period", "4")
    assert bad.returncode == 2 and "--start-period takes a period >= 1, with --option-age-scale" in bad.stderr


def test_a_dithered_schedule_runs_in_the_warm_up_and_mu_imitates_its_deviations(tmp_path: Path, run_benchmark) -> None:
    out = tmp_path / "rows.json"
    arguments = ["benchmarks/studies/linear", "--algorithm", "ppo_random_skip", "--seeds", "1", "--option-age-scale"]
    arguments += ["0.1", "--start-period", "4", "--start-dither", "0.5", "0.0", "--timesteps", "2048"]
    arguments += ["--warm-up", "1024", "--out", str(out), "--progress-every", "1"]
    done = run_benchmark(SCRIPT, *arguments, check=True)
    # half of the scheduled messages skipped: an agent broadcasts at age 3 or later with probability 1/2,
    # every 5 steps on average instead of 4
    first = re.search(r"critic alone: 1024 steps, savings in the last rollout ([\d.]+)", done.stdout)
    assert first is not None and abs(float(first.group(1)) - 0.8) < 0.03
    assert "mu imitated DitheredTrigger(PeriodicTrigger(period=4, staggered=False), skip_prob=0.5" in done.stdout
    (row,) = json.loads(out.read_text())
    # mu learned to broadcast about half the time from age 3 on: the most likely option matches the
    # deviations only by chance there
    assert 0.6 < row["imitation_accuracy"] < 0.95
    bad = run_benchmark(SCRIPT, *arguments[:5], "--start-dither", "0.1", "0.1")
    assert bad.returncode == 2 and "--start-dither takes two probabilities in [0, 1], with --start-period" in bad.stderr


def test_a_fresh_mu_may_decide_inside_a_window_of_broadcast_intervals(tmp_path: Path, run_benchmark) -> None:
    out, saved = tmp_path / "rows.json", tmp_path / "policies"
    arguments = ["benchmarks/studies/linear", "--algorithm", "ppo_random_skip", "--seeds", "1", "--option-age-scale"]
    arguments += ["0.1", "--timesteps", "2048", "--warm-up", "1024", "--out", str(out), "--save-dir", str(saved)]
    # a window of one interval leaves mu no choice: a message every 4th step, whatever mu learned
    kwargs = "dict(net_arch=[64, 64], learn_log_std=True, critic='afterstate', age_scale=0.0, "
    kwargs += "broadcast_interval=(4, 4), option_others_age_scale=0.1)"  # a fresh mu may read the others' ages too
    run_benchmark(SCRIPT, *arguments, "--set", json.dumps({"policy_kwargs": kwargs}), check=True)
    (row,) = json.loads(out.read_text())
    policy = MlpHybridPolicy.load(str(saved / row["saved"]), device="cpu")
    assert policy.broadcast_interval == (4, 4) and policy.option_others_age_scale == 0.1
    # the learned trigger is the schedule (an episode's last interval may end unfinished)
    assert abs(row["metrics"]["savings"] - 0.75) < 0.01
    assert abs(row["metrics"]["control_return"] - row["periodic_nearest"]["control_return"]) < 1e-6


def test_the_policy_best_on_validation_episodes_is_kept(tmp_path: Path, run_benchmark) -> None:
    out, saved = tmp_path / "rows.json", tmp_path / "policies"
    arguments = ["benchmarks/studies/linear", "--algorithm", "ppo_random_skip", "--seeds", "1", "--option-age-scale"]
    arguments += ["0.1", "--timesteps", "5120", "--warm-up", "1024", "--out", str(out), "--save-dir", str(saved)]
    kwargs = "dict(net_arch=[64, 64], learn_log_std=True, critic='afterstate', age_scale=0.0, broadcast_prob_init=0.3)"
    arguments += ["--set", json.dumps({"target_savings": 0.7, "policy_kwargs": kwargs})]
    done = run_benchmark(SCRIPT, *arguments, "--select-every", "2048", "--select-episodes", "3", check=True)
    (row,) = json.loads(out.read_text())
    evaluations, kept = row["selection"]["evaluations"], row["selection"]["kept"]
    # at every multiple of 2048 steps in mu's training (rollouts of 1024 steps, from 1024 on) and at its end
    assert [e["timesteps"] for e in evaluations] == [2048, 4096, 5120]
    assert len(re.findall(r"^validation at \d+ steps: control return", done.stdout, re.MULTILINE)) == 3
    eligible = [e for e in evaluations if e["savings"] >= 0.7 - 0.01]
    assert kept == max(eligible, key=lambda e: e["control_return"])
    # the later ones returned more but fell below the target: the earliest policy is restored
    assert kept["timesteps"] == 2048 and evaluations[-1]["control_return"] > kept["control_return"]
    # the saved policy is the kept one: it repeats its validation episodes (right after the evaluation's)
    spec = load_folder_study(ROOT / "benchmarks" / "studies" / "linear")
    policy = MlpHybridPolicy.load(str(saved / row["saved"]), device="cpu")
    first = spec.eval_seed + spec.episodes
    with gym.make(spec.env, **row["env_kwargs"]) as env:
        episodes = evaluate_episodes(policy, env, list(range(first, first + 3)), sample_options=True)
    assert float(np.mean(episodes.control_returns)) == pytest.approx(kept["control_return"], rel=1e-6)
    assert episodes.savings == pytest.approx(kept["savings"])
    bad = run_benchmark(SCRIPT, *arguments[:5], "--select-every", "0")
    assert bad.returncode == 2 and "--select-every must be at least 1" in bad.stderr
