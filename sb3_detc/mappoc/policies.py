"""Hybrid policies for MAPPOC: per agent a policy over options, a control policy and an option-value critic.

For every agent ``i`` (Sec. 3 of the method reference):

* ``mu_i(o_i | trigger_i, trigger_held_i)``: categorical over {silent, broadcast}
  (policy over options, re-sampled every step: option termination ``beta = 1``);
* ``pi_i(u_i | x^_i)``: Gaussian control policy with a state-independent log standard
  deviation, evaluated on the networked observation ``x^_i`` *after* this step's
  broadcasts (same-step delivery);
* ``Q_i(s, o)``: option-value critic, centralised during training only (it also sees the
  true messages of all agents), either with one output per option (the paper) or as an
  afterstate critic ``Q_i(s, o) = W_i(s after the options)`` that values the network state
  the options lead to (see :class:`MlpHybridPolicy`'s ``critic``).

All networks of all agents are evaluated by agent-batched layers (one batched matmul per
layer, weights shaped (groups, in, out)); no Python loop over agents on the hot path.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.nn import functional as F

from sb3_detc.envs.wrappers import JOINT_KEYS
from sb3_detc.network import advance_timer, hold, others_index, relative_views

#: Order of the networks inside the batched chains: ``mu`` (and the option-heads critic) do
#: not depend on this step's options and run before the options are sampled, ``pi`` (and the
#: afterstate critic) run after.
NETS = ("mu", "q", "pi")
#: Kinds of option-value critic.
CRITICS = ("option_heads", "afterstate", "centred")


def broadcast_probability(logits: th.Tensor) -> th.Tensor:
    """Probability of broadcasting under ``mu`` from its logits (..., 2): ``sigmoid(logit_1 - logit_0)``."""
    return th.sigmoid(logits[..., 1] - logits[..., 0])


class BatchedMLP(nn.Module):
    """Independent MLPs of one hidden architecture, evaluated together with one ``baddbmm`` per layer.

    Group ``g`` reads the first ``in_features[g]`` input columns and writes the first
    ``out_features[g]`` output columns; the rest is zero padding whose weights stay zero
    (their gradients are zero).

    :param in_features: input width of every group
    :param out_features: output width of every group
    :param hidden: hidden layer sizes (common to all groups)
    :param activation_fn: activation class applied after every hidden layer
    :param output_gains: orthogonal-init gain of every group's output layer
    :param hidden_gain: orthogonal-init gain of the hidden layers
    """

    def __init__(
        self,
        in_features: Sequence[int],
        out_features: Sequence[int],
        hidden: Sequence[int],
        activation_fn: type[nn.Module],
        output_gains: Sequence[float],
        hidden_gain: float = math.sqrt(2),
    ) -> None:
        super().__init__()
        self.in_features = list(in_features)
        self.out_features = list(out_features)
        self.activation = activation_fn()
        self.activation_fn = activation_fn
        sizes = [max(self.in_features), *hidden, max(self.out_features)]
        n_groups, n_layers = len(self.in_features), len(sizes) - 1
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for layer in range(n_layers):
            weight = th.zeros(n_groups, sizes[layer], sizes[layer + 1])
            for g in range(n_groups):
                rows = self.in_features[g] if layer == 0 else sizes[layer]
                cols = self.out_features[g] if layer == n_layers - 1 else sizes[layer + 1]
                gain = output_gains[g] if layer == n_layers - 1 else hidden_gain
                block = th.empty(cols, rows)
                nn.init.orthogonal_(block, gain=gain)
                weight[g, :rows, :cols] = block.T
            self.weights.append(nn.Parameter(weight))
            self.biases.append(nn.Parameter(th.zeros(n_groups, 1, sizes[layer + 1])))

    def forward(self, x: th.Tensor, start: int = 0, stop: int | None = None) -> th.Tensor:
        """Evaluate groups ``start:stop``.

        :param x: inputs, shape (groups, batch, max input width)
        :param start: first group
        :param stop: one past the last group (None: all)
        :return: outputs, shape (groups, batch, max output width)
        """
        last = len(self.weights) - 1
        for layer, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = th.baddbmm(bias[start:stop], x, weight[start:stop])
            if layer < last:
                x = self.activation(x)
        return x

    def extract(self, group: int) -> nn.Sequential:
        """A standalone copy of one group's MLP made of ordinary ``nn.Linear`` layers.

        :param group: index of the group
        :return: the group's network, input width ``in_features[group]``
        """
        layers: list[nn.Module] = []
        last = len(self.weights) - 1
        for layer, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            rows = self.in_features[group] if layer == 0 else weight.shape[1]
            cols = self.out_features[group] if layer == last else weight.shape[2]
            linear = nn.Linear(rows, cols)
            with th.no_grad():
                linear.weight.copy_(weight[group, :rows, :cols].T)
                linear.bias.copy_(bias[group, 0, :cols])
            layers.append(linear)
            if layer < last:
                layers.append(self.activation_fn())
        return nn.Sequential(*layers)


class HybridAction(NamedTuple):
    """One joint hybrid action of all agents with what training needs about it."""

    comm: th.Tensor  # (B, N) options, int64
    control: th.Tensor  # (B, N, m) controls (with any extra exploration noise, unclipped)
    log_prob_comm: th.Tensor  # (B, N) log mu_i(o_i)
    log_prob_control: th.Tensor  # (B, N) log pi_i(u_i)
    option_values: th.Tensor  # (B, N, 2) Q_i(s, o) for both options


class HybridEvaluation(NamedTuple):
    """Log-probabilities, option entropy and option values of stored hybrid actions."""

    log_prob_comm: th.Tensor  # (B, N)
    entropy_comm: th.Tensor  # (B, N)
    log_prob_control: th.Tensor  # (B, N)
    option_values: th.Tensor  # (B, N, 2)


class ChainInput(NamedTuple):
    """Inputs of some networks of one batched chain, stacked: (groups, B, variants x agents per group, width).

    ``variants`` > 1 evaluates every network on several inputs per sample (the afterstate
    critic's two own options).
    """

    chain: int  # index of the chain
    nets: tuple[str, ...]  # consecutive networks of the chain these inputs feed, in chain order
    x: th.Tensor
    variants: int = 1

    def select(self, idx: th.Tensor) -> ChainInput:
        """The same inputs for the samples ``idx`` of the batch axis."""
        return ChainInput(self.chain, self.nets, self.x[:, idx], self.variants)


def _variants(features: th.Tensor) -> int:
    """Inputs per sample of a network's features: (B, N, f) -> 1, (B, variants, N, f) -> variants."""
    return features.shape[1] if features.dim() == 4 else 1


def gaussian_log_prob(x: th.Tensor, mean: th.Tensor, log_std: th.Tensor) -> th.Tensor:
    """Log-density of a diagonal Gaussian, summed over the last axis."""
    z = (x - mean) * th.exp(-log_std)
    return (-0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)


class MlpHybridPolicy(BasePolicy):
    """Per-agent policy over options, Gaussian control policy and centralised option-value critic.

    :param observation_space: joint observation space of an event-triggered env (Dict with
        keys ``local``, ``message``, ``held``, ``age``, ``trigger``, ``trigger_held``)
    :param action_space: joint action space (Dict with ``comm`` MultiDiscrete and ``control`` Box)
    :param lr_schedule: learning rate schedule (None: a constant placeholder, for a policy
        loaded on its own with :meth:`load` to act, not to train)
    :param net_arch: hidden layer sizes, either one list for all networks or a dict with keys
        ``mu``, ``pi`` and ``q`` (None: three layers of 96 units, as in the paper)
    :param activation_fn: activation function of the hidden layers
    :param log_std_init: initial log standard deviation of the control policies (paper: -0.7)
    :param learn_log_std: whether the log standard deviation is trained (the paper keeps it constant)
    :param share_parameters: one network set for all agents with a one-hot agent id input
        (default: every agent has its own networks, as in the paper)
    :param age_scale: factor applied to ages of information (in steps) before they enter a network
        (>= 0; 0: no network sees the ages)
    :param broadcast_prob_init: probability of broadcasting of the untrained policies over
        options (through the bias of their output layer; 0.5: undecided). A low value lets
        training start where every broadcast carries information that would otherwise stay
        stale for several steps, so its value stands out from the noise of the returns
    :param critic: ``"option_heads"`` (the paper: ``Q_i`` reads the state before the options
        and has one output per option) or ``"afterstate"`` (one output ``W_i`` that reads the
        held broadcasts *after* the options, with the ages before them;
        ``Q_i(s, o) = W_i(after(s, o_i = o, o_-i)) - o price_i`` with the others' options as
        taken, see :meth:`afterstate_features`). The
        afterstate critic learns the value of stale information from every step, whichever
        option led to it, so both options' values come from one function and the difference
        between them has no per-head offset; or ``"centred"`` (two outputs on the state before
        the options, a state value ``V_i(s)`` and an option gap ``D_i(s)``:
        ``Q_i(s, o) = V_i(s) + (o - p_i(s)) (D_i(s) - price_i)`` with ``p_i`` the probability
        of broadcasting under ``mu_i`` when the step was taken). The centred critic is fitted
        by the same squared error as the others, which then is the R-learner of causal
        inference (Nie and Wager, 2021) for the effect of a broadcast: because the options are
        drawn with known probabilities, ``o - p`` is uncorrelated with every function of the
        state, so the error of ``V_i``, the large part of the value, does not leak into the
        option gap, the small part on which ``mu`` acts
    :param ortho_init: orthogonal initialisation (otherwise PyTorch's default init)
    :param use_sde: not supported, must be False (present for SB3 compatibility)
    :param optimizer_class: optimizer class
    :param optimizer_kwargs: optimizer keyword arguments, excluding the learning rate
        (default ``eps=1e-5`` as in the paper's code, and PyTorch's fused Adam kernel)
    :param normalize_images: unused (no image inputs); present for SB3 compatibility, it is
        among the constructor parameters that SB3 saves with a policy
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Dict,
        lr_schedule: Schedule | None = None,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.Tanh,
        log_std_init: float = -0.7,
        learn_log_std: bool = False,
        share_parameters: bool = False,
        age_scale: float = 0.1,
        broadcast_prob_init: float = 0.5,
        critic: str = "option_heads",
        ortho_init: bool = True,
        use_sde: bool = False,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
    ) -> None:
        if use_sde:
            raise ValueError("MlpHybridPolicy does not support gSDE (use_sde=True).")
        n_agents, n_control = check_joint_spaces(observation_space, action_space)
        if not 0.0 < broadcast_prob_init < 1.0:
            raise ValueError(f"broadcast_prob_init must be in (0, 1), got {broadcast_prob_init}.")
        if not (np.isfinite(age_scale) and age_scale >= 0):
            raise ValueError(f"age_scale must be a finite number >= 0 (0: the networks ignore ages), got {age_scale}.")
        if critic not in CRITICS:
            raise ValueError(f"critic must be one of {CRITICS}, got {critic!r}.")
        if optimizer_kwargs is None:
            # The paper's epsilon (for optimizers that have one); the fused Adam kernel saves about
            # 12 % of an eager update step here.
            optimizer_kwargs = {"eps": 1e-5} if "eps" in inspect.signature(optimizer_class).parameters else {}
            if optimizer_class is th.optim.Adam:
                optimizer_kwargs["fused"] = True
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=False,
            normalize_images=normalize_images,
        )
        self.n_agents = n_agents
        self.n_control = n_control
        self.net_arch = [96, 96, 96] if net_arch is None else net_arch
        self.activation_fn = activation_fn
        self.log_std_init = log_std_init
        self.learn_log_std = learn_log_std
        self.share_parameters = share_parameters
        self.age_scale = age_scale
        self.broadcast_prob_init = broadcast_prob_init
        self.critic = critic
        self.ortho_init = ortho_init

        n_local = observation_space["local"].shape[1]
        n_msg = observation_space["message"].shape[1]
        n_trig = observation_space["trigger"].shape[1]
        n = n_agents
        self.register_buffer("others", th.as_tensor(others_index(n)), persistent=False)
        self.register_buffer("everyone", th.arange(n).repeat(n, 1), persistent=False)
        self.register_buffer("agent_id", th.eye(n), persistent=False)
        self.register_buffer("control_low", th.as_tensor(action_space["control"].low), persistent=False)
        self.register_buffer("control_high", th.as_tensor(action_space["control"].high), persistent=False)
        n_id = n if share_parameters else 0
        self.in_features = {
            "mu": 2 * n_trig + n_id,
            "q": n_local + n * (n_msg + 1) + (n - 1) * n_msg + n_id,
            "pi": n_local + (n - 1) * (n_msg + 1) + n_id,
        }
        self.out_features = {"mu": 2, "q": 1 if critic == "afterstate" else 2, "pi": n_control}
        self._build(lr_schedule)

    # ------------------------------------------------------------------ building
    def _arch(self, net: str) -> tuple[int, ...]:
        arch = self.net_arch
        if isinstance(arch, dict):
            if set(arch) != set(NETS):
                raise ValueError(f"net_arch as a dict needs exactly the keys {sorted(NETS)}, got {sorted(arch)}.")
            arch = arch[net]
        if not all(isinstance(h, int) and h > 0 for h in arch):
            raise ValueError(f"net_arch must list positive layer sizes, got {arch!r}.")
        return tuple(arch)

    def _build(self, lr_schedule: Schedule | None) -> None:
        groups = 1 if self.share_parameters else self.n_agents
        gains = {"mu": 0.01, "q": 1.0, "pi": 0.01}
        # Networks with the same hidden architecture share one batched chain.
        by_arch: dict[tuple[int, ...], list[str]] = {}
        for net in NETS:
            by_arch.setdefault(self._arch(net), []).append(net)
        self.chains = nn.ModuleList()
        self._where: dict[str, tuple[int, int, int]] = {}  # net -> (chain, first group, stop)
        for hidden, nets in by_arch.items():
            ins, outs, out_gains = [], [], []
            for net in nets:
                self._where[net] = (len(self.chains), len(ins), len(ins) + groups)
                ins += [self.in_features[net]] * groups
                outs += [self.out_features[net]] * groups
                out_gains += [gains[net] if self.ortho_init else 1.0] * groups
            chain = BatchedMLP(ins, outs, hidden, self.activation_fn, out_gains)
            if not self.ortho_init:
                for weight in chain.weights:
                    nn.init.normal_(weight, std=1.0 / math.sqrt(weight.shape[1]))
            self.chains.append(chain)
        # mu's output layer: logit(broadcast) - logit(silent) = log(p / (1 - p)) at initialisation.
        chain_idx, start, stop = self._where["mu"]
        with th.no_grad():
            self.chains[chain_idx].biases[-1][start:stop, 0, 1] = math.log(
                self.broadcast_prob_init / (1.0 - self.broadcast_prob_init)
            )
        log_std = th.full((groups, self.n_control), float(self.log_std_init))
        self.log_std = nn.Parameter(log_std, requires_grad=self.learn_log_std)
        params = [p for p in self.parameters() if p.requires_grad]
        learning_rate = 0.0 if lr_schedule is None else lr_schedule(1)
        self.optimizer = self.optimizer_class(params, lr=learning_rate, **self.optimizer_kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            log_std_init=self.log_std_init,
            learn_log_std=self.learn_log_std,
            share_parameters=self.share_parameters,
            age_scale=self.age_scale,
            broadcast_prob_init=self.broadcast_prob_init,
            critic=self.critic,
            ortho_init=self.ortho_init,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data

    def net_parameters(self, net: str) -> list[th.Tensor]:
        """Every agent's parameters of one network: views into the batched chain (``pi`` includes ``log_std``).

        :param net: one of ``"mu"``, ``"q"``, ``"pi"``
        :return: detached views (writing into them changes the network)
        """
        chain_idx, start, stop = self._where[net]
        chain = self.chains[chain_idx]
        views = [p.detach()[start:stop] for p in (*chain.weights, *chain.biases)]
        return [*views, self.log_std.detach()] if net == "pi" else views

    # ------------------------------------------------------------------ features
    def network_after(self, obs: PyTorchObs, comm: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Held broadcasts and timers after this step's options (the rule of :mod:`sb3_detc.network`).

        :param obs: joint observation, tensors shaped (B, N, ...)
        :param comm: options (B, N)
        :return: held broadcasts (B, N, n_msg) and timers (B, N, 1)
        """
        comm = comm.to(obs["held"].dtype)
        return hold(obs["held"], obs["message"], comm), advance_timer(obs["age"], comm)

    def option_features(self, obs: PyTorchObs) -> th.Tensor:
        """Inputs of ``mu_i``: trigger features now and at the own last broadcast, (B, N, 2 n_trig)."""
        return th.cat([obs["trigger"], obs["trigger_held"]], dim=-1)

    def control_features(self, obs: PyTorchObs, comm: th.Tensor) -> th.Tensor:
        """Inputs of ``pi_i``: networked observation ``x^_i`` after this step's broadcasts.

        Own local state, the others' held broadcasts relative to the own current message
        and their ages (Sec. 2, networked observation).

        :param obs: joint observation (B, N, ...)
        :param comm: options (B, N)
        :return: (B, N, n_local + (N - 1) (n_msg + 1))
        """
        held, age = self.network_after(obs, comm)
        views = relative_views(held, obs["message"], self.others).flatten(2)
        ages = age[:, self.others, 0] * self.age_scale
        return th.cat([obs["local"], views, ages], dim=-1)

    def critic_features(self, obs: PyTorchObs) -> th.Tensor:
        """Inputs of the option-heads critic ``Q_i``: the network state before this step's options.

        Own local state, every agent's held broadcast (the own one included: what the
        others believe about agent ``i``) relative to the own message, every age, and the
        others' true current messages relative to the own one (centralised training).

        :param obs: joint observation (B, N, ...)
        :return: (B, N, n_local + N (n_msg + 1) + (N - 1) n_msg)
        """
        return self._centralised_features(obs, obs["held"][:, self.everyone], obs["age"][:, self.everyone])

    def afterstate_features(self, obs: PyTorchObs, comm: th.Tensor) -> th.Tensor:
        """Inputs of the afterstate critic ``W_i`` for both own options, the others' as in ``comm``.

        The features of :meth:`critic_features` with the held broadcasts after this step's
        broadcasts: variant ``v`` of agent ``i`` applies the hold rule (:func:`hold`, as
        :meth:`network_after` does) to the options ``comm`` with agent ``i``'s own option
        replaced by ``v``. The ages stay those before the options, the same for both
        variants: a broadcast is worth the information it delivers, and an age reset that
        differs between the options in every state, whatever the broadcast carries, would let
        the critic credit "age 0" with the average value of broadcasting everywhere (it
        then valued broadcasting far above what the returns showed, and ``mu`` learned to
        broadcast at every step even when a broadcast cost more than any information).

        :param obs: joint observation (B, N, ...) from before the options
        :param comm: options (B, N)
        :return: (B, 2, N, features): ``[:, v, i]`` feeds ``W_i`` for ``o_i = v``
        """
        n = self.n_agents
        own = self.agent_id.bool()  # (N receivers, N agents): the receiver's own option
        age = obs["age"][:, None].expand(-1, n, -1, -1)  # every critic sees all ages before the options
        variants = []
        for option in (0, 1):
            # row i: everyone's options with agent i's own replaced by `option`, (B, N, N)
            options = th.where(own, option, comm[:, None, :].expand(-1, n, -1)).to(obs["held"].dtype)
            held = hold(obs["held"][:, None], obs["message"][:, None], options)
            variants.append(self._centralised_features(obs, held, age))
        return th.stack(variants, dim=1)

    def _centralised_features(self, obs: PyTorchObs, held: th.Tensor, age: th.Tensor) -> th.Tensor:
        """Critic inputs from what every agent's critic sees of everyone's held broadcasts.

        :param obs: joint observation (B, N, ...)
        :param held: row ``i`` holds all agents' held broadcasts seen by agent ``i``'s critic, (B, N, N, n_msg)
        :param age: their ages, (B, N, N, 1)
        :return: (B, N, n_local + N (n_msg + 1) + (N - 1) n_msg)
        """
        views = (held - obs["message"][:, :, None, :]).flatten(2)
        true = relative_views(obs["message"], obs["message"], self.others).flatten(2)
        return th.cat([obs["local"], views, age[..., 0] * self.age_scale, true], dim=-1)

    @property
    def critic_reads_afterstate(self) -> bool:
        """Whether the critic reads the network state after this step's options (else: before)."""
        return self.critic == "afterstate"

    def option_values(
        self, q: th.Tensor, comm_price: th.Tensor | None = None, p_broadcast: th.Tensor | None = None
    ) -> th.Tensor:
        """Both options' values from the critic's outputs.

        The own broadcast's cost in this step's reward is known exactly; the afterstate and
        centred critics add it analytically instead of learning it. The afterstate critic
        values the network state after the options, ``Q_i(s, o) = W_i(after(s, o)) - o price_i``.
        The centred critic has a state value and an option gap,
        ``Q_i(s, o) = V_i(s) + (o - p_i) (D_i(s) - price_i)``, so that
        ``sum_o mu_i(o) Q_i(s, o) = V_i(s)`` and ``Q_i(s, 1) - Q_i(s, 0) = D_i(s) - price_i``.

        :param q: option heads or centred outputs ``(V, D)`` (B, N, 2), or afterstate values of
            both own options (B, 2, N, 1)
        :param comm_price: what a broadcast costs agent ``i`` in the learner's reward units (B, N);
            not used by the option heads (None: zero)
        :param p_broadcast: probability of broadcasting ``p_i`` with which the options were
            drawn (B, N); needed by the centred critic only
        :return: ``Q_i(s, o)``, (B, N, 2)
        """
        price = 0.0 if comm_price is None else comm_price
        if self.critic == "option_heads":
            return q
        if self.critic == "afterstate":
            values = q[..., 0].transpose(1, 2)
            return th.stack([values[..., 0], values[..., 1] - price], dim=-1)
        if p_broadcast is None:
            raise ValueError("The centred critic needs the probabilities of broadcasting (p_broadcast).")
        value, gap = q[..., 0], q[..., 1] - price
        return th.stack([value - p_broadcast * gap, value + (1 - p_broadcast) * gap], dim=-1)

    def stack_inputs(self, features: dict[str, th.Tensor]) -> list[ChainInput]:
        """Arrange per-network features for the batched chains.

        The result depends on no parameter, so training computes it once per rollout and
        only indexes it (:meth:`ChainInput.select`) for every minibatch.

        :param features: inputs of some of the networks ``mu``, ``q``, ``pi``, each (B, N, features)
            or, for several inputs per sample, (B, variants, N, features)
        :return: one :class:`ChainInput` per run of consecutive networks of a chain with the
            same number of variants
        """
        stacked = []
        for c, chain in enumerate(self.chains):
            width = max(chain.in_features)
            run: list[str] = []
            for net in (*(net for net in NETS if self._where[net][0] == c), None):
                variants = _variants(features[net]) if net in features else 0
                if run and (variants != _variants(features[run[0]])):
                    grouped = [self._to_groups(features[name]) for name in run]
                    x = th.cat([F.pad(g, (0, width - g.shape[-1])) for g in grouped])
                    stacked.append(ChainInput(c, tuple(run), x, _variants(features[run[0]])))
                    run = []
                if variants:
                    run.append(net)
        return stacked

    def apply_chains(self, stacked: list[ChainInput]) -> dict[str, th.Tensor]:
        """Evaluate the networks of all agents on stacked inputs.

        :param stacked: inputs from :meth:`stack_inputs` (possibly indexed by :meth:`ChainInput.select`)
        :return: outputs of every network in ``stacked``, each (B, N, outputs), or
            (B, variants, N, outputs) for inputs with variants
        """
        outputs: dict[str, th.Tensor] = {}
        for item in stacked:
            groups, batch, rows, width = item.x.shape
            start, stop = self._where[item.nets[0]][1], self._where[item.nets[-1]][2]
            out = self.chains[item.chain](item.x.reshape(groups, batch * rows, width), start, stop)
            size = self._where[item.nets[0]][2] - self._where[item.nets[0]][1]
            for k, net in enumerate(item.nets):
                block = out[k * size : (k + 1) * size, :, : self.out_features[net]]
                block = self._from_groups(block, batch * item.variants)
                outputs[net] = block if item.variants == 1 else block.unflatten(0, (batch, item.variants))
        return outputs

    def _to_groups(self, x: th.Tensor) -> th.Tensor:
        """(B, [variants,] N, f) -> (groups, B, variants x agents per group, f).

        One group per agent, or one shared group with a one-hot agent id appended.
        """
        batch = x.shape[0]
        x = x.flatten(0, -3)
        if self.share_parameters:
            ids = self.agent_id.expand(x.shape[0], -1, -1)
            return th.cat([x, ids], dim=-1)[None].reshape(1, batch, -1, x.shape[-1] + self.n_agents)
        return x.transpose(0, 1).reshape(self.n_agents, batch, -1, x.shape[-1])

    def _from_groups(self, y: th.Tensor, batch: int) -> th.Tensor:
        """(groups, B * agents per group, outputs) -> (B, N, outputs)."""
        if self.share_parameters:
            return y.reshape(batch, self.n_agents, -1)
        return y.transpose(0, 1)

    def _run(self, features: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
        return self.apply_chains(self.stack_inputs(features))

    def training_inputs(self, obs: PyTorchObs, comm: th.Tensor) -> list[ChainInput]:
        """Stacked inputs of all networks for stored observations and options (no parameters involved).

        :param obs: joint observations (B, N, ...) from before the options
        :param comm: stored options (B, N)
        """
        return self.stack_inputs(
            {
                "mu": self.option_features(obs),
                "q": self._q_features(obs, comm),
                "pi": self.control_features(obs, comm),
            }
        )

    def _q_features(self, obs: PyTorchObs, comm: th.Tensor) -> th.Tensor:
        """The critic's inputs: before the options, or after them for both own options (afterstate)."""
        return self.afterstate_features(obs, comm) if self.critic_reads_afterstate else self.critic_features(obs)

    # ------------------------------------------------------------------ acting
    def forward(
        self,
        obs: PyTorchObs,
        deterministic: bool = False,
        comm: th.Tensor | None = None,
        action_noise_std: float = 0.0,
        deterministic_options: bool | None = None,
        comm_price: th.Tensor | None = None,
    ) -> HybridAction:
        """Sample all options, deliver the broadcasts, then sample all controls (same-step delivery).

        :param obs: joint observation (B, N, ...)
        :param deterministic: mode of ``mu`` and mean of ``pi`` instead of samples
        :param comm: options to use instead of sampling them from ``mu`` (e.g. a baseline's)
        :param action_noise_std: standard deviation of extra Gaussian exploration noise added
            to the sampled controls (curriculum); log-probabilities refer to the noisy controls
        :param deterministic_options: mode (True) or sample (False) of ``mu`` regardless of
            ``deterministic`` (None: as ``deterministic``)
        :param comm_price: cost of a broadcast in the learner's reward units (B, N), see
            :meth:`option_values`
        :return: the hybrid action with its log-probabilities and the option values
        """
        out, comm, control = self._sample(obs, deterministic, comm, action_noise_std, deterministic_options, True)
        log_std = self.log_std.expand(self.n_agents, -1)
        log_prob_comm = F.log_softmax(out["mu"], dim=-1).gather(-1, comm[..., None])[..., 0]
        return HybridAction(
            comm,
            control,
            log_prob_comm,
            gaussian_log_prob(control, out["pi"], log_std),
            self.option_values(out["q"], comm_price, broadcast_probability(out["mu"])),
        )

    def sample_actions(
        self, obs: PyTorchObs, action_noise_std: float = 0.0, comm: th.Tensor | None = None
    ) -> tuple[th.Tensor, th.Tensor]:
        """The options and controls :meth:`forward` samples, without evaluating the critic.

        What a :class:`~sb3_detc.mappoc.workers.RolloutWorker` needs: it draws the same random
        numbers as :meth:`forward`; the learner evaluates probabilities and values later.

        :param obs: joint observation (B, N, ...)
        :param action_noise_std: extra Gaussian noise on the controls (see :meth:`forward`)
        :param comm: options to use instead of sampling them (an option override)
        :return: options (B, N) and controls (B, N, m)
        """
        _, comm, control = self._sample(obs, False, comm, action_noise_std, None, False)
        return comm, control

    def _sample(
        self,
        obs: PyTorchObs,
        deterministic: bool,
        comm: th.Tensor | None,
        action_noise_std: float,
        deterministic_options: bool | None,
        with_critic: bool,
    ) -> tuple[dict[str, th.Tensor], th.Tensor, th.Tensor]:
        """Options, then the broadcasts delivered, then controls; with the networks' outputs.

        :param obs: joint observation (B, N, ...)
        :param deterministic: mode of ``mu`` and mean of ``pi`` instead of samples
        :param comm: options to use instead of sampling them (None: sample)
        :param action_noise_std: extra Gaussian noise on the controls
        :param deterministic_options: mode (True) or sample (False) of ``mu`` (None: as ``deterministic``)
        :param with_critic: whether to evaluate the critic too (output ``q``)
        :return: the outputs of ``mu``, ``pi`` (and ``q``), the options, the controls
        """
        before = {"mu": self.option_features(obs)}
        if with_critic and not self.critic_reads_afterstate:
            before["q"] = self.critic_features(obs)
        out = self._run(before)
        if deterministic_options is None:
            deterministic_options = deterministic
        if comm is None:
            comm = self._sample_options(out["mu"], deterministic_options)
        comm = comm.long()
        after = {"pi": self.control_features(obs, comm)}
        if with_critic and self.critic_reads_afterstate:
            after["q"] = self.afterstate_features(obs, comm)
        out.update(self._run(after))
        mean = out["pi"]
        control = mean
        if not deterministic:
            control = mean + th.randn_like(mean) * self.log_std.expand(self.n_agents, -1).exp()
        if action_noise_std > 0:
            control = control + th.randn_like(mean) * action_noise_std
        return out, comm, control

    @staticmethod
    def _sample_options(logits: th.Tensor, deterministic: bool) -> th.Tensor:
        """Options from the logits of ``mu``: the mode, or a sample (B, N)."""
        if deterministic:
            return logits.argmax(-1)
        p_broadcast = broadcast_probability(logits)
        return (th.rand_like(p_broadcast) < p_broadcast).long()

    def evaluate_actions(
        self,
        obs: PyTorchObs,
        comm: th.Tensor,
        control: th.Tensor,
        comm_price: th.Tensor | None = None,
        p_broadcast: th.Tensor | None = None,
    ) -> HybridEvaluation:
        """Evaluate stored hybrid actions with the current networks (one pass through all chains).

        :param obs: joint observations (B, N, ...) from before the options
        :param comm: stored options (B, N)
        :param control: stored controls (B, N, m)
        :param comm_price: cost of a broadcast in the learner's reward units (B, N), see :meth:`option_values`
        :param p_broadcast: probabilities of broadcasting with which ``comm`` was drawn (B, N),
            see :meth:`option_values` (None: those of the current ``mu``)
        """
        return self.evaluate_inputs(self.training_inputs(obs, comm), comm, control, comm_price, p_broadcast)

    def evaluate_inputs(
        self,
        stacked: list[ChainInput],
        comm: th.Tensor,
        control: th.Tensor,
        comm_price: th.Tensor | None = None,
        p_broadcast: th.Tensor | None = None,
    ) -> HybridEvaluation:
        """Like :meth:`evaluate_actions`, from inputs prepared by :meth:`training_inputs`.

        :param stacked: stacked inputs of the same samples as ``comm`` and ``control``
        :param comm: stored options (B, N)
        :param control: stored controls (B, N, m)
        :param comm_price: cost of a broadcast in the learner's reward units (B, N), see :meth:`option_values`
        :param p_broadcast: probabilities of broadcasting with which ``comm`` was drawn (B, N),
            see :meth:`option_values` (None: those of the current ``mu``)
        """
        out = self.apply_chains(stacked)
        log_p = F.log_softmax(out["mu"], dim=-1)
        log_prob_comm = log_p.gather(-1, comm.long()[..., None])[..., 0]
        entropy = -(log_p.exp() * log_p).sum(-1)
        log_std = self.log_std.expand(self.n_agents, -1)
        control_log_prob = gaussian_log_prob(control, out["pi"], log_std)
        if p_broadcast is None:
            p_broadcast = log_p[..., 1].exp().detach()
        option_values = self.option_values(out["q"], comm_price, p_broadcast)
        return HybridEvaluation(log_prob_comm, entropy, control_log_prob, option_values)

    def state_values(self, obs: PyTorchObs, comm_price: th.Tensor | None = None) -> th.Tensor:
        """Option-value critic averaged under the policy over options, ``V_i(s) = sum_o mu_i(o) Q_i(s, o)``.

        The afterstate critic takes the others' options from one sample of their policies.

        :param obs: joint observation (B, N, ...)
        :param comm_price: cost of a broadcast in the learner's reward units (B, N), see :meth:`option_values`
        :return: values (B, N)
        """
        if self.critic_reads_afterstate:
            out = self._run({"mu": self.option_features(obs)})
            comm = self._sample_options(out["mu"], deterministic=False)
            out["q"] = self._run({"q": self.afterstate_features(obs, comm)})["q"]
        else:
            out = self._run({"mu": self.option_features(obs), "q": self.critic_features(obs)})
        q = self.option_values(out["q"], comm_price, broadcast_probability(out["mu"]))
        return (F.softmax(out["mu"], dim=-1) * q).sum(-1)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        """Options and controls side by side, (B, N, 1 + m); :meth:`predict` returns them as a Dict."""
        action = self.forward(observation, deterministic=deterministic)
        return th.cat([action.comm[..., None].to(action.control.dtype), action.control], dim=-1)

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[dict[str, np.ndarray] | list[dict[str, np.ndarray]], tuple[np.ndarray, ...] | None]:
        """Joint hybrid action(s) for joint observation(s).

        :param observation: one joint observation or a batch of them (from a VecEnv)
        :param state: unused (no recurrent state), returned as is
        :param episode_start: unused
        :param deterministic: mode of ``mu`` and mean of ``pi``
        :return: ``{"comm": (N,), "control": (N, m)}`` for one observation, or a list of
            such dicts, one per environment, for a batch (what a VecEnv's ``step`` takes);
            controls are clipped to the action bounds
        :raises ValueError: for the ``(obs, info)`` tuple of a Gymnasium env's ``reset``
        """
        if isinstance(observation, tuple) and len(observation) == 2 and isinstance(observation[1], dict):
            raise ValueError(
                "predict() got an (obs, info) tuple instead of an observation: you are probably mixing the "
                "Gymnasium API (`obs, info = env.reset()`) with the SB3 VecEnv API (`obs = vec_env.reset()`); "
                "pass `obs` alone."
            )
        self.set_training_mode(False)
        obs_tensor, vectorized = self.obs_to_tensor(observation)
        with th.no_grad():
            joint = self._predict(obs_tensor, deterministic=deterministic)
        comm = joint[..., 0].long().cpu().numpy()
        control = th.clamp(joint[..., 1:], self.control_low, self.control_high).cpu().numpy()
        actions = [{"comm": c, "control": u} for c, u in zip(comm, control, strict=True)]
        return (actions if vectorized else actions[0]), state

    def agent_controller(self, agent: int) -> AgentController:
        """Agent ``agent``'s policy over options and control policy as a small standalone controller.

        :param agent: index of the agent
        :return: a controller that needs only what the agent itself receives
        """
        if not 0 <= agent < self.n_agents:
            raise ValueError(f"agent must be in [0, {self.n_agents}), got {agent}.")
        group = 0 if self.share_parameters else agent
        nets = {}
        for net in ("mu", "pi"):
            chain_idx, start, _ = self._where[net]
            nets[net] = self.chains[chain_idx].extract(start + group)
        return AgentController(
            option_net=nets["mu"],
            control_net=nets["pi"],
            log_std=self.log_std[group].detach().clone(),
            agent=agent,
            n_agents=self.n_agents,
            age_scale=self.age_scale,
            agent_id=self.agent_id[agent].clone() if self.share_parameters else None,
            control_low=self.control_low[agent].clone(),
            control_high=self.control_high[agent].clone(),
        )


class AgentController(nn.Module):
    """One agent's executable policies, fed only with what this agent receives.

    Decentralised execution in two phases per step: :meth:`decide` whether to broadcast
    (from the own trigger features), then, after the step's broadcasts were exchanged,
    :meth:`act` on the own local state and the others' held broadcasts relative to the own
    message, with their ages. The controller keeps no state.

    :param option_net: the agent's ``mu`` network (trigger features -> 2 logits)
    :param control_net: the agent's ``pi`` mean network
    :param log_std: log standard deviation of the control policy (m,)
    :param agent: index of the agent
    :param n_agents: number of agents N
    :param age_scale: factor applied to ages before they enter the network
    :param agent_id: one-hot id input for shared-parameter policies, else None
    :param control_low: lower control bounds (m,)
    :param control_high: upper control bounds (m,)
    """

    def __init__(
        self,
        option_net: nn.Module,
        control_net: nn.Module,
        log_std: th.Tensor,
        agent: int,
        n_agents: int,
        age_scale: float,
        agent_id: th.Tensor | None,
        control_low: th.Tensor,
        control_high: th.Tensor,
    ) -> None:
        super().__init__()
        self.option_net = option_net
        self.control_net = control_net
        self.agent = agent
        self.n_agents = n_agents
        self.age_scale = age_scale
        self.register_buffer("log_std", log_std)
        self.register_buffer("agent_id", agent_id if agent_id is not None else th.zeros(0))
        self.register_buffer("control_low", control_low)
        self.register_buffer("control_high", control_high)

    def _with_id(self, x: th.Tensor) -> th.Tensor:
        return th.cat([x, self.agent_id.to(x.dtype)])

    @th.no_grad()
    def decide(self, trigger: np.ndarray, trigger_held: np.ndarray, deterministic: bool = True) -> bool:
        """Whether to broadcast now.

        :param trigger: own trigger features now (n_trig,)
        :param trigger_held: own trigger features at the own last broadcast (n_trig,)
        :param deterministic: the most likely option instead of a sample
        """
        x = th.as_tensor(np.concatenate([trigger, trigger_held]), dtype=th.float32)
        logits = self.option_net(self._with_id(x))
        if deterministic:
            return bool(logits.argmax() == 1)
        return bool(th.distributions.Categorical(logits=logits).sample() == 1)

    @th.no_grad()
    def act(
        self, local: np.ndarray, neighbours: np.ndarray, neighbour_age: np.ndarray, deterministic: bool = True
    ) -> np.ndarray:
        """Control from the own state and the others' held broadcasts after this step's exchange.

        :param local: own local state (n_local,)
        :param neighbours: the others' held broadcasts minus the own current message (N - 1, n_msg)
        :param neighbour_age: the others' ages of information in steps (N - 1,)
        :param deterministic: the mean control instead of a sample
        :return: control (m,), clipped to the bounds
        """
        x = np.concatenate([local, np.ravel(neighbours), np.asarray(neighbour_age) * self.age_scale])
        mean = self.control_net(self._with_id(th.as_tensor(x, dtype=th.float32)))
        control = mean if deterministic else mean + th.randn_like(mean) * self.log_std.exp()
        return th.clamp(control, self.control_low, self.control_high).numpy()


def check_joint_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> tuple[int, int]:
    """Check that the spaces are those of a joint event-triggered env.

    :param observation_space: observation space to check
    :param action_space: action space to check
    :return: number of agents N and control dimension m
    :raises ValueError: naming what does not fit
    """
    hint = "use an env from sb3_detc (e.g. 'sb3_detc/LinearETC-v0') or wrap a system in JointEnv"
    if not isinstance(observation_space, spaces.Dict) or set(observation_space.spaces) != set(JOINT_KEYS):
        keys = sorted(observation_space.spaces) if isinstance(observation_space, spaces.Dict) else observation_space
        raise ValueError(f"expected a Dict observation space with keys {sorted(JOINT_KEYS)}, got {keys}; {hint}.")
    if (
        not isinstance(action_space, spaces.Dict)
        or set(action_space.spaces) != {"comm", "control"}
        or not isinstance(action_space["comm"], spaces.MultiDiscrete)
        or not isinstance(action_space["control"], spaces.Box)
    ):
        raise ValueError(
            f"expected a Dict action space with 'comm' (MultiDiscrete) and 'control' (Box), got {action_space}; {hint}."
        )
    n_agents = len(action_space["comm"].nvec)
    if not np.all(action_space["comm"].nvec == 2):
        raise ValueError(f"'comm' must be MultiDiscrete([2] * N), got nvec {action_space['comm'].nvec}.")
    control = action_space["control"]
    if control.shape[0] != n_agents or len(control.shape) != 2:
        raise ValueError(f"'control' must have shape (N={n_agents}, m), got {control.shape}.")
    for key, space in observation_space.spaces.items():
        if not isinstance(space, spaces.Box) or len(space.shape) != 2 or space.shape[0] != n_agents:
            raise ValueError(f"observation '{key}' must be a Box of shape (N={n_agents}, features), got {space}.")
    if observation_space["age"].shape[1] != 1:
        raise ValueError(f"observation 'age' must have shape (N, 1), got {observation_space['age'].shape}.")
    return n_agents, control.shape[1]
