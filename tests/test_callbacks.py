"""Curriculum, baseline and communication-metric callbacks (sb3_detc.callbacks) and the non-learned triggers."""

from __future__ import annotations

import copy
import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from logged import capture_logger  # tests/logged.py
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.callbacks import (
    IMITATED,
    ActionNoiseSchedule,
    BroadcastEntropySchedule,
    CommMetricsCallback,
    ControlFirstCallback,
    CurriculumCallback,
    DeltaFirstCallback,
    FixedTriggerCallback,
    PeriodicCommCallback,
    RandomSkipCallback,
    ScheduleFirstCallback,
    SelectBestCallback,
    TentNoiseSchedule,
    linear_decay,
    set_broadcast_cost,
    tent,
)
from sb3_detc.envs import linear_etc_v0, multiwalker_etc_v0
from sb3_detc.evaluation import evaluate_episodes
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.mappoc import PAPER_ITERATION
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.mappoc.workers import RolloutWorker
from sb3_detc.triggers import PeriodicTrigger, RandomTrigger, SendOnDelta

ENV_ID = "sb3_detc/LinearETC-v0"
TINY = {"net_arch": [16, 16]}


# --------------------------------------------------------------------------- helpers
def make_model(
    n_agents: int = 2, n_envs: int = 1, max_cycles: int = 20, broadcast_cost: float = 0.01, **kwargs: Any
) -> MAPPOC:
    env = make_vec_env(
        ENV_ID,
        n_envs=n_envs,
        env_kwargs={"n_agents": n_agents, "max_cycles": max_cycles, "broadcast_cost": broadcast_cost},
    )
    kwargs = {"n_steps": 8, "batch_size": 8, "n_epochs": 1, "learning_rate": 1e-3, **kwargs}
    return MAPPOC("MlpHybridPolicy", env, seed=0, policy_kwargs=TINY, **kwargs)


def net_slices(model: MAPPOC, net: str) -> list[th.Tensor]:
    return [view.clone() for view in model.policy.net_parameters(net)]


class Record(BaseCallback):
    """Records the model's curriculum attributes during every rollout and the infos of every step."""

    def __init__(self) -> None:
        super().__init__()
        self.noise: list[float] = []  # per rollout, read during its steps
        self.zeta: list[float] = []  # per rollout, read before its update
        self.infos: list[list[dict[str, Any]]] = []

    def _on_step(self) -> bool:
        if len(self.noise) < self.n_rollouts:
            self.noise.append(self.model.action_noise_std)
        self.infos.append(self.locals["infos"])
        return True

    def _on_training_start(self) -> None:
        self.n_rollouts = 0

    def _on_rollout_start(self) -> None:
        self.n_rollouts += 1

    def _on_rollout_end(self) -> None:
        self.zeta.append(float(self.model.broadcast_ent_coef))


# --------------------------------------------------------------------------- pure schedules
def test_schedule_functions_hand_computed() -> None:
    assert linear_decay(-5, 0, 10, 2.0, 1.0) == 2.0
    assert linear_decay(5, 0, 10, 2.0, 1.0) == 1.5
    assert linear_decay(15, 0, 10, 2.0, 1.0) == 1.0
    assert [tent(t, 10, 20, 40, 1.0) for t in (0, 10, 15, 20, 30, 40, 50)] == [0, 0, 0.5, 1, 0.5, 0, 0]


@pytest.mark.parametrize(("h", "sigma"), [(0, 0.25), (450, 0.125), (900, 0.0), (1000, 0.0), (3000, 0.0)])
def test_phase_one_noise_decay_paper_values(h: int, sigma: float) -> None:
    assert ActionNoiseSchedule().value(h) == pytest.approx(sigma, abs=1e-12)


@pytest.mark.parametrize(
    ("h", "zeta"), [(0, 3.2), (800, 3.2), (1150, (3.2 + 0.64) / 2), (1500, 0.64), (2000, 0.64), (3000, 0.64)]
)
def test_phase_two_entropy_paper_values(h: int, zeta: float) -> None:
    assert BroadcastEntropySchedule().value(h) == pytest.approx(zeta, abs=1e-12)
    # The paper's minibatch-sum numbers times the minibatch size 32.
    assert BroadcastEntropySchedule().value(0) == pytest.approx(32 * 0.1)
    assert BroadcastEntropySchedule().value(1500) == pytest.approx(32 * 0.02)


@pytest.mark.parametrize(
    ("h", "sigma"),
    [(0, 0.0), (1500, 0.0), (1750, 0.125), (2000, 0.25), (2250, 0.125), (2500, 0.0), (3000, 0.0)],
)
def test_phase_three_tent_paper_values(h: int, sigma: float) -> None:
    assert TentNoiseSchedule().value(h) == pytest.approx(sigma, abs=1e-12)


@pytest.mark.parametrize(
    ("h", "phase", "noise", "zeta"),
    [
        (0, "I", 0.25, 3.2),
        (450, "I", 0.125, 3.2),
        (799, "I", 0.25 * 101 / 900, 3.2),
        (800, "II", 0.25 / 9, 3.2),
        (900, "II", 0.0, 3.2 - (3.2 - 0.64) / 7),
        (1150, "II", 0.0, 1.92),
        (1499, "II", 0.0, 0.64 + (3.2 - 0.64) / 700),
        (1500, "III", 0.0, 0.64),
        (1750, "III", 0.125, 0.64),
        (2000, "III", 0.25, 0.64),
        (2250, "III", 0.125, 0.64),
        (2499, "III", 0.25 / 500, 0.64),
        (2500, "done", 0.0, 0.64),
        (5000, "done", 0.0, 0.64),
    ],
)
def test_curriculum_values_and_phases(h: int, phase: str, noise: float, zeta: float) -> None:
    values = CurriculumCallback().values(h)
    assert values["phase"] == phase
    assert values["action_noise_std"] == pytest.approx(noise, abs=1e-12)
    assert values["broadcast_ent_coef"] == pytest.approx(zeta, abs=1e-12)
    assert values["action_noise_std"] == max(values["noise_decay"], values["noise_tent"])


def test_timesteps_unit_defaults_are_the_paper_iterations_times_2048() -> None:
    steps = PAPER_ITERATION
    assert steps == 2048
    curriculum = CurriculumCallback(unit="timesteps")
    for h in (0, 450, 800, 900, 1150, 1500, 1750, 2000, 2250, 2500):
        assert curriculum.values(h * steps) == CurriculumCallback().values(h)
    assert curriculum.values(450) == CurriculumCallback().values(450 / steps)
    # Explicit boundaries are taken as timesteps as given.
    noise = ActionNoiseSchedule(initial_std=0.5, end=1000, unit="timesteps")
    assert [noise.value(t) for t in (0, 500, 1000, 2000)] == [0.5, 0.25, 0.0, 0.0]
    zeta = BroadcastEntropySchedule(initial=1.0, final=0.0, start=100, end=300, unit="timesteps")
    assert [zeta.value(t) for t in (0, 100, 200, 300, 400)] == [1.0, 1.0, 0.5, 0.0, 0.0]
    bump = TentNoiseSchedule(peak_std=1.0, start=100, peak=200, end=400, unit="timesteps")
    assert [bump.value(t) for t in (100, 150, 200, 300, 400)] == [0.0, 0.5, 1.0, 0.5, 0.0]


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: ActionNoiseSchedule(initial_std=-0.1), "initial_std"),
        (lambda: ActionNoiseSchedule(initial_std=math.nan), "initial_std"),
        (lambda: ActionNoiseSchedule(end=0), "increase"),
        (lambda: ActionNoiseSchedule(start=-1), "start"),
        (lambda: ActionNoiseSchedule(unit="episodes"), "unit"),
        (lambda: BroadcastEntropySchedule(final=-1), "final"),
        (lambda: BroadcastEntropySchedule(start=1500, end=800), "increase"),
        (lambda: TentNoiseSchedule(start=1500, peak=1500, end=2500), "increase"),
        (lambda: TentNoiseSchedule(peak=3000), "increase"),
        (lambda: TentNoiseSchedule(peak_std=-1), "peak_std"),
        (lambda: CurriculumCallback(ent_start=2000), "increase"),
        (lambda: CurriculumCallback(tent_std=-0.25), "peak_std"),
        (lambda: CurriculumCallback(unit="rollouts"), "unit"),
        (lambda: ControlFirstCallback(0), "switch"),
        (lambda: ControlFirstCallback(-3), "switch"),
        (lambda: ControlFirstCallback(math.inf), "switch"),
        (lambda: ControlFirstCallback(5, skip_prob=1.5), "skip_prob"),
        (lambda: ScheduleFirstCallback(0, 16), "switch"),
        (lambda: ScheduleFirstCallback(5, 0), "period"),
        (lambda: ScheduleFirstCallback(5, 16, imitation_steps=0), "imitation_steps"),
        (lambda: DeltaFirstCallback(5, -1.0), "delta"),
        (lambda: DeltaFirstCallback(5, 0.1, max_age=0), "max_age"),
    ],
)
def test_bad_schedule_arguments_are_rejected(make: Any, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make()


# --------------------------------------------------------------------------- curriculum in training
SCALED = {"noise_end": 4, "ent_start": 3, "ent_end": 6, "tent_start": 6, "tent_peak": 8, "tent_end": 10}


@pytest.mark.parametrize("unit", ["iterations", "timesteps"])
def test_curriculum_values_reach_the_model_and_the_logger(unit: str) -> None:
    n_steps, n_iterations = 8, 12
    model = make_model(n_steps=n_steps)
    scale = 1 if unit == "iterations" else n_steps
    curriculum = CurriculumCallback(**{key: value * scale for key, value in SCALED.items()}, unit=unit)
    reference = CurriculumCallback(**SCALED)  # the same schedule in iterations
    record = Record()
    capture = capture_logger(model)
    model.learn(n_steps * n_iterations, callback=CallbackList([curriculum, record]))

    expected = [reference.values(h) for h in range(n_iterations)]
    # During rollout h the model uses the noise of iteration h; its update uses zeta of iteration h.
    np.testing.assert_allclose(record.noise, [v["action_noise_std"] for v in expected], atol=1e-12)
    np.testing.assert_allclose(record.zeta, [v["broadcast_ent_coef"] for v in expected], atol=1e-12)
    assert len(set(record.noise)) > 3 and len(set(record.zeta)) > 2  # the values really change
    assert len(capture.rows) == n_iterations
    position = "curriculum/iteration" if unit == "iterations" else "curriculum/timesteps"
    for h, (row, values) in enumerate(zip(capture.rows, expected, strict=True)):
        assert row[position] == h * scale
        assert row["curriculum/phase"] == values["phase"]
        for key in ("action_noise_std", "noise_decay", "noise_tent", "broadcast_ent_coef"):
            assert row[f"curriculum/{key}"] == pytest.approx(values[key], abs=1e-12), (h, key)
        if h > 0:  # train() of iteration h - 1 is dumped with iteration h
            previous = expected[h - 1]
            assert row["train/broadcast_ent_coef"] == pytest.approx(previous["broadcast_ent_coef"], abs=1e-12)
            assert row["train/action_noise_std"] == pytest.approx(previous["action_noise_std"], abs=1e-12)
    phases = [row["curriculum/phase"] for row in capture.rows]
    assert phases == ["I"] * 3 + ["II"] * 3 + ["III"] * 4 + ["done"] * 2


@pytest.mark.parametrize("decay_first", [True, False])
def test_noise_schedules_in_a_callback_list_combine_by_their_maximum(decay_first: bool) -> None:
    n_steps, n_iterations = 8, 8
    model = make_model(n_steps=n_steps)
    decay = ActionNoiseSchedule(initial_std=0.4, end=6)  # 0.4, 1/3, ..., 0 at 6
    bump = TentNoiseSchedule(peak_std=0.3, start=1, peak=3, end=7)  # overlaps the decay
    record = Record()
    callbacks = [decay, bump] if decay_first else [bump, decay]
    model.learn(n_steps * n_iterations, callback=CallbackList([*callbacks, record]))
    expected = [max(decay.value(h), bump.value(h)) for h in range(n_iterations)]
    np.testing.assert_allclose(record.noise, expected, atol=1e-12)
    assert any(bump.value(h) > decay.value(h) > 0 for h in range(n_iterations))  # the maximum switches


# --------------------------------------------------------------------------- two stages
def optimizer_rate(model: MAPPOC) -> float:
    """The learning rate in the optimizer: the one that train() set for its last update."""
    return model.policy.optimizer.param_groups[0]["lr"]


class Stages(BaseCallback):
    """Records per rollout the options' source, which levels train and the optimizer's learning rate at its start."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[tuple[Any, bool, bool]] = []
        self.rates_at_start: list[float] = []  # of the update before the rollout (the first: the initial rate)

    def _on_rollout_start(self) -> None:
        model = self.model
        self.rows.append((model.fixed_trigger, model.train_broadcast_policy, model.train_control_policy))
        self.rates_at_start.append(optimizer_rate(model))

    def update_rates(self) -> list[float]:
        """The learning rate of every update so far, after learn() returned: each rollout's is read at the next."""
        return [*self.rates_at_start[1:], optimizer_rate(self.model)]

    def _on_step(self) -> bool:
        return True


@pytest.mark.parametrize("unit", ["iterations", "timesteps"])
def test_control_first_trains_pi_under_random_skips_then_mu_for_the_frozen_pi(unit: str) -> None:
    n_steps, switch, n_iterations = 32, 2, 4
    model = make_model(n_agents=3, n_steps=n_steps, batch_size=16)
    stages = ControlFirstCallback(switch * (1 if unit == "iterations" else n_steps), 0.7, 5e-4, unit=unit)
    record, metrics, levels = Record(), CommMetricsCallback(), Stages()
    capture = capture_logger(model)
    mu_before = net_slices(model, "mu")
    model.learn(n_steps * switch, callback=[stages, metrics, record, levels])
    mu_stage_1, pi_stage_1 = net_slices(model, "mu"), net_slices(model, "pi")
    model.learn(n_steps * (n_iterations - switch), callback=[stages, metrics, levels], reset_num_timesteps=False)

    assert [row["curriculum/stage"] for row in capture.rows] == [1, 1, 2, 2]
    assert [(trigger is stages.trigger, mu, pi) for trigger, mu, pi in levels.rows] == [
        (True, False, True),
        (True, False, True),
        (False, True, False),
        (False, True, False),
    ]
    assert isinstance(stages.trigger, RandomTrigger) and stages.trigger.skip_prob == 0.7
    assert levels.update_rates() == [1e-3, 1e-3, 5e-4, 5e-4]
    # The logged rates agree (the update of an iteration is dumped with the next iteration).
    assert [row["train/learning_rate"] for row in capture.rows[1:]] == levels.update_rates()[:-1]
    # Stage 1: random options at the rate asked for, mu unchanged, pi trained.
    broadcast = np.array([info["broadcast"] for step in record.infos for info in step])
    assert abs(broadcast.mean() - 0.3) < 4 * math.sqrt(0.3 * 0.7 / broadcast.size)
    assert all(th.equal(a, b) for a, b in zip(mu_before, mu_stage_1, strict=True))
    # Stage 2: mu trained, pi exactly as stage 1 left it.
    assert all(th.equal(a, b) for a, b in zip(pi_stage_1, net_slices(model, "pi"), strict=True))
    assert any(not th.equal(a, b) for a, b in zip(mu_stage_1, net_slices(model, "mu"), strict=True))


def aged_copies(observations: dict[str, th.Tensor], ages: range) -> dict[str, th.Tensor]:
    """Copies of the observations, every agent's own age set to each of ``ages`` in turn."""
    return {
        key: th.cat([th.full_like(value, float(a)) if key == "age" else value for a in ages])
        for key, value in observations.items()
    }


@pytest.mark.parametrize("unit", ["iterations", "timesteps"])
def test_schedule_first_trains_pi_for_the_schedule_then_mu_from_the_schedule_on(unit: str) -> None:
    n_steps, switch, period = 64, 2, 4
    env = make_vec_env(ENV_ID, n_envs=1, env_kwargs={"n_agents": 3, "max_cycles": 20})
    model = MAPPOC(
        "MlpHybridPolicy",
        env,
        n_steps=n_steps,
        batch_size=32,
        n_epochs=1,
        target_savings=0.75,
        seed=0,
        policy_kwargs={**TINY, "option_age_scale": 0.1},
    )
    stages = ScheduleFirstCallback(switch * (1 if unit == "iterations" else n_steps), period, unit=unit)
    levels, record = Stages(), Record()
    capture = capture_logger(model)
    mu_before, pi_before = net_slices(model, "mu"), net_slices(model, "pi")
    model.learn(n_steps, callback=[stages, levels, record])
    # Stage 1: the schedule decides, pi learns, mu does not.
    assert all(th.equal(a, b) for a, b in zip(mu_before, net_slices(model, "mu"), strict=True))
    assert any(not th.equal(a, b) for a, b in zip(pi_before, net_slices(model, "pi"), strict=True))
    steps = [info for step in record.infos for info in step]
    assert [info["broadcast"].tolist() for info in steps[:8]] == [[0, 0, 0]] * 3 + [[1, 1, 1]] + [[0, 0, 0]] * 3 + [
        [1, 1, 1]
    ]
    model.learn(n_steps, callback=[stages, levels], reset_num_timesteps=False)
    # The rollout that ends stage 1 makes mu the schedule: broadcast from age period - 1 on, in every state met.
    observations = aged_copies(model.rollout_buffer.tensors().observations, range(2 * period))
    with th.no_grad():
        mode = (model.policy.broadcast_probabilities(observations) > 0.5).numpy()
    schedule = stages.trigger({"age": observations["age"].numpy()})
    assert (mode == schedule).mean() > 0.99
    assert capture.rows[-1]["curriculum/imitation_accuracy"] > 0.99
    assert model.broadcast_price == 0.0  # the price waits for mu
    mu_imitated, pi_stage_1 = net_slices(model, "mu"), net_slices(model, "pi")
    model.learn(2 * n_steps, callback=[stages, levels], reset_num_timesteps=False)

    assert [row["curriculum/stage"] for row in capture.rows] == [1, 1, 2, 2]
    assert [(trigger is stages.trigger, mu, pi) for trigger, mu, pi in levels.rows] == [
        (True, False, True),
        (True, False, True),
        (False, True, True),
        (False, True, True),
    ]
    assert any(not th.equal(a, b) for a, b in zip(mu_imitated, net_slices(model, "mu"), strict=True))
    assert any(not th.equal(a, b) for a, b in zip(pi_stage_1, net_slices(model, "pi"), strict=True))
    assert model.broadcast_price != 0.0


class SaveAt(BaseCallback):
    """Saves the model after the step at which the step count reaches ``steps`` (within a rollout)."""

    def __init__(self, steps: int, path: Any) -> None:
        super().__init__()
        self.steps, self.path = steps, path

    def _on_step(self) -> bool:
        if self.model.num_timesteps == self.steps:
            self.model.save(self.path)
        return True


def test_schedule_first_resumed_before_the_imitation_imitates_first(tmp_path) -> None:
    """A model saved within stage 1's last rollout (a checkpoint every k steps) runs one more rollout in stage 1."""
    n_steps, switch, period = 32, 2, 4
    env = make_vec_env(ENV_ID, n_envs=1, env_kwargs={"n_agents": 3, "max_cycles": 20})
    policy_kwargs = {**TINY, "option_age_scale": 0.1}
    model = MAPPOC("MlpHybridPolicy", env, n_steps=n_steps, batch_size=32, seed=0, policy_kwargs=policy_kwargs)
    path = tmp_path / "within.zip"
    model.learn(n_steps * switch, callback=[ScheduleFirstCallback(switch, period), SaveAt(n_steps * switch, path)])
    assert getattr(model, IMITATED) == "PeriodicTrigger(period=4, staggered=False)"
    model.save(tmp_path / "after.zip")  # at a rollout's start: imitated
    within = MAPPOC.load(path, env=env)
    assert within.num_timesteps == n_steps * switch and not hasattr(within, IMITATED)
    mu_before = net_slices(within, "mu")
    stages, levels = ScheduleFirstCallback(switch, period), Stages()
    capture = capture_logger(within)
    within.learn(n_steps * 2, callback=[stages, levels], reset_num_timesteps=False)
    assert [(trigger is stages.trigger, mu) for trigger, mu, _ in levels.rows] == [(True, False), (False, True)]
    assert capture.rows[0]["curriculum/imitation_accuracy"] > 0.99
    assert any(not th.equal(a, b) for a, b in zip(mu_before, net_slices(within, "mu"), strict=True))
    after, levels = MAPPOC.load(tmp_path / "after.zip", env=env), Stages()
    after.learn(n_steps, callback=[ScheduleFirstCallback(switch, period), levels], reset_num_timesteps=False)
    assert [mu for _, mu, _ in levels.rows] == [True]  # straight on in stage 2


def test_schedule_first_can_keep_pi_and_needs_the_age_as_an_input_of_mu() -> None:
    model = make_model(n_steps=8)
    levels = Stages()
    with pytest.raises(ValueError, match="option_age_scale"):
        model.learn(8, callback=[ScheduleFirstCallback(1, 4)])
    env = make_vec_env(ENV_ID, n_envs=1, env_kwargs={"n_agents": 2, "max_cycles": 20})
    model = MAPPOC("MlpHybridPolicy", env, n_steps=8, batch_size=8, policy_kwargs={**TINY, "option_age_scale": 0.1})
    model.learn(8 * 2, callback=[ScheduleFirstCallback(1, 4, train_control=False), levels])
    assert [(mu, pi) for _, mu, pi in levels.rows] == [(False, True), (True, False)]


def test_delta_first_starts_mu_as_predictive_triggering_without_reading_the_age() -> None:
    """On the linear system with the receivers' predictions shown, send-on-delta is predictive triggering."""
    env_kwargs = {"n_agents": 3, "max_cycles": 40, "prediction": True, "predicted_held": True}
    env = make_vec_env("sb3_detc/LinearETC-LQR-v0", n_envs=2, env_kwargs=env_kwargs)
    policy_kwargs = {**TINY, "option_distance_scale": 5.0}
    model = MAPPOC("MlpHybridPolicy", env, n_steps=64, batch_size=64, seed=0, policy_kwargs=policy_kwargs)
    stages, levels = DeltaFirstCallback(1, 0.2, imitation_steps=2000), Stages()
    capture = capture_logger(model)
    model.learn(2 * 64 * 2, callback=[stages, levels])  # two rollouts of two envs
    assert [trigger is stages.trigger for trigger, _, _ in levels.rows] == [True, False]
    assert repr(stages.trigger) == "SendOnDelta(delta=0.2, norm=2, max_age=None)"
    # mu decides as the rule on the first rollout's states (its second rollout came from mu itself)
    assert capture.rows[0]["curriculum/imitation_accuracy"] > 0.97
    observations = model.rollout_buffer.tensors().observations
    with th.no_grad():
        mode = (model.policy.broadcast_probabilities(observations) > 0.5).numpy()
    rule = stages.trigger({key: value.numpy() for key, value in observations.items()})
    assert 0.0 < rule.mean() < 1.0 and (mode == rule).mean() > 0.9


def test_imitated_options_change_mu_alone() -> None:
    env = make_vec_env(ENV_ID, n_envs=1, env_kwargs={"n_agents": 3, "max_cycles": 20})
    model = MAPPOC("MlpHybridPolicy", env, n_steps=32, seed=0, policy_kwargs={**TINY, "option_age_scale": 0.1})
    model.learn(32)
    observations = aged_copies(model.rollout_buffer.tensors().observations, range(10))
    options = PeriodicTrigger(5)({"age": observations["age"].numpy()})
    others = {net: net_slices(model, net) for net in ("q", "pi")}
    optimizer_state = copy.deepcopy(model.policy.optimizer.state_dict()["state"])
    accuracy = model.policy.imitate_options(observations, th.as_tensor(options))
    assert accuracy > 0.99
    for net, before in others.items():
        assert all(th.equal(a, b) for a, b in zip(before, net_slices(model, net), strict=True)), net
    after = model.policy.optimizer.state_dict()["state"]
    assert after.keys() == optimizer_state.keys()
    for key, state in optimizer_state.items():
        assert all(th.equal(th.as_tensor(value), th.as_tensor(after[key][name])) for name, value in state.items())
    with pytest.raises(ValueError, match="shaped"):
        model.policy.imitate_options(observations, th.as_tensor(options[:, :2]))


def test_control_first_without_a_learning_rate_keeps_the_models() -> None:
    model = make_model(n_steps=8)
    levels = Stages()
    model.learn(8 * 3, callback=[ControlFirstCallback(1), levels])
    assert levels.update_rates() == [1e-3] * 3
    assert [trigger is None for trigger, _, _ in levels.rows] == [False, True, True]
    assert model.normalize_reward is False


def test_control_first_normalises_the_rewards_of_stage_two_only() -> None:
    rewards = []
    for normalise in (True, False):
        model = make_model(n_steps=8, broadcast_cost=0.0)
        stages = ControlFirstCallback(1, trigger_normalize_reward=normalise)
        model.learn(8, callback=stages)
        stage_1 = model.rollout_buffer.rewards.copy()
        assert model.normalize_reward is False and model.reward_transform.return_rms is None
        model.learn(8, callback=stages, reset_num_timesteps=False)
        assert model.normalize_reward is normalise and (model.reward_transform.return_rms is not None) is normalise
        rewards.append((stage_1, model.rollout_buffer.rewards.copy()))
    (normalised_1, normalised_2), (raw_1, raw_2) = rewards
    np.testing.assert_array_equal(normalised_1, raw_1)  # stage 1: the same rewards
    assert not np.allclose(normalised_2, raw_2)  # stage 2: the same episodes, rescaled rewards
    np.testing.assert_array_equal(np.sign(normalised_2), np.sign(raw_2))


@pytest.mark.parametrize("unit", ["iterations", "timesteps"])
def test_control_first_measures_the_spread_of_stage_two_on_its_own_returns(unit: str) -> None:
    model = make_model(n_steps=8, broadcast_cost=0.0, normalize_reward=True)  # normalised in both stages
    samples = 8 * model.n_envs  # returns measured per iteration
    switch = 2 if unit == "iterations" else 2 * samples - 3  # within the second rollout of stage 1
    stages = ControlFirstCallback(switch, trigger_normalize_reward=True, unit=unit)
    model.learn(16, callback=stages)  # stage 1
    assert model.reward_transform.return_rms.count == pytest.approx(2 * samples, abs=1e-3)
    for iterations in (1, 2):  # stage 2: measured anew at its first rollout, then continued
        model.learn(8, callback=stages, reset_num_timesteps=False)
        assert model.reward_transform.return_rms.count == pytest.approx(iterations * samples, abs=1e-3)


# --------------------------------------------------------------------------- baselines
@pytest.mark.parametrize("skip_prob", [0.55, 0.2])
def test_random_skip_rate_frozen_mu_and_no_broadcast_cost(skip_prob: float) -> None:
    n_agents, n_envs, n_steps, n_iterations = 3, 2, 128, 2
    model = make_model(n_agents=n_agents, n_envs=n_envs, n_steps=n_steps, batch_size=64, broadcast_cost=0.5)
    mu_before, pi_before = net_slices(model, "mu"), net_slices(model, "pi")
    record, metrics = Record(), CommMetricsCallback()
    capture = capture_logger(model)
    model.learn(n_steps * n_envs * n_iterations, callback=[RandomSkipCallback(skip_prob), metrics, record])

    assert isinstance(model.fixed_trigger, RandomTrigger) and model.fixed_trigger.skip_prob == skip_prob
    broadcast = np.array([info["broadcast"] for step in record.infos for info in step])
    n = broadcast.size
    assert n == n_agents * n_envs * n_steps * n_iterations
    rate = 1 - skip_prob
    tolerance = 4 * math.sqrt(rate * (1 - rate) / n)  # 4 binomial standard deviations
    assert abs(broadcast.mean() - rate) < tolerance
    for row in capture.rows:  # every rollout alone (n / 2 samples)
        assert abs(row["comm/savings"] - skip_prob) < 4 * math.sqrt(rate * (1 - rate) / (n / n_iterations))

    # mu is neither trained nor used; pi is trained.
    for before, after in zip(mu_before, net_slices(model, "mu"), strict=True):
        assert th.equal(before, after)
    assert any(not th.equal(a, b) for a, b in zip(pi_before, net_slices(model, "pi"), strict=True))

    # No communication cost charged although the env was made with 0.5 and agents broadcast.
    assert model.get_env().get_attr("broadcast_cost") == [0.0] * n_envs
    for step in record.infos:
        for info in step:
            np.testing.assert_array_equal(info["agent_rewards"], info["control_rewards"])


def test_random_skip_seed_defaults_to_the_model_seed() -> None:
    options = []
    for _ in range(2):
        model = make_model(n_steps=16)
        record = Record()
        model.learn(16, callback=[RandomSkipCallback(0.5), record])
        options.append(np.array([info["broadcast"] for step in record.infos for info in step]))
    np.testing.assert_array_equal(options[0], options[1])
    assert 0 < options[0].mean() < 1


@pytest.mark.parametrize(("period", "charge"), [(1, False), (3, False), (3, True)])
def test_periodic_comm_callback_broadcasts_every_kth_step_of_each_episode(period: int, charge: bool) -> None:
    max_cycles, n_steps = 7, 32
    model = make_model(n_agents=3, max_cycles=max_cycles, n_steps=n_steps, broadcast_cost=0.5)
    record = Record()
    model.learn(n_steps, callback=[PeriodicCommCallback(period, charge_broadcast_cost=charge), record])
    assert isinstance(model.fixed_trigger, PeriodicTrigger)
    broadcast = np.array([step[0]["broadcast"] for step in record.infos])  # (steps, agents)
    step_in_episode = np.arange(n_steps) % max_cycles
    expected = ((step_in_episode + 1) % period == 0).astype(np.int64)  # e.g. period 3: steps 2 and 5 of 0..6
    np.testing.assert_array_equal(broadcast, np.repeat(expected[:, None], 3, axis=1))
    assert model.get_env().get_attr("broadcast_cost") == [0.5 if charge else 0.0]
    rewards = np.array([step[0]["agent_rewards"] for step in record.infos])
    control = np.array([step[0]["control_rewards"] for step in record.infos])
    np.testing.assert_allclose(rewards, control - (0.5 if charge else 0.0) * broadcast)


def test_fixed_trigger_needs_a_callable_and_joint_envs() -> None:
    with pytest.raises(ValueError, match="callable"):
        FixedTriggerCallback(trigger=0.5)
    with pytest.raises(ValueError, match="skip_prob"):
        RandomSkipCallback(skip_prob=1.5)
    with pytest.raises(ValueError, match="period"):
        PeriodicCommCallback(period=0)
    with pytest.raises(ValueError, match="broadcast_cost"):
        set_broadcast_cost(DummyVecEnv([lambda: gym.make("CartPole-v1")]), 0.0)


def test_joint_env_broadcast_cost_property() -> None:
    env = linear_etc_v0.joint_env(n_agents=2, max_cycles=5, broadcast_cost=0.3)
    assert env.broadcast_cost == 0.3
    env.reset(seed=0)
    broadcast, control = np.array([1, 0]), np.zeros((2, 1), np.float32)
    _, _, _, _, info = env.step({"broadcast": broadcast, "control": control})
    np.testing.assert_allclose(info["agent_rewards"], info["control_rewards"] - 0.3 * broadcast)
    env.broadcast_cost = 0.0
    assert env.network.broadcast_cost == 0.0
    _, _, _, _, info = env.step({"broadcast": broadcast, "control": control})
    np.testing.assert_array_equal(info["agent_rewards"], info["control_rewards"])
    for bad in (-0.1, math.inf, math.nan):
        with pytest.raises(ValueError, match="broadcast_cost"):
            env.broadcast_cost = bad
    assert env.broadcast_cost == 0.0
    # Through gym.make's wrappers, Monitor and the VecEnv.
    vec_env = make_vec_env(ENV_ID, n_envs=2, env_kwargs={"broadcast_cost": 0.2})
    set_broadcast_cost(vec_env, 0.7)
    assert vec_env.get_attr("broadcast_cost") == [0.7, 0.7]
    assert [e.unwrapped.network.broadcast_cost for e in vec_env.envs] == [0.7, 0.7]


# --------------------------------------------------------------------------- triggers
@pytest.mark.parametrize("trigger", [RandomTrigger(0.3, seed=2), PeriodicTrigger(3), SendOnDelta(0.5)])
def test_triggers_tell_their_probabilities_of_broadcasting_without_drawing(trigger) -> None:
    rng = np.random.default_rng(0)
    obs = {
        "age": rng.integers(0, 4, (4000, 3, 1)).astype(np.float32),
        "trigger": rng.normal(size=(4000, 3, 2)).astype(np.float32),
        "trigger_held": np.zeros((4000, 3, 2), np.float32),
    }
    twin = copy.deepcopy(trigger)
    p = trigger.broadcast_probability(obs)
    options = trigger(obs)
    np.testing.assert_array_equal(options, twin(obs))  # asking drew nothing
    assert p.shape == options.shape and ((p >= 0) & (p <= 1)).all()
    assert abs(options.mean() - p.mean()) < 0.02
    if not isinstance(trigger, RandomTrigger):
        np.testing.assert_array_equal(p, options)


def test_send_on_delta_broadcasts_exactly_when_the_threshold_is_crossed() -> None:
    # Moves (dx, dy) from the held features, exactly representable: |(0.375, 0.5)| = 0.625.
    eps = 2.0**-10
    moves = np.array([[0.375, 0.5], [0.375, 0.5 - eps], [0.375, 0.5 + eps], [0.0, 0.0], [-0.375, -0.5 - eps]])
    held = np.array([[1.0, -2.0]] * len(moves))
    obs = {
        "trigger": (held + moves)[None].astype(np.float32),  # (B=1, N=5, 2)
        "trigger_held": held[None].astype(np.float32),
        "age": np.zeros((1, 5, 1), np.float32),
    }
    np.testing.assert_array_equal(SendOnDelta(0.625)(obs), [[0, 0, 1, 0, 1]])  # equal is not more than delta
    # |(0.375, 0.5 - eps)| = 0.625 - 0.8 eps + O(eps^2): above 0.625 - eps.
    np.testing.assert_array_equal(SendOnDelta(0.625 - eps)(obs), [[1, 1, 1, 0, 1]])
    np.testing.assert_array_equal(SendOnDelta(0.0)(obs), [[1, 1, 1, 0, 1]])
    # Other norms: L1 of the first move is 0.875, the maximum norm 0.5.
    np.testing.assert_array_equal(SendOnDelta(0.875, norm=1)(obs), [[0, 0, 1, 0, 1]])
    np.testing.assert_array_equal(SendOnDelta(0.5, norm=np.inf)(obs), [[0, 0, 1, 0, 1]])
    np.testing.assert_array_equal(SendOnDelta(0.5 - eps, norm=np.inf)(obs), [[1, 0, 1, 0, 1]])  # max(...) = 0.5 - eps
    np.testing.assert_array_equal(SendOnDelta(0.5 - 2 * eps, norm=np.inf)(obs), [[1, 1, 1, 0, 1]])
    for bad in ({"delta": -1.0}, {"delta": math.nan}, {"delta": 1.0, "norm": 0.5}, {"delta": 1.0, "norm": -np.inf}):
        with pytest.raises(ValueError, match="delta|norm"):
            SendOnDelta(**bad)


def test_send_on_delta_in_the_network_compares_with_the_own_last_broadcast() -> None:
    env = linear_etc_v0.joint_env(n_agents=3, max_cycles=60)
    trigger = SendOnDelta(0.3)
    obs, _ = env.reset(seed=1)
    at_last = obs["trigger"].astype(np.float64)  # the reset counts as a broadcast
    rng = np.random.default_rng(0)
    sent = []
    for _ in range(60):
        expected = (np.linalg.norm(obs["trigger"] - at_last, axis=-1) > 0.3).astype(np.int64)
        broadcast = trigger({key: value[None] for key, value in obs.items()})[0]
        np.testing.assert_array_equal(broadcast, expected)
        at_last[broadcast == 1] = obs["trigger"][broadcast == 1]
        sent.append(broadcast)
        obs, _, _, _, _ = env.step({"broadcast": broadcast, "control": rng.normal(size=(3, 1)).astype(np.float32)})
    assert 0 < np.mean(sent) < 1


@pytest.mark.parametrize("period", [1, 2, 4])
def test_periodic_trigger_drives_a_joint_env_every_kth_step(period: int) -> None:
    max_cycles = 10
    env = linear_etc_v0.joint_env(n_agents=3, max_cycles=max_cycles)
    trigger = PeriodicTrigger(period)
    obs, _ = env.reset(seed=0)
    k = 0
    for _ in range(25):
        broadcast = trigger({key: value[None] for key, value in obs.items()})[0]
        expected = 1 if (k + 1) % period == 0 else 0  # steps period - 1, 2 period - 1, ... of the episode
        np.testing.assert_array_equal(broadcast, [expected] * 3)
        obs, _, terminated, truncated, _ = env.step({"broadcast": broadcast, "control": np.zeros((3, 1), np.float32)})
        k += 1
        if terminated or truncated:
            obs, _ = env.reset()
            k = 0
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="period"):
            PeriodicTrigger(bad)


# --------------------------------------------------------------------------- metrics
# Scripted options of 2 agents over 24 steps (one env, episodes of 5 steps: 0-4, 5-9, 10-14,
# 15-19, 20-24; rollouts of 12 steps: 0-11, 12-23).
SENDS = {0: {0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22}, 1: {1, 4, 5, 9, 11, 13, 14, 22}}


def test_comm_metrics_equal_hand_counts_in_a_scripted_run() -> None:
    xi, n_steps = 0.01, 12
    model = make_model(n_agents=2, max_cycles=5, n_steps=n_steps, broadcast_cost=xi)
    counter = iter(range(10**6))

    def script(obs: dict[str, np.ndarray]) -> np.ndarray:
        g = next(counter)
        return np.array([[int(g in SENDS[0]), int(g in SENDS[1])]])

    model.set_fixed_trigger(script)
    record = Record()
    capture = capture_logger(model)
    model.learn(2 * n_steps, callback=[CommMetricsCallback(), record])
    first, second = capture.rows

    # Savings: rollout 1 agent 0 sends at 0, 2, 4, 6, 8, 10 (6 of 12), agent 1 at 1, 4, 5, 9, 11 (5 of 12);
    # rollout 2 agent 0 at 12, ..., 22 (6), agent 1 at 13, 14, 22 (3).
    assert first["comm/savings_agent_0"] == pytest.approx(0.5)
    assert first["comm/savings_agent_1"] == pytest.approx(7 / 12)
    assert first["comm/savings"] == pytest.approx((0.5 + 7 / 12) / 2)
    assert second["comm/savings_agent_0"] == pytest.approx(0.5)
    assert second["comm/savings_agent_1"] == pytest.approx(0.75)

    # Inter-event times within episodes. Rollout 1: agent 0: 2, 2 (episode 0-4), 2 (6, 8);
    # agent 1: 3 (1, 4), 4 (5, 9). Rollout 2: agent 0: 2 (10, 12), 2 (12, 14), 2 (16, 18), 2 (20, 22);
    # agent 1: 2 (11, 13), 1 (13, 14); 22 is alone in its episode.
    assert first["comm/inter_event_time_mean_agent_0"] == 2 and first["comm/inter_event_time_min_agent_0"] == 2
    assert first["comm/inter_event_time_mean_agent_1"] == 3.5 and first["comm/inter_event_time_min_agent_1"] == 3
    assert first["comm/inter_event_time_mean"] == pytest.approx(13 / 5) and first["comm/inter_event_time_min"] == 2
    assert sorted(first["comm/inter_event_times"].tolist()) == [2, 2, 2, 3, 4]
    assert second["comm/inter_event_time_mean_agent_1"] == 1.5 and second["comm/inter_event_time_min_agent_1"] == 1
    assert sorted(second["comm/inter_event_times"].tolist()) == [1, 2, 2, 2, 2, 2]

    # Episodes: 0-4 and 5-9 finish in rollout 1, 10-14 and 15-19 in rollout 2.
    control = np.array([step[0]["control_rewards"] for step in record.infos])  # (24, 2)
    sends = np.array([[g in SENDS[i] for i in range(2)] for g in range(24)])
    for row, episodes in ((first, [(0, 5), (5, 10)]), (second, [(10, 15), (15, 20)])):
        assert row["comm/episodes"] == 2
        assert row["comm/fall_rate"] == 0.0  # truncated, never terminated
        assert "comm/package_travel" not in row
        control_return = np.mean([control[a:b].sum(0) for a, b in episodes], axis=0)
        cost = xi * np.mean([sends[a:b].sum(0) for a, b in episodes], axis=0)
        for i in range(2):
            assert row[f"comm/ep_control_return_agent_{i}"] == pytest.approx(control_return[i], rel=1e-6)
            assert row[f"comm/ep_return_agent_{i}"] == pytest.approx(control_return[i] - cost[i], rel=1e-6)
        assert row["comm/ep_return"] == pytest.approx(np.mean(control_return - cost), rel=1e-6)
    # By hand: agent 0 sends 3 and 2 times in the first two episodes, agent 1 2 and 2 times.
    assert first["comm/ep_control_return_agent_0"] - first["comm/ep_return_agent_0"] == pytest.approx(2.5 * xi)
    assert first["comm/ep_control_return_agent_1"] - first["comm/ep_return_agent_1"] == pytest.approx(2.0 * xi)
    # The team return agrees with SB3's Monitor (team-mean reward per step).
    monitor = [info["r"] for info in model.ep_info_buffer]
    assert len(monitor) == 4
    assert first["comm/ep_return"] == pytest.approx(np.mean(monitor[:2]), abs=1e-5)
    assert second["comm/ep_return"] == pytest.approx(np.mean(monitor[2:]), abs=1e-5)

    # A later learn() starts inside episode 20-24: only episodes seen from their start count.
    capture.rows.clear()
    model.learn(n_steps, callback=CommMetricsCallback(), reset_num_timesteps=False)
    # Steps 24-35: 20-24 ends at step 24 (its start was not seen), 25-29 and 30-34 count.
    assert capture.rows[0]["comm/episodes"] == 2


class ShiftedPackage(gym.Wrapper):
    """Shifts ``package_x`` by the episode's index (the package starts at the same x in every episode)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.episode = -1

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.episode += 1
        return obs, {**info, "package_x": info["package_x"] + self.episode}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, {**info, "package_x": info["package_x"] + self.episode}


def test_comm_metrics_package_travel_and_fall_rate_in_multiwalker() -> None:
    # Env 0 walks steadily and is truncated after 50 steps; env 1 throws its legs and falls.
    max_cycles, n_steps = 50, 130
    envs = DummyVecEnv([lambda: ShiftedPackage(multiwalker_etc_v0.joint_env(max_cycles=max_cycles))] * 2)
    envs.seed(0)
    model = MAPPOC("MlpHybridPolicy", envs, n_steps=n_steps, seed=0, policy_kwargs=TINY)
    capture = capture_logger(model)
    callback = CommMetricsCallback()
    callback.init_callback(model)
    envs.reset()

    def start_x(e: int) -> float:  # the package's x in the env's current episode before its first step
        return envs.envs[e].unwrapped.network.system.physics.package.position.x + envs.envs[e].episode

    start = [start_x(0), start_x(1)]
    callback.on_training_start({}, {})
    callback.on_rollout_start()
    controls = np.array([[[1, 0, -1, 0]] * 3, [[1, 1, 1, 1]] * 3], np.float32)
    travel, fell = [], []
    for _ in range(n_steps):
        _, _, dones, infos = envs.step([{"broadcast": np.ones(3, np.int64), "control": u} for u in controls])
        callback.update_locals({"infos": infos, "dones": dones})
        assert callback.on_step()
        for e in np.flatnonzero(dones):
            travel.append(infos[e]["package_x"] - start[e])
            fell.append(not infos[e]["TimeLimit.truncated"])
            start[e] = start_x(e)  # the env was reset after this step
    callback.on_rollout_end()
    logged = model.logger.name_to_value
    assert 0 < np.mean(fell) < 1  # both kinds of episode end happened
    assert logged["comm/episodes"] == len(travel) >= 4
    assert logged["comm/fall_rate"] == pytest.approx(np.mean(fell))
    assert logged["comm/package_travel"] == pytest.approx(np.mean(travel))
    assert np.all(np.abs(travel) > 1e-3) and np.all(np.abs(travel) < 5)
    assert logged["comm/savings"] == 0.0 and logged["comm/inter_event_time_mean"] == 1.0
    assert capture.rows == []  # nothing dumped yet: the values wait in the logger


def test_paper_setup_runs_end_to_end_on_multiwalker() -> None:
    """The README's usage: MAPPOC on Multiwalker with the curriculum and the metrics."""
    from stable_baselines3.common.callbacks import CallbackList

    from sb3_detc import MAPPOC
    from sb3_detc.callbacks import CommMetricsCallback, CurriculumCallback
    from sb3_detc.mappoc.workers import default_n_envs

    model = MAPPOC("MlpHybridPolicy", "sb3_detc/MultiwalkerETC-v0", n_steps=128, n_epochs=1, seed=0)
    assert model.n_envs == default_n_envs()  # the fast setting: rollout workers built from the id
    capture = capture_logger(model)
    model.learn(2 * 128 * model.n_envs, callback=CallbackList([CurriculumCallback(), CommMetricsCallback()]))
    assert model.action_noise_std == pytest.approx(0.25 * (1 - 1 / 900))  # phase I, iteration 1
    assert len(capture.rows) == 2  # one dump per iteration, before its update
    first, second = capture.rows
    # The metrics of the second rollout count the broadcasts that its buffer holds (the update leaves them).
    broadcast = model.rollout_buffer.broadcast  # (n_steps, n_envs, N)
    assert broadcast.shape[-1] == 3 and 0 < broadcast.mean() < 1
    for i in range(3):
        assert second[f"comm/savings_agent_{i}"] == pytest.approx(1 - broadcast[..., i].mean()), i
    assert second["comm/savings"] == pytest.approx(1 - broadcast.mean())
    # The first update's broadcast rate (dumped with the second iteration) is one minus the first rollout's savings.
    assert second["rollout/broadcast_rate"] == pytest.approx(1 - first["comm/savings"])
    assert second["train/broadcast_ent_coef"] == pytest.approx(3.2)
    assert model.logger.name_to_value["train/broadcast_ent_coef"] == pytest.approx(3.2)  # the second update's


@pytest.mark.parametrize("workers", [False, True])
def test_package_travel_starts_from_each_episodes_own_reset(workers: bool) -> None:
    """Several episodes of one env end within a rollout: each is measured from the reset before it.

    The shifted package starts one unit further in every episode, so a start taken from a later
    reset would be off by a whole unit.
    """
    wrapper = RolloutWorker if workers else None
    envs = make_vec_env(
        lambda: ShiftedPackage(multiwalker_etc_v0.joint_env(max_cycles=10)), n_envs=2, seed=0, wrapper_class=wrapper
    )
    model = MAPPOC("MlpHybridPolicy", envs, n_steps=40, n_epochs=1, seed=0, policy_kwargs=TINY)
    capture = capture_logger(model)
    model.learn(80, callback=CommMetricsCallback())
    assert model.sampler.last_in_workers is workers
    assert len(capture.rows) == 1  # one rollout of 2 x 40 steps
    assert all(row["comm/episodes"] >= 6 for row in capture.rows)
    assert all(abs(row["comm/package_travel"]) < 0.5 for row in capture.rows)


# --------------------------------------------------------------------------- selection of the best policy
def validation_env() -> gym.Env:
    return gym.make(ENV_ID, n_agents=2, max_cycles=20, broadcast_cost=0.01)


def test_the_best_policy_at_the_target_is_kept_saved_and_restored(tmp_path) -> None:
    model = make_model(target_savings=0.5, learning_rate=3e-3)
    select = SelectBestCallback(validation_env(), [100, 101], eval_freq=16, save_path=tmp_path, verbose=0)
    model.learn(80, callback=select)
    evaluations = select.evaluations
    assert [e["timesteps"] for e in evaluations] == [16, 32, 48, 64, 80]  # every 16 steps, the last at the end
    eligible = [e for e in evaluations if e["savings"] >= 0.5 - 0.01]
    assert eligible, "no policy reached the target: the test checks nothing"
    kept = max(eligible, key=lambda e: e["control_return"])
    assert select.best == kept
    selection = select.restore()
    assert selection == {"evaluations": evaluations, "kept": kept}
    # the model's policy is now the kept one, and so is the saved file: both repeat its validation
    saved = MlpHybridPolicy.load(str(tmp_path / "best_policy.pt"), device="cpu")
    for policy in (model.policy, saved):
        episodes = evaluate_episodes(policy, validation_env(), [100, 101])
        assert float(np.mean(episodes.control_returns)) == pytest.approx(kept["control_return"], rel=1e-6)
    # a callback made again with the folder (a run resumed from a checkpoint) goes on from there
    again = SelectBestCallback(validation_env(), [100, 101], eval_freq=16, save_path=tmp_path, verbose=0)
    again.init_callback(model)
    assert again.evaluations == evaluations and again.best == kept
    for key, value in saved.state_dict().items():
        assert th.equal(again.best_state[key], value)


def test_without_an_eligible_policy_the_last_one_stays() -> None:
    model = make_model(target_savings=0.99)  # far above what a fresh policy over options saves
    select = SelectBestCallback(validation_env(), [100], eval_freq=8, tolerance=0.0, verbose=0)
    model.learn(24, callback=select)
    last = {key: value.clone() for key, value in model.policy.state_dict().items()}
    assert len(select.evaluations) == 3 and all(e["savings"] < 0.99 for e in select.evaluations)
    assert select.restore()["kept"] is None
    for key, value in model.policy.state_dict().items():
        assert th.equal(value, last[key])


def test_rollouts_of_a_fixed_trigger_are_not_evaluated() -> None:
    model = make_model()
    model.set_fixed_trigger(PeriodicTrigger(2))
    select = SelectBestCallback(validation_env(), [100], eval_freq=8, verbose=0)
    model.learn(16, callback=select)
    assert select.evaluations == [] and select.restore()["kept"] is None
    model.set_fixed_trigger(None)
    model.learn(8, callback=select, reset_num_timesteps=False)
    assert [e["timesteps"] for e in select.evaluations] == [24]


def test_select_best_refuses_bad_settings() -> None:
    with pytest.raises(ValueError, match="at least one validation seed"):
        SelectBestCallback(validation_env(), [], eval_freq=8)
    with pytest.raises(ValueError, match="tolerance must be a finite number >= 0"):
        SelectBestCallback(validation_env(), [1], eval_freq=8, tolerance=-0.1)
    with pytest.raises(ValueError, match="eval_freq"):
        SelectBestCallback(validation_env(), [1], eval_freq=0)
