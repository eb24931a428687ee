"""Non-learned communication triggers, usable wherever MAPPOC accepts a fixed trigger.

A trigger maps a batch of joint observations (dict of arrays shaped (B, N, ...)) to
options (B, N) in {0, 1}. The triggers here other than :class:`RandomTrigger` are
stateless: their options are a function of the observation alone, so they can be called on
batches whose rows change from call to call (episodes run side by side and refilled as
they end) and one object serves every rollout worker. The families: random skips,
periodic (all agents in phase, or staggered over the agents), send-on-delta (with an
optional maximum age) and, on the linear system, predictive triggering (:class:`PredictiveTrigger`
with :func:`lqr_on_predicted_states`). :class:`DitheredTrigger` adds random deviations to any of
them, for exploration.

:func:`evaluate_trigger` runs a trigger with a given control law (e.g.
:func:`lqr_on_held_states` on the linear system) and reports a :class:`TriggerPoint`
(savings and control cost); :func:`sweep_send_on_delta` gives the cost-versus-savings curve;
:func:`tune_trigger` finds the parameter at which a family reaches a given savings
(:func:`tune_trigger_on_env` with a control law on a joint env), :func:`bracket_trigger` two
that enclose it, whose mixture meets it exactly.
:class:`FixedControl` does the converse: it fixes the control law, so that MAPPOC learns
only when to communicate.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_detc.envs.linear import HeldStatePredictor, LinearSystem, LQRController
from sb3_detc.envs.wrappers import JointEnv
from sb3_detc.network import advance_timer, hold
from sb3_detc.validation import check_integer


class RandomTrigger:
    """Every agent broadcasts independently with probability ``1 - skip_prob`` (the paper's baseline).

    :param skip_prob: probability of staying silent in a step (paper: about 0.5)
    :param seed: seed of the trigger's own random generator
    """

    def __init__(self, skip_prob: float, seed: int | None = None) -> None:
        if not 0.0 <= skip_prob <= 1.0:
            raise ValueError(f"skip_prob must be in [0, 1], got {skip_prob!r}.")
        self.skip_prob = float(skip_prob)
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N).

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key; only the
            shape of ``age`` (B, N, 1) is read
        :return: options (B, N), int64: 1 (broadcast) with probability ``1 - skip_prob``, independently
        """
        shape = obs["age"].shape[:-1]
        return (self.rng.random(shape) >= self.skip_prob).astype(np.int64)

    def broadcast_probability(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Every agent's probability of broadcasting in these observations (draws nothing), (B, N).

        :param obs: a batch of joint observations, as :meth:`__call__` reads them
        :return: ``1 - skip_prob`` everywhere, float64
        """
        return np.full(obs["age"].shape[:-1], 1.0 - self.skip_prob)

    def fork(self, seed: int) -> RandomTrigger:
        """An independent copy with its own seed (one per rollout worker, see :mod:`sb3_detc.mappoc.workers`).

        :param seed: seed of the copy's random generator
        :return: a :class:`RandomTrigger` with the same ``skip_prob`` and a generator of its own
        """
        return RandomTrigger(self.skip_prob, seed)


class StatelessTrigger(abc.ABC):
    """A trigger whose options follow from the observations alone: no state, no random draws.

    The base of the package's fixed triggers other than :class:`RandomTrigger`; a subclass
    defines :meth:`__call__` and runs wherever a fixed trigger is accepted (one object serves
    every rollout worker).
    """

    @abc.abstractmethod
    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N).

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key
        """

    def fork(self, seed: int) -> StatelessTrigger:
        """A copy for a rollout worker: the trigger itself, which has no state.

        :param seed: unused
        :return: the trigger
        """
        return self

    def broadcast_probability(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Every agent's probability of broadcasting in these observations, (B, N): its options.

        :param obs: a batch of joint observations, as :meth:`__call__` reads them
        :return: 1.0 where an agent broadcasts, else 0.0
        """
        return self(obs).astype(np.float64)


def _check_threshold(delta: float, norm: float) -> tuple[float, float]:
    """Check the threshold and the norm of a send-on-delta-like trigger.

    :param delta: threshold (a finite number >= 0, not a bool)
    :param norm: order of the vector norm: a number >= 1 or ``numpy.inf`` (not a bool)
    :return: ``delta`` as a float and ``norm``
    :raises ValueError: if either is out of range
    """
    if isinstance(delta, bool) or not np.isfinite(delta) or delta < 0:
        raise ValueError(f"delta must be a finite number >= 0, got {delta!r}.")
    if isinstance(norm, bool) or not (norm == np.inf or (np.isfinite(norm) and norm >= 1)):
        raise ValueError(f"norm must be a number >= 1 or numpy.inf, got {norm!r}.")
    return float(delta), norm


def _silent_age(obs: dict[str, np.ndarray]) -> np.ndarray:
    """Every agent's age of information after this step if it stays silent, (B, N).

    :param obs: a batch of joint observations; reads ``age`` (B, N, 1), the timers before this step's decisions
    :return: ``age + 1`` by :func:`~sb3_detc.network.advance_timer` with no broadcast, float64
    """
    age = np.asarray(obs["age"], dtype=np.float64)
    return advance_timer(age, np.zeros(age.shape[:-1]))[..., 0]


def _age_reached(obs: dict[str, np.ndarray], steps: int) -> np.ndarray:
    """Where an agent's age of information would reach ``steps`` if it stayed silent now, (B, N).

    :param obs: a batch of joint observations; reads ``age`` (B, N, 1)
    :param steps: the age that forces a broadcast (>= 1)
    :return: True where ``age + 1 >= steps``
    """
    # Ages are whole numbers of steps (float32 in the observation): compare with half a step of margin.
    return _silent_age(obs) > steps - 0.5


class PeriodicTrigger(StatelessTrigger):
    """Every agent broadcasts every ``period``-th step, counted per episode: all in phase, or staggered.

    **In phase** (default): an agent broadcasts when its age of information reaches
    ``period - 1``, i.e. when ``age + 1 >= period`` (``age`` is the timer before this step's
    decision). Since the initial message of an episode counts as received (age 0 at reset),
    the broadcasts fall on the steps ``period - 1, 2 period - 1, ...`` of every episode (step
    0 is the first step), so all agents broadcast at the same steps.

    **Staggered** (round robin, ``staggered=True``): the broadcasts are spread evenly over the
    period. Agent i has the offset ``o_i = floor(i * period / N)`` and broadcasts at the steps
    ``period - 1 - o_i + m * period`` (m = 0, 1, ...), so no more than ``ceil(N / period)``
    agents broadcast in one step (one agent per step if ``N <= period``). The team's clock is
    agent 0's age of information, which every agent receives: agent 0 broadcasts when
    ``age_0 + 1 >= period``, as in phase, so its age counts the steps of the period from
    the reset on (``age_0 = k mod period`` at step k); agent i broadcasts when
    ``min(age_0, period - 1) = period - 1 - o_i``. Agents with offset 0 broadcast with agent
    0. If agent 0's age runs past ``period - 1`` (a trigger switched mid-episode), only the
    offset-0 agents broadcast until its broadcast restarts the clock.

    Either way an agent broadcasts once per ``period`` steps; savings are ``1 - 1 / period``
    over whole periods (episodes whose length is not a multiple of ``period`` differ a little:
    in phase, the last incomplete period has no broadcast; staggered, some agents broadcast
    in it). ``period=1`` is periodic communication every step (no savings).

    :param period: steps between two broadcasts of an agent (an integer >= 1)
    :param staggered: spread the agents' broadcasts over the period (round robin) instead of all at once
    """

    def __init__(self, period: int, staggered: bool = False) -> None:
        self.period = check_integer("period", period)
        if not isinstance(staggered, (bool, np.bool_)):
            raise ValueError(f"staggered must be a bool, got {staggered!r}.")
        self.staggered = bool(staggered)

    def __repr__(self) -> str:
        return f"PeriodicTrigger(period={self.period}, staggered={self.staggered})"

    def offsets(self, n_agents: int) -> np.ndarray:
        """The agents' offsets in steps: how much earlier in the period each agent broadcasts than agent 0.

        :param n_agents: number of agents N
        :return: ``floor(i * period / N)`` for ``i = 0 .. N - 1`` if staggered, else zeros, int64 (N,)
        """
        if not self.staggered:
            return np.zeros(n_agents, dtype=np.int64)
        return np.arange(n_agents, dtype=np.int64) * self.period // n_agents

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N).

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key; reads ``age``
            (B, N, 1), the ages of information in steps before this step's decision
        :return: options (B, N), int64: in phase, 1 (broadcast) where ``age + 1 >= period``;
            staggered, 1 where agent 0's age (capped at ``period - 1``) is ``period - 1 - o_i``
        """
        if not self.staggered:
            return _age_reached(obs, self.period).astype(np.int64)
        clock = np.minimum(np.rint(np.asarray(obs["age"], dtype=np.float64)[..., :1, 0]), self.period - 1)  # (B, 1)
        offsets = self.offsets(np.shape(obs["age"])[-2])
        return (clock + offsets == self.period - 1).astype(np.int64)


class DitheredTrigger:
    """A fixed trigger with random deviations, for exploration around it.

    Each of the trigger's broadcasts is skipped with ``skip_prob``, and each of its silences
    broken with ``extra_prob``, independently per agent and step. A critic that learns under a
    deterministic trigger never sees the options it does not take (a schedule's skipped
    message, an early one), and a policy over options started as that trigger would follow the
    critic's guesses there. ``DitheredTrigger(PeriodicTrigger(16), 0.1, 0.01)`` stays close to
    the schedule's rate and shows both options at every age.

    :param trigger: the trigger followed, a stateless one (e.g. :class:`PeriodicTrigger`)
    :param skip_prob: probability of staying silent where the trigger broadcasts, in [0, 1]
    :param extra_prob: probability of broadcasting where the trigger stays silent, in [0, 1]
    :param seed: seed of the deviations' random generator
    :raises ValueError: for a probability outside [0, 1]
    """

    def __init__(self, trigger: StatelessTrigger, skip_prob: float, extra_prob: float, seed: int | None = None) -> None:
        for name, value in (("skip_prob", skip_prob), ("extra_prob", extra_prob)):
            if isinstance(value, bool) or not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value!r}.")
        self.trigger = trigger
        self.skip_prob = float(skip_prob)
        self.extra_prob = float(extra_prob)
        self.rng = np.random.default_rng(seed)

    def __repr__(self) -> str:
        return f"DitheredTrigger({self.trigger!r}, skip_prob={self.skip_prob:g}, extra_prob={self.extra_prob:g})"

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N).

        :param obs: a batch of joint observations, as the followed trigger reads them
        :return: options (B, N), int64: the trigger's, each broadcast kept with ``1 - skip_prob``
            and each silence broken with ``extra_prob``
        """
        followed = np.asarray(self.trigger(obs)) == 1
        draws = self.rng.random(followed.shape)
        return np.where(followed, draws >= self.skip_prob, draws < self.extra_prob).astype(np.int64)

    def broadcast_probability(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Every agent's probability of broadcasting in these observations (draws nothing), (B, N).

        :param obs: a batch of joint observations, as :meth:`__call__` reads them
        :return: ``p (1 - skip_prob) + (1 - p) extra_prob`` with ``p`` the followed trigger's probability, float64
        """
        p = self.trigger.broadcast_probability(obs)
        return p * (1.0 - self.skip_prob) + (1.0 - p) * self.extra_prob

    def fork(self, seed: int) -> DitheredTrigger:
        """An independent copy with its own seed (one per rollout worker, see :mod:`sb3_detc.mappoc.workers`).

        :param seed: seed of the copy's random generator
        :return: a :class:`DitheredTrigger` of the followed trigger's fork with the same probabilities
        """
        return DitheredTrigger(self.trigger.fork(seed), self.skip_prob, self.extra_prob, seed)


class SendOnDelta(StatelessTrigger):
    """Send-on-delta: an agent broadcasts when its trigger features moved more than ``delta`` since its last broadcast.

    Agent i broadcasts when ``||trigger_i - trigger_held_i|| > delta`` (strictly), where
    ``trigger_held_i`` are the trigger features at the agent's own last broadcast (or at the
    reset), both read from the joint observation. The classic event-triggered reference:
    ``delta = 0`` broadcasts whenever anything changed, a large ``delta`` never. With
    ``max_age``, an agent also broadcasts when its age of information would reach ``max_age``
    (``age + 1 >= max_age``, as :class:`PeriodicTrigger` with that period): no receiver's view
    of it is ever older than ``max_age - 1`` steps after a step's broadcasts.

    :param delta: threshold (a finite number >= 0), in the units of the trigger features
    :param norm: order of the vector norm (``numpy.linalg.norm``'s ``ord``): a number >= 1
        or ``numpy.inf`` (default 2, the Euclidean norm)
    :param max_age: broadcast at the latest every ``max_age`` steps (an integer >= 1), or None
        for no maximum age
    """

    def __init__(self, delta: float, norm: float = 2, max_age: int | None = None) -> None:
        self.delta, self.norm = _check_threshold(delta, norm)
        self.max_age = None if max_age is None else check_integer("max_age", max_age)

    def __repr__(self) -> str:
        return f"SendOnDelta(delta={self.delta!r}, norm={self.norm:g}, max_age={self.max_age})"

    def distance(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """How far every agent's trigger features moved since its last broadcast, (B, N).

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key; reads
            ``trigger`` and ``trigger_held`` (B, N, n_trig)
        :return: norms (of order ``norm``) of ``trigger - trigger_held``, (B, N), float64
        """
        moved = np.asarray(obs["trigger"], dtype=np.float64) - np.asarray(obs["trigger_held"], dtype=np.float64)
        return np.linalg.norm(moved, ord=self.norm, axis=-1)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N).

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key; reads
            ``trigger`` and ``trigger_held`` (see :meth:`distance`), and ``age`` (B, N, 1) with ``max_age``
        :return: options (B, N), int64: 1 (broadcast) where :meth:`distance` exceeds ``delta`` or
            (with ``max_age``) ``age + 1 >= max_age``, else 0
        """
        broadcast = self.distance(obs) > self.delta
        if self.max_age is not None:
            broadcast |= _age_reached(obs, self.max_age)
        return broadcast.astype(np.int64)


def _linear_system(system_or_env: LinearSystem | gym.Env, name: str) -> LinearSystem:
    """The linear system itself, or the one inside a joint env whose ``held`` are the held broadcasts.

    Every caller reads ``held`` as the broadcasts themselves (and predicts from them, or acts on
    them): an env that shows the receivers' predictions in their place
    (:class:`ReceiverPredictions`) is refused rather than predicted from twice.

    :param system_or_env: a :class:`~sb3_detc.envs.linear.LinearSystem` or a joint env around one
    :param name: the caller's name, for the message
    :return: the linear system
    :raises ValueError: if no linear system is found, or the env shows predictions as ``held``
    """
    wrapper = system_or_env
    while isinstance(wrapper, gym.Wrapper):
        if isinstance(wrapper, ReceiverPredictions):
            raise ValueError(
                f"{name} reads the held broadcasts, but {system_or_env} shows the receivers' predictions in their "
                "place (ReceiverPredictions): pass the env without it (predicted_held=False)."
            )
        wrapper = wrapper.env
    system = system_or_env
    if not isinstance(system, LinearSystem):
        network = getattr(getattr(system_or_env, "unwrapped", None), "network", None)
        system = getattr(network, "system", None)
    if not isinstance(system, LinearSystem):
        raise ValueError(f"{name} needs a LinearSystem or a joint env around one, got {system_or_env!r}.")
    return system


class PredictiveTrigger(StatelessTrigger):
    """Predictive triggering on the linear system: broadcast when the receivers' prediction is off by > ``delta``.

    The receivers predict every agent's current state from its held broadcast and its age
    with the known model (:class:`~sb3_detc.envs.linear.HeldStatePredictor`: the agent's own
    closed-loop block under the LQR gain). Agent i, which knows its state and what its
    receivers hold, broadcasts when ``||m_i - x^_i|| > delta`` (strictly), with ``m_i`` its
    current message (its state) and ``x^_i`` the receivers' prediction of it if it stays
    silent now (held broadcast, age ``age_i + 1``). The control law that goes with it,
    :func:`lqr_on_predicted_states`, acts on the same predictions: this is what a control
    engineer with the model deploys, the model-based anchor of the matched-rate comparison.
    ``delta = 0`` broadcasts whenever the prediction is not exact.

    At the reset the initial message counts as received with age 0 (as after a broadcast a
    step before), so until an agent first broadcasts, its prediction runs one step ahead of
    its state.

    :param system_or_env: a :class:`~sb3_detc.envs.linear.LinearSystem` or a joint env around one
    :param delta: threshold (a finite number >= 0), in the units of the state ``(e_i, v_i)``
    :param norm: order of the vector norm, as in :class:`SendOnDelta` (default 2)
    :param gain: the control law's gain (N, 2N), as for :func:`lqr_on_predicted_states`; None for the LQR gain
    :raises ValueError: if no linear system is found, or on a bad ``delta``, ``norm`` or ``gain``
    """

    def __init__(
        self, system_or_env: LinearSystem | gym.Env, delta: float, norm: float = 2, gain: np.ndarray | None = None
    ) -> None:
        self.delta, self.norm = _check_threshold(delta, norm)
        self.predictor = HeldStatePredictor(_linear_system(system_or_env, "PredictiveTrigger"), gain)

    def __repr__(self) -> str:
        return f"PredictiveTrigger(delta={self.delta!r}, norm={self.norm:g})"

    def deviation(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """What the receivers' prediction of every agent would miss if it stayed silent now, (B, N, 2).

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key; reads
            ``message`` and ``held`` (B, N, 2), ``age`` (B, N, 1)
        :return: ``message - prediction``, (B, N, 2), float64
        """
        predicted = self.predictor(obs["held"], _silent_age(obs)[..., None])
        return np.asarray(obs["message"], dtype=np.float64) - predicted

    def error(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """How far the receivers' prediction of every agent would be off if it stayed silent now, (B, N).

        :param obs: a batch of joint observations, as :meth:`deviation` reads them
        :return: norms (of order ``norm``) of :meth:`deviation`, (B, N), float64
        """
        return np.linalg.norm(self.deviation(obs), ord=self.norm, axis=-1)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N).

        :param obs: a batch of joint observations, as :meth:`error` reads them
        :return: options (B, N), int64: 1 (broadcast) where :meth:`error` exceeds ``delta``, else 0
        """
        return (self.error(obs) > self.delta).astype(np.int64)


# --------------------------------------------------------------------- evaluation of triggers
#: A trigger: options (B, N) from a batch of joint observations (dict of (B, N, ...) arrays).
Trigger = Callable[[dict[str, np.ndarray]], np.ndarray]
#: A control law: controls (N, m) from one joint observation (no batch axis) and this step's options (N,).
Control = Callable[[dict[str, np.ndarray], np.ndarray], np.ndarray]


@dataclass
class TriggerPoint:
    """One point of a cost-versus-savings curve.

    :param label: name of the trigger (e.g. ``"send-on-delta 0.1"``)
    :param savings: communication savings ``Gamma = 1 - broadcasts / agent-steps``
    :param cost: mean team control cost per episode (minus the sum of the agents' control
        rewards over the episode; the communication cost is not included)
    :param cost_sem: standard error of ``cost`` over the episodes (0 for a single episode)
    :param episodes: number of episodes
    """

    label: str
    savings: float
    cost: float
    cost_sem: float
    episodes: int


def evaluate_trigger(
    env: gym.Env,
    trigger: Trigger,
    control: Control,
    n_episodes: int = 20,
    seed: int = 0,
    label: str = "",
) -> TriggerPoint:
    """Run whole episodes of a joint env with a non-learned trigger and a given control law.

    Every step, the options are ``trigger(batch)[0]`` with ``batch`` the joint observation
    with a batch axis of size 1, and the controls ``control(obs, options)`` (same-step
    delivery: the control law may use this step's broadcasts). Episode ``i`` is reset with
    seed ``seed + i``, so different triggers and controls see the same initial states and
    disturbances (for systems whose randomness does not depend on the actions, like
    :class:`~sb3_detc.envs.linear.LinearSystem`). A trigger with its own random generator
    (:class:`RandomTrigger`) is not re-seeded: seed it when it is built.

    :param env: a joint env (e.g. ``gymnasium.make("sb3_detc/LinearETC-v0")``), not vectorised
    :param trigger: options (B, N) from a batch of joint observations, e.g. :class:`SendOnDelta`
    :param control: controls (N, m) from one joint observation and this step's options (N,),
        e.g. :func:`lqr_on_held_states`
    :param n_episodes: number of episodes (>= 1)
    :param seed: seed of the first episode
    :param label: name of the point
    :return: savings and team control cost per episode
    :raises ValueError: if ``env`` is not a joint env or ``n_episodes < 1``
    """
    n_episodes = check_integer("n_episodes", n_episodes)
    if not isinstance(env.unwrapped, JointEnv):
        raise ValueError(f"evaluate_trigger needs a joint sb3_detc env, got {env}.")
    costs = np.zeros(n_episodes)
    broadcasts, agent_steps = 0, 0
    for episode in range(n_episodes):
        obs, _ = env.reset(seed=int(seed) + episode)
        done = False
        while not done:
            batch = {key: np.asarray(value)[None] for key, value in obs.items()}
            broadcast = np.asarray(trigger(batch))[0].astype(np.int64)
            controls = control(obs, broadcast)
            obs, _, terminated, truncated, info = env.step({"broadcast": broadcast, "control": controls})
            costs[episode] -= float(np.sum(info["control_rewards"]))
            broadcasts += int(broadcast.sum())
            agent_steps += broadcast.size
            done = terminated or truncated
    sem = float(costs.std(ddof=1) / np.sqrt(n_episodes)) if n_episodes > 1 else 0.0
    return TriggerPoint(
        label=label,
        savings=1.0 - broadcasts / agent_steps,
        cost=float(costs.mean()),
        cost_sem=sem,
        episodes=n_episodes,
    )


def lqr_on_held_states(system_or_env: LinearSystem | gym.Env) -> Control:
    """Control law of the model-based event-triggered baseline: LQR on held broadcasts.

    Every agent applies its row of the centralised LQR gain to its own view of the team
    after this step's broadcasts (same-step delivery): the others' held broadcasts, its own
    current state. With broadcasts every step it is the centralised LQR controller.

    :param system_or_env: a :class:`~sb3_detc.envs.linear.LinearSystem` or a joint env around one
    :return: ``control(obs, broadcast)`` -> controls (N, 1)
    :raises ValueError: if no linear system is found
    """
    controller = LQRController(_linear_system(system_or_env, "lqr_on_held_states"))

    def control(obs: dict[str, np.ndarray], broadcast: np.ndarray) -> np.ndarray:
        held = hold(np.asarray(obs["held"]), np.asarray(obs["message"]), np.asarray(broadcast))
        return controller.on_views(held, obs["local"])

    return control


def lqr_on_predicted_states(system_or_env: LinearSystem | gym.Env, gain: np.ndarray | None = None) -> Control:
    """Control law of predictive triggering: LQR on the receivers' predictions of the held states.

    As :func:`lqr_on_held_states`, but every agent sees the others' states as predicted from
    their held broadcasts and ages after this step's broadcasts (same-step delivery), by the
    prediction that :class:`PredictiveTrigger` triggers on
    (:class:`~sb3_detc.envs.linear.HeldStatePredictor`); its own row is its current state. With
    broadcasts every step it is the centralised LQR controller. Use it with
    :func:`evaluate_trigger` or :class:`FixedControl`.

    :param system_or_env: a :class:`~sb3_detc.envs.linear.LinearSystem` or a joint env around one
    :param gain: the gain (N, 2N) of the control law ``u = -K x`` and of the prediction (e.g. a
        detuned one; pass the same to :class:`PredictiveTrigger`); None for the LQR gain
    :return: ``control(obs, broadcast)`` -> controls (N, 1)
    :raises ValueError: if no linear system is found, or ``gain`` has the wrong shape
    """
    system = _linear_system(system_or_env, "lqr_on_predicted_states")
    controller = LQRController(system, gain)
    predictor = HeldStatePredictor(system, controller.gain)

    def control(obs: dict[str, np.ndarray], broadcast: np.ndarray) -> np.ndarray:
        broadcast = np.asarray(broadcast)
        held = hold(np.asarray(obs["held"]), np.asarray(obs["message"]), broadcast)
        age = advance_timer(np.asarray(obs["age"]), broadcast)
        return controller.on_views(predictor(held, age), obs["local"])

    return control


#: Control laws that :class:`FixedControl` builds by name for its env's linear system.
CONTROL_LAWS: dict[str, Callable[[LinearSystem | gym.Env], Control]] = {
    "lqr_on_held_states": lqr_on_held_states,
    "lqr_on_predicted_states": lqr_on_predicted_states,
}


class FixedControl(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """A joint env whose controls come from a fixed control law; the options pass through.

    Every step, the control law gets the observation before the step's decisions and the
    step's options (same-step delivery) and its controls replace the agent's. MAPPOC then
    learns only when to communicate for that controller (its control policy's output has
    no effect), e.g. with :func:`lqr_on_held_states`, the model-based event-triggered
    setting in which send-on-delta is the classic trigger.

    Its arguments are recorded in the env's spec, so ``gym.make(env.spec)`` makes it again (as
    :func:`~sb3_detc.evaluation.evaluate_episodes` does to run episodes side by side): a law
    named by a key of :data:`CONTROL_LAWS` is built anew for the copy's system, a law given as a
    callable is shared with the copy, not copied (right for a law that is a function of its
    arguments only, as every law of this module is).

    :param env: a joint env (:class:`~sb3_detc.envs.wrappers.JointEnv`, possibly wrapped)
    :param control: the control law ``control(obs, broadcast) -> controls (N, m)``, a function of
        its arguments only; or the name of one of :data:`CONTROL_LAWS`, built for the env's linear
        system; None for ``"lqr_on_held_states"``
    :raises ValueError: for a name that is not a key of :data:`CONTROL_LAWS`
    """

    def __init__(self, env: gym.Env, control: Control | str | None = None) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, control=control, _disable_deepcopy=True)
        gym.Wrapper.__init__(self, env)
        if control is None or isinstance(control, str):
            name = "lqr_on_held_states" if control is None else control
            if name not in CONTROL_LAWS:
                raise ValueError(f"unknown control law {name!r}; the named laws are {sorted(CONTROL_LAWS)}.")
            control = CONTROL_LAWS[name](env)
        self.control = control
        self._obs: dict[str, np.ndarray] | None = None

    def reset(self, **kwargs: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Reset the env and remember the observation for the control law.

        :param kwargs: passed to the env's ``reset`` (``seed``, ``options``)
        :return: the env's first observation and info
        """
        self._obs, info = self.env.reset(**kwargs)
        return self._obs, info

    def step(self, action: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Step with the action's options and the control law's controls.

        :param action: joint action; its ``control`` entry is ignored
        :return: the env's observation, reward, terminated, truncated and info of the step
        :raises RuntimeError: if ``reset`` was not called first
        """
        if self._obs is None:
            raise RuntimeError("FixedControl: call reset() before step().")
        broadcast = np.asarray(action["broadcast"])
        control = np.asarray(self.control(self._obs, broadcast), dtype=self.action_space["control"].dtype)
        self._obs, reward, terminated, truncated, info = self.env.step({"broadcast": broadcast, "control": control})
        return self._obs, reward, terminated, truncated, info


class ReceiverPredictions(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """A joint env on the linear system in which what the receivers hold of an agent is their prediction of it.

    Every agent's held broadcast (``held``, as every receiver and the critic see it) and its own
    ``trigger_held`` are replaced by the receivers' prediction of its state if it stays silent now:
    the prediction that :class:`PredictiveTrigger` compares with and :func:`lqr_on_predicted_states`
    acts on (:class:`~sb3_detc.envs.linear.HeldStatePredictor`, held broadcast and age + 1), which
    the agent can compute from what it last broadcast and when. After this step's options the
    network's rule (a broadcast replaces what is held) then gives exactly what the receivers
    believe: a policy over options reads how far that belief is off, as predictive triggering
    does, and a critic values the belief itself, instead of both having to learn the model's
    prediction from the age. :class:`SendOnDelta` on this env is predictive triggering;
    :class:`PredictiveTrigger` itself runs on the env without this wrapper (it predicts from the
    held broadcasts). The network, the controls (a :class:`FixedControl` inside reads the env's own
    observations) and ``local``, ``message``, ``age`` and ``trigger`` are unchanged.
    ``sb3_detc/LinearETC-LQR-v0`` with ``prediction=True, predicted_held=True`` is this env.

    :param env: a joint env around a :class:`~sb3_detc.envs.linear.LinearSystem` (possibly wrapped)
    :param gain: the control law's gain (N, 2N), as for :func:`lqr_on_predicted_states`; None for the LQR gain
    :raises ValueError: if no linear system is found, or ``gain`` has the wrong shape
    """

    def __init__(self, env: gym.Env, gain: np.ndarray | None = None) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, gain=gain)
        gym.ObservationWrapper.__init__(self, env)
        self.predictor = HeldStatePredictor(_linear_system(env, "ReceiverPredictions"), gain)

    def observation(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The joint observation with the receivers' predictions as ``held`` and ``trigger_held``.

        :param observation: the env's joint observation; ``held`` (N, 2) and ``age`` (N, 1) are read
        :return: a copy whose ``held`` and ``trigger_held`` (N, 2) are every agent's predicted state if it
            stays silent now
        """
        predicted = self.predictor(observation["held"], _silent_age(observation)[..., None])
        held = predicted.astype(observation["held"].dtype)
        return {**observation, "held": held, "trigger_held": held.astype(observation["trigger_held"].dtype)}


def sweep_send_on_delta(
    env: gym.Env,
    control: Control,
    deltas: Sequence[float],
    n_episodes: int = 20,
    seed: int = 0,
) -> list[TriggerPoint]:
    """Cost versus savings of send-on-delta over thresholds: the classic event-triggered reference.

    :param env: a joint env, as for :func:`evaluate_trigger`
    :param control: the control law, e.g. :func:`lqr_on_held_states`
    :param deltas: thresholds (non-empty, each a finite number >= 0)
    :param n_episodes: episodes per threshold (>= 1), the same seeds for every threshold
    :param seed: seed of the first episode
    :return: one point per threshold, in the order of ``deltas``, labelled ``"send-on-delta <delta>"``
    :raises ValueError: on an empty ``deltas``, a negative or non-finite threshold, or ``n_episodes < 1``
    """
    deltas = list(deltas)
    if not deltas:
        raise ValueError("deltas must not be empty.")
    for delta in deltas:
        _check_threshold(delta, 2)
    check_integer("n_episodes", n_episodes)
    return [
        evaluate_trigger(env, SendOnDelta(delta), control, n_episodes, seed, label=f"send-on-delta {delta:g}")
        for delta in deltas
    ]


# --------------------------------------------------------------------- matching a savings target
#: The families of fixed triggers that :func:`tune_trigger` matches to a savings target, by name.
TRIGGER_FAMILIES = ("periodic", "periodic_staggered", "send_on_delta", "send_on_delta_max_age", "predictive")
#: The families of :data:`TRIGGER_FAMILIES` whose parameter is a period (the others' is a threshold).
PERIODIC_FAMILIES = ("periodic", "periodic_staggered")


class SavingsNotReached(ValueError):
    """A family of triggers reaches no savings within the tolerance of the target on the given episodes."""


def family_max_age(target_savings: float) -> int:
    """The maximum age of the family ``"send_on_delta_max_age"`` at a savings target: twice the period.

    A periodic trigger reaches the savings ``s`` with the period ``1 / (1 - s)``. With a maximum
    age of that period, send-on-delta would reach the target only as periodic communication
    (forced broadcasts alone use the whole budget); with twice the period, forced broadcasts use
    at most half of it, so the events decide, and every agent's silence is still bounded.

    :param target_savings: the savings target, in (0, 1)
    :return: ``round(2 / (1 - target_savings))``, at least 1
    """
    return max(1, round(2.0 / (1.0 - target_savings)))


def _tune_period(
    staggered: bool, savings_of: Callable[[Trigger], float], target_savings: float, tolerance: float
) -> tuple[Trigger, float]:
    """The periodic trigger whose savings are closest to the target, see :func:`tune_trigger`.

    :param staggered: in phase (False) or staggered periodic
    :param savings_of: savings of a trigger on the given episodes
    :param target_savings: the target, in (0, 1)
    :param tolerance: the largest accepted distance of the savings from the target
    :return: the trigger and its savings
    :raises SavingsNotReached: if neither period around ``1 / (1 - target_savings)`` is within the tolerance
    """
    period = 1.0 / (1.0 - target_savings)
    periods = sorted({max(1, math.floor(period + 1e-9)), max(1, math.ceil(period - 1e-9))})
    tried = [(trigger, float(savings_of(trigger))) for trigger in (PeriodicTrigger(p, staggered) for p in periods)]
    trigger, savings = min(tried, key=lambda pair: abs(pair[1] - target_savings))
    if abs(savings - target_savings) > tolerance:
        found = ", ".join(f"period {t.period} gives {s:.4f}" for t, s in tried)
        raise SavingsNotReached(
            f"no period reaches savings {target_savings:g} within {tolerance:g} on these episodes: {found}."
        )
    return trigger, savings


def _threshold_search(
    make_trigger: Callable[[float], Trigger],
    savings_of: Callable[[Trigger], float],
    target_savings: float,
    max_iterations: int,
    initial: float,
    factor: float,
) -> Iterator[tuple[_Point, _Point | None, _Point | None]]:
    """The triggers of a bisection on a threshold, one after another, see :func:`tune_trigger`.

    The threshold starts at ``initial`` and is multiplied or divided by ``factor`` until the
    target lies between the savings of two thresholds, then the geometric mean of the two is
    tried (thresholds span decades), for at most ``max_iterations`` triggers.

    :param make_trigger: the trigger at a threshold > 0
    :param savings_of: savings of a trigger on the given episodes
    :param target_savings: the target, in (0, 1)
    :param max_iterations: the most triggers to evaluate
    :param initial: the first threshold
    :param factor: the step of the search before the target is enclosed, > 1
    :return: per trigger tried: its point, and the closest points found so far below the target and at or above it
    """
    below = above = None
    threshold = initial
    for _ in range(max_iterations):
        trigger = make_trigger(threshold)
        point = _Point(threshold, trigger, float(savings_of(trigger)))
        below, above = _closest(point, below, above, target_savings)
        yield point, below, above
        threshold = (
            threshold * factor
            if above is None
            else threshold / factor
            if below is None
            else math.sqrt(below.parameter * above.parameter)
        )


def _tune_threshold(
    make_trigger: Callable[[float], Trigger],
    savings_of: Callable[[Trigger], float],
    target_savings: float,
    tolerance: float,
    max_iterations: int,
    initial: float,
) -> tuple[Trigger, float]:
    """Bisection on a threshold, see :func:`tune_trigger`.

    :param make_trigger: the trigger at a threshold > 0
    :param savings_of: savings of a trigger on the given episodes
    :param target_savings: the target, in (0, 1)
    :param tolerance: the largest accepted distance of the savings from the target
    :param max_iterations: the most triggers to evaluate
    :param initial: the first threshold
    :return: the first trigger found within the tolerance and its savings
    :raises SavingsNotReached: if none is within the tolerance after ``max_iterations`` evaluations
    """
    tried = []
    for point, _, _ in _threshold_search(make_trigger, savings_of, target_savings, max_iterations, initial, 2.0):
        if abs(point.savings - target_savings) <= tolerance:
            return point.trigger, point.savings
        tried.append(point)
    closest = min(tried, key=lambda point: abs(point.savings - target_savings))
    raise SavingsNotReached(
        f"no threshold reached savings {target_savings:g} within {tolerance:g} in {max_iterations} evaluations; "
        f"closest: {closest.parameter:g} with savings {closest.savings:.4f}."
    )


def tune_trigger(
    family: str | Callable[[float], Trigger],
    savings_of: Callable[[Trigger], float],
    target_savings: float,
    tolerance: float = 0.01,
    max_iterations: int = 30,
    system_or_env: LinearSystem | gym.Env | None = None,
    initial: float = 1.0,
) -> tuple[Trigger, float]:
    """The trigger of a family that reaches a savings target on given episodes, within a tolerance.

    ``savings_of(trigger)`` runs the episodes with the trigger (always the same, seeded
    episodes, and whatever control runs them: a control law, a learned controller) and
    returns their savings; e.g. ``lambda t: evaluate_trigger(env, t, control, 50).savings``,
    which :func:`tune_trigger_on_env` does. The families (:data:`TRIGGER_FAMILIES`):

    * ``"periodic"``, ``"periodic_staggered"``: :class:`PeriodicTrigger` in phase or staggered.
      Periodic savings are ``1 - 1 / period``: if ``1 / (1 - target_savings)`` is an integer,
      that period is evaluated; otherwise both integers around it, and the one whose savings
      are closer to the target is taken. If it is further than ``tolerance`` (between the
      savings of two neighbouring periods, e.g. 0.6 lies between 0.5 and 0.667),
      :class:`SavingsNotReached` is raised: no period matches that rate.
    * ``"send_on_delta"``: :class:`SendOnDelta` with threshold ``delta``.
    * ``"send_on_delta_max_age"``: :class:`SendOnDelta` with threshold ``delta`` and the maximum
      age :func:`family_max_age` (twice the period at the target).
    * ``"predictive"``: :class:`PredictiveTrigger` on the linear system of ``system_or_env``.
    * a callable ``make_trigger(threshold) -> trigger``: any family of a threshold > 0.

    Threshold families are searched by bisection: the threshold starts at ``initial`` and is
    doubled or halved until the target lies between the savings of two thresholds, then the
    geometric mean of the two is tried, until the savings are within ``tolerance`` of the
    target. This assumes that the savings grow with the threshold, as they do for a
    send-on-delta rule; on a fixed set of episodes they change in steps of one broadcast, so a
    tolerance below one broadcast per agent-steps of the episodes may not be reached.

    :param family: a name from :data:`TRIGGER_FAMILIES`, or a callable from a threshold to a trigger
    :param savings_of: savings of a trigger on the given episodes (the same episodes for every trigger)
    :param target_savings: the savings to reach, in (0, 1)
    :param tolerance: the largest accepted distance of the savings from the target, in (0, 1)
    :param max_iterations: the most triggers a threshold search evaluates (an integer >= 1;
        periodic families evaluate one or two)
    :param system_or_env: the linear system, or a joint env around it, for ``"predictive"``
    :param initial: the first threshold of a threshold search (> 0), in the units of the family's threshold
    :return: the trigger and its savings on the episodes
    :raises ValueError: on an unknown family or an argument out of range
    :raises SavingsNotReached: if no trigger of the family is found within the tolerance
    """
    max_iterations = _check_search(family, target_savings, tolerance, max_iterations, initial)
    if family in PERIODIC_FAMILIES:
        return _tune_period(family == "periodic_staggered", savings_of, target_savings, tolerance)
    make_trigger = _threshold_family(family, target_savings, system_or_env)
    return _tune_threshold(make_trigger, savings_of, target_savings, tolerance, max_iterations, initial)


def _threshold_family(
    family: str | Callable[[float], Trigger], target_savings: float, system_or_env: LinearSystem | gym.Env | None
) -> Callable[[float], Trigger]:
    """The trigger of a threshold family at a threshold, see :func:`tune_trigger`.

    :param family: a name from :data:`TRIGGER_FAMILIES` other than the periodic ones, or a callable
        from a threshold to a trigger (returned as it is)
    :param target_savings: the savings target (sets the maximum age of ``"send_on_delta_max_age"``)
    :param system_or_env: the linear system, or a joint env around it, for ``"predictive"``
    :return: a callable from a threshold > 0 to a trigger
    :raises ValueError: for ``"predictive"`` without a linear system
    """
    if family == "send_on_delta":
        return SendOnDelta
    if family == "send_on_delta_max_age":
        max_age = family_max_age(target_savings)
        return lambda delta: SendOnDelta(delta, max_age=max_age)
    if family == "predictive":
        system = _linear_system(system_or_env, "the family 'predictive'")
        return lambda delta: PredictiveTrigger(system, delta)
    return family


def _check_search(
    family: str | Callable[[float], Trigger],
    target_savings: float,
    tolerance: float,
    max_iterations: int,
    initial: float,
) -> int:
    """Refuse a search's bad arguments with one clear line, see :func:`tune_trigger`.

    :param family: a name from :data:`TRIGGER_FAMILIES`, or a callable from a threshold to a trigger
    :param target_savings: the savings to reach, in (0, 1)
    :param tolerance: in (0, 1)
    :param max_iterations: an integer >= 1
    :param initial: the first threshold, > 0
    :return: ``max_iterations``
    :raises ValueError: on an unknown family or an argument out of range
    """
    if family not in TRIGGER_FAMILIES if isinstance(family, str) else not callable(family):
        raise ValueError(f"family must be one of {TRIGGER_FAMILIES} or a callable, got {family!r}.")
    if isinstance(target_savings, bool) or not 0.0 < target_savings < 1.0:
        raise ValueError(f"target_savings must be in (0, 1), got {target_savings!r}.")
    if isinstance(tolerance, bool) or not 0.0 < tolerance < 1.0:
        raise ValueError(f"tolerance must be in (0, 1), got {tolerance!r}.")
    if isinstance(initial, bool) or not (np.isfinite(initial) and initial > 0):
        raise ValueError(f"initial must be a finite number > 0, got {initial!r}.")
    return check_integer("max_iterations", max_iterations)


@dataclass(frozen=True)
class _Point:
    """A trigger of a family tried on the episodes of a search: its parameter (period, threshold) and savings."""

    parameter: float
    trigger: Trigger
    savings: float


def _closest(
    point: _Point, below: _Point | None, above: _Point | None, target_savings: float
) -> tuple[_Point | None, _Point | None]:
    """A search's closest points on either side of the target after trying ``point`` (the searches narrow in on it).

    :param point: the latest point
    :param below: the closest point below the target so far, or None
    :param above: the closest point at or above it so far, or None
    :param target_savings: the target
    :return: ``below`` and ``above`` with ``point`` in place of the one on its side
    """
    return (point, above) if point.savings < target_savings else (below, point)


@dataclass(frozen=True)
class Bracket:
    """Two triggers of a family whose savings on the same episodes enclose a target (:func:`bracket_trigger`).

    Their mixture reaches the target exactly: run ``lower`` in a share of the episodes and
    ``upper`` in the others (:meth:`sb3_detc.evaluation.Episodes.mixture` computes its expected
    results from both triggers' episodes). Where one trigger meets the target, it is both.

    :param lower: the trigger with savings at or below the target (the smaller period or threshold)
    :param lower_parameter: its period or threshold
    :param lower_savings: its savings on the episodes
    :param upper: the trigger with savings at or above the target
    :param upper_parameter: its period or threshold
    :param upper_savings: its savings on the episodes
    """

    lower: Trigger
    lower_parameter: float
    lower_savings: float
    upper: Trigger
    upper_parameter: float
    upper_savings: float

    @classmethod
    def of(cls, lower: _Point, upper: _Point) -> Bracket:
        """The bracket of two points of a search.

        :param lower: the point at or below the target
        :param upper: the point at or above it
        :return: their bracket
        """
        return cls(lower.trigger, lower.parameter, lower.savings, upper.trigger, upper.parameter, upper.savings)


def bracket_trigger(
    family: str | Callable[[float], Trigger],
    savings_of: Callable[[Trigger], float],
    target_savings: float,
    tolerance: float = 0.01,
    max_iterations: int = 30,
    system_or_env: LinearSystem | gym.Env | None = None,
    initial: float = 1.0,
    factor: float = 2.0,
) -> Bracket:
    """Two triggers of a family whose savings on given episodes enclose a target: a match at exactly that rate.

    :func:`tune_trigger` takes the first trigger within a tolerance of the target, so a
    comparison at "the same savings" may differ by up to the tolerance, and the family's return
    changes with its savings. The bracket's mixture (:class:`Bracket`) meets the target
    exactly instead. ``savings_of`` is as for :func:`tune_trigger`.

    * Periodic families: from the period ``floor(1 / (1 - target_savings))`` the period steps
      down or up by one until two neighbouring periods enclose the target (their savings on the
      episodes, which differ a little from ``1 - 1 / period``); ``tolerance`` is not used.
    * Threshold families: the bisection of :func:`tune_trigger` (from ``initial``, multiplied or
      divided by ``factor`` until the target is enclosed), until the two thresholds closest to
      the target on either side differ by at most ``tolerance`` in savings, or one meets it.

    :param family: a name from :data:`TRIGGER_FAMILIES`, or a callable from a threshold to a trigger
    :param savings_of: savings of a trigger on the given episodes (the same episodes for every trigger)
    :param target_savings: the savings to enclose, in (0, 1)
    :param tolerance: the width in savings at which a threshold search stops, in (0, 1); on a fixed
        set of episodes the savings change in steps of one broadcast, so the search may end wider
        (after ``max_iterations``): its bracket still encloses the target
    :param max_iterations: the most triggers the search evaluates (an integer >= 1)
    :param system_or_env: the linear system, or a joint env around it, for ``"predictive"``
    :param initial: the first threshold of a threshold search (> 0)
    :param factor: the step of a threshold search before the target is enclosed (> 1)
    :return: the bracket
    :raises ValueError: on an unknown family or an argument out of range
    :raises SavingsNotReached: if no two triggers tried enclose the target
    """
    max_iterations = _check_search(family, target_savings, tolerance, max_iterations, initial)
    if isinstance(factor, bool) or not (np.isfinite(factor) and factor > 1):
        raise ValueError(f"factor must be a finite number > 1, got {factor!r}.")
    if family in PERIODIC_FAMILIES:
        search = _period_search(family == "periodic_staggered", savings_of, target_savings, max_iterations)
    else:
        make_trigger = _threshold_family(family, target_savings, system_or_env)
        search = _threshold_search(make_trigger, savings_of, target_savings, max_iterations, initial, factor)
    below = above = None
    for point, below, above in search:
        if point.savings == target_savings:
            return Bracket.of(point, point)
        if below is not None and above is not None and above.savings - below.savings <= tolerance:
            break
    if below is None or above is None:
        found = below or above
        raise SavingsNotReached(
            f"no two triggers enclose savings {target_savings:g} in {max_iterations} evaluations; "
            f"closest: {found.parameter:g} with savings {found.savings:.4f}."
        )
    return Bracket.of(below, above)


def _period_search(
    staggered: bool, savings_of: Callable[[Trigger], float], target_savings: float, max_iterations: int
) -> Iterator[tuple[_Point, _Point | None, _Point | None]]:
    """The periodic triggers of :func:`bracket_trigger`, one after another, until two neighbours enclose the target.

    :param staggered: in phase (False) or staggered periodic
    :param savings_of: savings of a trigger on the given episodes
    :param target_savings: the target, in (0, 1)
    :param max_iterations: the most triggers to evaluate
    :return: per trigger tried: its point, and the closest points found so far below the target and at or above it
    """
    below = above = None
    period = max(1, math.floor(1.0 / (1.0 - target_savings) + 1e-9))
    for _ in range(max_iterations):
        trigger = PeriodicTrigger(period, staggered)
        point = _Point(period, trigger, float(savings_of(trigger)))
        below, above = _closest(point, below, above, target_savings)
        yield point, below, above
        if below is not None and above is not None or (above is not None and period == 1):
            return
        period = period + 1 if above is None else period - 1


def tune_trigger_on_env(
    env: gym.Env,
    family: str | Callable[[float], Trigger],
    target_savings: float,
    control: Control | None = None,
    n_episodes: int = 20,
    seed: int = 0,
    tolerance: float = 0.01,
    max_iterations: int = 30,
    initial: float = 1.0,
) -> tuple[Trigger, TriggerPoint]:
    """:func:`tune_trigger` on the episodes of :func:`evaluate_trigger` with a control law.

    Every trigger tried runs the same episodes (seeds ``seed`` to ``seed + n_episodes - 1``).

    :param env: a joint env, as for :func:`evaluate_trigger`
    :param family: a name from :data:`TRIGGER_FAMILIES` or a callable from a threshold to a
        trigger, see :func:`tune_trigger`
    :param target_savings: the savings to reach, in (0, 1)
    :param control: the control law; None for the one that goes with the family on the linear
        system: :func:`lqr_on_predicted_states` for ``"predictive"``, else :func:`lqr_on_held_states`
    :param n_episodes: number of episodes (>= 1)
    :param seed: seed of the first episode
    :param tolerance: the largest accepted distance of the savings from the target, in (0, 1)
    :param max_iterations: the most triggers a threshold search evaluates (>= 1)
    :param initial: the first threshold of a threshold search (> 0)
    :return: the trigger and its point on the episodes (labelled with the trigger's ``repr``)
    :raises ValueError: on an argument out of range, or with ``control=None`` on an env without a linear system
    :raises SavingsNotReached: if no trigger of the family is found within the tolerance
    """
    if control is None:
        control = lqr_on_predicted_states(env) if family == "predictive" else lqr_on_held_states(env)
    n_episodes = check_integer("n_episodes", n_episodes)
    points: list[tuple[Trigger, TriggerPoint]] = []

    def savings_of(trigger: Trigger) -> float:
        points.append((trigger, evaluate_trigger(env, trigger, control, n_episodes, seed, label=repr(trigger))))
        return points[-1][1].savings

    trigger, _ = tune_trigger(family, savings_of, target_savings, tolerance, max_iterations, env, initial)
    return trigger, next(point for tried, point in points if tried is trigger)
