"""MAPPOC's loss (Sec. 3 of the method reference): PPO on both policy levels and the critic's error.

* control policy ``pi``: PPO's clipped surrogate on GAE advantages of the taken option;
* critic ``Q``: squared error of the taken option's value against the lambda-return;
* policy over options ``mu``: PPO's clipped surrogate on a broadcast advantage (greedy:
  ``Q(o) - max_o' Q(o')`` with the current critic; sampled: the lambda-return minus the
  state value at collection time; or replayed: measured in copies of the env,
  :mod:`sb3_detc.mappoc.replays`, as the draw's or its expected gradient), plus an entropy
  bonus; or, with ``"replayed_value"``, least squares of the broadcast logit against the
  replayed value of a broadcast.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import torch as th
from torch import nn

if TYPE_CHECKING:
    from sb3_detc.mappoc.batched import ChainInput
    from sb3_detc.mappoc.buffers import HybridRolloutSamples
    from sb3_detc.mappoc.policies import HybridEvaluation, MlpHybridPolicy

#: Statistics of every gradient step, in the order :class:`MAPPOCLoss` returns them (logged as ``train/<name>``).
STEP_STATS = ("pi_loss", "mu_loss", "q_loss", "entropy_mu", "clip_pi", "clip_mu", "kl_pi", "kl_mu")

#: Kinds of broadcast advantage in ``mu``'s loss.
BROADCAST_ADVANTAGES = ("greedy", "return", "replayed", "replayed_expected", "replayed_value")

#: ``mu``'s loss from the evaluation, the minibatch, ``mu``'s probability ratios and its clipping parameter.
OptionLoss = Callable[["HybridEvaluation", "HybridRolloutSamples", th.Tensor, "float | th.Tensor"], th.Tensor]

#: The kinds that measure the value of a broadcast in copies of the env (:mod:`sb3_detc.mappoc.replays`).
REPLAYED_ADVANTAGES = ("replayed", "replayed_expected", "replayed_value")


class UpdateInputs(NamedTuple):
    """What every gradient step of one update needs besides the minibatch's indices.

    :param inputs: stacked network inputs of the whole rollout (``MlpHybridPolicy.training_inputs``)
    :param samples: the rollout's tensors (of the observations only the ages, which a broadcast interval reads)
    :param p_broadcast: probabilities of broadcasting with which the options were drawn (B, N)
    :param clip_pi: clip range of pi
    :param clip_mu: clip range of mu
    :param zeta: broadcast entropy coefficient
    :param train_pi: whether pi's loss is part of the loss
    :param train_mu: whether mu's loss and entropy bonus are part of the loss
    """

    inputs: list[ChainInput]
    samples: HybridRolloutSamples
    p_broadcast: th.Tensor
    clip_pi: float | th.Tensor
    clip_mu: float | th.Tensor
    zeta: float | th.Tensor
    train_pi: bool
    train_mu: bool


def clipped_surrogate_loss(advantages: th.Tensor, ratio: th.Tensor, clip: float | th.Tensor) -> th.Tensor:
    """PPO's clipped surrogate loss, averaged over the batch and summed over agents.

    Summing over agents keeps every agent's gradient what it would be if it trained alone.

    :param advantages: advantages (B, N)
    :param ratio: probability ratios new / old (B, N)
    :param clip: clipping parameter epsilon
    :return: scalar loss
    """
    surrogate = th.min(advantages * ratio, advantages * th.clamp(ratio, 1 - clip, 1 + clip))
    return -surrogate.mean(0).sum()


def greedy_broadcast_advantage(option_values: th.Tensor, broadcast: th.Tensor, offset: float = 0.0) -> th.Tensor:
    """Greedy advantage of the taken options, ``A_mu = Q(o) - max_o' Q(o') + offset`` (Sec. 3).

    Evaluated with the current critic and detached: no gradient flows into ``Q``.

    :param option_values: ``Q_i(s, o)`` for both options, (B, N, 2)
    :param broadcast: taken options (B, N)
    :param offset: constant added to the advantage (the paper's code: 0.1, the paper: 0)
    :return: advantages (B, N), at most ``offset``
    """
    q = option_values.detach()
    return q.gather(-1, broadcast.long()[..., None])[..., 0] - q.max(-1).values + offset


def broadcast_gap_scale(option_values: th.Tensor) -> th.Tensor:
    """Every agent's root mean square broadcast gap ``Q(1) - Q(0)`` over a batch, detached, (N,).

    :param option_values: ``Q_i(s, o)`` for both options, (B, N, 2)
    :return: the scales (N,), each plus 1e-8 so that it is never zero
    """
    gap = option_values.detach()[..., 1] - option_values.detach()[..., 0]
    return gap.pow(2).mean(0).sqrt() + 1e-8


def unchanged(advantages: th.Tensor) -> th.Tensor:
    """Advantages as they are (:class:`MAPPOCLoss` without ``normalize_advantage``).

    :param advantages: advantages (B, N)
    :return: ``advantages`` itself
    """
    return advantages


def standardized(advantages: th.Tensor) -> th.Tensor:
    """Advantages standardised per agent over the batch, (B, N) (unchanged for a batch of one).

    :param advantages: advantages (B, N)
    :return: every agent's advantages minus their mean over the batch, divided by their standard deviation
        (plus 1e-8), (B, N); ``advantages`` itself for a batch of one
    """
    if len(advantages) > 1:
        return (advantages - advantages.mean(0)) / (advantages.std(0) + 1e-8)
    return advantages


def fitted_logit_loss(
    evaluation: HybridEvaluation, data: HybridRolloutSamples, ratio: th.Tensor, clip: float | th.Tensor
) -> th.Tensor:
    """Squared error of ``mu``'s broadcast logit against its target, at the decisions that have one.

    For ``broadcast_advantage="replayed_value"``: the targets (``data.broadcast_advantages``) are the
    replayed values of a broadcast divided by ``replay_temperature``, NaN where no decision was replayed.
    Averaged over every agent's replayed decisions in the minibatch, summed over agents.

    :param evaluation: the current networks' evaluation of the minibatch (its ``broadcast_logit``)
    :param data: the minibatch (its ``broadcast_advantages``: the targets)
    :param ratio: ``mu``'s probability ratios (unused: a regression is not clipped)
    :param clip: ``mu``'s clipping parameter (unused)
    :return: scalar loss
    """
    target = data.broadcast_advantages
    replayed = ~th.isnan(target)
    error = th.where(replayed, evaluation.broadcast_logit - th.nan_to_num(target), 0.0)
    return (error.pow(2).sum(0) / replayed.sum(0).clamp(min=1)).sum()


class MAPPOCLoss(nn.Module):
    """The loss of one gradient step on a minibatch, and its statistics (a module holding the policy).

    A module, so that :func:`torch.func.functional_call` can evaluate it with other parameter
    values (the fused gradient step, :mod:`sb3_detc.mappoc.steps`).

    :param policy: the policy whose networks are trained
    :param vf_coef: coefficient of the critic's squared error
    :param broadcast_advantage: ``"greedy"``, ``"return"``, ``"replayed"``, ``"replayed_expected"`` or
        ``"replayed_value"`` (see :class:`~sb3_detc.MAPPOC`)
    :param broadcast_advantage_offset: constant added to the broadcast advantages
    :param normalize_broadcast_advantage: divide the greedy broadcast advantages by every agent's
        root mean square broadcast gap over the minibatch (:func:`broadcast_gap_scale`)
    :param normalize_advantage: standardise the control advantages (and the sampled option
        advantages) per agent and minibatch
    :raises ValueError: for an unknown ``broadcast_advantage``
    """

    def __init__(
        self,
        policy: MlpHybridPolicy,
        vf_coef: float,
        broadcast_advantage: str,
        broadcast_advantage_offset: float,
        normalize_broadcast_advantage: bool,
        normalize_advantage: bool,
    ) -> None:
        super().__init__()
        if broadcast_advantage not in BROADCAST_ADVANTAGES:
            kinds = " or ".join(map(repr, BROADCAST_ADVANTAGES))
            raise ValueError(f"broadcast_advantage must be {kinds}, got {broadcast_advantage!r}.")
        self.policy = policy
        self.vf_coef = vf_coef
        self.offset = broadcast_advantage_offset
        self.normalized: Callable[[th.Tensor], th.Tensor] = standardized if normalize_advantage else unchanged
        self.broadcast_advantages: Callable[[HybridEvaluation, HybridRolloutSamples], th.Tensor] = (
            self._sampled
            if broadcast_advantage == "return"
            else self._replayed
            if broadcast_advantage in REPLAYED_ADVANTAGES  # "replayed_value": the targets of option_loss
            else self._greedy_normalized
            if normalize_broadcast_advantage
            else self._greedy
        )
        self.option_loss: OptionLoss = fitted_logit_loss if broadcast_advantage == "replayed_value" else self._surrogate

    def _greedy(self, evaluation: HybridEvaluation, data: HybridRolloutSamples) -> th.Tensor:
        """Greedy broadcast advantages with the current critic, plus the offset.

        :param evaluation: the current networks' evaluation of the minibatch (its ``option_values``)
        :param data: the minibatch (its taken options ``broadcast``)
        :return: advantages (B, N)
        """
        return greedy_broadcast_advantage(evaluation.option_values, data.broadcast) + self.offset

    def _greedy_normalized(self, evaluation: HybridEvaluation, data: HybridRolloutSamples) -> th.Tensor:
        """Greedy broadcast advantages divided by every agent's broadcast gap scale, plus the offset.

        :param evaluation: the current networks' evaluation of the minibatch (its ``option_values``)
        :param data: the minibatch (its taken options ``broadcast``)
        :return: advantages (B, N)
        """
        advantages = greedy_broadcast_advantage(evaluation.option_values, data.broadcast)
        return advantages / broadcast_gap_scale(evaluation.option_values) + self.offset

    def _sampled(self, evaluation: HybridEvaluation, data: HybridRolloutSamples) -> th.Tensor:
        """Sampled broadcast advantages (lambda-return minus the state value at collection), plus the offset.

        Standardised like the control advantages if ``normalize_advantage``.

        :param evaluation: the current networks' evaluation of the minibatch (unused)
        :param data: the minibatch (its ``broadcast_advantages``)
        :return: advantages (B, N)
        """
        return self.normalized(data.broadcast_advantages) + self.offset

    def _replayed(self, evaluation: HybridEvaluation, data: HybridRolloutSamples) -> th.Tensor:
        """Replayed broadcast advantages as stored (zero where no decision was replayed), without the offset.

        :param evaluation: the current networks' evaluation of the minibatch (unused)
        :param data: the minibatch (its ``broadcast_advantages``)
        :return: advantages (B, N)
        """
        return data.broadcast_advantages

    def _surrogate(
        self, evaluation: HybridEvaluation, data: HybridRolloutSamples, ratio: th.Tensor, clip: float | th.Tensor
    ) -> th.Tensor:
        """``mu``'s clipped surrogate loss on the broadcast advantages of its kind.

        :param evaluation: the current networks' evaluation of the minibatch
        :param data: the minibatch
        :param ratio: ``mu``'s probability ratios new / old (B, N)
        :param clip: ``mu``'s clipping parameter
        :return: scalar loss
        """
        return clipped_surrogate_loss(self.broadcast_advantages(evaluation, data), ratio, clip)

    def forward(self, update: UpdateInputs, idx: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """The loss of one gradient step on the minibatch ``idx`` and its statistics.

        :param update: what every step of the update needs (:class:`UpdateInputs`)
        :param idx: indices of the minibatch's samples
        :return: the loss, and the statistics named in :data:`STEP_STATS` as one tensor
        """
        clip_pi, clip_mu = update.clip_pi, update.clip_mu
        data = update.samples.select(idx)
        evaluation = self.policy.evaluate_inputs(
            [x.select(idx) for x in update.inputs],
            data.broadcast,
            data.control,
            data.broadcast_price,
            update.p_broadcast[idx],
            data.observations.get("age"),  # read with a broadcast interval only
        )

        # Control policy: PPO clipped surrogate on GAE advantages of the taken option.
        log_ratio_pi = evaluation.log_prob_control - data.old_log_prob_control
        ratio_pi = th.exp(log_ratio_pi)
        pi_loss = clipped_surrogate_loss(self.normalized(data.advantages), ratio_pi, clip_pi)

        # Critic: squared error of Q(s, o_taken) against the lambda-return.
        q_taken = evaluation.option_values.gather(-1, data.broadcast[..., None])[..., 0]
        q_loss = (data.returns - q_taken).pow(2).mean(0).sum()
        loss = self.vf_coef * q_loss
        if update.train_pi:
            loss = loss + pi_loss

        # Options: PPO clipped surrogate on the broadcast advantage (or the fitted logit), no gradient into Q.
        log_ratio_mu = evaluation.log_prob_broadcast - data.old_log_prob_broadcast
        ratio_mu = th.exp(log_ratio_mu)
        mu_loss = self.option_loss(evaluation, data, ratio_mu, clip_mu)
        entropy_mu = evaluation.entropy_broadcast.mean(0).sum()
        if update.train_mu:
            loss = loss + mu_loss - update.zeta * entropy_mu

        with th.no_grad():
            step_stats = th.stack(
                [
                    pi_loss,
                    mu_loss,
                    q_loss,
                    entropy_mu / self.policy.n_agents,
                    ((ratio_pi - 1).abs() > clip_pi).float().mean(),
                    ((ratio_mu - 1).abs() > clip_mu).float().mean(),
                    ((ratio_pi - 1) - log_ratio_pi).mean(),
                    ((ratio_mu - 1) - log_ratio_mu).mean(),
                ]
            )
        return loss, step_stats
