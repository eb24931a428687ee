"""The event-triggered network around a communicating system, and its joint Gymnasium view.

:class:`EventTriggeredNetwork` is a PettingZoo parallel wrapper that turns any
:class:`~sb3_detc.envs.system.CommunicatingSystem` into the paper's setting: every agent
decides each step whether to broadcast its message, receivers hold the last broadcasts
(zero-order hold) with their age, and each broadcast costs ``broadcast_cost`` reward.

:class:`JointEnv` is the single-agent Gymnasium view of the same network that SB3
vectorises: the agent axis lives inside the arrays of a Dict observation and a Dict action.
Both views advance the network through the same code, :meth:`EventTriggeredNetwork.step_joint`,
which applies the one rule of :mod:`sb3_detc.network`.
"""

from __future__ import annotations

import inspect
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo.utils.wrappers import BaseParallelWrapper

from sb3_detc.envs.system import CommunicatingSystem, SystemObs
from sb3_detc.network import advance_timer, hold, initial_network, others_ages, others_index, relative_views

#: Which :class:`SystemObs` field feeds the policy over options, by name.
TRIGGER_SOURCES = ("default", "local", "message")

JOINT_KEYS = ("local", "message", "held", "age", "trigger", "trigger_held")


def _box(shape: tuple[int, ...], low: float = -np.inf) -> spaces.Box:
    """Float32 ``Box`` bounded below by ``low`` and unbounded above.

    :param shape: shape of the space
    :param low: lower bound of every entry (default: none; 0 for ages)
    :return: ``Box(low, inf, shape, float32)``
    """
    return spaces.Box(low=np.float32(low), high=np.float32(np.inf), shape=shape, dtype=np.float32)


class EventTriggeredNetwork(BaseParallelWrapper):
    """Event-triggered communication between the agents of a communicating system.

    Per agent, the action is ``Dict(broadcast=Discrete(2), control=Box)`` and the observation
    is ``Dict(local, neighbours, neighbour_age, trigger, trigger_held)``: the own local
    state, the others' held broadcasts relative to the own current message (N - 1, n_msg),
    their ages in steps (N - 1,), the option policy's features now and at the agent's own
    last broadcast. Observations show the network *before* this step's decisions; the
    options of a step are delivered in the same step, before its controls act (same-step
    delivery). At reset every agent's initial message counts as received (age 0), so no
    broadcast is forced at the first step.

    :param env: the physical system
    :param broadcast_cost: communication cost ``xi >= 0`` subtracted from an agent's reward for
        every broadcast (``r_i = r_ctrl_i - xi * o_i``, Sec. 2)
    :param trigger: features of the policy over options: ``"default"`` (the system's own
        choice, e.g. the package information in Multiwalker), ``"local"`` (the whole local
        state) or ``"message"`` (the own message)
    """

    def __init__(self, env: CommunicatingSystem, broadcast_cost: float = 0.25, trigger: str = "default") -> None:
        if not isinstance(env, CommunicatingSystem):
            raise TypeError(f"EventTriggeredNetwork wraps a CommunicatingSystem, got {type(env).__name__}.")
        if not np.isfinite(broadcast_cost) or broadcast_cost < 0:
            raise ValueError(f"broadcast_cost must be a finite number >= 0, got {broadcast_cost!r}.")
        if trigger not in TRIGGER_SOURCES:
            raise ValueError(f"trigger must be one of {TRIGGER_SOURCES}, got {trigger!r}.")
        super().__init__(env)
        self.system = env
        self.broadcast_cost = float(broadcast_cost)
        self.trigger = trigger
        self.possible_agents = list(env.possible_agents)
        self.agents: list[str] = []
        self.metadata = env.metadata
        self.render_mode = getattr(env, "render_mode", None)
        n = env.n_agents
        self.n_agents = n
        self.others = others_index(n)
        trigger_space = {"default": env.trigger_space, "local": env.local_space, "message": env.message_space}[trigger]
        self.n_local = env.local_space.shape[0]
        self.n_msg = env.message_space.shape[0]
        self.n_trig = trigger_space.shape[0]
        self._agent_observation_space = spaces.Dict(
            {
                "local": _box((self.n_local,)),
                "neighbours": _box((n - 1, self.n_msg)),
                "neighbour_age": _box((n - 1,), low=0.0),
                "trigger": _box((self.n_trig,)),
                "trigger_held": _box((self.n_trig,)),
            }
        )
        self._agent_action_space = spaces.Dict({"broadcast": spaces.Discrete(2), "control": env.control_space})
        self.joint_observation_space = spaces.Dict(
            {
                "local": _box((n, self.n_local)),
                "message": _box((n, self.n_msg)),
                "held": _box((n, self.n_msg)),
                "age": _box((n, 1), low=0.0),
                "trigger": _box((n, self.n_trig)),
                "trigger_held": _box((n, self.n_trig)),
            }
        )
        control = env.control_space
        self.joint_action_space = spaces.Dict(
            {
                "broadcast": spaces.MultiDiscrete([2] * n),
                "control": spaces.Box(
                    low=np.broadcast_to(control.low, (n, *control.shape)).astype(control.dtype),
                    high=np.broadcast_to(control.high, (n, *control.shape)).astype(control.dtype),
                    dtype=control.dtype,
                ),
            }
        )
        self.held = np.zeros((n, self.n_msg))
        self.age = np.zeros((n, 1))
        self.trigger_held = np.zeros((n, self.n_trig))
        self.broadcasts = np.zeros(n, dtype=np.int64)
        self.last_broadcast = np.zeros(n, dtype=np.int64)

    def observation_space(self, agent: str) -> spaces.Dict:
        """Networked observation space of one agent.

        :param agent: name of the agent (all agents share one space)
        :return: ``Dict(local, neighbours, neighbour_age, trigger, trigger_held)``
        """
        return self._agent_observation_space

    def action_space(self, agent: str) -> spaces.Dict:
        """Hybrid action space of one agent: option and control.

        :param agent: name of the agent (all agents share one space)
        :return: ``Dict(broadcast=Discrete(2), control=Box)``
        """
        return self._agent_action_space

    # ----------------------------------------------------------------- array core
    def _trigger_of(self, obs: SystemObs) -> np.ndarray:
        """Features of the policy over options in a system observation, as chosen by ``trigger``.

        :param obs: the system's observation
        :return: ``obs.trigger`` (``"default"``), ``obs.local`` or ``obs.message``, shape (N, n_trig)
        """
        return obs.trigger if self.trigger == "default" else getattr(obs, self.trigger)

    def _joint_obs(self, obs: SystemObs) -> dict[str, np.ndarray]:
        """Joint observation: the system's observation and the network's held broadcasts, ages and held features.

        :param obs: the system's observation
        :return: float32 arrays (agent axis first) by the keys of ``joint_observation_space``
        """
        return {
            "local": obs.local.astype(np.float32),
            "message": obs.message.astype(np.float32),
            "held": self.held.astype(np.float32),
            "age": self.age.astype(np.float32),
            "trigger": self._trigger_of(obs).astype(np.float32),
            "trigger_held": self.trigger_held.astype(np.float32),
        }

    def reset_joint(self, seed: int | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Start an episode; every agent's initial message counts as received.

        :param seed: seed of the system's random generator
        :return: joint observation (agent axis first) and info
        """
        obs, info = self.system.reset_arrays(seed)
        self.agents = list(self.possible_agents)
        self.held, self.age = initial_network(obs.message)
        self.trigger_held, _ = initial_network(self._trigger_of(obs))  # the trigger features count as sent
        self.broadcasts = np.zeros(self.n_agents, dtype=np.int64)
        self.last_broadcast = np.zeros(self.n_agents, dtype=np.int64)
        return self._joint_obs(obs), info

    def step_joint(
        self, broadcast: np.ndarray, control: np.ndarray
    ) -> tuple[dict[str, np.ndarray], np.ndarray, bool, bool, dict[str, Any]]:
        """One step of the network and the system (same-step delivery).

        :param broadcast: broadcast decisions of all agents, shape (N,), values in {0, 1}
        :param control: controls of all agents, shape (N, m)
        :return: joint observation, per-agent rewards with the communication cost (N,),
            terminated, truncated, info (adds ``broadcast``, ``broadcasts`` of the episode so
            far and ``control_rewards`` without the communication cost)
        :raises RuntimeError: if no episode is running
        :raises ValueError: on a wrong shape or options outside {0, 1}
        """
        if not self.agents:
            raise RuntimeError("step called without a running episode: the last episode ended; call reset() first.")
        broadcast = np.asarray(broadcast)
        if broadcast.shape != (self.n_agents,):
            raise ValueError(
                f"broadcast must have shape ({self.n_agents},) (one decision per agent), got {broadcast.shape}."
            )
        if not np.all((broadcast == 0) | (broadcast == 1)):
            raise ValueError(f"broadcast decisions must be 0 (silent) or 1 (broadcast), got {broadcast.tolist()}.")
        broadcast = broadcast.astype(np.int64)
        before = self.system.last_obs
        held = hold(self.held, before.message, broadcast)
        trigger_held = hold(self.trigger_held, self._trigger_of(before), broadcast)
        # The system checks the controls; the network changes only once the step succeeded.
        obs, control_rewards, terminated, truncated, info = self.system.step_arrays(control)
        self.held, self.trigger_held = held, trigger_held
        self.age = advance_timer(self.age, broadcast)
        self.broadcasts += broadcast
        self.last_broadcast = broadcast
        rewards = control_rewards - self.broadcast_cost * broadcast
        if terminated or truncated:
            self.agents = []
        info = {
            **info,
            "broadcast": broadcast,
            "broadcasts": self.broadcasts.copy(),
            "control_rewards": control_rewards,
        }
        return self._joint_obs(obs), rewards, terminated, truncated, info

    # ------------------------------------------------------------ PettingZoo API
    def agent_views(self, joint_obs: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
        """Split a joint observation into what every agent receives.

        :param joint_obs: joint observation from :meth:`reset_joint` or :meth:`step_joint`
        :return: per-agent observations of :meth:`observation_space`
        """
        neighbours = relative_views(joint_obs["held"], joint_obs["message"], self.others)
        ages = others_ages(joint_obs["age"], self.others)
        return {
            agent: {
                "local": joint_obs["local"][i],
                "neighbours": neighbours[i],
                "neighbour_age": ages[i],
                "trigger": joint_obs["trigger"][i],
                "trigger_held": joint_obs["trigger_held"][i],
            }
            for i, agent in enumerate(self.possible_agents)
        }

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """PettingZoo reset: per-agent networked observations.

        :param seed: seed of the system's random generator, or None to continue it
        :param options: unused (PettingZoo API)
        :return: agent name -> observation of :meth:`observation_space`, and agent name -> a copy of the
            reset's info dict
        """
        obs, info = self.reset_joint(seed)
        return self.agent_views(obs), {a: dict(info) for a in self.possible_agents}

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        """PettingZoo step: an option and a control for every live agent.

        :param actions: agent name -> ``{"broadcast": 0 or 1, "control": control of shape (m,)}``, for
            every agent (all agents live together)
        :return: five dicts keyed by agent name: networked observations, rewards with the communication
            cost, terminated, truncated and infos (the system's info with the agent's ``broadcast``, its
            ``broadcasts`` of the episode so far and its ``control_reward``)
        :raises RuntimeError: if no episode is running
        :raises ValueError: on a missing or malformed action (see :meth:`step_joint`)
        """
        if not self.agents:
            raise RuntimeError("step called without a running episode: the last episode ended; call reset() first.")
        missing = set(self.agents) - set(actions)
        if missing:
            raise ValueError(f"actions are missing for agents {sorted(missing)}.")
        try:
            broadcast = np.array([actions[a]["broadcast"] for a in self.possible_agents])
            control = np.stack([np.asarray(actions[a]["control"], dtype=np.float64) for a in self.possible_agents])
        except (KeyError, TypeError, IndexError) as err:
            raise ValueError(
                f"each agent's action must be a dict with keys 'broadcast' and 'control' ({err!r})."
            ) from err
        obs, rewards, terminated, truncated, info = self.step_joint(broadcast, control)
        names = self.possible_agents
        shared = {
            key: value for key, value in info.items() if key not in ("broadcast", "broadcasts", "control_rewards")
        }
        agent_infos = {
            a: {
                **shared,
                "broadcast": int(info["broadcast"][i]),
                "broadcasts": int(info["broadcasts"][i]),
                "control_reward": float(info["control_rewards"][i]),
            }
            for i, a in enumerate(names)
        }
        return (
            self.agent_views(obs),
            {a: float(r) for a, r in zip(names, rewards, strict=True)},
            dict.fromkeys(names, terminated),
            dict.fromkeys(names, truncated),
            agent_infos,
        )

    def render(self) -> np.ndarray | None:
        """Render the system; a system whose ``render`` takes ``broadcast`` (Multiwalker) marks the last step's options.

        :return: the system's frame (None without render mode)
        """
        if "broadcast" in inspect.signature(self.system.render).parameters:
            return self.system.render(broadcast=self.last_broadcast)
        return self.system.render()

    def state(self) -> np.ndarray:
        """Global state of the system (for centralised critics).

        :return: the system's :meth:`~sb3_detc.envs.system.CommunicatingSystem.state`: every agent's local
            state and message, flattened, float32
        """
        return self.system.state()


class JointEnv(gym.Env):
    """Joint single-agent Gymnasium view of an :class:`EventTriggeredNetwork` (all agents in one env).

    Observation ``Dict``: ``local`` (N, n_local), ``message`` (N, n_msg, the true current
    messages, for the centralised critic), ``held`` (N, n_msg, each agent's last broadcast
    as held before this step's decisions), ``age`` (N, 1, the timers ``tau_i[k-1]`` before
    this step's decisions), ``trigger`` and ``trigger_held`` (N, n_trig). Action ``Dict``:
    ``broadcast`` ``MultiDiscrete([2] * N)``, ``control`` ``Box(N, m)``. The reward is the mean
    of the agents' rewards; ``info["agent_rewards"]`` has them all (N,), ``info["broadcast"]``
    this step's options (N,).

    :param network: the event-triggered network to drive
    """

    def __init__(self, network: EventTriggeredNetwork) -> None:
        if not isinstance(network, EventTriggeredNetwork):
            raise TypeError(f"JointEnv needs an EventTriggeredNetwork, got {type(network).__name__}.")
        self.network = network
        self.observation_space = network.joint_observation_space
        self.action_space = network.joint_action_space
        self.metadata = dict(network.metadata)
        self.render_mode = network.render_mode
        self.n_agents = network.n_agents

    @property
    def broadcast_cost(self) -> float:
        """Communication cost ``xi >= 0`` charged per broadcast, read from and written to the network.

        Settable through wrappers and vectorised envs, e.g.
        ``vec_env.env_method("set_wrapper_attr", "broadcast_cost", 0.0)``; the new cost applies
        from the next step on.

        :raises ValueError: on setting a negative or non-finite cost
        """
        return self.network.broadcast_cost

    @broadcast_cost.setter
    def broadcast_cost(self, value: float) -> None:
        """Set the network's communication cost.

        :param value: the new cost per broadcast (>= 0)
        :raises ValueError: if ``value`` is negative or not finite
        """
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"broadcast_cost must be a finite number >= 0, got {value!r}.")
        self.network.broadcast_cost = float(value)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Start an episode (Gymnasium seeding).

        :param seed: seed of the system's random generator (and of ``np_random``), or None to continue it
        :param options: unused (Gymnasium API)
        :return: joint observation (agent axis first) and info
        """
        super().reset(seed=seed)
        return self.network.reset_joint(seed)

    def step(self, action: dict[str, np.ndarray]) -> tuple[dict, float, bool, bool, dict]:
        """Advance all agents by one step.

        :param action: ``{"broadcast": (N,) in {0, 1}, "control": (N, m)}``
        :return: joint observation, the mean of the agents' rewards (with the communication cost),
            terminated, truncated, info (that of :meth:`EventTriggeredNetwork.step_joint` with ``agent_rewards`` (N,))
        """
        if not isinstance(action, dict) or set(action) != {"broadcast", "control"}:
            got = sorted(action) if isinstance(action, dict) else type(action).__name__
            raise ValueError(f"action must be a dict with keys 'broadcast' and 'control', got {got}.")
        obs, rewards, terminated, truncated, info = self.network.step_joint(action["broadcast"], action["control"])
        info["agent_rewards"] = rewards
        return obs, float(rewards.mean()), terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """Render the physical system, the last step's broadcasts marked (:meth:`EventTriggeredNetwork.render`).

        :return: the system's frame (None without render mode)
        """
        return self.network.render()

    def close(self) -> None:
        """Close the physical system."""
        self.network.system.close()


def as_joint_env(env: Any) -> Any:
    """Adapt a PettingZoo event-triggered env to the joint Gymnasium view.

    :param env: an env id, a Gymnasium or vector env, a PettingZoo :class:`EventTriggeredNetwork`, or None
    :return: a :class:`JointEnv` of an :class:`EventTriggeredNetwork`, anything else as given
    """
    return JointEnv(env) if isinstance(env, EventTriggeredNetwork) else env
