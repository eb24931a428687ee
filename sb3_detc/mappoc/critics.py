"""Option-value critics: how ``Q_i(s, o)`` for both options comes from a critic network.

Every critic is one :class:`OptionCritic` subclass, registered by name in :data:`CRITICS`
(the name is what ``MlpHybridPolicy(critic=...)`` and hyperparameter files take). A critic
says what its network reads (the network state before the options, or the afterstates of
both own options: ``reads_afterstate``; the policy that holds the critic builds these
inputs), how many outputs it has, how its outputs become both options' values
(:meth:`OptionCritic.option_values`) and what training must give it (the broadcast price,
the probabilities the options were drawn with). Adding a critic means adding a subclass
here and registering it.
"""

from __future__ import annotations

from typing import ClassVar

import torch as th


class OptionCritic:
    """What turns a critic network into option values ``Q_i(s, o)``, (B, N, 2).

    Class attributes, read by the policy and by MAPPOC:

    * ``name``: the critic's name in :data:`CRITICS`;
    * ``outputs``: outputs of the critic network per input;
    * ``reads_afterstate``: what the critic network reads. False: the network state before
      this step's options, one input per agent, (B, N, features) (the network runs before the
      options are sampled, together with ``mu``). True: the afterstates of both own options,
      the others' options as taken, two inputs per agent, (B, 2, N, features) (the network
      runs after the options are sampled);
    * ``needs_price``: whether :meth:`option_values` adds the cost of the own broadcast
      analytically (then MAPPOC reads the environments' ``broadcast_cost``; otherwise the critic
      learns it from the rewards);
    * ``needs_draw_probabilities``: whether :meth:`option_values` needs the probabilities
      with which the options were drawn (then options must come from ``mu``, not from a fixed
      trigger).
    """

    name: ClassVar[str]
    outputs: ClassVar[int]
    reads_afterstate: ClassVar[bool] = False
    needs_price: ClassVar[bool] = True
    needs_draw_probabilities: ClassVar[bool] = False

    def option_values(
        self, q: th.Tensor, broadcast_price: th.Tensor | None = None, p_broadcast: th.Tensor | None = None
    ) -> th.Tensor:
        """Both options' values from the critic network's outputs.

        :param q: outputs of the critic network on the inputs ``reads_afterstate`` names
        :param broadcast_price: what a broadcast costs agent ``i`` in the learner's reward units (B, N)
            (None: zero); read only if ``needs_price``
        :param p_broadcast: probability of broadcasting ``p_i`` with which the options were
            drawn (B, N); required if ``needs_draw_probabilities``
        :return: ``Q_i(s, o)``, (B, N, 2)
        :raises ValueError: if ``p_broadcast`` is required and missing
        """
        if self.needs_draw_probabilities and p_broadcast is None:
            raise ValueError(f"The {self.name} critic needs the probabilities of broadcasting (p_broadcast).")
        return self._option_values(q, 0.0 if broadcast_price is None else broadcast_price, p_broadcast)

    def _option_values(self, q: th.Tensor, price: th.Tensor | float, p_broadcast: th.Tensor | None) -> th.Tensor:
        """:meth:`option_values` with the price filled in and the probabilities checked.

        :param q: outputs of the critic network on the inputs ``reads_afterstate`` names
        :param price: what a broadcast costs agent ``i`` (B, N), or 0.0
        :param p_broadcast: probability of broadcasting with which the options were drawn (B, N), or None
        :return: ``Q_i(s, o)``, (B, N, 2)
        """
        raise NotImplementedError


class OptionHeadsCritic(OptionCritic):
    """The paper's critic: one output per option on the state before the options, ``Q_i(s, o) = q_i(s)[o]``.

    The broadcast's cost is learned from the rewards like everything else.
    """

    name = "option_heads"
    outputs = 2
    needs_price = False

    def _option_values(self, q: th.Tensor, price: th.Tensor | float, p_broadcast: th.Tensor | None) -> th.Tensor:
        """The option heads as they are (see :meth:`OptionCritic._option_values`).

        :param q: outputs of the critic network, the option values (B, N, 2)
        :param price: what a broadcast costs agent ``i`` (unused: learned from the rewards)
        :param p_broadcast: probability of broadcasting with which the options were drawn (unused)
        :return: ``q``
        """
        return q


class AfterstateCritic(OptionCritic):
    """One output ``W_i`` valuing the network state the options lead to, ``Q_i(s, o) = W_i(after(s, o)) - o price_i``.

    ``W_i`` reads the held broadcasts after the options, with agent ``i``'s own option set to
    ``o`` and the others' as taken, and the ages before them
    (:meth:`~sb3_detc.mappoc.policies.MlpHybridPolicy.afterstate_features`). It learns the
    value of stale information from every step, whichever option led to it, so both
    options' values come from one function and the difference between them has no per-head
    offset.
    """

    name = "afterstate"
    outputs = 1
    reads_afterstate = True

    def _option_values(self, q: th.Tensor, price: th.Tensor | float, p_broadcast: th.Tensor | None) -> th.Tensor:
        """``[W_i(after(s, 0)), W_i(after(s, 1)) - price_i]`` from the afterstate values ``q`` (B, 2, N, 1).

        :param q: outputs of the critic network on the afterstates: ``[:, v, i, 0]`` is ``W_i`` of agent
            ``i``'s afterstate for its own option ``v``, (B, 2, N, 1)
        :param price: what a broadcast costs agent ``i`` (B, N), or 0.0
        :param p_broadcast: probability of broadcasting with which the options were drawn (unused)
        :return: ``Q_i(s, o)``, (B, N, 2)
        """
        values = q[..., 0].transpose(1, 2)
        return th.stack([values[..., 0], values[..., 1] - price], dim=-1)


class CentredCritic(OptionCritic):
    """Two outputs on the state before the options: a state value ``V_i(s)`` and a broadcast gap ``D_i(s)``.

    ``Q_i(s, o) = V_i(s) + (o - p_i) (D_i(s) - price_i)`` with ``p_i`` the probability of
    broadcasting with which the options were drawn, so that ``sum_o mu_i(o) Q_i(s, o) = V_i(s)``
    and ``Q_i(s, 1) - Q_i(s, 0) = D_i(s) - price_i``. Fitted by the same squared error as the
    others, this is the R-learner of causal inference (Nie and Wager, 2021) for the effect of
    a broadcast: because the options are drawn with known probabilities, ``o - p`` is
    uncorrelated with every function of the state, so the error of ``V_i``, the large part of
    the value, does not leak into the broadcast gap, the small part on which ``mu`` acts.
    """

    name = "centred"
    outputs = 2
    needs_draw_probabilities = True

    def _option_values(self, q: th.Tensor, price: th.Tensor | float, p_broadcast: th.Tensor | None) -> th.Tensor:
        """``V - p (D - price)`` and ``V + (1 - p) (D - price)`` from ``q = (V, D)`` (B, N, 2).

        :param q: outputs of the critic network: state value ``V_i(s)`` and broadcast gap ``D_i(s)``, (B, N, 2)
        :param price: what a broadcast costs agent ``i`` (B, N), or 0.0
        :param p_broadcast: probability of broadcasting ``p_i`` with which the options were drawn (B, N);
            not None (checked by :meth:`OptionCritic.option_values`)
        :return: ``Q_i(s, o)``, (B, N, 2)
        """
        value, gap = q[..., 0], q[..., 1] - price
        return th.stack([value - p_broadcast * gap, value + (1 - p_broadcast) * gap], dim=-1)


#: The option-value critics by name.
CRITICS: dict[str, type[OptionCritic]] = {
    critic.name: critic for critic in (OptionHeadsCritic, AfterstateCritic, CentredCritic)
}
