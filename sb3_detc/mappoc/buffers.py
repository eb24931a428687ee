"""Rollout buffer for hybrid (option, control) actions of several agents, with per-agent GAE."""

from __future__ import annotations

from collections.abc import Generator
from typing import NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.utils import get_device


class HybridRolloutSamples(NamedTuple):
    """A minibatch of hybrid transitions; B samples, N agents.

    :param observations: joint observations before the options, (B, N, ...) per key
    :param broadcast: options taken (B, N)
    :param control: controls taken (B, N, m), unclipped, with exploration noise
    :param old_log_prob_broadcast: ``log mu_i(o_i)`` (B, N) under the policy that sampled the options
    :param old_log_prob_control: ``log pi_i(u_i)`` (B, N) under the policy that sampled the controls
    :param advantages: GAE advantages (B, N)
    :param returns: lambda-returns (B, N), targets of ``Q_i(s, o_taken)``
    :param broadcast_advantages: lambda-return minus ``V_i(s) = sum_o mu_i(o) Q_i(s, o)`` at collection (B, N),
        or what :meth:`HybridRolloutBuffer.set_broadcast_advantages` put in its place (replayed advantages,
        or targets of the broadcast logit, NaN where there is none)
    :param broadcast_price: the learner's reward lost by the own broadcast (B, N) (afterstate critic)
    """

    observations: dict[str, th.Tensor]
    broadcast: th.Tensor
    control: th.Tensor
    old_log_prob_broadcast: th.Tensor
    old_log_prob_control: th.Tensor
    advantages: th.Tensor
    returns: th.Tensor
    broadcast_advantages: th.Tensor
    broadcast_price: th.Tensor

    def select(self, idx: th.Tensor) -> HybridRolloutSamples:
        """The samples ``idx`` of the batch axis.

        :param idx: indices of the samples to keep (1-D), e.g. a minibatch of
            :meth:`HybridRolloutBuffer.minibatch_indices`
        :return: those samples, every field indexed by ``idx`` on its first axis (observations per key)
        """
        observations = {key: value[idx] for key, value in self.observations.items()}
        return HybridRolloutSamples(observations, *(field[idx] for field in self[1:]))


class HybridRolloutBuffer:
    """On-policy storage of joint observations, options, controls and per-agent rewards.

    Advantages follow the option-critic form of the method (Sec. 3): GAE with the value
    of the *taken* option, ``delta_t = r_t + gamma Q(s_{t+1}, o_{t+1}) - Q(s_t, o_t)``,
    per agent, cut at episode ends; truncated episodes are bootstrapped by the caller
    (added to the reward, as SB3 does). The lambda-returns ``A + Q(s, o)`` are the
    critic's regression targets. ``broadcast_advantages`` are the lambda-returns minus the
    state value ``V(s) = sum_o mu(o | s) Q(s, o)`` at collection time (a sampled advantage
    of the taken option, for :class:`~sb3_detc.mappoc.mappoc.MAPPOC` with
    ``broadcast_advantage="return"``; the replayed kinds put theirs in place with
    :meth:`set_broadcast_advantages`). The log-probabilities are those of the policy that sampled
    the rollout.

    :param buffer_size: steps per environment and rollout
    :param observation_space: joint observation space (Dict of (N, ...) boxes)
    :param action_space: joint action space (Dict with ``broadcast`` and ``control``)
    :param device: PyTorch device of the sampled minibatches
    :param gamma: discount factor
    :param gae_lambda: GAE factor
    :param n_envs: number of parallel environments
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Dict,
        device: th.device | str = "auto",
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        n_envs: int = 1,
    ) -> None:
        self.buffer_size = buffer_size
        self.observation_space = observation_space
        self.action_space = action_space
        self.device = get_device(device)
        self.gamma = gamma
        self.gae_lambda = gae_lambda
        self.n_envs = n_envs
        self.n_agents = len(action_space["broadcast"].nvec)
        self.control_shape = action_space["control"].shape
        self.reset()

    def reset(self) -> None:
        """Empty the buffer (storage is reused)."""
        shape = (self.buffer_size, self.n_envs)
        n = self.n_agents
        self.observations = {
            key: np.zeros(shape + space.shape, dtype=np.float32) for key, space in self.observation_space.spaces.items()
        }
        self.broadcast = np.zeros((*shape, n), dtype=np.int64)
        self.control = np.zeros(shape + self.control_shape, dtype=np.float32)
        self.rewards = np.zeros((*shape, n), dtype=np.float32)
        self.episode_starts = np.zeros(shape, dtype=np.float32)
        self.option_values = np.zeros((*shape, n, 2), dtype=np.float32)
        self.values = np.zeros((*shape, n), dtype=np.float32)
        self.state_values = np.zeros((*shape, n), dtype=np.float32)
        self.log_prob_broadcast = np.zeros((*shape, n), dtype=np.float32)
        self.log_prob_control = np.zeros((*shape, n), dtype=np.float32)
        self.advantages = np.zeros((*shape, n), dtype=np.float32)
        self.returns = np.zeros((*shape, n), dtype=np.float32)
        self.broadcast_advantages = np.zeros((*shape, n), dtype=np.float32)
        self.broadcast_price = np.zeros((*shape, n), dtype=np.float32)
        self.pos = 0
        self.full = False

    def add(
        self,
        obs: dict[str, np.ndarray],
        broadcast: np.ndarray,
        control: np.ndarray,
        rewards: np.ndarray,
        episode_start: np.ndarray,
        option_values: np.ndarray,
        log_prob_broadcast: np.ndarray,
        log_prob_control: np.ndarray,
        broadcast_price: np.ndarray | None = None,
    ) -> None:
        """Store one step of all environments.

        :param obs: joint observations before the options, (n_envs, N, ...) per key
        :param broadcast: broadcast decisions (n_envs, N)
        :param control: controls (n_envs, N, m)
        :param rewards: per-agent rewards (n_envs, N), already scaled and bootstrapped at timeouts
        :param episode_start: whether ``obs`` starts an episode (n_envs,)
        :param option_values: ``Q_i(s, o)`` of both options (n_envs, N, 2)
        :param log_prob_broadcast: ``log mu_i(o_i)`` (n_envs, N)
        :param log_prob_control: ``log pi_i(u_i)`` (n_envs, N)
        :param broadcast_price: what the own broadcast costs in the learner's reward units (n_envs, N),
            for critics that add it to their option values (None: zero)
        """
        self.extend(
            {key: value[None] for key, value in obs.items()},
            *(np.asarray(x)[None] for x in (broadcast, control, rewards, episode_start, option_values)),
            np.asarray(log_prob_broadcast)[None],
            np.asarray(log_prob_control)[None],
            None if broadcast_price is None else np.asarray(broadcast_price)[None],
        )

    def extend(
        self,
        obs: dict[str, np.ndarray],
        broadcast: np.ndarray,
        control: np.ndarray,
        rewards: np.ndarray,
        episode_start: np.ndarray,
        option_values: np.ndarray,
        log_prob_broadcast: np.ndarray,
        log_prob_control: np.ndarray,
        broadcast_price: np.ndarray | None = None,
    ) -> None:
        """Store several consecutive steps of all environments: :meth:`add` with a leading step axis (T, ...).

        :param obs: joint observations before the options, (T, n_envs, N, ...) per key
        :param broadcast: broadcast decisions (T, n_envs, N)
        :param control: controls (T, n_envs, N, m)
        :param rewards: per-agent rewards (T, n_envs, N)
        :param episode_start: whether ``obs`` starts an episode (T, n_envs)
        :param option_values: ``Q_i(s, o)`` of both options (T, n_envs, N, 2)
        :param log_prob_broadcast: ``log mu_i(o_i)`` (T, n_envs, N)
        :param log_prob_control: ``log pi_i(u_i)`` (T, n_envs, N)
        :param broadcast_price: what the own broadcast costs (T, n_envs, N) (None: zero)
        """
        steps = len(broadcast)
        if self.pos + steps > self.buffer_size:
            raise RuntimeError("HybridRolloutBuffer is full; call reset() before adding.")
        at = slice(self.pos, self.pos + steps)
        for key, value in obs.items():
            self.observations[key][at] = value
        self.broadcast[at] = broadcast
        self.control[at] = control
        self.rewards[at] = rewards
        self.episode_starts[at] = episode_start
        taken = np.take_along_axis(option_values, broadcast[..., None], axis=-1)[..., 0]
        p_taken = np.exp(log_prob_broadcast)
        other = option_values.sum(-1) - taken  # two options: the one not taken
        self.option_values[at] = option_values
        self.values[at] = taken
        self.state_values[at] = p_taken * taken + (1 - p_taken) * other
        self.log_prob_broadcast[at] = log_prob_broadcast
        self.log_prob_control[at] = log_prob_control
        self.broadcast_price[at] = 0.0 if broadcast_price is None else broadcast_price
        self.pos += steps
        self.full = self.pos == self.buffer_size

    def compute_returns_and_advantage(self, last_values: np.ndarray, dones: np.ndarray) -> None:
        """Per-agent GAE(lambda) over the stored rollout (Sec. 3).

        :param last_values: value of the observation after the last step, (n_envs, N)
        :param dones: whether the last step ended an episode, (n_envs,)
        """
        # Every step's TD error and decay at once; only the recursion goes step by step.
        next_non_terminal = 1.0 - np.concatenate([self.episode_starts[1:], np.asarray(dones, np.float32)[None]])
        next_values = np.concatenate([self.values[1:], np.asarray(last_values, np.float32)[None]])
        alive = next_non_terminal[..., None]
        delta = self.rewards + self.gamma * next_values * alive - self.values
        decay = self.gamma * self.gae_lambda * alive
        last_gae = np.zeros((self.n_envs, self.n_agents), dtype=np.float32)
        for t in reversed(range(self.buffer_size)):
            last_gae = delta[t] + decay[t] * last_gae
            self.advantages[t] = last_gae
        self.returns = self.advantages + self.values
        self.broadcast_advantages = self.returns - self.state_values

    def set_broadcast_advantages(
        self, steps: np.ndarray, envs: np.ndarray, agents: np.ndarray, advantages: np.ndarray, elsewhere: float = 0.0
    ) -> None:
        """Put broadcast advantages of some decisions in place of the stored ones, ``elsewhere`` everywhere else.

        For the replayed kinds of ``broadcast_advantage``: ``mu`` learns from the replayed decisions only
        (``"replayed_value"`` stores the targets of its broadcast logit, NaN elsewhere).

        :param steps: the decisions' steps (K,)
        :param envs: their envs (K,)
        :param agents: their agents (K,)
        :param advantages: their advantages (K,)
        :param elsewhere: the value of every other decision
        """
        shape = (self.buffer_size, self.n_envs, self.n_agents)
        self.broadcast_advantages = np.full(shape, elsewhere, dtype=np.float32)
        self.broadcast_advantages[steps, envs, agents] = advantages

    def tensors(self, partial: bool = False) -> HybridRolloutSamples:
        """The whole rollout as tensors, environments and steps flattened into one batch axis.

        :param partial: also before the rollout is complete (steps not stored yet hold zeros or
            an earlier rollout's values: inputs of the right shapes, e.g. to compile the update)
        :return: all ``buffer_size * n_envs`` samples, step by step (the envs of a step together), on the
            buffer's device
        :raises RuntimeError: if the rollout is incomplete and ``partial`` is False
        """
        if not (self.full or partial):
            raise RuntimeError("HybridRolloutBuffer needs a full rollout; keep adding steps.")
        total = self.buffer_size * self.n_envs

        def flat(array: np.ndarray) -> th.Tensor:
            return th.as_tensor(array.reshape(total, *array.shape[2:]), device=self.device)

        return HybridRolloutSamples(
            {key: flat(value) for key, value in self.observations.items()},
            *(
                flat(a)
                for a in (
                    self.broadcast,
                    self.control,
                    self.log_prob_broadcast,
                    self.log_prob_control,
                    self.advantages,
                    self.returns,
                    self.broadcast_advantages,
                    self.broadcast_price,
                )
            ),
        )

    def minibatch_indices(self, batch_size: int) -> Generator[th.Tensor, None, None]:
        """Shuffled index minibatches over all stored samples (the last one may be smaller).

        Select a minibatch of :meth:`tensors` with ``HybridRolloutSamples.select``.

        :param batch_size: samples per minibatch
        :return: a generator of 1-D index tensors, together one random permutation of all
            ``buffer_size * n_envs`` samples
        """
        total = self.buffer_size * self.n_envs
        order = th.randperm(total, device=self.device)
        for start in range(0, total, batch_size):
            yield order[start : start + batch_size]
