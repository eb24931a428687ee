"""What MAPPOC learns from: every agent's reward, and the price of its own broadcast, in the same units.

The environments report every agent's reward in ``info["agent_rewards"]``. The learner
scales them (the paper: by 0.1), may share them as the team's mean, and may divide them by
a running standard deviation of each agent's discounted return (as SB3's ``VecNormalize``
does for one agent). Critics that add the communication cost analytically need what a
broadcast costs in exactly those units: :meth:`RewardTransform.price`.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from stable_baselines3.common.running_mean_std import RunningMeanStd


def agent_rewards(infos: list[dict[str, Any]]) -> np.ndarray:
    """The per-agent rewards in a list of infos (e.g. every env's of one step), (len(infos), N), checked to be finite.

    :param infos: infos, each with ``agent_rewards`` (N,)
    :return: the rewards as float32, one row per info (len(infos), N)
    :raises ValueError: if an info lacks ``agent_rewards`` or a reward is not finite
    """
    try:
        rewards = np.stack([info["agent_rewards"] for info in infos]).astype(np.float32)
    except KeyError as err:
        raise ValueError(
            "MAPPOC needs per-agent rewards in info['agent_rewards']: use a joint sb3_detc env (JointEnv)."
        ) from err
    finite = np.isfinite(rewards).all(axis=-1)
    if not finite.all():
        first = int(np.argmin(finite))
        raise ValueError(f"the environment returned non-finite rewards: {rewards[first].tolist()} (info {first}).")
    return rewards


class RewardTransform:
    """Per-agent rewards as the learner sees them: scaled, optionally shared, optionally normalised.

    Stateful when normalising (the running statistics and every env's discounted return);
    the statistics are saved with the model, the discounted returns start again at zero.

    :param n_agents: number of agents N
    :param gamma: discount factor of the returns whose spread normalises the rewards
    :param scale: factor applied to every reward
    :param team: every agent learns from the team's mean reward instead of its own
    :param normalize: divide by the running standard deviation of every agent's discounted
        return and clip to [-10, 10]
    """

    def __init__(self, n_agents: int, gamma: float, scale: float, team: bool, normalize: bool) -> None:
        self.n_agents = n_agents
        self.gamma = gamma
        self.scale = scale
        self.team = team
        self.normalize = normalize
        #: running mean and variance of every agent's discounted return (None until normalising starts)
        self.return_rms: RunningMeanStd | None = None
        #: every env's discounted return so far, (n_envs, N); not saved
        self.discounted_returns: np.ndarray | None = None

    def __call__(self, rewards: np.ndarray, dones: np.ndarray) -> np.ndarray:
        """The learner's rewards of one step of all envs, (n_envs, N).

        :param rewards: every env's per-agent rewards (n_envs, N)
        :param dones: episode ends of the step (n_envs,)
        """
        rewards = self.scale * rewards
        if self.team:
            rewards = np.repeat(rewards.mean(axis=1, keepdims=True), self.n_agents, axis=1)
        if not self.normalize:
            return rewards.astype(np.float32)
        if self.return_rms is None:
            self.return_rms = RunningMeanStd(shape=(self.n_agents,))
        if self.discounted_returns is None or self.discounted_returns.shape != rewards.shape:
            self.discounted_returns = np.zeros_like(rewards, dtype=np.float64)
        self.discounted_returns = self.discounted_returns * self.gamma + rewards
        self.return_rms.update(self.discounted_returns)
        self.discounted_returns[np.asarray(dones, dtype=bool)] = 0.0
        return np.clip(rewards / self.spread(), -10.0, 10.0).astype(np.float32)

    def switch(self, normalize: bool, fresh_statistics: bool = False) -> None:
        """Switch the normalisation on or off.

        :param normalize: whether to divide rewards by the running spread of the returns
        :param fresh_statistics: forget the spread measured so far
        """
        self.normalize = normalize
        if fresh_statistics:
            self.return_rms = None
            self.discounted_returns = None

    def spread(self) -> np.ndarray | float:
        """What rewards are divided by when normalising: every agent's return standard deviation (1 before).

        :return: ``sqrt(var + 1e-8)`` of every agent's discounted return (N,), or 1.0 when not normalising
            or before the first step
        """
        if not self.normalize or self.return_rms is None:
            return 1.0
        return np.sqrt(self.return_rms.var + 1e-8)

    def converted(self, rewards: np.ndarray) -> np.ndarray:
        """Per-agent rewards (or sums of them) in the learner's units, without touching the statistics.

        Scaled, shared by the team, divided by the return spread, as :meth:`__call__` does; the
        clipping is ignored (as in :meth:`price`). For quantities that are not steps of the training
        envs, e.g. the replayed differences of :mod:`sb3_detc.mappoc.replays`.

        :param rewards: per-agent rewards (..., N)
        :return: the same in the learner's units, float64 (..., N)
        """
        rewards = self.scale * np.asarray(rewards, dtype=np.float64)
        if self.team:
            rewards = np.repeat(rewards.mean(axis=-1, keepdims=True), self.n_agents, axis=-1)
        return rewards / self.spread()

    def price(self, broadcast_cost: np.ndarray) -> np.ndarray:
        """What an agent's own broadcast costs in the learner's reward units, (n_envs, N).

        The communication cost through the same transformation as the rewards (scaled,
        shared by the team, divided by the return spread; the clipping is ignored).

        :param broadcast_cost: communication cost of every env (n_envs,)
        :return: the price of every agent's broadcast in every env, float32 (n_envs, N)
        """
        price = np.repeat(broadcast_cost[:, None] * self.scale, self.n_agents, axis=1)
        if self.team:
            price = price / self.n_agents
        return (price / self.spread()).astype(np.float32)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "discounted_returns": None}


def broadcast_costs(env: Any, needs_price: bool, critic: str) -> np.ndarray:
    """The communication cost ``xi`` of every environment of a vector env, (n_envs,); zeros unless the critic needs it.

    :param env: the training env (a VecEnv)
    :param needs_price: whether the critic adds the price of a broadcast to its option values
    :param critic: the critic's name (for the error message)
    :return: the cost of a broadcast in every env, float32 (n_envs,)
    :raises ValueError: if the critic needs the cost and the envs have no ``broadcast_cost``
    """
    if not needs_price:
        return np.zeros(env.num_envs, dtype=np.float32)  # such critics learn it from the rewards
    try:
        return np.asarray(env.get_attr("broadcast_cost"), dtype=np.float32)
    except AttributeError as err:
        raise ValueError(
            f"critic={critic!r} needs the environment's communication cost (attribute 'broadcast_cost', as the "
            "sb3_detc envs have) to add it to its option values."
        ) from err


class PriceRule:
    """How the rate target's price per broadcast (MAPPOC's ``target_savings``) follows the rollouts.

    A rule is chosen once by name (:data:`PRICE_RULES`, MAPPOC's ``broadcast_price_rule``) and
    gives the price after every update from what the rollout showed.

    Class attributes:

    * ``name``: the rule's name in :data:`PRICE_RULES`;
    * ``needs_price``: whether the rule needs option values that take the price analytically
      (a critic with ``needs_price``);
    * ``mu_only``: whether the price moves only after rollouts whose options ``mu`` took
      (not those of a fixed trigger, e.g. in the first stage of a two-stage callback).

    :param target_savings: the savings to settle at, in (0, 1)
    :param lr: the rule's step size (MAPPOC's ``broadcast_price_lr``), where it has one
    """

    name: ClassVar[str]
    needs_price: ClassVar[bool]
    mu_only: ClassVar[bool]

    def __init__(self, target_savings: float, lr: float) -> None:
        self.target_savings = target_savings
        self.lr = lr

    def updated(self, price: float, broadcast: np.ndarray, option_values: np.ndarray, mu_took: bool) -> float:
        """The price after a rollout.

        :param price: the price charged during the rollout, in the learner's reward units
        :param broadcast: the rollout's options, (..., N)
        :param option_values: the critic's ``Q_i(s, o)`` of both options at the rollout's steps, with
            the rollout's price, (..., N, 2)
        :param mu_took: whether ``mu`` took the rollout's options
        :return: the new price (``price`` itself after a fixed trigger's rollout if ``mu_only``)
        """
        if self.mu_only and not mu_took:
            return price
        return price + self._step(np.asarray(broadcast), np.asarray(option_values))

    def _step(self, broadcast: np.ndarray, option_values: np.ndarray) -> float:
        """How far the price moves after a rollout (see :meth:`updated`)."""
        raise NotImplementedError


class DualAscent(PriceRule):
    """Dual ascent on ``mu``'s rate: ``price += lr * (broadcast rate - (1 - target_savings))``.

    It follows ``mu``'s own rate, with any critic; the price lags behind ``mu``, and a sharp
    ``mu`` may swing around the target.
    """

    name = "dual"
    needs_price = False
    mu_only = True

    def _step(self, broadcast: np.ndarray, option_values: np.ndarray) -> float:
        return self.lr * (float(broadcast.mean()) - (1.0 - self.target_savings))


class GapQuantile(PriceRule):
    """The price at which the critic's greedy options broadcast at the target rate on the rollout's states.

    The price moves by the ``target_savings``-quantile of the critic's broadcast gaps
    ``Q_i(s, 1) - Q_i(s, 0)`` on the rollout, as the critic valued them when the rollout was
    stored, with the rollout's price: then exactly ``1 - target_savings`` of the rollout's
    agent-steps have a broadcast worth more than it costs. It follows the critic, one update
    behind, not ``mu``'s own rate (a ``mu`` softer than the critic's greedy options broadcasts
    at another rate). No step size (``lr`` is not used), and it moves during a fixed trigger's
    stage too, so that ``mu`` starts learning at a price that fits the target. It needs a
    critic that takes the price analytically: where the critic learns the price from the
    rewards, its gaps do not move with the price.
    """

    name = "quantile"
    needs_price = True
    mu_only = False

    def _step(self, broadcast: np.ndarray, option_values: np.ndarray) -> float:
        return float(np.quantile(option_values[..., 1] - option_values[..., 0], self.target_savings))


#: Rules for the rate target's price, by name (MAPPOC's ``broadcast_price_rule``).
PRICE_RULES: dict[str, type[PriceRule]] = {rule.name: rule for rule in (DualAscent, GapQuantile)}
