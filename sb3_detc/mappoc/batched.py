"""Agent-batched MLPs: the networks of all agents evaluated together, one batched matmul per layer.

A :class:`BatchedMLP` holds independent MLPs of one hidden architecture as weights shaped
(groups, in, out). :class:`AgentBatchedNetworks` packs several named per-agent networks
(e.g. a policy's ``mu``, ``q`` and ``pi``) into as few such chains as their architectures
allow: networks with the same hidden layers share one chain, each agent's copy of a network
is one group of it (or one group for all agents, with a one-hot agent id input, when the
agents share parameters). Where a network lives, its per-agent parameters and a standalone
copy of one agent's network are its public seam; the chains' layout stays inside.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import torch as th
from torch import nn
from torch.nn import functional as F


class BatchedMLP(nn.Module):
    """Independent MLPs of one hidden architecture, evaluated together with one ``baddbmm`` per layer.

    Group ``g`` reads the first ``in_features[g]`` input columns and writes the first
    ``out_features[g]`` output columns; the rest is zero padding whose weights stay zero
    (their gradients are zero).

    :param in_features: input width of every group
    :param out_features: output width of every group
    :param hidden: hidden layer sizes (common to all groups)
    :param activation_fn: activation class applied after every hidden layer
    :param output_gains: orthogonal-init gain of every group's output layer (the hidden layers': sqrt(2))
    """

    def __init__(
        self,
        in_features: Sequence[int],
        out_features: Sequence[int],
        hidden: Sequence[int],
        activation_fn: type[nn.Module],
        output_gains: Sequence[float],
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
                gain = output_gains[g] if layer == n_layers - 1 else math.sqrt(2)  # as SB3's hidden layers
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


class NetSpec(NamedTuple):
    """Shape of one per-agent network.

    :param in_features: input width, without the one-hot agent id of shared parameters
    :param out_features: output width
    :param hidden: hidden layer sizes
    :param gain: orthogonal-init gain of the output layer
    """

    in_features: int
    out_features: int
    hidden: tuple[int, ...]
    gain: float


class NetLocation(NamedTuple):
    """Where a network lives: its groups ``start:stop`` of chain ``chain``.

    :param chain: index of the chain (a :class:`BatchedMLP` of :class:`AgentBatchedNetworks`)
    :param start: the network's first group in the chain
    :param stop: one past its last group
    """

    chain: int
    start: int
    stop: int


class ChainInput(NamedTuple):
    """Inputs of some networks of one batched chain, stacked: (groups, B, variants x agents per group, width).

    ``variants`` > 1 evaluates every network on several inputs per sample (the afterstate
    critic's two own options).

    :param chain: index of the chain
    :param nets: consecutive networks of the chain these inputs feed, in chain order
    :param x: the inputs, shaped (groups, B, variants x agents per group, width), zero-padded to the chain's
        input width; the groups of ``nets`` one after the other
    :param variants: inputs per sample
    """

    chain: int
    nets: tuple[str, ...]
    x: th.Tensor
    variants: int = 1

    def select(self, idx: th.Tensor) -> ChainInput:
        """The same inputs for the samples ``idx`` of the batch axis.

        :param idx: indices of the samples to keep (1-D), into the batch axis B
        :return: the same chain, networks and variants, ``x`` shaped
            (groups, len(idx), variants x agents per group, width)
        """
        return ChainInput(self.chain, self.nets, self.x[:, idx], self.variants)


def _variants(features: th.Tensor) -> int:
    """Inputs per sample of a network's features: (B, N, f) -> 1, (B, variants, N, f) -> variants.

    :param features: the network's features, (B, N, f) or (B, variants, N, f)
    :return: the number of variants
    """
    return features.shape[1] if features.dim() == 4 else 1


class AgentBatchedNetworks(nn.ModuleList):
    """Named per-agent networks packed into batched chains (a list of :class:`BatchedMLP`).

    Networks with the same hidden layers share one chain, in the order of ``specs``; each
    network takes one group per agent, or one group for all agents (with a one-hot agent id
    appended to its inputs) when they share parameters. Features and outputs are shaped
    (B, N, features), or (B, variants, N, features) for several inputs per sample.

    :param specs: shape of every network, by name, in chain order
    :param n_agents: number of agents N
    :param share_parameters: one group per network for all agents instead of one per agent
    :param activation_fn: activation class of the hidden layers
    :param ortho_init: orthogonal initialisation with the gains of ``specs`` (otherwise every
        weight is drawn from a normal distribution with standard deviation 1 / sqrt(fan in))
    """

    def __init__(
        self,
        specs: Mapping[str, NetSpec],
        n_agents: int,
        share_parameters: bool,
        activation_fn: type[nn.Module],
        ortho_init: bool = True,
    ) -> None:
        super().__init__()
        self.specs = dict(specs)
        self.n_agents = n_agents
        self.share_parameters = share_parameters
        self.register_buffer("agent_id", th.eye(n_agents), persistent=False)
        groups = 1 if share_parameters else n_agents
        n_id = n_agents if share_parameters else 0
        by_hidden: dict[tuple[int, ...], list[str]] = {}
        for net, spec in self.specs.items():
            by_hidden.setdefault(tuple(spec.hidden), []).append(net)
        self._locations: dict[str, NetLocation] = {}
        for hidden, nets in by_hidden.items():
            ins, outs, gains = [], [], []
            for net in nets:
                spec = self.specs[net]
                self._locations[net] = NetLocation(len(self), len(ins), len(ins) + groups)
                ins += [spec.in_features + n_id] * groups
                outs += [spec.out_features] * groups
                gains += [spec.gain if ortho_init else 1.0] * groups
            chain = BatchedMLP(ins, outs, hidden, activation_fn, gains)
            if not ortho_init:
                for weight in chain.weights:
                    nn.init.normal_(weight, std=1.0 / math.sqrt(weight.shape[1]))
            self.append(chain)

    def location(self, net: str) -> NetLocation:
        """Where network ``net`` lives: its chain and its groups there.

        :param net: name of the network
        :return: its :class:`NetLocation`
        """
        return self._locations[net]

    def agent_weights(self, net: str) -> list[th.Tensor]:
        """Every group's weights of network ``net``, one (groups, in, out) view per layer.

        :param net: name of the network
        :return: detached views (writing into them changes the network)
        """
        chain, start, stop = self._locations[net]
        return [weight.detach()[start:stop] for weight in self[chain].weights]

    def agent_biases(self, net: str) -> list[th.Tensor]:
        """Every group's biases of network ``net``, one (groups, 1, out) view per layer.

        :param net: name of the network
        :return: detached views (writing into them changes the network)
        """
        chain, start, stop = self._locations[net]
        return [bias.detach()[start:stop] for bias in self[chain].biases]

    def extract(self, net: str, group: int) -> nn.Sequential:
        """A standalone copy of one group of network ``net`` (see :meth:`BatchedMLP.extract`).

        :param net: name of the network
        :param group: the agent's index, or 0 with shared parameters
        :return: the network, made of ``nn.Linear`` layers; with shared parameters it expects
            the one-hot agent id after the features
        """
        chain, start, _ = self._locations[net]
        return self[chain].extract(start + group)

    def stack(self, features: Mapping[str, th.Tensor]) -> list[ChainInput]:
        """Arrange per-network features for the batched chains.

        The result depends on no parameter, so training computes it once per rollout and
        only indexes it (:meth:`ChainInput.select`) for every minibatch.

        :param features: inputs of some of the networks, each (B, N, features) or, for several
            inputs per sample, (B, variants, N, features)
        :return: one :class:`ChainInput` per run of consecutive networks of a chain with the
            same number of variants
        """
        stacked = []
        for c, chain in enumerate(self):
            width = max(chain.in_features)
            run: list[str] = []
            for net in (*(net for net, where in self._locations.items() if where.chain == c), None):
                variants = _variants(features[net]) if net in features else 0
                if run and (variants != _variants(features[run[0]])):
                    grouped = [self._to_groups(features[name]) for name in run]
                    x = th.cat([F.pad(g, (0, width - g.shape[-1])) for g in grouped])
                    stacked.append(ChainInput(c, tuple(run), x, _variants(features[run[0]])))
                    run = []
                if variants:
                    run.append(net)
        return stacked

    def evaluate(self, stacked: Sequence[ChainInput]) -> dict[str, th.Tensor]:
        """Evaluate the networks of all agents on stacked inputs.

        :param stacked: inputs from :meth:`stack` (possibly indexed by :meth:`ChainInput.select`)
        :return: outputs of every network in ``stacked``, each (B, N, outputs), or
            (B, variants, N, outputs) for inputs with variants
        """
        outputs: dict[str, th.Tensor] = {}
        for item in stacked:
            groups, batch, rows, width = item.x.shape
            first, last = self._locations[item.nets[0]], self._locations[item.nets[-1]]
            out = self[item.chain](item.x.reshape(groups, batch * rows, width), first.start, last.stop)
            size = first.stop - first.start
            for k, net in enumerate(item.nets):
                block = out[k * size : (k + 1) * size, :, : self.specs[net].out_features]
                block = self._from_groups(block, batch * item.variants)
                outputs[net] = block if item.variants == 1 else block.unflatten(0, (batch, item.variants))
        return outputs

    def run(self, features: Mapping[str, th.Tensor]) -> dict[str, th.Tensor]:
        """Evaluate some networks of all agents on their features: :meth:`evaluate` of :meth:`stack`.

        :param features: see :meth:`stack`
        :return: see :meth:`evaluate`
        """
        return self.evaluate(self.stack(features))

    def _to_groups(self, x: th.Tensor) -> th.Tensor:
        """(B, [variants,] N, f) -> (groups, B, variants x agents per group, f).

        One group per agent, or one shared group with a one-hot agent id appended.

        :param x: one network's features, (B, N, f) or (B, variants, N, f)
        :return: (N, B, variants, f), or (1, B, variants x N, f + N) with shared parameters
        """
        batch = x.shape[0]
        x = x.flatten(0, -3)
        if self.share_parameters:
            ids = self.agent_id.expand(x.shape[0], -1, -1)
            return th.cat([x, ids], dim=-1)[None].reshape(1, batch, -1, x.shape[-1] + self.n_agents)
        return x.transpose(0, 1).reshape(self.n_agents, batch, -1, x.shape[-1])

    def _from_groups(self, y: th.Tensor, batch: int) -> th.Tensor:
        """(groups, B * agents per group, outputs) -> (B, N, outputs).

        :param y: one network's outputs of all groups, (groups, B * agents per group, outputs)
        :param batch: samples B (times the variants, which then form part of the first axis);
            read only with shared parameters
        :return: the outputs by agent, (B, N, outputs)
        """
        if self.share_parameters:
            return y.reshape(batch, self.n_agents, -1)
        return y.transpose(0, 1)
