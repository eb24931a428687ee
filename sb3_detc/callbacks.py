"""SB3 callbacks for MAPPOC: the paper's curriculum, its communication baselines and communication metrics.

Put them in a :class:`~stable_baselines3.common.callbacks.CallbackList` (or an rl-zoo
hyperparameter file, e.g. ``callback: sb3_detc.callbacks.CurriculumCallback``):

* curriculum (Sec. 4 of the method reference): :class:`ActionNoiseSchedule` (phase I),
  :class:`BroadcastEntropySchedule` (phase II), :class:`TentNoiseSchedule` (phase III), or
  all three with the paper's numbers in :class:`CurriculumCallback`;
* baselines (Sec. 6): :class:`RandomSkipCallback` (the paper's random communication
  skips), :class:`PeriodicCommCallback` (broadcast every step or every k-th step), or any
  trigger of :mod:`sb3_detc.triggers` with :class:`FixedTriggerCallback`;
* two stages instead of the curriculum: :class:`ControlFirstCallback` (the control policy
  under random skips first, then the policies over options for the frozen controller),
  :class:`ScheduleFirstCallback` (a periodic schedule with a controller trained for it first,
  then the policy over options, started as the schedule, learned with the controller),
  :class:`DeltaFirstCallback` (the same from send-on-delta; on the linear system with the
  receivers' predictions shown, predictive triggering) and :class:`FixedFirstCallback` (from any
  stateless trigger);
* :class:`CommMetricsCallback`: communication savings, inter-event times, per-agent
  returns with and without the communication cost, package travel and fall rate, per rollout;
* :class:`SelectBestCallback`: the policy that did best on validation episodes at the rate
  target, kept instead of the last one (as rl-zoo3 keeps ``best_model.zip``).

**Iterations.** The curriculum counts iterations ``h`` as the paper does: one iteration is
one rollout (one ``collect_rollouts`` call, ``n_steps * n_envs`` environment steps; the
paper's 2048). ``h`` at a rollout's start is ``model.num_timesteps // (n_steps * n_envs)``,
the number of rollouts collected before it, so it continues over ``learn`` calls with
``reset_num_timesteps=False``. With ``unit="timesteps"`` the boundaries are environment steps
(``model.num_timesteps`` at the rollout's start) instead. Values are set at the start of a
rollout, so a rollout and the update that follows it use the values of the same iteration.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import Schedule

from sb3_detc.evaluation import EpisodeCounter, Episodes, evaluate_episodes
from sb3_detc.files import replace_atomically
from sb3_detc.mappoc.checks import check_rate_target
from sb3_detc.mappoc.mappoc import PAPER_ITERATION
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.triggers import PeriodicTrigger, RandomTrigger, SendOnDelta, StatelessTrigger
from sb3_detc.validation import check_integer

__all__ = [
    "IMITATED",
    "set_broadcast_cost",
    "ActionNoiseSchedule",
    "CommMetricsCallback",
    "ControlFirstCallback",
    "CurriculumCallback",
    "DeltaFirstCallback",
    "FixedFirstCallback",
    "FixedTriggerCallback",
    "BroadcastEntropySchedule",
    "PeriodicCommCallback",
    "RandomSkipCallback",
    "ScheduleFirstCallback",
    "SelectBestCallback",
    "TentNoiseSchedule",
    "linear_decay",
    "tent",
]

UNITS = ("iterations", "timesteps")


# ----------------------------------------------------------------------------- pure schedules
def linear_decay(t: float, start: float, end: float, initial: float, final: float) -> float:
    """``initial`` until ``start``, linear to ``final`` at ``end``, then ``final``.

    :param t: position (iteration or timestep)
    :param start: last position with the initial value
    :param end: first position with the final value (``> start``)
    :param initial: value until ``start``
    :param final: value from ``end`` on
    :return: the value at ``t``
    """
    return float(np.interp(t, [start, end], [initial, final]))


def tent(t: float, start: float, peak: float, end: float, height: float) -> float:
    """0 until ``start``, linear to ``height`` at ``peak``, linear back to 0 at ``end``, then 0.

    :param t: position (iteration or timestep)
    :param start: last position with 0
    :param peak: position of the maximum (``start < peak < end``)
    :param end: first position with 0 again
    :param height: value at ``peak``
    :return: the value at ``t``
    """
    return float(np.interp(t, [start, peak, end], [0.0, height, 0.0]))


def _check_unit(unit: str) -> str:
    """Check the unit of a schedule's positions.

    :param unit: ``"iterations"`` or ``"timesteps"``
    :return: ``unit``
    :raises ValueError: on any other unit
    """
    if unit not in UNITS:
        raise ValueError(f"unit must be one of {UNITS}, got {unit!r}.")
    return unit


def _check_value(name: str, value: float) -> float:
    """Check a number of a schedule (a boundary, a noise level or a coefficient).

    :param name: the argument's name, for the message
    :param value: the value (an int or a float, not a bool)
    :return: ``value`` as a float
    :raises ValueError: if ``value`` is not a number, not finite or negative
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}.")
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}.")
    return float(value)


def _boundaries(unit: str, **named: tuple[float | None, float]) -> list[float]:
    """Resolve boundaries (None: the paper's iteration, converted to timesteps if needed) and check them.

    :param unit: ``"iterations"`` or ``"timesteps"``
    :param named: name -> (given value or None, the paper's value in iterations), in increasing order
    :return: the boundaries in the order given
    :raises ValueError: if a boundary is negative or not finite, or they do not strictly increase
    """
    scale = 1 if unit == "iterations" else PAPER_ITERATION
    values = []
    for name, (given, paper) in named.items():
        values.append(_check_value(name, paper * scale if given is None else given))
    names = list(named)
    for j in range(1, len(values)):
        if not values[j - 1] < values[j]:
            a, b = names[j - 1], names[j]
            raise ValueError(f"the boundaries must increase: {a}={values[j - 1]:g} must be < {b}={values[j]:g}.")
    return values


# ----------------------------------------------------------------------------- curriculum
class _Schedule(BaseCallback):
    """Sets a model attribute from a schedule of the iteration (or timestep) at every rollout start.

    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps)
    :param verbose: verbosity level
    """

    def __init__(self, unit: str = "iterations", verbose: int = 0) -> None:
        super().__init__(verbose)
        self.unit = _check_unit(unit)

    def position(self) -> int:
        """Current iteration (rollouts collected so far) or timestep, depending on :attr:`unit`."""
        if self.unit == "timesteps":
            return int(self.model.num_timesteps)
        return int(self.model.num_timesteps // (self.model.n_steps * self.model.n_envs))

    def rollout_length(self) -> int:
        """How far one rollout moves the position: 1 iteration, or ``n_steps * n_envs`` timesteps."""
        return 1 if self.unit == "iterations" else self.model.n_steps * self.model.n_envs

    def value(self, t: float) -> float:
        """The scheduled value at position ``t`` (pure: depends on the constructor's arguments only).

        :param t: iteration or timestep (as :attr:`unit`)
        :return: the value at ``t``
        """
        raise NotImplementedError

    def _on_rollout_start(self) -> None:
        self.apply(self.position())

    def apply(self, t: float) -> None:
        """Set and log the value of position ``t`` on the model.

        :param t: iteration or timestep (as :attr:`unit`)
        """
        raise NotImplementedError

    def _on_step(self) -> bool:
        return True


class _NoiseSchedule(_Schedule):
    """A schedule of the extra action noise; several of them on one model combine by their maximum."""

    #: Key of the own term in the logger (``curriculum/<term_name>``).
    term_name = "noise"

    def _init_callback(self) -> None:
        self.model.set_action_noise_std(0.0, source=self)

    def apply(self, t: float) -> None:
        """Set this schedule's term of position ``t`` (the model uses the largest term), and log both.

        :param t: iteration or timestep (as :attr:`unit`)
        """
        value = self.value(t)
        self.model.set_action_noise_std(value, source=self)
        self.logger.record(f"curriculum/{self.term_name}", value)
        self.logger.record("curriculum/action_noise_std", self.model.action_noise_std)

    def _on_training_end(self) -> None:
        # A finished callback no longer contributes (e.g. to a later learn() with other callbacks).
        self.model.set_action_noise_std(None, source=self)


class ActionNoiseSchedule(_NoiseSchedule):
    """Phase I of the curriculum: extra Gaussian action noise decaying linearly to 0.

    Sets ``model.action_noise_std`` to ``initial_std`` at ``start``, linearly decaying to 0 at
    ``end`` (paper: 0.25 -> 0 over iterations 0..900). Logs its own term as
    ``curriculum/noise_decay`` and the model's value as ``curriculum/action_noise_std``.

    The noise schedules (this one and :class:`TentNoiseSchedule`) each set their own term
    (``model.set_action_noise_std(value, source=self)``) while they train: the model's value is
    the **maximum** of the terms of all noise schedules attached to it (whatever their order
    in a ``CallbackList``), and the constructor's value is overwritten when training starts.

    :param initial_std: noise standard deviation until ``start`` (>= 0)
    :param start: end of the constant part (default 0)
    :param end: first position without noise (default: the paper's 900 iterations, or
        ``900 * 2048`` in timesteps)
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps)
    :param verbose: verbosity level
    :raises ValueError: on a negative value or boundaries that do not increase
    """

    term_name = "noise_decay"

    def __init__(
        self,
        initial_std: float = 0.25,
        start: float = 0,
        end: float | None = None,
        unit: str = "iterations",
        verbose: int = 0,
    ) -> None:
        super().__init__(unit, verbose)
        self.initial_std = _check_value("initial_std", initial_std)
        self.start, self.end = _boundaries(self.unit, start=(start, 0), end=(end, 900))

    def value(self, t: float) -> float:
        """Noise standard deviation at position ``t``.

        :param t: iteration or timestep (as :attr:`unit`)
        :return: ``initial_std`` until ``start``, linear to 0 at ``end``, then 0
        """
        return linear_decay(t, self.start, self.end, self.initial_std, 0.0)


class TentNoiseSchedule(_NoiseSchedule):
    """Phase III of the curriculum: tent-shaped extra Gaussian action noise.

    ``model.action_noise_std`` rises linearly from 0 at ``start`` to ``peak_std`` at ``peak``
    and falls back to 0 at ``end`` (paper: 0 -> 0.25 over iterations 1500..2000, back to 0 at
    2500). Logs its own term as ``curriculum/noise_tent`` and the model's value as
    ``curriculum/action_noise_std``. Combines with :class:`ActionNoiseSchedule` by the maximum.

    :param peak_std: noise standard deviation at ``peak`` (>= 0)
    :param start: last position without noise (default: 1500 iterations)
    :param peak: position of the maximum (default: 2000 iterations)
    :param end: first position without noise again (default: 2500 iterations)
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps; default
        boundaries: the paper's iterations times 2048)
    :param verbose: verbosity level
    :raises ValueError: on a negative value or boundaries that do not increase
    """

    term_name = "noise_tent"

    def __init__(
        self,
        peak_std: float = 0.25,
        start: float | None = None,
        peak: float | None = None,
        end: float | None = None,
        unit: str = "iterations",
        verbose: int = 0,
    ) -> None:
        super().__init__(unit, verbose)
        self.peak_std = _check_value("peak_std", peak_std)
        self.start, self.peak, self.end = _boundaries(
            self.unit, start=(start, 1500), peak=(peak, 2000), end=(end, 2500)
        )

    def value(self, t: float) -> float:
        """Noise standard deviation at position ``t``.

        :param t: iteration or timestep (as :attr:`unit`)
        :return: 0 until ``start``, linear to ``peak_std`` at ``peak``, back to 0 at ``end``, then 0
        """
        return tent(t, self.start, self.peak, self.end, self.peak_std)


class BroadcastEntropySchedule(_Schedule):
    """Phase II of the curriculum: decay of the entropy coefficient ``zeta`` of the policy over options.

    Sets ``model.broadcast_ent_coef`` to ``initial`` until ``start``, then linearly to ``final`` at
    ``end``, then ``final``. The paper's code uses 0.1 until iteration 800 and 0.02 from 1500
    on for an entropy *summed* over minibatches of 32; MAPPOC averages over the minibatch, so
    the defaults are ``32 * 0.1 = 3.2`` and ``32 * 0.02 = 0.64``. Logged as
    ``curriculum/broadcast_ent_coef``; the update after the rollout uses the same value
    (``train/broadcast_ent_coef``).

    :param initial: coefficient until ``start`` (>= 0)
    :param final: coefficient from ``end`` on (>= 0)
    :param start: end of the constant initial part (default: 800 iterations)
    :param end: first position with the final value (default: 1500 iterations)
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps; default
        boundaries: the paper's iterations times 2048)
    :param verbose: verbosity level
    :raises ValueError: on a negative value or boundaries that do not increase
    """

    def __init__(
        self,
        initial: float = 3.2,
        final: float = 0.64,
        start: float | None = None,
        end: float | None = None,
        unit: str = "iterations",
        verbose: int = 0,
    ) -> None:
        super().__init__(unit, verbose)
        self.initial = _check_value("initial", initial)
        self.final = _check_value("final", final)
        self.start, self.end = _boundaries(self.unit, start=(start, 800), end=(end, 1500))

    def value(self, t: float) -> float:
        """Entropy coefficient at position ``t``.

        :param t: iteration or timestep (as :attr:`unit`)
        :return: ``initial`` until ``start``, linear to ``final`` at ``end``, then ``final``
        """
        return linear_decay(t, self.start, self.end, self.initial, self.final)

    def apply(self, t: float) -> None:
        """Set ``model.broadcast_ent_coef`` to the value of position ``t`` and log it.

        :param t: iteration or timestep (as :attr:`unit`)
        """
        value = self.value(t)
        self.model.broadcast_ent_coef = value
        self.logger.record("curriculum/broadcast_ent_coef", value)


class CurriculumCallback(BaseCallback):
    """The paper's three-phase curriculum (Sec. 4) in one callback, with the paper's numbers by default.

    * phase I, :class:`ActionNoiseSchedule`: extra action noise 0.25 -> 0 over iterations 0..900;
    * phase II, :class:`BroadcastEntropySchedule`: ``zeta`` 3.2 until 800, linear to 0.64 at 1500
      (the paper's 0.1 and 0.02 for a minibatch sum over 32, as a mean);
    * phase III, :class:`TentNoiseSchedule`: extra action noise 0 -> 0.25 over 1500..2000,
      back to 0 at 2500.

    Phases I and III both set ``model.action_noise_std``: it is the **maximum** of the two
    terms. With the default boundaries they do not overlap, so the maximum is exactly the
    paper's piecewise schedule; with overlapping custom boundaries the maximum never exceeds
    the larger of the two intended noise levels (a sum could exceed both peaks, and standard
    deviations of independent noises do not add anyway).

    Every rollout start logs ``curriculum/action_noise_std``, its terms
    ``curriculum/noise_decay`` and ``curriculum/noise_tent``, ``curriculum/broadcast_ent_coef``,
    the position ``curriculum/iteration`` (or ``curriculum/timesteps``) and the phase
    ``curriculum/phase``: the latest phase that has started (``"I"`` until phase II starts,
    then ``"II"`` until phase III starts, ...; so ``"II"`` from 800 on although phase I's noise
    decays until 900), and ``"done"`` once every phase has ended (default: from 2500 on).

    :param noise_std: phase I initial noise standard deviation
    :param noise_end: phase I end (first position without noise; default 900 iterations)
    :param ent_initial: phase II initial entropy coefficient (mean over the minibatch)
    :param ent_final: phase II final entropy coefficient
    :param ent_start: phase II start (end of the constant initial coefficient; default 800)
    :param ent_end: phase II end (first position with the final coefficient; default 1500)
    :param tent_std: phase III peak noise standard deviation
    :param tent_start: phase III start (default 1500)
    :param tent_peak: phase III peak (default 2000)
    :param tent_end: phase III end (default 2500)
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps; default
        boundaries: the paper's iterations times 2048)
    :param verbose: verbosity level
    :raises ValueError: on a negative value or boundaries that do not increase within a phase
    """

    def __init__(
        self,
        noise_std: float = 0.25,
        noise_end: float | None = None,
        ent_initial: float = 3.2,
        ent_final: float = 0.64,
        ent_start: float | None = None,
        ent_end: float | None = None,
        tent_std: float = 0.25,
        tent_start: float | None = None,
        tent_peak: float | None = None,
        tent_end: float | None = None,
        unit: str = "iterations",
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        self.unit = _check_unit(unit)
        self.noise = ActionNoiseSchedule(noise_std, end=noise_end, unit=unit)
        self.entropy = BroadcastEntropySchedule(ent_initial, ent_final, start=ent_start, end=ent_end, unit=unit)
        self.tent = TentNoiseSchedule(tent_std, start=tent_start, peak=tent_peak, end=tent_end, unit=unit)
        self.schedules: tuple[_Schedule, ...] = (self.noise, self.entropy, self.tent)

    def values(self, t: float) -> dict[str, float | str]:
        """Everything the curriculum sets at position ``t`` and the phase (pure).

        :param t: iteration or timestep (as :attr:`unit`)
        :return: ``action_noise_std``, ``noise_decay``, ``noise_tent``, ``broadcast_ent_coef``, ``phase``
        """
        decay, bump = self.noise.value(t), self.tent.value(t)
        return {
            "action_noise_std": max(decay, bump),
            "noise_decay": decay,
            "noise_tent": bump,
            "broadcast_ent_coef": self.entropy.value(t),
            "phase": self.phase(t),
        }

    def phase(self, t: float) -> str:
        """Phase at position ``t``: ``"I"``, ``"II"``, ``"III"`` (the latest started) or ``"done"``.

        :param t: iteration or timestep (as :attr:`unit`)
        :return: ``"done"`` once ``t`` reaches the latest end of the three phases, else the latest
            phase whose start ``t`` has reached (``"I"`` before phase II starts)
        """
        if t >= max(self.noise.end, self.entropy.end, self.tent.end):
            return "done"
        if t >= self.tent.start:
            return "III"
        if t >= self.entropy.start:
            return "II"
        return "I"

    def _init_callback(self) -> None:
        for schedule in self.schedules:
            schedule.init_callback(self.model)

    def _on_training_start(self) -> None:
        for schedule in self.schedules:
            schedule.on_training_start(self.locals, self.globals)

    def _on_rollout_start(self) -> None:
        t = self.noise.position()
        for schedule in self.schedules:
            schedule.on_rollout_start()
        self.logger.record(f"curriculum/{'iteration' if self.unit == 'iterations' else 'timesteps'}", t)
        self.logger.record("curriculum/phase", self.phase(t))

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        for schedule in self.schedules:
            schedule.on_training_end()


def _seeded_random_trigger(trigger: RandomTrigger, seed: int | None, model: Any) -> tuple[RandomTrigger, int | None]:
    """A callback's random trigger, seeded with the model's seed if the callback was given none.

    :param trigger: the callback's trigger
    :param seed: the seed the callback was given (None: none yet)
    :param model: the model being trained
    :return: the trigger to use and its seed
    """
    if seed is None and getattr(model, "seed", None) is not None:
        return RandomTrigger(trigger.skip_prob, model.seed), model.seed
    return trigger, seed


class _TwoStages(_Schedule):
    """A schedule of two stages: stage 1 before ``switch``, stage 2 from ``switch`` on.

    :param switch: first position of stage 2 (iterations or timesteps, as ``unit``; > 0)
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps)
    :param verbose: verbosity level
    :raises ValueError: on a ``switch`` that is not positive and finite
    """

    def __init__(self, switch: float, unit: str = "iterations", verbose: int = 0) -> None:
        super().__init__(unit, verbose)
        if not _check_value("switch", switch) > 0:
            raise ValueError(f"switch must be > 0 (stage 1 must last), got {switch!r}.")
        self.switch = float(switch)

    def value(self, t: float) -> float:
        """Stage at position ``t``: 1 or 2.

        :param t: iteration or timestep (as :attr:`unit`)
        :return: 1.0 before ``switch``, 2.0 from ``switch`` on
        """
        return 1.0 if t < self.switch else 2.0

    def first_of_stage_two(self, t: float) -> bool:
        """Whether the rollout that ends at (or starts after) position ``t`` is the first of stage 2's positions.

        :param t: iteration or timestep (as :attr:`unit`)
        :return: True if the position one rollout before ``t`` is in stage 1 and ``t`` in stage 2
        """
        return self.value(t - self.rollout_length()) == 1 and self.value(t) == 2

    def set_stage(self, stage: int, trigger: Any, train_control: bool) -> None:
        """Options from ``trigger`` and ``pi`` trained in stage 1; options from ``mu``, ``mu`` trained in stage 2.

        :param stage: 1 or 2
        :param trigger: stage 1's fixed trigger
        :param train_control: whether ``pi`` learns in stage 2
        """
        self.model.set_fixed_trigger(trigger if stage == 1 else None)
        self.model.set_trained_policies(control_policy=stage == 1 or train_control, broadcast_policy=stage == 2)
        self.logger.record("curriculum/stage", stage)


class ControlFirstCallback(_TwoStages):
    """Two stages: the control policy under random skips, then the policies over options for it.

    * stage 1 (positions before ``switch``): options are drawn by
      :class:`~sb3_detc.triggers.RandomTrigger` with ``skip_prob`` (``model.set_fixed_trigger``),
      ``pi`` and the critic learn, ``mu`` does not;
    * stage 2 (from ``switch`` on): the options come from ``mu`` again, ``mu`` and the critic
      learn, ``pi`` stays as stage 1 left it (``model.set_trained_policies``), with
      ``trigger_learning_rate`` if given, and rewards normalised if ``trigger_normalize_reward``
      with a spread measured in stage 2 only (``model.set_reward_normalization(True,
      fresh_statistics=True)``: the returns of a controller that still learns to stabilise can be
      orders of magnitude larger than those of the finished controller, and the scale that suits
      option values can spoil a controller's learning, so each stage has its own).

    Why: a trigger can only be learned for a controller that already controls, and while
    ``pi`` still changes, the value of a broadcast changes with it. Random options in stage 1
    show the critic both options in every kind of state, so stage 2 starts from option values
    that are right for the controller it keeps. The communication cost stays charged in both
    stages (in stage 1 it does not depend on anything ``pi`` does). The stage is a function of
    the position only, so a continued run resumes in the right stage; it is logged as
    ``curriculum/stage``.

    :param switch: first position of stage 2 (iterations or timesteps, as ``unit``; > 0)
    :param skip_prob: probability of staying silent in stage 1 (in [0, 1])
    :param trigger_learning_rate: learning rate (a number or a schedule of the remaining
        progress, as SB3's ``learning_rate``) from stage 2 on; None: the model's own
    :param trigger_normalize_reward: normalise the rewards from stage 2 on, by the spread of stage 2's
        returns (False: the model's own setting, and its statistics continue)
    :param seed: seed of stage 1's random options (None: the model's seed at training start)
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps)
    :param verbose: verbosity level
    :raises ValueError: on a ``switch`` that is not positive and finite, or a ``skip_prob`` outside [0, 1]
    """

    def __init__(
        self,
        switch: float,
        skip_prob: float = 0.5,
        trigger_learning_rate: float | Schedule | None = None,
        trigger_normalize_reward: bool = False,
        seed: int | None = None,
        unit: str = "iterations",
        verbose: int = 0,
    ) -> None:
        super().__init__(switch, unit, verbose)
        self.trigger = RandomTrigger(skip_prob, seed)
        self.skip_prob = self.trigger.skip_prob
        self.seed = seed
        self.trigger_learning_rate = trigger_learning_rate
        self.trigger_normalize_reward = bool(trigger_normalize_reward)

    def _on_training_start(self) -> None:
        self.trigger, self.seed = _seeded_random_trigger(self.trigger, self.seed, self.model)

    def apply(self, t: float) -> None:
        """Put the model into the stage of position ``t`` and log the stage.

        :param t: iteration or timestep (as :attr:`unit`)
        """
        stage = int(self.value(t))
        self.set_stage(stage, self.trigger, train_control=False)
        if stage == 2 and self.trigger_learning_rate is not None:
            self.model.set_learning_rate(self.trigger_learning_rate)
        if stage == 2 and self.trigger_normalize_reward:
            # Fresh at the first rollout of stage 2, decided by the position: the same when a run resumes there.
            self.model.set_reward_normalization(True, fresh_statistics=self.first_of_stage_two(t))


def imitate_trigger(
    model: Any, trigger: Callable[[dict[str, np.ndarray]], np.ndarray], span: int, gradient_steps: int = 500
) -> float:
    """Fit a MAPPOC model's ``mu`` to a fixed trigger on the observations of the rollout in its buffer.

    ``mu`` is shown the rollout's observations twice: as they are, and with their own ages drawn
    from ``[0, 2 span)``, so that it follows the trigger at every age (e.g. a schedule broadcasts
    from age ``period - 1`` on in every state). Behaviour cloning
    (:meth:`~sb3_detc.mappoc.policies.MlpHybridPolicy.imitate_options`); nothing else changes.

    :param model: the model (MAPPOC) after a rollout
    :param trigger: the trigger to imitate, one of :mod:`sb3_detc.triggers` that reads the observations it
        is given (a stateless one, or a :class:`~sb3_detc.triggers.DitheredTrigger` of one: ``mu`` then
        learns its probabilities of broadcasting)
    :param span: half the range of the drawn own ages (an integer >= 1)
    :param gradient_steps: gradient steps of the imitation
    :return: the share of the imitated decisions whose most likely option matches the trigger
    """
    observations = model.rollout_buffer.tensors().observations
    age = observations["age"]
    drawn = th.randint(0, 2 * span, age.shape, device=age.device).to(age.dtype)
    obs = {key: th.cat([value, drawn if key == "age" else value]) for key, value in observations.items()}
    options = trigger({key: value.cpu().numpy() for key, value in obs.items()})
    return model.policy.imitate_options(obs, th.as_tensor(options), gradient_steps=gradient_steps)


#: The model attribute in which :class:`FixedFirstCallback` records the trigger ``mu`` imitated (its repr).
IMITATED = "imitated_trigger"


class FixedFirstCallback(_TwoStages):
    """Two stages: a fixed trigger with a controller trained for it, then ``mu`` learned from that trigger on.

    * stage 1 (positions before ``switch``): the options come from :attr:`trigger`
      (``model.set_fixed_trigger``); ``pi`` and the critic learn, ``mu`` does not;
    * at the end of stage 1's last rollout (the first that ends at ``switch`` or later), ``mu``
      imitates the trigger (:meth:`~sb3_detc.mappoc.policies.MlpHybridPolicy.imitate_options`) on
      that rollout's observations and on copies of them whose own ages are drawn from
      ``[0, 2 span)`` (:meth:`age_span`), so that it follows the trigger at every age;
    * stage 2 (from ``switch`` on, once ``mu`` imitated the trigger): the options come from
      ``mu``; ``mu``, the critic and (with ``train_control``) ``pi`` learn. A rate target's price
      (``target_savings``) moves only here, from the rate the trigger left.

    The model records the imitation (:data:`IMITATED`, saved with it), so a run continued from
    any saved model resumes in the right stage: one saved within stage 1's last rollout, before
    the imitation, runs one more rollout under the trigger and imitates it then. Logged:
    ``curriculum/stage``, and the imitation's share of matched decisions as
    ``curriculum/imitation_accuracy``. The communication cost stays charged in both stages.

    :param switch: first position of stage 2 (iterations or timesteps, as ``unit``; > 0)
    :param trigger: the fixed trigger of stage 1, a stateless one of :mod:`sb3_detc.triggers`
    :param reads_age: whether the trigger reads the own age, so that ``mu`` must read it too
        (``option_age_scale > 0``, checked when training starts)
    :param train_control: whether ``pi`` keeps learning in stage 2 (False: as stage 1 left it)
    :param imitation_steps: gradient steps of the imitation
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps)
    :param verbose: verbosity level
    :raises ValueError: on a ``switch`` that is not positive and finite, or ``imitation_steps`` < 1
    """

    def __init__(
        self,
        switch: float,
        trigger: StatelessTrigger,
        reads_age: bool = True,
        train_control: bool = True,
        imitation_steps: int = 500,
        unit: str = "iterations",
        verbose: int = 0,
    ) -> None:
        super().__init__(switch, unit, verbose)
        self.trigger = trigger
        self.reads_age = bool(reads_age)
        self.train_control = bool(train_control)
        self.imitation_steps = check_integer("imitation_steps", imitation_steps)

    def _on_training_start(self) -> None:
        if self.reads_age and not self.model.policy.option_age_scale > 0:
            raise ValueError(
                f"{type(self).__name__} needs a policy over options that reads its own age, to start as "
                f"{self.trigger!r}: set policy_kwargs option_age_scale > 0 (e.g. 0.1)."
            )

    def imitated(self) -> bool:
        """Whether the model's ``mu`` imitated this callback's trigger (recorded as :data:`IMITATED` on the model)."""
        return getattr(self.model, IMITATED, None) == repr(self.trigger)

    def apply(self, t: float) -> None:
        """Put the model into the stage of position ``t`` and log the stage: 2 from ``switch`` on once imitated.

        :param t: iteration or timestep (as :attr:`unit`)
        """
        self.set_stage(2 if self.value(t) == 2 and self.imitated() else 1, self.trigger, self.train_control)

    def _on_rollout_end(self) -> None:
        if self.value(self.position()) == 2 and not self.imitated():  # the rollout that ends stage 1
            self.logger.record("curriculum/imitation_accuracy", self.imitate())
            setattr(self.model, IMITATED, repr(self.trigger))

    def age_span(self, ages: th.Tensor) -> int:
        """The ages the imitation shows ``mu``: ``[0, 2 span)``.

        :param ages: the own ages met in the rollout
        :return: one more than the largest age met (subclasses: the trigger's own period or maximum age)
        """
        return int(ages.max()) + 1

    def imitate(self) -> float:
        """Fit ``mu`` to the trigger on the observations of the rollout in the model's buffer (:func:`imitate_trigger`).

        :return: the share of the imitated decisions whose most likely option matches the trigger
        """
        span = self.age_span(self.model.rollout_buffer.tensors().observations["age"])
        return imitate_trigger(self.model, self.trigger, span, self.imitation_steps)


class ScheduleFirstCallback(FixedFirstCallback):
    """Two stages: a periodic schedule with a controller trained for it, then ``mu`` learned from the schedule on.

    Stage 1: every agent broadcasts every ``period``-th step, all in phase
    (:class:`~sb3_detc.triggers.PeriodicTrigger`); at the switch ``mu`` imitates the schedule
    (own ages drawn from ``[0, 2 period)``, so that it broadcasts from age ``period - 1`` on in
    every state; the policy must read its own age, ``option_age_scale > 0``); stage 2 learns it,
    as described in :class:`FixedFirstCallback`.

    Why: the schedule, with a controller trained for it, is the strongest fixed trigger at its
    savings on Multiwalker. Started as that schedule, with that controller, a learned trigger can
    then lose to it only by learning badly.

    :param switch: first position of stage 2 (iterations or timesteps, as ``unit``; > 0)
    :param period: steps between two broadcasts of an agent in stage 1 (an integer >= 1)
    :param train_control: whether ``pi`` keeps learning in stage 2 (False: as stage 1 left it)
    :param imitation_steps: gradient steps of the imitation
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps)
    :param verbose: verbosity level
    :raises ValueError: on a ``switch`` that is not positive and finite, a ``period`` that is not an
        integer >= 1 or ``imitation_steps`` < 1
    """

    def __init__(
        self,
        switch: float,
        period: int,
        train_control: bool = True,
        imitation_steps: int = 500,
        unit: str = "iterations",
        verbose: int = 0,
    ) -> None:
        super().__init__(switch, PeriodicTrigger(period), True, train_control, imitation_steps, unit, verbose)
        self.period = self.trigger.period

    def age_span(self, ages: th.Tensor) -> int:
        """The ages the imitation shows ``mu``: ``[0, 2 period)``.

        :param ages: the own ages met in the rollout (unused)
        :return: the period
        """
        return self.period


class DeltaFirstCallback(FixedFirstCallback):
    """Two stages: send-on-delta with a controller trained for it, then ``mu`` learned from that rule on.

    Stage 1: :class:`~sb3_detc.triggers.SendOnDelta` with ``delta`` (and ``max_age``); at the
    switch ``mu`` imitates it; stage 2 learns it, as described in :class:`FixedFirstCallback`. On
    ``sb3_detc/LinearETC-LQR-v0`` with ``prediction=True, predicted_held=True`` send-on-delta is
    predictive triggering (:class:`~sb3_detc.triggers.ReceiverPredictions`): the learned trigger
    then starts as the model-based anchor. ``mu`` follows the rule most closely when it reads
    the distance itself (``option_distance_scale > 0``); with ``max_age`` it must read its own age.

    :param switch: first position of stage 2 (iterations or timesteps, as ``unit``; > 0)
    :param delta: the rule's threshold (a finite number >= 0), in the units of the trigger features
    :param max_age: the rule's maximum age (an integer >= 1), or None
    :param train_control: whether ``pi`` keeps learning in stage 2 (False: as stage 1 left it)
    :param imitation_steps: gradient steps of the imitation
    :param unit: ``"iterations"`` (rollouts) or ``"timesteps"`` (environment steps)
    :param verbose: verbosity level
    :raises ValueError: on a ``switch`` that is not positive and finite, a bad ``delta`` or ``max_age``
        (see :class:`~sb3_detc.triggers.SendOnDelta`) or ``imitation_steps`` < 1
    """

    def __init__(
        self,
        switch: float,
        delta: float,
        max_age: int | None = None,
        train_control: bool = True,
        imitation_steps: int = 500,
        unit: str = "iterations",
        verbose: int = 0,
    ) -> None:
        trigger = SendOnDelta(delta, max_age=max_age)
        super().__init__(switch, trigger, max_age is not None, train_control, imitation_steps, unit, verbose)

    def age_span(self, ages: th.Tensor) -> int:
        """The ages the imitation shows ``mu``: ``[0, 2 max_age)``, or up to twice the largest age met.

        :param ages: the own ages met in the rollout
        :return: the maximum age, or one more than the largest age met without one
        """
        return self.trigger.max_age or super().age_span(ages)


# ----------------------------------------------------------------------------- baselines
class FixedTriggerCallback(BaseCallback):
    """Train MAPPOC's control policy with a fixed, non-learned trigger instead of the policy over options.

    At the start of training: ``model.set_fixed_trigger(trigger)`` (the rollouts take their
    options from it, and ``mu`` is not updated), and,
    unless ``charge_broadcast_cost``, the communication cost of every training env is set to 0.

    This is a training *mode*: nothing is restored at the end of training, so a following
    ``learn`` keeps the trigger and the zero cost. The trigger is not saved with the model
    and evaluation envs are not changed: evaluate with
    :func:`~sb3_detc.evaluation.evaluate_communication` and ``fixed_trigger=callback.trigger``
    (its ``mean_control_return`` excludes the communication cost).

    :param trigger: callable joint observations (B, N, ...) -> options (B, N), e.g. from
        :mod:`sb3_detc.triggers`
    :param charge_broadcast_cost: keep the training envs' communication cost (default: set it to 0)
    :param verbose: verbosity level
    """

    def __init__(self, trigger: Any, charge_broadcast_cost: bool = False, verbose: int = 0) -> None:
        if not callable(trigger):
            raise ValueError(f"trigger must be callable (joint observations -> options), got {trigger!r}.")
        super().__init__(verbose)
        self.trigger = trigger
        self.charge_broadcast_cost = bool(charge_broadcast_cost)

    def _on_training_start(self) -> None:
        check_rate_target(getattr(self.model, "target_savings", None), self.trigger)
        self.model.set_fixed_trigger(self.trigger)
        if not self.charge_broadcast_cost:
            set_broadcast_cost(self.training_env, 0.0)

    def _on_step(self) -> bool:
        return True


def set_broadcast_cost(vec_env: Any, broadcast_cost: float) -> None:
    """Set the communication cost of every env of a VecEnv (through its wrappers).

    :param vec_env: a VecEnv of joint sb3_detc envs (:class:`~sb3_detc.envs.wrappers.JointEnv`)
    :param broadcast_cost: the new cost per broadcast (>= 0)
    :raises ValueError: if an env has no ``broadcast_cost`` (not a joint sb3_detc env)
    """
    done = vec_env.env_method("set_wrapper_attr", "broadcast_cost", broadcast_cost, force=False)
    if not all(done):
        raise ValueError("the training envs have no broadcast_cost: use joint sb3_detc envs (JointEnv).")


class RandomSkipCallback(FixedTriggerCallback):
    """The paper's baseline (Sec. 6): random communication skips, no communication cost, ``mu`` not trained.

    Every agent stays silent with probability ``skip_prob`` in every step, independently
    (:class:`~sb3_detc.triggers.RandomTrigger`), so the expected savings are ``skip_prob``.
    Combine it with :class:`ActionNoiseSchedule` for the paper's baseline (phase I only).
    See :class:`FixedTriggerCallback` for what changes on the model and the envs (not restored).

    :param skip_prob: probability of staying silent (paper: about 0.55; its code: 0.495)
    :param seed: seed of the trigger's random generator (None: the model's seed at training start)
    :param charge_broadcast_cost: keep the training envs' communication cost (default: set it to 0)
    :param verbose: verbosity level
    """

    def __init__(
        self, skip_prob: float = 0.55, seed: int | None = None, charge_broadcast_cost: bool = False, verbose: int = 0
    ) -> None:
        super().__init__(RandomTrigger(skip_prob, seed), charge_broadcast_cost, verbose)
        self.skip_prob = self.trigger.skip_prob
        self.seed = seed

    def _on_training_start(self) -> None:
        self.trigger, self.seed = _seeded_random_trigger(self.trigger, self.seed, self.model)
        super()._on_training_start()


class PeriodicCommCallback(FixedTriggerCallback):
    """Periodic communication baseline: every agent broadcasts every ``period``-th step; ``mu`` not trained.

    ``period=1`` (default) is communication in every step, the reference of the savings
    ``Gamma``. Steps are counted per episode and all agents broadcast at the same steps
    (:class:`~sb3_detc.triggers.PeriodicTrigger`: steps ``period - 1, 2 period - 1, ...`` of
    every episode). No communication cost is charged by default, as for the random-skip
    baseline: with a fixed trigger the cost cannot change any decision, it only shifts the
    returns (and with terminating episodes a per-step penalty would even reward ending early).
    See :class:`FixedTriggerCallback` for what changes on the model and the envs (not restored).

    :param period: steps between two broadcasts of an agent (integer >= 1)
    :param charge_broadcast_cost: keep the training envs' communication cost (default: set it to 0)
    :param verbose: verbosity level
    """

    def __init__(self, period: int = 1, charge_broadcast_cost: bool = False, verbose: int = 0) -> None:
        super().__init__(PeriodicTrigger(period), charge_broadcast_cost, verbose)
        self.period = self.trigger.period


# ----------------------------------------------------------------------------- metrics
class CommMetricsCallback(BaseCallback):
    """Communication metrics of every rollout, logged to the SB3 logger (stdout, CSV, TensorBoard, ...).

    Counts every step's ``infos`` and ``dones`` with :class:`~sb3_detc.evaluation.EpisodeCounter`,
    the count that evaluation uses too (``info["broadcast"]``, ``info["agent_rewards"]``,
    ``info["control_rewards"]``, and ``info["package_x"]`` and ``info["failed"]`` where present).
    Per rollout:

    * ``comm/savings_agent_{i}``: ``Gamma_i = 1 - broadcasts_i / steps`` over the rollout's
      steps (all envs), and their mean ``comm/savings``;
    * inter-event times, the numbers of steps between two consecutive broadcasts of one agent
      in one episode (the reset is not an event; an interval counts in the rollout of its
      closing broadcast): ``comm/inter_event_time_mean_agent_{i}``,
      ``comm/inter_event_time_min_agent_{i}``, over all agents ``comm/inter_event_time_mean``
      and ``comm/inter_event_time_min``, and the histogram ``comm/inter_event_times``
      (TensorBoard only); not logged in a rollout without intervals;
    * over the episodes that finished in the rollout (and that the callback saw from their
      start): ``comm/ep_return_agent_{i}`` (with the communication cost) and
      ``comm/ep_control_return_agent_{i}`` (without), their agent means ``comm/ep_return``
      and ``comm/ep_control_return``, ``comm/episodes`` (how many), ``comm/fall_rate`` (the
      fraction that ended by a failure: ``info["failed"]`` where the env reports it, in
      Multiwalker a fall or a dropped package, else the fraction that terminated rather than
      being truncated) and, where the env reports ``package_x`` (Multiwalker),
      ``comm/package_travel`` (final minus initial package x, the initial one from the info of
      the reset before the episode: ``info["reset_info"]`` of the step that ended the one
      before, which MAPPOC's rollouts add, else the VecEnv's ``reset_infos``); not logged in a
      rollout in which no episode finished.

    :param histogram: record the inter-event times as a histogram (TensorBoard)
    :param verbose: verbosity level
    """

    def __init__(self, histogram: bool = True, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.histogram = histogram

    def _on_training_start(self) -> None:
        n_envs = self.training_env.num_envs
        self.counter = EpisodeCounter(n_envs)
        starts = getattr(self.model, "_last_episode_starts", None)
        # Only episodes seen from their first step are reported (learn() may continue an episode).
        for e in range(n_envs):
            if starts is None or starts[e]:
                self.counter.start(e, self._reset_info(e))

    def _reset_info(self, env_idx: int) -> dict[str, Any] | None:
        """The info of the VecEnv's last reset of one env.

        :param env_idx: index of the env in the training VecEnv
        :return: its ``reset_infos`` entry; None if the VecEnv has none for it
        """
        reset_infos = getattr(self.training_env, "reset_infos", None)
        if reset_infos is None or env_idx >= len(reset_infos):
            return None
        return reset_infos[env_idx]

    def _on_rollout_start(self) -> None:
        self.counter.clear()

    def _on_step(self) -> bool:
        infos, dones = self.locals["infos"], self.locals["dones"]
        for e, (info, done) in enumerate(zip(infos, dones, strict=True)):
            truncated = bool(done) and info.get("TimeLimit.truncated", False)
            self.counter.step(e, info, terminated=bool(done) and not truncated, truncated=truncated)
            if done:  # the VecEnv reset env e after this step
                reset_info = info.get("reset_info")
                self.counter.start(e, reset_info if reset_info is not None else self._reset_info(e))
        return True

    def _on_rollout_end(self) -> None:
        counter = self.counter
        if counter.steps == 0:
            return
        record = self.logger.record
        savings = 1.0 - counter.broadcasts / counter.steps
        for i, value in enumerate(savings):
            record(f"comm/savings_agent_{i}", float(value))
        record("comm/savings", float(savings.mean()))

        every = [t for agent in counter.intervals for t in agent]
        if every:
            for i, agent in enumerate(counter.intervals):
                record(f"comm/inter_event_time_mean_agent_{i}", float(np.mean(agent)) if agent else math.nan)
                record(f"comm/inter_event_time_min_agent_{i}", float(np.min(agent)) if agent else math.nan)
            record("comm/inter_event_time_mean", float(np.mean(every)))
            record("comm/inter_event_time_min", float(np.min(every)))
            if self.histogram:
                record(
                    "comm/inter_event_times",
                    th.tensor(every, dtype=th.float32),
                    exclude=("stdout", "log", "json", "csv"),
                )

        if counter.episodes:
            episodes = Episodes.from_records(counter.episodes)
            returns, control = episodes.agent_returns.mean(axis=0), episodes.agent_control_returns.mean(axis=0)
            for i in range(len(returns)):
                record(f"comm/ep_return_agent_{i}", float(returns[i]))
                record(f"comm/ep_control_return_agent_{i}", float(control[i]))
            record("comm/ep_return", float(returns.mean()))
            record("comm/ep_control_return", float(control.mean()))
            record("comm/episodes", len(counter.episodes))
            record("comm/fall_rate", float(np.mean(episodes.failed)))
            travel = episodes.package_travel[np.isfinite(episodes.package_travel)]
            if len(travel):
                record("comm/package_travel", float(np.mean(travel)))


class SelectBestCallback(BaseCallback):
    """Keep the policy that did best on validation episodes at the rate target, instead of the last one.

    As rl-zoo3 keeps ``best_model.zip`` by periodic evaluation: at the start of the first rollout
    from every multiple of ``eval_freq`` environment steps on (the policy after the update before
    it, the one a checkpoint then holds) and at the end of training, the policy runs the
    validation episodes (:func:`~sb3_detc.evaluation.evaluate_episodes`: seeded, deterministic
    controls, the options as ``sample_options`` says). Of the
    evaluations whose savings lie at or above the model's ``target_savings`` less ``tolerance``
    (all of them without a target), the one with the highest mean control return is kept, and
    :meth:`restore` loads it into the model's policy once training is over. Rollouts whose
    options come from a fixed trigger (``model.fixed_trigger``, e.g. the first stage of a
    two-stage callback) are not evaluated: the policy over options did not choose them.

    With ``save_path``, every evaluation is written to ``selection.json`` there and the kept
    policy to ``best_policy.pt`` (policy only, :meth:`MlpHybridPolicy.load
    <sb3_detc.mappoc.policies.MlpHybridPolicy.load>`; written before the record); a callback
    made with the same folder for a run resumed from a checkpoint reads them back and goes on
    after the last evaluation, so nothing kept is lost on interruption. Whatever is in the folder
    is read: evaluations made after that checkpoint by the interrupted run stay (their policies
    were trained like any other); remove the files to start afresh. The logged values
    ``selection/control_return`` and ``selection/savings`` go out with the rollout's.

    Keep the validation seeds apart from those the policy is evaluated on afterwards: the kept
    policy's validation return is biased upwards (it is the maximum of several noisy ones).

    :param eval_env: the joint env the validation episodes run in (not vectorised; the caller closes it)
    :param seeds: the validation episodes' seeds, one episode each
    :param eval_freq: environment steps between two evaluations (>= 1)
    :param tolerance: how far below the target the savings of a kept policy may lie (>= 0)
    :param sample_options: options sampled from the policy over options (True) or its most likely
        ones (False); None: as the policy is deployed (its ``sample_options``)
    :param save_path: folder for ``selection.json`` and ``best_policy.pt`` (None: kept in memory only)
    :param verbose: 1 prints a line per evaluation
    """

    def __init__(
        self,
        eval_env: gym.Env,
        seeds: Sequence[int],
        eval_freq: int,
        tolerance: float = 0.01,
        sample_options: bool | None = None,
        save_path: str | Path | None = None,
        verbose: int = 1,
    ) -> None:
        super().__init__(verbose)
        if not seeds:
            raise ValueError("SelectBestCallback needs at least one validation seed.")
        if not (math.isfinite(tolerance) and tolerance >= 0):
            raise ValueError(f"tolerance must be a finite number >= 0, got {tolerance}.")
        self.eval_env = eval_env
        self.seeds = [int(seed) for seed in seeds]
        self.eval_freq = check_integer("eval_freq", eval_freq, 1)
        self.tolerance = float(tolerance)
        self.sample_options = sample_options
        self.save_path = None if save_path is None else Path(save_path)
        self.evaluations: list[dict[str, Any]] = []
        self.best: dict[str, Any] | None = None  # the kept evaluation
        self.best_state: dict[str, th.Tensor] | None = None  # the kept policy's parameters
        self.last = 0  # the steps of the last evaluation

    def _init_callback(self) -> None:
        if self.save_path is None or not (self.save_path / "selection.json").is_file():
            return
        saved = json.loads((self.save_path / "selection.json").read_text())
        self.evaluations = saved["evaluations"]
        self.best = saved["kept"]
        self.last = max((e["timesteps"] for e in self.evaluations), default=0)
        if self.best is not None:
            policy = MlpHybridPolicy.load(str(self.save_path / "best_policy.pt"), device="cpu")
            self.best_state = {key: value.clone() for key, value in policy.state_dict().items()}

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        if self.model.num_timesteps // self.eval_freq > self.last // self.eval_freq:
            self.evaluate()

    def _on_training_end(self) -> None:
        if self.model.num_timesteps > self.last:
            self.evaluate()

    def eligible(self, savings: float) -> bool:
        """Whether a policy with these savings may be kept: at or above the target less the tolerance.

        :param savings: the savings on the validation episodes
        :return: True without a target
        """
        target = getattr(self.model, "target_savings", None)
        return target is None or savings >= target - self.tolerance

    def evaluate(self) -> None:
        """Run the validation episodes with the current policy and keep it if it is the best so far."""
        self.last = self.model.num_timesteps
        if getattr(self.model, "fixed_trigger", None) is not None:
            return
        episodes = evaluate_episodes(self.model.policy, self.eval_env, self.seeds, sample_options=self.sample_options)
        result = {
            "timesteps": self.model.num_timesteps,
            "control_return": float(np.mean(episodes.control_returns)),
            "savings": float(episodes.savings),
        }
        self.evaluations.append(result)
        eligible = self.eligible(result["savings"])
        if eligible and (self.best is None or result["control_return"] > self.best["control_return"]):
            self.best = result
            self.best_state = {key: value.detach().clone() for key, value in self.model.policy.state_dict().items()}
        if self.save_path is not None:
            folder, policy = self.save_path, self.model.policy
            folder.mkdir(parents=True, exist_ok=True)
            if self.best is result:  # the policy first: the record never names a kept policy that is not there
                replace_atomically(folder / "best_policy.pt", lambda path: policy.save(str(path)), "best.tmp.pt")
            text = json.dumps({"evaluations": self.evaluations, "kept": self.best}, indent=1)
            replace_atomically(folder / "selection.json", lambda path: path.write_text(text))
        self.logger.record("selection/control_return", result["control_return"])
        self.logger.record("selection/savings", result["savings"])
        if self.verbose:
            below = "" if eligible else " (below the target)"
            print(
                f"validation at {self.model.num_timesteps} steps: control return {result['control_return']:.1f}, "
                f"savings {result['savings']:.3f}{below}",
                flush=True,
            )

    def restore(self) -> dict[str, Any]:
        """Load the kept policy into the model's policy (the last one stays if none was eligible).

        :return: ``evaluations`` (every evaluation's steps, control return and savings) and ``kept``
            (the kept one's, None if none was eligible)
        """
        if self.best_state is not None:
            self.model.policy.load_state_dict(self.best_state)
        return {"evaluations": list(self.evaluations), "kept": self.best}
