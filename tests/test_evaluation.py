"""Evaluation episodes side by side (copies of the env, one policy call per step) and one after another."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc import evaluation
from sb3_detc.envs.linear_etc_v0 import joint_env
from sb3_detc.evaluation import evaluate_episodes
from sb3_detc.mappoc import MAPPOC
from sb3_detc.triggers import PeriodicTrigger, RandomTrigger

ENV_ID = "sb3_detc/LinearETC-v0"
SETTINGS = {"n_agents": 2, "max_cycles": 15}


@pytest.fixture(scope="module")
def policy():
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **SETTINGS), n_steps=16, policy_kwargs={"net_arch": [8]}, seed=0)
    return model.policy


@pytest.mark.parametrize("trigger", [PeriodicTrigger(3), RandomTrigger(1.0)])
def test_side_by_side_matches_one_after_another(monkeypatch: pytest.MonkeyPatch, policy, trigger) -> None:
    """Deterministic episodes give the same results in copies of the env as in one env, in the order of the seeds."""
    monkeypatch.setattr(evaluation, "MAX_SIDE_BY_SIDE", 2)  # 5 episodes in 2 envs: finished ones make room
    seeds = [7, 3, 11, 5, 9]
    made = gym.make(ENV_ID, **SETTINGS)
    side_by_side = evaluate_episodes(policy, made, seeds, fixed_trigger=trigger)
    alone = joint_env(**SETTINGS)
    assert alone.spec is None  # cannot be copied: one episode after another
    one_by_one = evaluate_episodes(policy, alone, seeds, fixed_trigger=trigger)
    for field in evaluation.Episodes.__dataclass_fields__:
        np.testing.assert_allclose(getattr(side_by_side, field), getattr(one_by_one, field), rtol=1e-6, err_msg=field)
    first = evaluate_episodes(policy, made, seeds[:1], fixed_trigger=trigger)
    assert side_by_side.returns[0] == pytest.approx(first.returns[0])  # episode k belongs to seeds[k]
    assert len(np.unique(side_by_side.returns)) == len(seeds)


def test_sampled_options_side_by_side_are_recorded_per_episode(policy) -> None:
    episodes = evaluate_episodes(policy, gym.make(ENV_ID, **SETTINGS), [1, 2, 3], sample_options=True)
    assert episodes.broadcasts.shape == (3, 2) and (episodes.lengths == SETTINGS["max_cycles"]).all()
    broadcasts = episodes.broadcasts
    assert np.array_equal(broadcasts, np.round(broadcasts)) and ((broadcasts >= 0) & (broadcasts <= 15)).all()
    assert 0 < broadcasts.sum() < 3 * 2 * 15  # sampled options: some broadcasts, not at every step
    # Savings: one minus the broadcasts per agent-step, over 3 episodes x 2 agents x 15 steps.
    assert episodes.savings == pytest.approx(1 - broadcasts.sum() / 90, abs=1e-12)
    # Known options: every third step, 5 broadcasts per agent and episode.
    periodic = evaluate_episodes(policy, gym.make(ENV_ID, **SETTINGS), [1, 2, 3], fixed_trigger=PeriodicTrigger(3))
    np.testing.assert_array_equal(periodic.broadcasts, np.full((3, 2), 5))
    assert periodic.savings == pytest.approx(2 / 3, abs=1e-12)


@pytest.mark.parametrize("sample_options", [False, True])
def test_deterministic_episodes_take_options_as_the_policy_says(sample_options: bool) -> None:
    """Deterministic episodes take the most likely options, or samples where the policy's ``sample_options`` says."""
    model = MAPPOC(
        "MlpHybridPolicy",
        gym.make(ENV_ID, **SETTINGS),
        policy_kwargs={"net_arch": [8], "broadcast_prob_init": 0.5, "sample_options": sample_options},
        seed=0,
    )
    runs = []
    for first in (1, 101):  # the first episode's seed seeds the draws: episodes 2 and 3 are the same
        runs.append(evaluate_episodes(model.policy, gym.make(ENV_ID, **SETTINGS), [first, 2, 3]).broadcasts[1:])
    assert np.array_equal(runs[0], runs[1]) is not sample_options


def test_seeded_episodes_draw_the_same_options_and_leave_the_global_generator() -> None:
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **SETTINGS), policy_kwargs={"net_arch": [8]}, seed=0)
    th.manual_seed(5)
    state = th.random.get_rng_state()
    runs = [
        evaluate_episodes(model.policy, gym.make(ENV_ID, **SETTINGS), [1, 2, 3], deterministic=False) for _ in range(2)
    ]
    assert th.equal(th.random.get_rng_state(), state)
    np.testing.assert_array_equal(runs[0].broadcasts, runs[1].broadcasts)
    np.testing.assert_array_equal(runs[0].returns, runs[1].returns)


def test_evaluate_communication_seeds_every_episode() -> None:
    """Episode k of an evaluation with seed s is the episode seeded s + k: other triggers see the same episodes."""
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **SETTINGS), policy_kwargs={"net_arch": [8]}, seed=0)
    report = evaluation.evaluate_communication(model, gym.make(ENV_ID, **SETTINGS), 3, seed=7)
    episodes = evaluate_episodes(model.policy, gym.make(ENV_ID, **SETTINGS), [7, 8, 9])
    assert report.mean_control_return == pytest.approx(float(np.mean(episodes.control_returns)))
    assert report.savings == pytest.approx(episodes.savings)
