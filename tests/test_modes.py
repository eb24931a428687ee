"""MAPPOC's public seams: the fast setting from an env id, and the modes that callbacks switch."""

from __future__ import annotations

import multiprocessing
import os

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.mappoc import PAPER_ITERATION
from sb3_detc.mappoc.rewards import RewardTransform
from sb3_detc.mappoc.sampling import has_rollout_workers
from sb3_detc.mappoc.steps import COMPILE_FROM_TIMESTEPS, FusedGradientStep, GradientStep, has_cxx_compiler
from sb3_detc.mappoc.workers import default_n_envs, make_rollout_workers
from sb3_detc.triggers import RandomTrigger

ENV_ID = "sb3_detc/LinearETC-v0"
TINY = {"net_arch": [8]}


def always_broadcast(obs: dict[str, np.ndarray]) -> np.ndarray:
    """A fixed trigger: every agent broadcasts (options for the batch of joint observations)."""
    return np.ones(obs["age"].shape[:-1], np.int64)


def make_model(**kwargs) -> MAPPOC:
    env = make_vec_env(ENV_ID, n_envs=1, seed=0, env_kwargs={"n_agents": 2, "max_cycles": 20})
    settings = {"n_steps": 16, "batch_size": 16, "n_epochs": 1, "policy_kwargs": TINY, "seed": 0, **kwargs}
    return MAPPOC("MlpHybridPolicy", env, **settings)


@pytest.mark.parametrize("cores, workers", [(1, 1), (2, 2), (3, 2), (6, 4), (7, 4), (8, 8), (64, 8)])
def test_default_workers_divide_the_paper_iteration(monkeypatch: pytest.MonkeyPatch, cores: int, workers: int) -> None:
    """One worker per core, rounded down to a power of two (at most 8): 2048 steps split evenly."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)), raising=False)
    assert default_n_envs() == workers and PAPER_ITERATION % workers == 0


def test_the_one_liner_builds_the_fast_setting() -> None:
    """From an env id alone: rollout workers (one process per core), the paper's iteration, compiled when worth it."""
    model = MAPPOC("MlpHybridPolicy", ENV_ID)
    env = model.get_env()
    try:
        assert has_rollout_workers(env) and model.n_envs == default_n_envs()
        assert isinstance(env, SubprocVecEnv if model.n_envs > 1 else DummyVecEnv)
        assert model.n_steps * model.n_envs == PAPER_ITERATION == 2048
        # compiled and fused for a long run where a C++ compiler exists, eager for a short one
        assert type(gradient_step_of_learn(model, COMPILE_FROM_TIMESTEPS)) is (
            FusedGradientStep if has_cxx_compiler() else GradientStep
        )
        assert type(gradient_step_of_learn(model, COMPILE_FROM_TIMESTEPS - 1)) is GradientStep
    finally:
        env.close()


class LearnStarted(Exception):
    """Ends a ``learn`` call before its first rollout."""


def gradient_step_of_learn(model: MAPPOC, total_timesteps: int) -> object:
    """The gradient step that ``model.learn(total_timesteps)`` trains with (stopped before it collects anything)."""

    class Peek(BaseCallback):
        def _on_training_start(self) -> None:
            raise LearnStarted(self.model.gradient_step)

        def _on_step(self) -> bool:
            return True

    with pytest.raises(LearnStarted) as started:
        model.learn(total_timesteps, callback=Peek())
    return started.value.args[0]


def test_envs_built_from_an_id_on_request(tmp_path) -> None:
    model = MAPPOC("MlpHybridPolicy", ENV_ID, n_envs=1, n_steps=16, batch_size=16, n_epochs=1, policy_kwargs=TINY)
    assert isinstance(model.get_env(), DummyVecEnv) and has_rollout_workers(model.get_env())
    model.learn(16)
    assert model.sampler.last_in_workers
    model.save(tmp_path / "model.zip")
    loaded = MAPPOC.load(tmp_path / "model.zip", env=ENV_ID)  # as many workers as it was trained with
    assert loaded.n_envs == 1 and has_rollout_workers(loaded.get_env())
    given = make_vec_env(ENV_ID, n_envs=1)
    assert MAPPOC("MlpHybridPolicy", given, policy_kwargs=TINY).n_steps == 2048  # one env: the whole iteration
    with pytest.raises(ValueError, match="n_envs is the number of envs MAPPOC builds from an env id"):
        MAPPOC("MlpHybridPolicy", given, n_envs=2)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="n_envs must be a positive integer"):
            MAPPOC("MlpHybridPolicy", ENV_ID, n_envs=bad)
    with pytest.raises(ValueError, match="torch_compile must be True, False or 'auto'"):
        MAPPOC("MlpHybridPolicy", given, torch_compile="yes")


def test_a_fixed_trigger_decides_and_mu_is_not_trained() -> None:
    model = make_model(fixed_trigger=always_broadcast)
    mu = [view.clone() for view in model.policy.net_parameters("mu")]
    model.learn(32)
    assert model.rollout_buffer.broadcast.all()
    for before, after in zip(mu, model.policy.net_parameters("mu"), strict=True):
        assert th.equal(before, after)
    model.set_fixed_trigger(None)
    model.learn(32)
    assert not model.rollout_buffer.broadcast.all()
    assert not all(th.equal(a, b) for a, b in zip(mu, model.policy.net_parameters("mu"), strict=True))
    with pytest.raises(ValueError, match="must be callable"):
        model.set_fixed_trigger(0.5)
    centred = make_model(policy_kwargs={**TINY, "critic": "centred"})  # needs the probabilities mu drew with
    with pytest.raises(ValueError, match="use critic='option_heads' or 'afterstate' with a fixed trigger"):
        centred.set_fixed_trigger(always_broadcast)


@pytest.mark.parametrize("critic", ["option_heads", "afterstate"])
@pytest.mark.parametrize("skip_prob", [0.0, 0.3])
def test_under_a_fixed_trigger_the_rollout_ends_are_valued_under_its_probabilities(
    critic: str, skip_prob: float
) -> None:
    """The bootstrap averages Q(s_T, o) under the trigger's probabilities of broadcasting, not under mu's.

    mu almost never broadcasts here, the trigger mostly does: the two values differ. The afterstate
    critic's values depend on the others' options, drawn from the trigger: exact where it always broadcasts.
    """
    kwargs = {**TINY, "critic": critic, "broadcast_prob_init": 1e-3}
    model = make_model(policy_kwargs=kwargs, learning_rate=0.0, fixed_trigger=RandomTrigger(skip_prob, seed=5))
    model.learn(16)  # one rollout of 16 steps; the episodes of 20 steps go on after it
    buffer = model.rollout_buffer
    assert not buffer.episode_starts[1:].any()
    obs = obs_as_tensor(model.last_obs, model.device)
    price = th.as_tensor(buffer.broadcast_price[-1], device=model.device)
    with th.no_grad():
        q = model.policy.evaluate_actions(obs, th.ones((1, 2)), th.zeros((1, 2, 1)), price).option_values
        under_mu = model.policy.state_values(obs, price)
    bootstrap = th.as_tensor((buffer.returns[-1] - buffer.rewards[-1]) / model.gamma)
    if critic == "option_heads" or skip_prob == 0.0:
        th.testing.assert_close(bootstrap, skip_prob * q[..., 0] + (1 - skip_prob) * q[..., 1], rtol=1e-4, atol=1e-5)
    assert not th.allclose(bootstrap, under_mu, rtol=1e-3, atol=1e-4)


def test_trained_policies_are_chosen_by_level() -> None:
    model = make_model()
    model.set_trained_policies(control_policy=False, broadcast_policy=True)
    pi, mu = ([view.clone() for view in model.policy.net_parameters(net)] for net in ("pi", "mu"))
    model.learn(32)
    assert all(th.equal(a, b) for a, b in zip(pi, model.policy.net_parameters("pi"), strict=True))
    assert not all(th.equal(a, b) for a, b in zip(mu, model.policy.net_parameters("mu"), strict=True))


def test_action_noise_is_the_largest_term_of_its_sources() -> None:
    model = make_model(action_noise_std=0.3)
    assert model.action_noise_std == 0.3
    first, second = object(), object()
    model.set_action_noise_std(0.1, source=first)
    assert model.action_noise_std == 0.1  # a source's term replaces the constructor's value
    model.set_action_noise_std(0.2, source=second)
    model.set_action_noise_std(0.05, source=first)
    assert model.action_noise_std == 0.2
    model.set_action_noise_std(None, source=second)
    model.set_action_noise_std(0.0, source=first)
    assert model.action_noise_std == 0.0
    with pytest.raises(ValueError, match="must be >= 0"):
        model.set_action_noise_std(-0.1)


def test_learning_rate_and_reward_normalization_switch_for_the_next_update() -> None:
    model = make_model(learning_rate=1e-3)
    model.learn(16)
    model.set_learning_rate(lambda progress: 5e-4)
    model.set_reward_normalization(True)
    model.learn(16)
    assert model.policy.optimizer.param_groups[0]["lr"] == 5e-4
    assert model.normalize_reward and model.reward_transform.return_rms is not None


def test_reward_transform_hand_computed() -> None:
    rewards, dones = np.array([[1.0, 3.0]], np.float32), np.array([False])
    own = RewardTransform(2, gamma=0.5, scale=0.1, team=False, normalize=False)
    np.testing.assert_allclose(own(rewards, dones), [[0.1, 0.3]], rtol=1e-6)
    np.testing.assert_allclose(own.price(np.array([0.4], np.float32)), [[0.04, 0.04]], rtol=1e-6)
    team = RewardTransform(2, gamma=0.5, scale=0.1, team=True, normalize=False)
    np.testing.assert_allclose(team(rewards, dones), [[0.2, 0.2]], rtol=1e-6)
    np.testing.assert_allclose(team.price(np.array([0.4], np.float32)), [[0.02, 0.02]], rtol=1e-6)

    normalized = RewardTransform(2, gamma=0.5, scale=1.0, team=False, normalize=True)
    normalized(rewards, dones)  # discounted returns (1, 3)
    out = normalized(rewards, np.array([True]))  # discounted returns (1.5, 4.5), then cut
    returns = np.array([[1.0, 3.0], [1.5, 4.5]])
    spread = np.sqrt(normalized.return_rms.var + 1e-8)
    np.testing.assert_allclose(normalized.return_rms.mean, returns.mean(0), rtol=1e-3)
    np.testing.assert_allclose(out, rewards / spread, rtol=1e-5)
    np.testing.assert_allclose(normalized.price(np.array([0.4], np.float32)), 0.4 / spread[None], rtol=1e-5)
    assert normalized.discounted_returns.tolist() == [[0.0, 0.0]]


def test_reward_transform_refuses_missing_or_non_finite_rewards() -> None:
    from sb3_detc.mappoc.rewards import agent_rewards

    with pytest.raises(ValueError, match="info\\['agent_rewards'\\]"):
        agent_rewards([{}])
    with pytest.raises(ValueError, match="non-finite rewards"):
        agent_rewards([{"agent_rewards": np.array([0.0, np.inf])}])


def test_a_saved_model_keeps_its_reward_statistics(tmp_path) -> None:
    model = make_model(normalize_reward=True)
    model.learn(32)
    model.save(tmp_path / "model.zip")
    loaded = MAPPOC.load(tmp_path / "model.zip")
    np.testing.assert_array_equal(loaded.reward_transform.return_rms.var, model.reward_transform.return_rms.var)
    assert loaded.reward_transform.discounted_returns is None  # the envs' episodes are not saved


def test_bad_arguments_with_an_env_id_start_no_worker_processes() -> None:
    before = set(multiprocessing.active_children())
    with pytest.raises(ValueError, match="batch_size must be a positive integer"):
        MAPPOC("MlpHybridPolicy", ENV_ID, batch_size=0)
    with pytest.raises(ValueError, match="broadcast_advantage must be"):
        MAPPOC("MlpHybridPolicy", ENV_ID, broadcast_advantage="best")
    assert set(multiprocessing.active_children()) == before


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"policy": "Mlp"}, "Policy Mlp unknown"),  # SB3's own refusal
        (  # what only the policy can check: its critic against the price rule
            {"target_savings": 0.9, "broadcast_price_rule": "quantile", "policy_kwargs": {"critic": "option_heads"}},
            "needs a critic that adds the price",
        ),
    ],
)
def test_a_model_that_cannot_be_built_ends_the_worker_processes_it_started(monkeypatch, arguments, message) -> None:
    from sb3_detc.mappoc import mappoc

    before, started = set(multiprocessing.active_children()), []

    def workers(*args, **kwargs):
        env = make_rollout_workers(*args, **kwargs)
        started.append(set(multiprocessing.active_children()) - before)
        return env

    monkeypatch.setattr(mappoc, "make_rollout_workers", workers)
    with pytest.raises(ValueError, match=message):
        MAPPOC(**{"policy": "MlpHybridPolicy", "env": ENV_ID, "n_envs": 2, **arguments})
    assert len(started) == 1 and len(started[0]) >= 2  # the workers had started
    assert set(multiprocessing.active_children()) == before
