"""Tests of the evaluation of non-learned triggers and the send-on-delta sweep (sb3_detc.triggers)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.envs.linear import LinearSystem, LQRController
from sb3_detc.triggers import (
    FixedControl,
    PeriodicTrigger,
    RandomTrigger,
    SendOnDelta,
    TriggerPoint,
    evaluate_trigger,
    lqr_on_held_states,
    sweep_send_on_delta,
)

EPISODES = 10
DELTAS = (0.0, 0.05, 0.2, 1.0)


@pytest.fixture
def env() -> gymnasium.Env:
    return gymnasium.make("sb3_detc/LinearETC-v0")


def centralised_lqr_costs(system: LinearSystem, n_episodes: int, seed: int) -> np.ndarray:
    """Team cost per episode of LQR on the true states, driving the system directly (no network)."""
    controller = LQRController(system)
    costs = np.zeros(n_episodes)
    for episode in range(n_episodes):
        obs, _ = system.reset_arrays(seed + episode)
        truncated = False
        while not truncated:
            # The joint env's observations are float32: use the same precision for the states.
            state = obs.local.astype(np.float32)
            obs, rewards, _, truncated, _ = system.step_arrays(controller(state))
            costs[episode] -= rewards.sum()
    return costs


def test_periodic_and_silent_savings(env):
    control = lqr_on_held_states(env)
    always = evaluate_trigger(env, PeriodicTrigger(1), control, n_episodes=3, label="periodic")
    never = evaluate_trigger(env, RandomTrigger(1.0, seed=0), control, n_episodes=3)
    assert isinstance(always, TriggerPoint)
    assert always.label == "periodic" and always.episodes == 3
    assert always.savings == 0.0
    assert never.savings == 1.0
    # Never communicating costs more than communicating every step.
    assert never.cost > always.cost


def test_identical_seeds_give_identical_points(env):
    control = lqr_on_held_states(env)
    first = evaluate_trigger(env, RandomTrigger(0.5, seed=3), control, n_episodes=4, seed=7)
    second = evaluate_trigger(env, RandomTrigger(0.5, seed=3), control, n_episodes=4, seed=7)
    assert first == second
    other = evaluate_trigger(env, RandomTrigger(0.5, seed=3), control, n_episodes=4, seed=8)
    assert other.cost != first.cost


def test_lqr_on_held_states_with_periodic_broadcasts_is_centralised_lqr(env):
    system = env.unwrapped.network.system
    point = evaluate_trigger(env, PeriodicTrigger(1), lqr_on_held_states(system), n_episodes=EPISODES, seed=5)
    costs = centralised_lqr_costs(LinearSystem(), EPISODES, seed=5)
    assert point.cost == pytest.approx(costs.mean(), rel=1e-9, abs=1e-9)
    assert point.cost_sem == pytest.approx(costs.std(ddof=1) / np.sqrt(EPISODES), rel=1e-9, abs=1e-9)


def test_lqr_on_held_states_accepts_system_and_env(env):
    obs, _ = env.reset(seed=0)
    broadcast = np.array([1, 0, 1])
    from_env = lqr_on_held_states(env)(obs, broadcast)
    from_system = lqr_on_held_states(env.unwrapped.network.system)(obs, broadcast)
    np.testing.assert_array_equal(from_env, from_system)
    assert from_env.shape == (3, 1)
    with pytest.raises(ValueError, match="LinearSystem"):
        lqr_on_held_states(gymnasium.make("CartPole-v1"))


def test_send_on_delta_sweep_trades_cost_for_savings(env):
    control = lqr_on_held_states(env)
    points = sweep_send_on_delta(env, control, DELTAS, n_episodes=EPISODES)
    periodic = evaluate_trigger(env, PeriodicTrigger(1), control, n_episodes=EPISODES)
    assert [p.label for p in points] == [f"send-on-delta {d:g}" for d in DELTAS]
    savings = [p.savings for p in points]
    assert all(a < b for a, b in zip(savings, savings[1:], strict=False))
    # delta = 0 broadcasts whenever the state moved, i.e. all but the first step of an episode.
    assert points[0].savings < 0.02
    assert points[0].cost == pytest.approx(periodic.cost, rel=1e-6)
    # Rare broadcasts cost clearly more than periodic ones (same episodes, so a paired comparison).
    assert points[-1].savings > 0.9
    assert points[-1].cost > 1.5 * periodic.cost


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(deltas=[]), "deltas must not be empty"),
        (dict(deltas=[0.1, -0.1]), "delta must be a finite number >= 0"),
        (dict(deltas=[float("nan")]), "delta must be a finite number >= 0"),
        (dict(deltas=[0.1], n_episodes=0), "n_episodes"),
    ],
)
def test_sweep_rejects_bad_arguments(env, kwargs, match):
    with pytest.raises(ValueError, match=match):
        sweep_send_on_delta(env, lqr_on_held_states(env), **kwargs)


def test_evaluate_trigger_rejects_bad_arguments(env):
    control = lqr_on_held_states(env)
    with pytest.raises(ValueError, match="n_episodes"):
        evaluate_trigger(env, PeriodicTrigger(1), control, n_episodes=0)
    with pytest.raises(ValueError, match="joint sb3_detc env"):
        evaluate_trigger(gymnasium.make("CartPole-v1"), PeriodicTrigger(1), control)


def test_fixed_control_replaces_the_controls_by_the_law(env):
    """Stepping FixedControl with any control equals evaluate_trigger with the law itself."""
    delta = 0.1
    law = lqr_on_held_states(env)
    point = evaluate_trigger(env, SendOnDelta(delta), law, n_episodes=3, seed=11)
    fixed = FixedControl(gymnasium.make("sb3_detc/LinearETC-v0"))
    trigger = SendOnDelta(delta)
    rng = np.random.default_rng(0)
    costs, broadcasts, steps = [], 0, 0
    for episode in range(3):
        obs, _ = fixed.reset(seed=11 + episode)
        cost, done = 0.0, False
        while not done:
            broadcast = trigger({key: value[None] for key, value in obs.items()})[0]
            junk = rng.normal(size=fixed.action_space["control"].shape).astype(np.float32) * 5
            obs, _, terminated, truncated, info = fixed.step({"broadcast": broadcast, "control": junk})
            cost -= float(np.sum(info["control_rewards"]))
            broadcasts += int(np.sum(broadcast))
            steps += broadcast.size
            done = terminated or truncated
        costs.append(cost)
    np.testing.assert_allclose(np.mean(costs), point.cost, rtol=1e-6)
    np.testing.assert_allclose(1 - broadcasts / steps, point.savings)


def test_fixed_control_needs_a_reset_first():
    fixed = FixedControl(gymnasium.make("sb3_detc/LinearETC-v0"))
    with pytest.raises(RuntimeError, match="reset"):
        fixed.step(fixed.action_space.sample())
