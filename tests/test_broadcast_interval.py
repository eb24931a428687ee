"""A policy over options inside a window of broadcast intervals (``broadcast_interval``)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.evaluation import ThresholdedOptions
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.critics import CRITICS
from sb3_detc.mappoc.losses import STEP_STATS
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.network import interval_window
from sb3_detc.triggers import PeriodicTrigger

LINEAR = "sb3_detc/LinearETC-v0"


def make(window: Any, **policy_kwargs: Any) -> MAPPOC:
    env = make_vec_env(LINEAR, n_envs=2, seed=0, env_kwargs={"max_cycles": 40})
    kwargs = {"net_arch": [8], "broadcast_interval": window, "broadcast_prob_init": 0.5, **policy_kwargs}
    return MAPPOC("MlpHybridPolicy", env, n_steps=64, batch_size=64, n_epochs=2, seed=0, policy_kwargs=kwargs)


@pytest.mark.parametrize("critic", sorted(CRITICS))
def test_the_window_decides_outside_it_and_mu_inside_it(critic: str) -> None:
    model = make((3, 6), critic=critic)
    model.learn(128)
    rollout = model.rollout_buffer.tensors()
    interval = rollout.observations["age"][..., 0] + 1  # what a broadcast now would end
    broadcast, log_prob = rollout.broadcast, rollout.old_log_prob_broadcast
    assert (broadcast[interval < 3] == 0).all() and (broadcast[interval >= 6] == 1).all()
    forced = (interval < 3) | (interval >= 6)
    assert forced.any() and (log_prob[forced] == 0).all()  # drawn with probability one
    free = broadcast[~forced].float()
    assert 0 < free.mean() < 1  # an undecided mu uses both options inside the window
    assert (interval <= 6).all()  # no silence outlasts the window


def test_decisions_the_window_takes_carry_no_gradient() -> None:
    model = make((3, 6))
    model.learn(64)
    rollout = model.rollout_buffer.tensors()
    interval = rollout.observations["age"][..., 0] + 1
    forced = (interval < 3) | (interval >= 6)
    evaluation = model.policy.evaluate_actions(rollout.observations, rollout.broadcast, rollout.control)
    assert (evaluation.entropy_broadcast[forced] == 0).all() and th.isfinite(evaluation.entropy_broadcast).all()
    params = [p for p in model.policy.parameters() if p.requires_grad]
    grads = th.autograd.grad(evaluation.log_prob_broadcast[forced].sum(), params, allow_unused=True, retain_graph=True)
    assert all(g is None or (g == 0).all() for g in grads)
    grads = th.autograd.grad(evaluation.log_prob_broadcast[~forced].sum(), params, allow_unused=True)
    assert any(g is not None and (g != 0).any() for g in grads)


def test_a_window_of_one_interval_runs_the_periodic_schedule() -> None:
    model = make((4, 4))
    env = model.get_env()
    obs = env.reset()
    trigger = PeriodicTrigger(4)
    for _ in range(30):
        action, _ = model.predict(obs, deterministic=False)
        np.testing.assert_array_equal([a["broadcast"] for a in action], trigger(obs))
        obs, _, _, _ = env.step(action)
    probabilities = model.policy.broadcast_probabilities(model.policy.obs_to_tensor(obs)[0])
    assert set(probabilities.unique().tolist()) <= {0.0, 1.0}


def test_the_window_is_saved_with_the_policy_and_reaches_the_agent_controllers(tmp_path) -> None:
    model = make([2, 5])
    model.policy.save(tmp_path / "policy.pt")
    loaded = MlpHybridPolicy.load(tmp_path / "policy.pt")
    assert loaded.broadcast_interval == model.policy.broadcast_interval == (2, 5)
    controller = loaded.agent_controller(0)
    trigger = np.zeros(loaded.observation_space["trigger"].shape[1], dtype=np.float32)
    assert not controller.decide(trigger, trigger, deterministic=False, own_age=0.0)  # an interval of 1 < 2
    assert controller.decide(trigger, trigger, deterministic=False, own_age=4.0)  # an interval of 5 reached
    with pytest.raises(ValueError, match="pass own_age"):
        controller.decide(trigger, trigger)


@pytest.mark.parametrize("window", [(0, 3), (5, 3), (2.5, 4), (2, 3, 4), "24", (True, 3), 16])
def test_a_bad_window_is_refused_in_one_line(window: Any) -> None:
    with pytest.raises(ValueError, match=r"broadcast_interval must be two integers .* got"):
        make(window)


def test_a_window_needs_the_ages_to_evaluate_stored_options() -> None:
    model = make((2, 4))
    model.learn(64)
    rollout = model.rollout_buffer.tensors()
    inputs = model.policy.training_inputs(rollout.observations, rollout.broadcast)
    with pytest.raises(ValueError, match="needs the agents' ages"):
        model.policy.evaluate_inputs(inputs, rollout.broadcast, rollout.control)


def forced_rows(model: MAPPOC) -> tuple[th.Tensor, th.Tensor]:
    """The last rollout's samples where the window decided every agent's option, and where it decided none."""
    interval = model.rollout_buffer.tensors().observations["age"][..., 0] + 1
    forced = (interval < 3) | (interval >= 6)
    return th.nonzero(forced.all(-1))[:, 0], th.nonzero((~forced).all(-1))[:, 0]


def test_the_training_loss_reads_the_window() -> None:
    model = make((3, 6))
    model.learn(128)
    update = model.update_inputs(model.rollout_buffer.tensors())
    forced, free = forced_rows(model)
    assert len(forced) and len(free)
    stats = {
        name: [dict(zip(STEP_STATS, model.loss(update, idx)[1].tolist(), strict=True))[name] for idx in (forced, free)]
        for name in ("entropy_mu", "kl_mu")
    }
    assert stats["entropy_mu"][0] == 0 and stats["kl_mu"][0] == 0  # pinned: no entropy, no change
    assert stats["entropy_mu"][1] > 0.1


def test_state_values_average_the_options_the_window_allows() -> None:
    model = make((3, 6))
    model.learn(64)
    obs = model.rollout_buffer.tensors().observations
    with th.no_grad():
        values = model.policy.state_values(obs)
        p = model.policy.broadcast_probabilities(obs)
        q = model.policy(obs).option_values  # the option heads' values do not depend on the options drawn
    assert set(p[forced_rows(model)[0]].unique().tolist()) <= {0.0, 1.0}
    th.testing.assert_close(values, (1 - p) * q[..., 0] + p * q[..., 1])


def test_imitation_cannot_move_the_options_the_window_takes() -> None:
    model = make((3, 6))
    model.learn(64)
    obs = model.rollout_buffer.tensors().observations
    interval = obs["age"][..., 0] + 1
    always = th.ones_like(interval, dtype=th.long)  # a broadcast at every step: not within the window
    accuracy = model.policy.imitate_options(obs, always, gradient_steps=300)
    assert accuracy == pytest.approx(float((interval >= 3).float().mean()), abs=1e-6)


def test_mu_thresholded_keeps_the_window_at_every_threshold() -> None:
    model = make((2, 4))
    env = model.get_env()
    obs = env.reset()
    for _ in range(12):  # ages across the whole window
        action, _ = model.predict(obs, deterministic=False)
        obs, _, _, _ = env.step(action)
        silent, broadcast = interval_window(obs["age"], 2, 4)
        for threshold in (1e-6, 0.5, 1.5):
            options = ThresholdedOptions(model.policy, threshold)(obs)
            assert (options[silent] == 0).all() and (options[broadcast] == 1).all()
        never = ThresholdedOptions(model.policy, 1.5)(obs)
        np.testing.assert_array_equal(never, broadcast)  # above 1: only the forced broadcasts
