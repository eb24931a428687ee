"""Benchmark scripts: bad input is a one-line usage error (`evaluate_run.py` and others)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--episodes", "0"], "--episodes must be >= 1"),
        (["--checkpoints"], "no checkpoints rl_model_<steps>_steps.zip"),
        ([], "no saved model"),
    ],
)
def test_bad_input_is_a_usage_error(tmp_path: Path, arguments: list[str], message: str, run_benchmark_here) -> None:
    options = ["--env", "sb3_detc/LinearETC-v0", *arguments]
    done = run_benchmark_here("evaluate_run.py", str(tmp_path), *options)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr
    missing = run_benchmark_here("evaluate_run.py", str(tmp_path / "none"), *options)
    assert missing.returncode == 2 and ("no run folder" in missing.stderr or "--episodes" in missing.stderr)


@pytest.mark.parametrize(
    ("script", "arguments", "message"),
    [
        ("value_of_information.py", ["--steps", "100"], "--steps must be more than the 200 steps of burn-in"),
        ("linear_pareto.py", ["--episodes", "0"], "--episodes must be >= 1"),
        ("linear_learning.py", ["--eval-episodes", "0"], "--eval-episodes must be at least 1"),
        ("linear_learning.py", ["--broadcast-costs", "0.03", "-1"], "at broadcast cost -1.0 refused"),
        ("linear_learning.py", ["--broadcast-advantages", "best"], "broadcast_advantage must be 'greedy' or 'return'"),
        ("linear_learning.py", ["--set", '{"n_epoch": 3}'], "unexpected keyword argument 'n_epoch'"),
        ("trigger_learning.py", ["--broadcast-costs", "-1"], "broadcast_cost must be a finite number >= 0"),
        ("option_value_estimation.py", ["--quantile", "1"], "--quantile must lie between 0 and 1"),
        ("option_value_estimation.py", ["--horizon", "512"], "--horizon must be below the rollout's 512 steps"),
        ("option_value_truth.py", ["--every", "0"], "--every must be at least 1"),
        ("train_throughput.py", ["--repeats", "0"], "--repeats must be at least 1"),
        ("train_throughput.py", ["--baseline", "/no/such/tree"], "is not a source tree of the package"),
        ("rate_target_stability.py", ["--target", "1.5"], "target_savings must be a number in (0, 1)"),
        ("rate_target_stability.py", ["--price-lr", "0"], "broadcast_price_lr must be > 0"),
        ("option_age_profile.py", ["README.md", "--episodes", "0"], "--episodes must be at least 1"),
        ("option_age_profile.py", ["README.md"], "README.md is not a saved MAPPOC model"),
        ("broadcast_synchrony.py", ["README.md", "--episodes", "0"], "--episodes must be at least 1"),
        ("broadcast_synchrony.py", ["README.md"], "README.md is not a saved MAPPOC model"),
        ("critic_gap_ranking.py", ["benchmarks/studies/linear_lqr_rate", "--arms", "best"], "no arms ['best']"),
        ("critic_gap_ranking.py", ["benchmarks", "--arms", "a"], "benchmarks is not a study folder (no study.yml)"),
        ("critic_gap_ranking.py", [".", "--arms", "a", "--episodes", "0"], "--episodes must be at least 1"),
        ("training_walk.py", ["benchmarks/studies/linear_lqr_rate", "--arms", "best"], "no such arms in"),
        ("training_walk.py", [".", "--arms", "a", "--tail", "0"], "--tail must lie in (0, 1]"),
        ("training_walk.py", [".", "--arms", "a", "--episodes", "0"], "--episodes must be at least 1"),
        ("training_walk.py", [".", "--arms", "a", "--grid", "1"], "--grid must be at least 2"),
        ("predictive_headroom.py", ["--episodes", "1"], "--episodes must be at least 2"),
        ("predictive_headroom.py", ["--targets", "0.9", "1"], "--targets must lie in (0, 1)"),
        ("predictive_headroom.py", ["--horizons", "0"], "--horizons must be at least 1"),
        ("learner_threads.py", ["no/such.zip"], "no/such.zip is not a saved model"),
        ("learner_threads.py", ["README.md", "--repeats", "0"], "--repeats must be at least 1"),
    ],
)
def test_other_benchmarks_check_their_numbers_first(
    script: str, arguments: list[str], message: str, run_benchmark_here
) -> None:
    done = run_benchmark_here(script, *arguments)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr


@pytest.mark.parametrize("script", ["linear_learning.py", "trigger_learning.py", "option_value_estimation.py"])
def test_sweeps_refuse_a_results_file_of_something_else(tmp_path: Path, script: str, run_benchmark_here) -> None:
    out = tmp_path / "results.json"
    out.write_text('{"a": "run of another script"}')
    done = run_benchmark_here(script, "--timesteps", "2048", "--out", str(out))
    assert done.returncode == 2 and "not the JSON rows of an earlier run" in done.stderr
    assert out.read_text() == '{"a": "run of another script"}'


def test_the_training_walk_reads_a_finished_arm(run_benchmark) -> None:
    arm = "predictive_first_90_replayed_expected_noent_anneal"
    arguments = ["--arms", arm, "--episodes", "1"]
    done = run_benchmark("training_walk.py", "benchmarks/studies/linear_lqr_rate", *arguments, check=True)
    lines = done.stdout.splitlines()
    assert lines[0] == f"## {arm}" and sum(line.startswith("seed") for line in lines) == 5
    assert sum("final policy: p in (0.02, 0.98) at" in line for line in lines) == 5
    assert lines[-1].startswith(f"{arm}: control return minus predictive triggering's at the same savings over 5 seeds")


def test_the_age_profile_bands_a_policys_probabilities_by_its_own_age(tmp_path: Path, run_benchmark) -> None:
    """A trigger trained at 90 % savings on the linear system broadcasts more often the older its information."""
    policy = Path("benchmarks/studies/linear_lqr_rate/trials/target_90/seed0/policy.pt")
    out = tmp_path / "profile.json"
    arguments = [str(policy), "--episodes", "2", "--broadcast-prob", "0.1", "--out", str(out)]
    done = run_benchmark("option_age_profile.py", *arguments, check=True)  # the env from the study
    assert "sb3_detc/LinearETC-LQR-v0" in done.stdout
    assert "| 0 to 3 |" in done.stdout and "Correlation of the option gap with the own age" in done.stdout
    result = json.loads(out.read_text())
    bands = result["bands"]
    assert [band["low"] for band in bands] == [0, 4, 8, 16, 32][: len(bands)] and len(bands) >= 3
    assert sum(band["n"] for band in bands) == 2 * 3 * 100  # 2 episodes of 100 steps, 3 agents
    assert bands[-1]["probability"] > bands[0]["probability"]
