"""The event-triggered network: one rule for held broadcasts, timers and relative views.

These are pure functions (arrays in, arrays out). They work unchanged on NumPy arrays and
on PyTorch tensors, so the environment uses them to advance the network and the policy
uses them to rebuild every agent's networked observation from a stored observation and a
vector of broadcast decisions. The agent axis is the second-to-last axis of ``held``/``current``
and the last axis of ``broadcast``; leading axes (environments, time) follow NumPy's broadcasting rules.

Notation follows the method reference (Kesper, Trimpe and Baumann, L4DC 2023, Sec. 2):
``o_i[k]`` option (1 = broadcast), ``m_i[k]`` message, ``x~_i[k]`` held broadcast,
``tau_i[k]`` age of information.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

ArrayT = TypeVar("ArrayT")


def initial_network(messages: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The network at an episode's start: every agent's initial message counts as received.

    ``x~_i[0] = m_i[0]``, ``tau_i[0] = 0``.

    :param messages: initial messages of all agents (NumPy), shape (N, d)
    :return: held broadcasts (a copy), shape (N, d), and timers (zeros), shape (N, 1)
    """
    return messages.copy(), np.zeros((messages.shape[0], 1))


def hold(held: ArrayT, current: ArrayT, broadcast: ArrayT) -> ArrayT:
    """Zero-order hold of broadcasts.

    ``x~_i[k] = m_i[k] if o_i[k] = 1 else x~_i[k-1]`` (held broadcast state, Sec. 2).

    The blend ``held * (1 - o) + current * o`` is exact for ``o`` in {0, 1} and finite
    values, and needs no backend-specific ``where``.

    :param held: held broadcasts before this step, shape (..., N, d)
    :param current: what every agent would broadcast now, shape (..., N, d)
    :param broadcast: broadcast decisions of this step in {0, 1}, shape (..., N)
    :return: held broadcasts after this step's broadcasts, shape (..., N, d)
    """
    o = broadcast[..., None]
    return held * (1 - o) + current * o


def advance_timer(age: ArrayT, broadcast: ArrayT) -> ArrayT:
    """Age of information.

    ``tau_i[k] = 0 if o_i[k] = 1 else tau_i[k-1] + 1`` (timer, Sec. 2).

    :param age: timers before this step, shape (..., N, 1)
    :param broadcast: broadcast decisions of this step in {0, 1}, shape (..., N)
    :return: timers after this step's broadcasts, shape (..., N, 1)
    """
    return (age + 1) * (1 - broadcast[..., None])


def interval_window(age: ArrayT, min_interval: int, max_interval: int) -> tuple[ArrayT, ArrayT]:
    """Which options a window of broadcast intervals leaves to an agent's trigger.

    A broadcast now ends an interval of ``tau_i[k-1] + 1`` steps since the agent's last one
    (:func:`advance_timer`). Within the window ``[min_interval, max_interval]`` the agent must
    stay silent while that interval would be shorter than ``min_interval`` and must broadcast
    once it reaches ``max_interval``; in between the trigger chooses. ``min_interval =
    max_interval = P`` leaves no choice: the periodic schedule of period ``P``, all agents in phase.

    :param age: timers before this step's decisions, shape (..., N, 1)
    :param min_interval: the shortest interval between two broadcasts of an agent (>= 1)
    :param max_interval: the longest interval (>= ``min_interval``)
    :return: where an agent must stay silent and where it must broadcast, two boolean arrays of shape (..., N)
    """
    interval = age[..., 0] + 1
    return interval < min_interval - 0.5, interval > max_interval - 0.5


def others_index(n_agents: int) -> np.ndarray:
    """Index of the other agents, row ``i`` lists ``j != i`` in increasing order.

    :param n_agents: number of agents N (at least 2)
    :return: integer array of shape (N, N - 1)
    """
    idx = np.arange(n_agents)
    return np.stack([np.delete(idx, i) for i in range(n_agents)])


def others_ages(age: ArrayT, others: ArrayT) -> ArrayT:
    """Every agent's view of the others' timers.

    :param age: timers of all agents, shape (..., N, 1)
    :param others: index from :func:`others_index`, shape (N, N - 1)
    :return: shape (..., N, N - 1); entry ``[i, k]`` is the age of agent ``others[i, k]``'s held broadcast
    """
    return age[..., others, 0]


def relative_to_receivers(seen: ArrayT, own: ArrayT) -> ArrayT:
    """Held broadcasts as their receivers see them: relative to the receiver's own message.

    Receivers compute ``x~_j - m_i`` themselves, with their own *current* message
    (networked observation ``x^_i``, Sec. 2), so a stale broadcast stays stale in
    absolute terms while the receiver's own motion is always up to date.

    :param seen: row ``i`` holds the broadcasts that agent ``i`` sees, shape (..., N, M, d)
    :param own: current messages of all agents, shape (..., N, d)
    :return: shape (..., N, M, d)
    """
    return seen - own[..., :, None, :]


def relative_views(held: ArrayT, own: ArrayT, others: ArrayT) -> ArrayT:
    """What every agent sees of the others: their held broadcasts relative to its own message.

    :func:`relative_to_receivers` of the others' held broadcasts.

    :param held: held broadcasts of all agents, shape (..., N, d)
    :param own: current messages of all agents, shape (..., N, d)
    :param others: index from :func:`others_index`, shape (N, N - 1)
    :return: shape (..., N, N - 1, d); entry ``[i, k]`` is agent ``others[i, k]`` seen by ``i``
    """
    return relative_to_receivers(held[..., others, :], own)
