"""``benchmarks/replayed_gap_trigger.py``: a trigger learned from replayed values of a broadcast."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from sb3_detc.triggers import PeriodicTrigger, PredictiveTrigger, lqr_on_predicted_states

SCRIPT = "replayed_gap_trigger.py"


@pytest.fixture(scope="module")
def script(benchmark_module):
    """The benchmark script as a module."""
    return benchmark_module(SCRIPT)


@pytest.fixture
def env():
    """The linear system's joint env."""
    with gym.make("sb3_detc/LinearETC-v0") as joint:
        yield joint


def test_the_fit_recovers_a_quadratic_form_per_agent(script) -> None:
    rng = np.random.default_rng(0)
    agents = rng.integers(3, size=600)
    deviations = rng.standard_normal((600, 2))
    true = np.array([[1.0, 0.5, 2.0], [3.0, -1.0, 0.2], [0.0, 0.0, 1.0]])
    gaps = np.einsum("sk,sk->s", script.quadratic_features(deviations), true[agents])
    coef, r2 = script.fit_gaps(agents, deviations, gaps, 3)
    np.testing.assert_allclose(coef, true, atol=1e-9)
    assert np.allclose(r2, 1.0)


def test_the_gap_trigger_broadcasts_where_the_fitted_value_exceeds_the_threshold(script, env) -> None:
    predictive = PredictiveTrigger(env, 0.2)
    obs, _ = env.reset(seed=3)
    batch = script.batched(obs)
    batch["held"] = batch["held"] + np.array([[[0.3, 0.0], [0.0, 0.1], [0.0, 0.0]]], dtype=np.float32)
    # With the form ||d||^2 the trigger is predictive triggering at delta = sqrt(threshold).
    trigger = script.GapTrigger(predictive, np.tile([1.0, 0.0, 1.0], (3, 1)), 0.2**2)
    np.testing.assert_allclose(trigger.value(batch), predictive.error(batch) ** 2, rtol=1e-6)
    np.testing.assert_array_equal(trigger(batch), predictive(batch))
    assert trigger(batch)[0, 0] == 1 and trigger(batch)[0, 2] == 0


def test_replays_share_the_noise(script, env) -> None:
    control = lqr_on_predicted_states(env)
    trigger = PeriodicTrigger(4)
    obs, _ = env.reset(seed=5)
    for _ in range(3):
        options = trigger(script.batched(obs))[0]
        obs, *_ = env.step({"broadcast": options, "control": control(obs, options)})
    # The option the trigger takes anyway gives the same return in two copies: the same noise.
    taken = int(trigger(script.batched(obs))[0, 1])
    before = copy.deepcopy(env)
    first = script.branch_return(env, obs, 1, taken, trigger, control, 20)
    assert script.branch_return(env, obs, 1, taken, trigger, control, 20) == first
    # A broadcast changes what follows; the replays leave the env as it was (its state and its noise).
    assert script.branch_return(env, obs, 1, 1 - taken, trigger, control, 20) != first
    options = trigger(script.batched(obs))[0]
    action = {"broadcast": options, "control": control(obs, options)}
    after, replayed = before.step(action)[0], env.step(action)[0]
    for key in after:
        np.testing.assert_array_equal(replayed[key], after[key])


def test_a_small_run_writes_its_record(tmp_path: Path, run_benchmark) -> None:
    out = tmp_path / "run.json"
    done = run_benchmark(
        SCRIPT, "--seeds", "0", "1", "--train-episodes", "4", "--decisions", "5", "--episodes", "3",
        "--tolerance", "0.02", "--out", str(out), check=True,
    )  # fmt: skip
    assert "learned minus predictive over 2 seeds" in done.stdout
    record = json.loads(out.read_text())
    assert [seed["seed"] for seed in record["seeds"]] == [0, 1]
    for seed in record["seeds"]:
        assert seed["iterations"][0]["samples"] == 4 * 5
        assert abs(seed["predictive_savings"] - seed["savings"]) <= 0.02


def test_bad_arguments_are_refused(run_benchmark_here) -> None:
    done = run_benchmark_here(SCRIPT, "--target", "1.5")
    assert done.returncode == 2 and "--target must lie in (0, 1)" in done.stderr
    done = run_benchmark_here(SCRIPT, "--horizon", "0")
    assert done.returncode == 2 and "--horizon must be at least 1" in done.stderr
