"""Non-learned communication triggers, usable wherever MAPPOC accepts a fixed trigger.

A trigger maps a batch of joint observations (dict of arrays shaped (B, N, ...)) to
options (B, N) in {0, 1}. :func:`evaluate_trigger` runs a trigger with a given control law
(e.g. :func:`lqr_on_held_states` on the linear system) and reports a :class:`TriggerPoint`
(savings and control cost); :func:`sweep_send_on_delta` gives the cost-versus-savings curve.
:class:`FixedControl` does the converse: it fixes the control law, so that MAPPOC learns
only when to communicate.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_detc.envs.linear import LinearSystem, LQRController
from sb3_detc.envs.wrappers import JointEnv
from sb3_detc.network import advance_timer, hold


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


class _StatelessTrigger(abc.ABC):
    """A trigger whose options follow from the observations alone: no state, no random draws."""

    @abc.abstractmethod
    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N).

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key
        """

    def fork(self, seed: int) -> _StatelessTrigger:
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


class PeriodicTrigger(_StatelessTrigger):
    """Every agent broadcasts every ``period``-th step, counted per episode; all agents at the same steps.

    Stateless: an agent broadcasts when its age of information reaches ``period - 1``, i.e.
    when ``age + 1 >= period`` (``age`` is the timer before this step's decision). Since the
    initial message of an episode counts as received (age 0 at reset), the broadcasts fall
    on the steps ``period - 1, 2 period - 1, ...`` of every episode (step 0 is the first
    step), so under this trigger all agents broadcast at the same steps. ``period=1`` is
    periodic communication every step (no savings); savings are ``1 - 1 / period``.

    :param period: steps between two broadcasts of an agent (an integer >= 1)
    """

    def __init__(self, period: int) -> None:
        if isinstance(period, bool) or not isinstance(period, (int, np.integer)) or period < 1:
            raise ValueError(f"period must be an integer >= 1, got {period!r}.")
        self.period = int(period)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N).

        :param obs: a batch of joint observations, arrays shaped (B, N, ...) by key; reads ``age``
            (B, N, 1), the ages of information in steps before this step's decision
        :return: options (B, N), int64: 1 (broadcast) where ``age + 1 >= period``, else 0
        """
        age = np.asarray(obs["age"])
        silent = advance_timer(age, np.zeros(age.shape[:-1]))[..., 0]  # the timers if nobody broadcast now
        # Ages are whole numbers of steps (float32 in the observation): compare with half a step of margin.
        return (silent > self.period - 0.5).astype(np.int64)


class SendOnDelta(_StatelessTrigger):
    """Send-on-delta: an agent broadcasts when its trigger features moved more than ``delta`` since its last broadcast.

    Agent i broadcasts when ``||trigger_i - trigger_held_i|| > delta`` (strictly), where
    ``trigger_held_i`` are the trigger features at the agent's own last broadcast (or at the
    reset), both read from the joint observation. The classic event-triggered reference:
    ``delta = 0`` broadcasts whenever anything changed, a large ``delta`` never.

    :param delta: threshold (a finite number >= 0), in the units of the trigger features
    :param norm: order of the vector norm (``numpy.linalg.norm``'s ``ord``): a number >= 1
        or ``numpy.inf`` (default 2, the Euclidean norm)
    """

    def __init__(self, delta: float, norm: float = 2) -> None:
        if isinstance(delta, bool) or not np.isfinite(delta) or delta < 0:
            raise ValueError(f"delta must be a finite number >= 0, got {delta!r}.")
        if isinstance(norm, bool) or not (norm == np.inf or (np.isfinite(norm) and norm >= 1)):
            raise ValueError(f"norm must be a number >= 1 or numpy.inf, got {norm!r}.")
        self.delta = float(delta)
        self.norm = norm

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
            ``trigger`` and ``trigger_held`` (see :meth:`distance`)
        :return: options (B, N), int64: 1 (broadcast) where :meth:`distance` exceeds ``delta``, else 0
        """
        return (self.distance(obs) > self.delta).astype(np.int64)


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


def _check_episodes(n_episodes: int) -> int:
    """Check a number of episodes.

    :param n_episodes: the number of episodes (an integer >= 1, not a bool)
    :return: ``n_episodes`` as an int
    :raises ValueError: if ``n_episodes`` is not an integer >= 1
    """
    if isinstance(n_episodes, bool) or not isinstance(n_episodes, (int, np.integer)) or n_episodes < 1:
        raise ValueError(f"n_episodes must be an integer >= 1, got {n_episodes!r}.")
    return int(n_episodes)


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
    n_episodes = _check_episodes(n_episodes)
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
    system = system_or_env
    if not isinstance(system, LinearSystem):
        network = getattr(getattr(system_or_env, "unwrapped", None), "network", None)
        system = getattr(network, "system", None)
    if not isinstance(system, LinearSystem):
        raise ValueError(f"lqr_on_held_states needs a LinearSystem or a joint env around one, got {system_or_env!r}.")
    controller = LQRController(system)

    def control(obs: dict[str, np.ndarray], broadcast: np.ndarray) -> np.ndarray:
        held = hold(np.asarray(obs["held"]), np.asarray(obs["message"]), np.asarray(broadcast))
        return controller.on_views(held, obs["local"])

    return control


class FixedControl(gym.Wrapper):
    """A joint env whose controls come from a fixed control law; the options pass through.

    Every step, the control law gets the observation before the step's decisions and the
    step's options (same-step delivery) and its controls replace the agent's. MAPPOC then
    learns only when to communicate for that controller (its control policy's output has
    no effect), e.g. with :func:`lqr_on_held_states`, the model-based event-triggered
    setting in which send-on-delta is the classic trigger.

    :param env: a joint env (:class:`~sb3_detc.envs.wrappers.JointEnv`, possibly wrapped)
    :param control: the control law ``control(obs, broadcast) -> controls (N, m)``, or None for
        :func:`lqr_on_held_states` of the env's linear system
    """

    def __init__(self, env: gym.Env, control: Control | None = None) -> None:
        super().__init__(env)
        self.control = lqr_on_held_states(env) if control is None else control
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
        if isinstance(delta, bool) or not np.isfinite(delta) or delta < 0:
            raise ValueError(f"every delta must be a finite number >= 0, got {delta!r}.")
    _check_episodes(n_episodes)
    return [
        evaluate_trigger(env, SendOnDelta(delta), control, n_episodes, seed, label=f"send-on-delta {delta:g}")
        for delta in deltas
    ]
