"""Agent-batched networks (sb3_detc.mappoc.batched): the public seam, and the policy's parameter names."""

from __future__ import annotations

from typing import Any

import pytest
import torch as th

from sb3_detc.envs import linear_etc_v0
from sb3_detc.mappoc import MlpHybridPolicy
from sb3_detc.mappoc.batched import AgentBatchedNetworks, NetLocation, NetSpec

SPECS = {
    "a": NetSpec(in_features=3, out_features=2, hidden=(8,), gain=0.01),
    "b": NetSpec(in_features=5, out_features=1, hidden=(6, 6), gain=1.0),
    "c": NetSpec(in_features=4, out_features=3, hidden=(8,), gain=0.01),
}


def networks(share: bool, n_agents: int = 3) -> AgentBatchedNetworks:
    th.manual_seed(0)
    return AgentBatchedNetworks(SPECS, n_agents, share, th.nn.Tanh)


@pytest.mark.parametrize("share", [False, True])
def test_networks_of_one_hidden_architecture_share_a_chain(share: bool) -> None:
    nets = networks(share)
    groups = 1 if share else 3
    assert len(nets) == 2
    assert nets.location("a") == NetLocation(0, 0, groups)
    assert nets.location("c") == NetLocation(0, groups, 2 * groups)
    assert nets.location("b") == NetLocation(1, 0, groups)
    id_width = 3 if share else 0
    assert nets[0].in_features == [3 + id_width] * groups + [4 + id_width] * groups
    for name, spec in SPECS.items():
        weights, biases = nets.agent_weights(name), nets.agent_biases(name)
        assert len(weights) == len(biases) == len(spec.hidden) + 1
        assert all(w.shape[0] == groups and b.shape[0] == groups for w, b in zip(weights, biases, strict=True))


def test_parameter_views_write_into_the_chain() -> None:
    nets = networks(share=False)
    chain, start, stop = nets.location("c")
    nets.agent_weights("c")[-1].fill_(0.5)
    nets.agent_biases("c")[0][1].fill_(-1.0)
    assert th.all(nets[chain].weights[-1][start:stop] == 0.5)
    assert th.all(nets[chain].biases[0][start + 1] == -1.0)
    assert not th.any(nets[chain].weights[-1][:start] == 0.5)  # network "a" untouched


@pytest.mark.parametrize("share", [False, True])
def test_run_matches_each_agents_extracted_network(share: bool) -> None:
    nets = networks(share)
    with th.no_grad():  # non-zero biases so that they are checked too
        for chain in nets:
            for bias in chain.biases:
                bias.normal_()
    gen = th.Generator().manual_seed(1)
    features = {
        "a": th.randn(4, 3, 3, generator=gen),  # (B, N, f)
        "b": th.randn(4, 2, 3, 5, generator=gen),  # two variants per sample: (B, variants, N, f)
        "c": th.randn(4, 3, 4, generator=gen),
    }
    with th.no_grad():
        outputs = nets.run(features)
        for name, x in features.items():
            assert outputs[name].shape == (*x.shape[:-1], SPECS[name].out_features)
            for i in range(3):
                xi = x[..., i, :]
                if share:
                    xi = th.cat([xi, th.eye(3)[i].expand(*xi.shape[:-1], -1)], dim=-1)
                expected = nets.extract(name, 0 if share else i)(xi)
                th.testing.assert_close(outputs[name][..., i, :], expected)


# ------------------------------------------------------------------ saved policies still load
#: Parameter names and shapes of MlpHybridPolicy on the linear env with 3 agents, as saved before
#: the batched networks became their own module (commit e74bc84): checkpoints of running studies load.
SAVED_SHAPES = {
    ("afterstate", False, "dict"): {
        "log_std": (3, 1),
        "chains.0.weights.0": (6, 8, 8),
        "chains.0.weights.1": (6, 8, 2),
        "chains.0.biases.0": (6, 1, 8),
        "chains.0.biases.1": (6, 1, 2),
        "chains.1.weights.0": (3, 15, 16),
        "chains.1.weights.1": (3, 16, 16),
        "chains.1.weights.2": (3, 16, 1),
        "chains.1.biases.0": (3, 1, 16),
        "chains.1.biases.1": (3, 1, 16),
        "chains.1.biases.2": (3, 1, 1),
    },
    ("centred", True, "list"): {
        "log_std": (1, 1),
        "chains.0.weights.0": (3, 18, 16),
        "chains.0.weights.1": (3, 16, 16),
        "chains.0.weights.2": (3, 16, 2),
        "chains.0.biases.0": (3, 1, 16),
        "chains.0.biases.1": (3, 1, 16),
        "chains.0.biases.2": (3, 1, 2),
    },
}
ARCHS: dict[str, Any] = {"list": [16, 16], "dict": {"mu": [8], "q": [16, 16], "pi": [8]}}


@pytest.mark.parametrize(("critic", "share", "arch"), list(SAVED_SHAPES))
def test_policy_parameter_names_are_those_of_saved_policies(critic: str, share: bool, arch: str) -> None:
    env = linear_etc_v0.joint_env(n_agents=3)
    policy = MlpHybridPolicy(
        env.observation_space, env.action_space, net_arch=ARCHS[arch], share_parameters=share, critic=critic
    )
    state = policy.state_dict()
    assert {name: tuple(value.shape) for name, value in state.items()} == SAVED_SHAPES[(critic, share, arch)]
    assert list(state) == list(SAVED_SHAPES[(critic, share, arch)])  # the order too
    policy.load_state_dict({name: th.zeros(shape) for name, shape in SAVED_SHAPES[(critic, share, arch)].items()})
