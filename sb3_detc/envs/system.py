"""Physical multi-agent systems whose agents can communicate.

A :class:`CommunicatingSystem` is a PettingZoo ``ParallelEnv`` of N agents that start and
end their episodes together. Besides the usual per-agent observation (the *local
state*), action (the *control*) and reward, it declares per agent the *message* it
would broadcast now and the *trigger features* that the policy over options sees.

Subclasses implement the array-level core :meth:`_reset_arrays` and :meth:`_step_arrays`
(agent axis first); the dictionary API of PettingZoo is built here once on top of it.
The event-triggered network (:mod:`sb3_detc.envs.wrappers`) uses the array core
directly, so the hot path never builds per-agent dictionaries.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv


@dataclass
class SystemObs:
    """Everything a communicating system reports about its agents at one time step.

    :param local: local states, shape (N, n_local)
    :param message: what every agent would broadcast now, shape (N, n_msg)
    :param trigger: features for the policy over options, shape (N, n_trig)
    """

    local: np.ndarray
    message: np.ndarray
    trigger: np.ndarray


class CommunicatingSystem(ParallelEnv):
    """Base class of the physical systems (PettingZoo parallel API, shared episode end).

    Subclasses set in ``__init__``: ``possible_agents`` (list of N names), ``local_space``,
    ``message_space``, ``trigger_space`` (per-agent 1-D ``Box`` spaces) and
    ``control_space`` (per-agent ``Box``), and implement :meth:`_reset_arrays` and
    :meth:`_step_arrays`.
    """

    metadata: dict[str, Any] = {"render_modes": [], "name": "communicating_system"}
    possible_agents: list[str]
    local_space: spaces.Box
    message_space: spaces.Box
    trigger_space: spaces.Box
    control_space: spaces.Box

    def __init__(self) -> None:
        self.agents: list[str] = []
        self._last_obs: SystemObs | None = None

    @property
    def n_agents(self) -> int:
        """Number of agents N."""
        return len(self.possible_agents)

    # ----------------------------------------------------------------- array core
    def _reset_arrays(self, seed: int | None = None) -> tuple[SystemObs, dict[str, Any]]:
        """Start an episode (Gymnasium seeding: the same seed gives the same episode).

        :param seed: seed of the episode's random generator, or None to continue it
        :return: the first observation and an info dict
        """
        raise NotImplementedError

    def _step_arrays(self, control: np.ndarray) -> tuple[SystemObs, np.ndarray, bool, bool, dict[str, Any]]:
        """Apply every agent's control for one step.

        :param control: controls, shape (N, m), already validated
        :return: observation, per-agent rewards (N,), terminated, truncated, info
        """
        raise NotImplementedError

    def reset_arrays(self, seed: int | None = None) -> tuple[SystemObs, dict[str, Any]]:
        """Array-level reset (agent axis first), see :meth:`_reset_arrays`.

        :param seed: seed of the episode's random generator, or None to continue it
        :return: the first observation (:class:`SystemObs`: ``local`` (N, n_local), ``message``
            (N, n_msg), ``trigger`` (N, n_trig)) and an info dict
        """
        obs, info = self._reset_arrays(seed)
        self.agents = list(self.possible_agents)
        self._last_obs = obs
        return obs, info

    def step_arrays(self, control: np.ndarray) -> tuple[SystemObs, np.ndarray, bool, bool, dict[str, Any]]:
        """Array-level step with input checks, see :meth:`_step_arrays`.

        :param control: controls, shape (N, m)
        :return: observation, per-agent rewards (N,), terminated, truncated, info (of :meth:`_step_arrays`)
        :raises RuntimeError: if no episode is running (call reset first)
        :raises ValueError: on a wrong shape or non-finite controls
        """
        if not self.agents:
            raise RuntimeError(
                f"{type(self).__name__}.step called without a running episode: "
                "the last episode ended (or reset was never called); call reset() first."
            )
        control = np.asarray(control, dtype=np.float64)
        expected = (self.n_agents, *self.control_space.shape)
        if control.shape != expected:
            raise ValueError(f"control must have shape {expected} (agents x control), got {control.shape}.")
        if not np.all(np.isfinite(control)):
            raise ValueError("control contains NaN or infinite values.")
        obs, rewards, terminated, truncated, info = self._step_arrays(control)
        self._last_obs = obs
        if terminated or truncated:
            self.agents = []
        return obs, rewards, terminated, truncated, info

    @property
    def last_obs(self) -> SystemObs:
        """The latest observation of all agents."""
        if self._last_obs is None:
            raise RuntimeError("No observation yet: call reset() first.")
        return self._last_obs

    # ------------------------------------------------------------ PettingZoo API
    def observation_space(self, agent: str) -> spaces.Box:
        """Local state space of one agent.

        :param agent: name of the agent (all agents share one space)
        :return: ``local_space``, a ``Box`` of shape (n_local,)
        """
        return self.local_space

    def action_space(self, agent: str) -> spaces.Box:
        """Control space of one agent.

        :param agent: name of the agent (all agents share one space)
        :return: ``control_space``, a ``Box`` of shape (m,)
        """
        return self.control_space

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """PettingZoo reset: per-agent local states and infos.

        :param seed: seed of the episode's random generator, or None to continue it
        :param options: unused (PettingZoo API)
        :return: agent name -> local state, float32 of shape (n_local,), and agent name -> a copy
            of the reset's info dict, for every agent of ``possible_agents``
        """
        obs, info = self.reset_arrays(seed)
        return self._per_agent(obs.local), {a: dict(info) for a in self.possible_agents}

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        """PettingZoo step: a control for every live agent.

        :param actions: agent name -> control of shape (m,), for every agent (all agents live
            together); entries of other names are ignored
        :return: five dicts keyed by agent name, over every agent of ``possible_agents``: local
            states (float32, shape (n_local,)), rewards (float), terminated and truncated (bool,
            the same for all agents) and infos (a copy of the step's info dict each)
        """
        missing = set(self.agents) - set(actions)
        if self.agents and missing:
            raise ValueError(f"actions are missing for agents {sorted(missing)}.")
        control = (
            np.stack([np.asarray(actions[a], dtype=np.float64) for a in self.possible_agents]) if self.agents else None
        )
        obs, rewards, terminated, truncated, info = self.step_arrays(control)
        names = self.possible_agents
        return (
            self._per_agent(obs.local),
            {a: float(r) for a, r in zip(names, rewards, strict=True)},
            dict.fromkeys(names, terminated),
            dict.fromkeys(names, truncated),
            {a: dict(info) for a in names},
        )

    def state(self) -> np.ndarray:
        """Global state: every agent's local state and message, flattened.

        :return: the local states (N * n_local) then the messages (N * n_msg) of the latest observation, float32
        """
        obs = self.last_obs
        return np.concatenate([obs.local.ravel(), obs.message.ravel()]).astype(np.float32)

    def _per_agent(self, array: np.ndarray) -> dict[str, np.ndarray]:
        """Split an array with the agent axis first into one entry per agent.

        :param array: per-agent values, shape (N, ...)
        :return: agent name -> its row as float32, for every agent of ``possible_agents``
        """
        return {a: array[i].astype(np.float32) for i, a in enumerate(self.possible_agents)}
