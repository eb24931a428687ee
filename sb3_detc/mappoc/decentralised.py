"""Decentralised execution: every agent runs its own controller on what it has received.

Training is centralised, execution is not: after training, agent ``i`` needs only its
:class:`~sb3_detc.mappoc.policies.AgentController` (``mu_i`` and ``pi_i``), its own
sensors and an :class:`Inbox`, its table of the last message received from every agent
with its age. One step of the team (same-step delivery, Sec. 2 of the method reference)
is :func:`run_decentralised_step`:

(a) every agent decides from its own trigger features (and the ages in its inbox, where its
    policy over options reads them) whether to broadcast;
(b) the broadcasts go out on the radio and every agent files them in its inbox
    (the rule of :mod:`sb3_detc.network`: zero-order hold and age of information);
(c) every agent builds its view, the others' held messages relative to its own current
    message with their ages, and computes its control;
(d) the caller applies the actions to the plant.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from sb3_detc.mappoc.policies import AgentController, options_sampled
from sb3_detc.network import advance_timer, hold, initial_network, others_ages, others_index, relative_views

#: This step's broadcasts as they go over the radio: ``{sender index: message (n_msg,)}``.
Radio = dict[int, np.ndarray]


class Inbox:
    """One agent's table of received messages and their ages (agent axis first).

    The table is advanced with :func:`~sb3_detc.network.hold` and
    :func:`~sb3_detc.network.advance_timer`, the same rule the event-triggered network
    applies. Like :meth:`EventTriggeredNetwork.reset_joint
    <sb3_detc.envs.wrappers.EventTriggeredNetwork.reset_joint>`, :meth:`reset` treats
    every agent's initial message as received with age 0.

    :param agent: index of the agent that owns this inbox
    :param n_agents: number of agents N
    """

    def __init__(self, agent: int, n_agents: int) -> None:
        if not 0 <= agent < n_agents:
            raise ValueError(f"agent must be in [0, {n_agents}), got {agent}.")
        self.agent = agent
        self.n_agents = n_agents
        self._others = others_index(n_agents)[agent : agent + 1]  # (1, N - 1)
        self.held: np.ndarray | None = None  # (N, n_msg) last message received from every agent
        self.age = np.zeros((n_agents, 1))  # (N, 1) steps since that message was sent

    def reset(self, messages: np.ndarray) -> None:
        """Start an episode: every agent's initial message counts as received (age 0).

        :param messages: initial messages of all agents, shape (N, n_msg)
        """
        messages = np.asarray(messages)
        if messages.ndim != 2 or messages.shape[0] != self.n_agents:
            raise ValueError(f"messages must have shape ({self.n_agents}, n_msg), got {messages.shape}.")
        self.held, self.age = initial_network(messages)

    def receive(self, radio: Radio) -> None:
        """File this step's broadcasts: senders' messages replace the held ones, their age becomes 0.

        :param radio: ``{sender index: message (n_msg,)}``; agents not in it stayed silent
        """
        if self.held is None:
            raise RuntimeError("the inbox has no messages yet: call reset() at the start of an episode.")
        broadcast = np.zeros(self.n_agents)  # (N,) 1 = broadcast this step
        current = np.zeros_like(self.held)  # (N, n_msg) silent agents' rows are never read by hold
        for sender, message in radio.items():
            if not 0 <= sender < self.n_agents:
                raise ValueError(f"sender must be in [0, {self.n_agents}), got {sender}.")
            broadcast[sender] = 1
            current[sender] = message
        self.held = hold(self.held, current, broadcast)
        self.age = advance_timer(self.age, broadcast)

    @property
    def own_age(self) -> float:
        """Steps since this agent's own last broadcast (what the others see as the age of its message)."""
        return float(self.age[self.agent, 0])

    @property
    def others_age(self) -> np.ndarray:
        """Steps since every other agent's last broadcast, others in increasing order (N - 1,)."""
        return others_ages(self.age, self._others)[0]

    def view(self, own_message: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The others' held messages relative to the own current message, and their ages.

        :param own_message: the agent's current message from its own sensors (n_msg,)
        :return: neighbours (N - 1, n_msg) and their ages in steps (N - 1,), others in increasing order
        """
        if self.held is None:
            raise RuntimeError("the inbox has no messages yet: call reset() at the start of an episode.")
        own = np.asarray(own_message)[None]  # (1, n_msg)
        neighbours = relative_views(self.held, own, self._others)[0]  # (N - 1, n_msg)
        return neighbours, self.others_age


def run_decentralised_step(
    controllers: Sequence[AgentController],
    inboxes: Sequence[Inbox],
    parallel_obs: Mapping[str, Mapping[str, np.ndarray]],
    messages: np.ndarray,
    deterministic: bool = True,
    sample_options: bool | None = None,
) -> dict[str, dict[str, Any]]:
    """One team step of decentralised execution: decide, exchange broadcasts, act.

    Agent ``i`` is ``controllers[i]``, ``inboxes[i]``, the ``i``-th key of ``parallel_obs``
    (PettingZoo order, ``possible_agents``) and ``messages[i]``. Each agent reads only its
    own entries; the only thing shared is the radio, which carries this step's broadcasts.
    The inboxes are updated in place.

    :param controllers: one controller per agent, from ``policy.agent_controller(i)``
    :param inboxes: one inbox per agent, reset at the start of the episode
    :param parallel_obs: per-agent PettingZoo observations (only ``local``, ``trigger`` and
        ``trigger_held`` are read: the neighbour information comes from the inboxes)
    :param messages: every agent's current message from its own sensors, shape (N, n_msg)
    :param deterministic: mean controls instead of samples, and the most likely options unless
        ``sample_options`` says otherwise
    :param sample_options: options sampled (True) or the most likely ones (False) whatever
        ``deterministic`` says (None: as every controller's ``sample_options`` says when
        ``deterministic``, else sampled)
    :return: ``{agent: {"broadcast": 0 or 1, "control": (m,)}}``, what the PettingZoo env's ``step`` takes
    """
    agents = list(parallel_obs)
    if not len(controllers) == len(inboxes) == len(agents) == len(messages):
        raise ValueError(
            f"need one controller, inbox, observation and message per agent, got {len(controllers)}, "
            f"{len(inboxes)}, {len(agents)} and {len(messages)}."
        )
    for i, (controller, inbox) in enumerate(zip(controllers, inboxes, strict=True)):
        if controller.agent != i or inbox.agent != i:
            raise ValueError(
                f"entry {i} must belong to agent {i}, got controller {controller.agent}, inbox {inbox.agent}."
            )
    # (a) every agent decides from its own trigger features and the ages in its inbox
    sent = [
        int(c.decide(obs["trigger"], obs["trigger_held"], not samples, inbox.own_age, inbox.others_age))
        for c, inbox, obs in zip(controllers, inboxes, (parallel_obs[a] for a in agents), strict=True)
        for samples in [options_sampled(c.sample_options, deterministic) if sample_options is None else sample_options]
    ]
    # (b) the broadcasts go out; every agent files them in its own table
    radio: Radio = {i: np.asarray(messages[i]) for i in range(len(agents)) if sent[i]}
    for inbox in inboxes:
        inbox.receive(radio)
    # (c) every agent views the others relative to its own current message, then acts
    actions = {}
    for i, (controller, inbox, agent) in enumerate(zip(controllers, inboxes, agents, strict=True)):
        neighbours, ages = inbox.view(messages[i])
        control = controller.act(parallel_obs[agent]["local"], neighbours, ages, deterministic=deterministic)
        actions[agent] = {"broadcast": sent[i], "control": control}
    return actions
