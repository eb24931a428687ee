"""Replayed values of a broadcast (sb3_detc.mappoc.replays) and MAPPOC's ``broadcast_advantage="replayed"``."""

from __future__ import annotations

import copy
import threading
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.losses import fitted_logit_loss
from sb3_detc.mappoc.policies import HybridEvaluation
from sb3_detc.mappoc.replays import Replays, copyable_env, gradient_choice, replay, snapshot, uniform_choice
from sb3_detc.mappoc.rewards import RewardTransform
from sb3_detc.mappoc.sampling import Rollout
from sb3_detc.triggers import PeriodicTrigger

ENV_ID = "sb3_detc/LinearETC-v0"
LOW, HIGH = np.full((3, 1), -10.0), np.full((3, 1), 10.0)


def states(env_id: str, seeds: list[int], steps: int = 3, **kwargs: Any) -> tuple[list[gym.Env], dict[str, np.ndarray]]:
    """Joint envs a few steps into seeded episodes (silent agents, zero controls), and their observations."""
    envs, observed = [], []
    for seed in seeds:
        env = gym.make(env_id, **kwargs)
        obs, _ = env.reset(seed=seed)
        for _ in range(steps):
            obs, *_ = env.step({"broadcast": np.zeros(3, np.int64), "control": np.zeros((3, 1), np.float32)})
        envs.append(env)
        observed.append(obs)
    return envs, {key: np.stack([obs[key] for obs in observed]) for key in observed[0]}


def random_act(obs: dict[str, np.ndarray], forced: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Options and controls drawn from PyTorch's generator, whatever the observation."""
    batch = len(obs["age"])
    options = (th.rand(batch, 3) < 0.5).long().numpy() if forced is None else forced
    return options, th.randn(batch, 3, 1).numpy()


def test_both_copies_draw_the_same_numbers() -> None:
    # Controls that ignore the observation: both copies move alike, so they differ only in the
    # agent's broadcast of the first step and its cost; any other random draw would set them apart.
    envs, obs = states(ENV_ID, [1, 2], broadcast_cost=0.3)
    agents = np.array([0, 2])
    rewards, broadcasts = replay(random_act, envs, obs, agents, 15, 0.9, LOW, HIGH, seed=7)
    expected = np.zeros((2, 3))
    expected[[0, 1], agents] = 1.0
    np.testing.assert_allclose(broadcasts, expected)
    np.testing.assert_allclose(rewards, -0.3 * expected, atol=1e-9)


def test_replayed_values_are_those_of_two_copies_stepped_by_hand() -> None:
    envs, obs = states("sb3_detc/LinearETC-LQR-v0", [3, 4, 5], steps=5)  # LQR on held broadcasts takes the controls
    trigger = PeriodicTrigger(4)

    def act(batch: dict[str, np.ndarray], forced: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        return (trigger(batch) if forced is None else forced), np.zeros((len(batch["age"]), 3, 1), np.float32)

    agents, gamma, horizon = np.array([1, 0, 2]), 0.9, 12
    expected = np.zeros((3, 3))
    for k, env in enumerate(envs):
        for option, sign in ((1, 1.0), (0, -1.0)):
            branch = copy.deepcopy(env)
            current = {key: value[k] for key, value in obs.items()}
            for step in range(horizon):
                options = trigger({key: value[None] for key, value in current.items()})[0]
                if step == 0:
                    options[agents[k]] = option
                current, _, _, _, info = branch.step({"broadcast": options, "control": np.zeros((3, 1), np.float32)})
                expected[k] += sign * gamma**step * info["agent_rewards"]
    rewards, _ = replay(act, [copyable_env(env) for env in envs], obs, agents, horizon, gamma, LOW, HIGH, seed=0)
    np.testing.assert_allclose(rewards, expected, rtol=1e-9, atol=1e-12)
    assert np.all(np.abs(rewards[np.arange(3), agents]) > 0)  # the broadcast changes the team's controls


class CountingSteps(gym.Wrapper):
    """Counts the steps taken."""

    steps = 0

    def step(self, action: Any) -> Any:
        self.steps += 1
        return self.env.step(action)


def test_a_replay_stops_at_the_episode_end() -> None:
    envs, obs = states(ENV_ID, [0], steps=17, max_cycles=20)  # three steps left
    counted = CountingSteps(envs[0])
    replay(random_act, [counted], obs, np.array([1]), 50, 1.0, LOW, HIGH, seed=3)
    assert counted.steps == 3  # the silent branch steps the given copy


def test_uniform_choice_replays_one_random_agent_at_a_share_of_the_steps() -> None:
    rng = np.random.default_rng(0)
    draws = [uniform_choice(5, 3, 0.25, rng) for _ in range(400)]
    chosen = np.stack([agents for agents, _ in draws])
    assert chosen.shape == (400, 5) and set(np.unique(chosen)) == {-1, 0, 1, 2}
    assert abs((chosen >= 0).mean() - 0.25) < 0.03
    assert all(np.allclose(chances, 0.25 / 3) for _, chances in draws)
    assert (uniform_choice(2, 3, 1.0, rng)[0] >= 0).all()


def test_gradient_choice_weighted_by_its_inverse_chance_counts_every_undecided_decision_once() -> None:
    # Importance sampling: E[1{d chosen} / chance_d] = 1 for every decision with p (1 - p) > 0, so a
    # sum over the replayed decisions weighted by 1 / chance is the sum over all in expectation.
    probabilities = np.array([[0.5, 0.1, 0.0], [0.9, 0.99, 0.3], [1.0, 0.0, 0.0], [0.02, 0.6, 0.5]])
    rng = np.random.default_rng(1)
    counts, chance, draws = np.zeros_like(probabilities), np.zeros_like(probabilities), 40_000
    replays_per_step = []
    for _ in range(draws):
        agents, chances = gradient_choice(probabilities, 0.25, rng)
        rows = np.flatnonzero(agents >= 0)
        counts[rows, agents[rows]] += 1.0 / chances[rows]
        chance[rows, agents[rows]] = chances[rows]
        replays_per_step.append(len(rows))
    undecided = probabilities * (1 - probabilities) > 0
    assert (chance[undecided] > 0).all()  # each was chosen
    standard_error = np.sqrt((1 / chance[undecided] - 1) / draws)  # of a mean of 1{chosen} / chance
    assert (np.abs(counts[undecided] / draws - 1.0) < 4 * standard_error).all()
    assert (counts[~undecided] == 0).all()  # pinned decisions carry no gradient: never replayed
    assert np.mean(replays_per_step) == pytest.approx(0.25 * 4, rel=0.05)  # share replays per env and step
    # where mu is sure everywhere, nothing is replayed
    agents, _ = gradient_choice(np.array([[0.0, 1.0], [1.0, 1.0]]), 1.0, rng)
    assert (agents == -1).all()


def test_what_is_copied_leaves_out_the_bookkeeping_wrappers() -> None:
    env = make_vec_env(ENV_ID, n_envs=1).envs[0]  # Monitor(OrderEnforcing(PassiveEnvChecker(JointEnv)))
    core = copyable_env(env)
    assert type(core).__name__ == "JointEnv" and core is env.unwrapped


def test_an_env_that_cannot_be_copied_is_refused_with_its_reason() -> None:
    env = gym.make(ENV_ID)
    env.unwrapped.lock = threading.Lock()
    with pytest.raises(ValueError, match="cannot be copied .*lock.*use another broadcast_advantage"):
        snapshot(env)


def test_converted_rewards_are_the_learners_without_touching_the_statistics() -> None:
    transform = RewardTransform(3, 0.9, 0.5, team=True, normalize=True)
    rng = np.random.default_rng(0)
    for _ in range(20):
        transform(rng.normal(size=(2, 3)), np.zeros(2, bool))
    before = transform.return_rms.var.copy()
    rewards = rng.normal(size=(4, 3))
    expected = np.repeat(0.5 * rewards.mean(1, keepdims=True), 3, axis=1) / transform.spread()
    np.testing.assert_allclose(transform.converted(rewards), expected)
    np.testing.assert_array_equal(transform.return_rms.var, before)


def replayed_model(**kwargs: Any) -> MAPPOC:
    env = make_vec_env(ENV_ID, n_envs=2, env_kwargs={"max_cycles": 20})
    settings = {
        "n_steps": 16,
        "batch_size": 16,
        "n_epochs": 2,
        "replay_horizon": 5,
        "torch_compile": False,
        "broadcast_advantage": "replayed",
        **kwargs,
    }
    return MAPPOC("MlpHybridPolicy", env, seed=0, **settings)


def test_mu_learns_from_the_replayed_decisions_only() -> None:
    model = replayed_model(replay_share=0.5, policy_kwargs={"net_arch": [8]})
    before = [view.clone() for view in model.policy.net_parameters("mu")]
    model.learn(32)
    advantages = model.rollout_buffer.broadcast_advantages
    assert 0 < (advantages != 0).sum() <= 16 * 2  # at most one decision per step and env
    assert (advantages != 0).any(axis=-1).mean() == pytest.approx(0.5, abs=0.3)
    assert any(not th.equal(old, new) for old, new in zip(before, model.policy.net_parameters("mu"), strict=True))


def test_gradient_choice_reads_mus_probabilities_of_the_step() -> None:
    model = replayed_model(replay_share=0.5, replay_choice="gradient", policy_kwargs={"net_arch": [8]})
    model.learn(32)
    assert np.isfinite(model.rollout_buffer.broadcast_advantages).all()
    rollout = model.sampler.sample(model.env, model.last_obs, 16, 0.0, None)
    replays = rollout.replays
    assert len(replays.agents) > 0
    for step, env, agent, chance in zip(replays.steps, replays.envs, replays.agents, replays.chances, strict=True):
        with th.no_grad():
            obs = {key: th.as_tensor(value[step]) for key, value in rollout.observations.items()}
            p = model.policy.broadcast_probabilities(obs).numpy().astype(np.float64)  # (B, N) of that step
        weights = p * (1 - p)
        env_chance = min(1.0, 0.5 * 2 * weights[env].sum() / weights.sum())
        assert chance == pytest.approx(env_chance * weights[env, agent] / weights[env].sum(), rel=1e-4)


def test_replayed_advantages_hand_computed() -> None:
    model = replayed_model(replay_share=0.5, normalize_broadcast_advantage=False, reward_scale=0.1)
    model.learn(16)  # reads the rollout's settings
    steps, envs, agents = np.array([0, 3, 5]), np.array([1, 0, 1]), np.array([2, 0, 1])
    rewards = np.array([[0.0, 1.0, 2.0], [-3.0, 0.0, 0.0], [0.0, 0.5, 0.0]])
    broadcast = np.zeros((16, 2, 3), np.int64)
    broadcast[0, 1, 2] = broadcast[5, 1, 1] = 1  # taken options: broadcast, silent, broadcast
    log_prob = np.full((16, 2, 3), np.log(0.2))  # every taken option was drawn with 0.2
    model.broadcast_price = 0.05
    chances = np.array([0.5 / 3, 0.5 / 3, 0.05])  # uniform choice at share 0.5, then one chosen with 0.05
    replays = Replays(steps, envs, agents, rewards, np.eye(3)[agents], chances)
    rollout = Rollout({}, broadcast, np.zeros(0), np.zeros(0), [], {}, replays)
    # (o - p) (0.1 r_agent - price) / chance; p = 0.2 for a taken broadcast, 0.8 for a taken silence
    expected = [(1 - 0.2) * (0.2 - 0.05) * 6, (0 - 0.8) * (-0.3 - 0.05) * 6, (1 - 0.2) * (0.05 - 0.05) * 20]
    np.testing.assert_allclose(model.replayed_advantages(rollout, log_prob), expected, atol=1e-7)


def test_replayed_expected_advantages_give_the_expected_gradient_for_either_option() -> None:
    model = replayed_model(
        broadcast_advantage="replayed_expected", replay_share=0.5, normalize_broadcast_advantage=False
    )
    model.learn(16)
    model.broadcast_price = 0.0
    agents = np.array([0, 1, 2])
    rewards = np.diag([2.0, -3.0, 1.0])  # values 0.2, -0.3, 0.1 (reward_scale 0.1)
    replays = Replays(np.zeros(3, np.int64), np.zeros(3, np.int64), agents, rewards, np.eye(3), np.full(3, 0.5 / 3))
    p = np.array([0.1, 0.5, 0.7])  # the probabilities of broadcasting
    for option in (0, 1):
        broadcast = np.full((16, 2, 3), option)
        log_prob = np.log(np.broadcast_to(p if option else 1 - p, (16, 2, 3)))
        rollout = Rollout({}, broadcast, np.zeros(0), np.zeros(0), [], {}, replays)
        advantages = model.replayed_advantages(rollout, log_prob) / 6  # N / share = 3 / 0.5
        # the surrogate's gradient in the broadcast logit: advantage times d log mu(o) / d logit = o - p
        np.testing.assert_allclose(advantages * (option - p), p * (1 - p) * [0.2, -0.3, 0.1], atol=1e-7)


def test_replays_need_envs_in_the_learners_process() -> None:
    env = make_vec_env(ENV_ID, n_envs=2, vec_env_cls=SubprocVecEnv)
    try:
        model = MAPPOC("MlpHybridPolicy", env, broadcast_advantage="replayed", n_steps=8, batch_size=8)
        with pytest.raises(ValueError, match="must run in the learner's process"):
            model.learn(16)
    finally:
        env.close()
    model = MAPPOC("MlpHybridPolicy", ENV_ID, broadcast_advantage="replayed", n_envs=2, n_steps=8)
    assert isinstance(model.env, DummyVecEnv)  # built in this process from an env id


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("replay_share", 0.0),
        ("replay_share", 1.5),
        ("replay_horizon", 0),
        ("replay_temperature", 0.0),
        ("replay_choice", "greedy"),
    ],
)
def test_bad_replay_settings_are_refused(name: str, value: float) -> None:
    with pytest.raises(ValueError, match=name):
        MAPPOC("MlpHybridPolicy", make_vec_env(ENV_ID, n_envs=1), broadcast_advantage="replayed", **{name: value})


def test_a_fixed_triggers_rollout_is_not_replayed() -> None:
    model = replayed_model()
    model.set_fixed_trigger(PeriodicTrigger(2))
    model.learn(16)
    assert model.sampler.sample(model.env, model.last_obs, 4, 0.0, PeriodicTrigger(2)).replays is None


def test_replayed_value_targets_hand_computed() -> None:
    model = replayed_model(
        broadcast_advantage="replayed_value",
        replay_share=0.5,
        replay_temperature=0.25,
        normalize_broadcast_advantage=False,
        policy_kwargs={"broadcast_interval": (2, 4)},
    )
    model.learn(16)  # reads the rollout's settings
    model.broadcast_price = 0.05
    steps, envs, agents = np.array([0, 3, 5]), np.array([1, 0, 1]), np.array([2, 0, 1])
    rewards = np.array([[0.0, 1.0, 2.0], [-3.0, 0.0, 0.0], [0.0, 0.5, 0.0]])
    age = np.ones((16, 2, 3, 1), np.float32)  # intervals of 2 if they broadcast now: the trigger's choice
    age[5, 1, 1] = 0.0  # an interval of 1, shorter than the window's 2: silence forced, no target
    replays = Replays(steps, envs, agents, rewards, np.eye(3)[agents], np.full(3, 0.5 / 3))
    rollout = Rollout({"age": age}, np.zeros((16, 2, 3), np.int64), np.zeros(0), np.zeros(0), [], {}, replays)
    expected = [(0.2 - 0.05) / 0.25, (-0.3 - 0.05) / 0.25, np.nan]  # (0.1 r_agent - price) / temperature
    np.testing.assert_allclose(model.replayed_logit_targets(rollout), expected, atol=1e-6)


def test_replayed_value_stores_targets_at_the_replayed_decisions_only() -> None:
    model = replayed_model(broadcast_advantage="replayed_value", replay_share=0.5)
    model.learn(32)
    targets = model.rollout_buffer.broadcast_advantages
    assert 0 < np.isfinite(targets).sum() <= 16 * 2
    assert np.isnan(targets).any(axis=-1).all()  # at most one agent per step and env
    assert all(th.isfinite(view).all() for view in model.policy.net_parameters("mu"))
    model.set_fixed_trigger(PeriodicTrigger(2))
    model.learn(16)  # a fixed trigger's rollout has no replays, so no targets
    assert np.isnan(model.rollout_buffer.broadcast_advantages).all()


def test_the_fitted_logit_loss_hand_computed() -> None:
    logit = th.tensor([[1.0, -2.0], [0.5, 0.0], [3.0, 1.0]])
    targets = th.tensor([[2.0, th.nan], [th.nan, th.nan], [1.0, 4.0]])
    evaluation = HybridEvaluation(*[th.zeros(3, 2)] * 3, th.zeros(3, 2, 2), logit)
    data = SimpleNamespace(broadcast_advantages=targets)
    # agent 0: errors 1 and 2 over its two targets; agent 1: error 3 over its one
    expected = (1.0 + 4.0) / 2 + 9.0
    logit.requires_grad_(True)
    loss = fitted_logit_loss(evaluation, data, th.ones(3, 2), 0.2)
    assert loss.item() == pytest.approx(expected)
    loss.backward()  # 2 (logit - target) / (the agent's targets), nothing where there is no target
    th.testing.assert_close(logit.grad, th.tensor([[-1.0, 0.0], [0.0, 0.0], [2.0, -6.0]]))


def test_replayed_value_fits_mus_logit_to_its_targets() -> None:
    model = replayed_model(broadcast_advantage="replayed_value", n_epochs=30, learning_rate=3e-3)
    model.learn(16)
    buffer = model.rollout_buffer
    steps, envs = np.nonzero(np.ones((16, 2), bool))
    buffer.set_broadcast_advantages(steps, envs, np.zeros_like(steps), np.full(len(steps), 2.0), elsewhere=np.nan)
    obs = {key: th.as_tensor(value.reshape(32, *value.shape[2:])) for key, value in buffer.observations.items()}

    def agent_0_logit() -> th.Tensor:
        with th.no_grad():
            p = model.policy.broadcast_probabilities(obs)[:, 0]
        return th.log(p / (1 - p))

    before = (agent_0_logit() - 2.0).abs().mean().item()
    model.train()
    assert (agent_0_logit() - 2.0).abs().mean().item() < 0.25 * before


def test_a_replaying_model_loaded_with_an_env_id_runs_its_envs_here(tmp_path: Any) -> None:
    model = MAPPOC("MlpHybridPolicy", ENV_ID, broadcast_advantage="replayed_expected", n_envs=2, n_steps=8)
    model.save(tmp_path / "model")
    loaded = MAPPOC.load(tmp_path / "model", ENV_ID)
    try:
        assert isinstance(loaded.env, DummyVecEnv) and loaded.n_envs == 2
        loaded.learn(16)  # replays copy the envs: rollout workers would be refused here
    finally:
        loaded.env.close()
