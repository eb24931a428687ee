"""Option-value critics (sb3_detc.mappoc.critics): the registry, each critic's option values, a new critic."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th

from sb3_detc.envs import linear_etc_v0
from sb3_detc.mappoc import MlpHybridPolicy, critics
from sb3_detc.mappoc.critics import CRITICS, AfterstateCritic, CentredCritic, OptionCritic, OptionHeadsCritic

B, N = 7, 3


def make_policy(critic: str, n_agents: int = N, **kwargs: Any) -> MlpHybridPolicy:
    th.manual_seed(0)
    env = linear_etc_v0.joint_env(n_agents=n_agents)
    return MlpHybridPolicy(
        env.observation_space, env.action_space, lambda _: 1e-3, net_arch=[16, 16], critic=critic, **kwargs
    )


def joint_obs(n_agents: int = N, steps: int = B) -> dict[str, th.Tensor]:
    """Joint observations (steps, N, ...) under random options and controls (no episode ends within 100 steps)."""
    env = linear_etc_v0.joint_env(n_agents=n_agents)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    visited = []
    for _ in range(steps):
        visited.append(obs)
        action = {
            "broadcast": rng.integers(0, 2, n_agents),
            "control": rng.uniform(-1, 1, (n_agents, 1)).astype(np.float32),
        }
        obs, *_ = env.step(action)
    return {key: th.as_tensor(np.stack([o[key] for o in visited])) for key in visited[0]}


def randn(*shape: int, seed: int) -> th.Tensor:
    return th.randn(*shape, generator=th.Generator().manual_seed(seed))


PRICE = th.rand(B, N, generator=th.Generator().manual_seed(1))
P_BROADCAST = th.rand(B, N, generator=th.Generator().manual_seed(2))


# ------------------------------------------------------------------ registry
def test_registry_lists_the_three_critics_by_name() -> None:
    assert list(CRITICS) == ["option_heads", "afterstate", "centred"]
    assert CRITICS == {"option_heads": OptionHeadsCritic, "afterstate": AfterstateCritic, "centred": CentredCritic}
    for name, critic in CRITICS.items():
        assert critic.name == name and issubclass(critic, OptionCritic)
    # what the policy and MAPPOC read from them
    flags = {
        name: (c.outputs, c.reads_afterstate, c.needs_price, c.needs_draw_probabilities) for name, c in CRITICS.items()
    }
    assert flags == {
        "option_heads": (2, False, False, False),
        "afterstate": (1, True, True, False),
        "centred": (2, False, True, True),
    }


@pytest.mark.parametrize("name", list(CRITICS))
def test_policy_holds_the_named_critic(name: str) -> None:
    policy = make_policy(name)
    assert policy.critic == name  # the constructor parameter, saved with the policy
    assert type(policy.option_critic) is CRITICS[name]
    obs, broadcast = joint_obs(), th.zeros(B, N, dtype=th.int64)
    q = policy.chains.run({"q": policy.critic_inputs(obs, broadcast)})["q"]  # the inputs the critic reads
    assert q.shape[-1] == CRITICS[name].outputs
    assert q.shape[:-1] == ((B, 2, N) if CRITICS[name].reads_afterstate else (B, N))


def test_a_critic_that_reads_the_afterstates_needs_the_options() -> None:
    policy = make_policy("afterstate")
    with pytest.raises(ValueError, match="afterstate critic reads this step's options"):
        policy.critic_inputs(joint_obs())


def test_the_critics_do_not_import_the_policy() -> None:
    """The policy builds the inputs of the critic it holds: the critics import nothing of the package.

    The package's ``__init__`` imports the policy (its public API), so the fresh interpreter
    imports the critics under empty parent packages; the source is checked too, type-checking
    imports included.
    """
    source = Path(critics.__file__)
    parents = {"sb3_detc": str(source.parents[1]), "sb3_detc.mappoc": str(source.parent)}
    script = (
        "import sys, types\n"
        f"for name, path in {parents!r}.items():\n"
        "    package = sys.modules[name] = types.ModuleType(name)\n"
        "    package.__path__ = [path]\n"
        "import sb3_detc.mappoc.critics\n"
        "print(sorted(name for name in sys.modules if name.startswith('sb3_detc')))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "['sb3_detc', 'sb3_detc.mappoc', 'sb3_detc.mappoc.critics']"
    imported = set()
    for node in ast.walk(ast.parse(source.read_text())):
        if isinstance(node, ast.Import):
            imported.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            imported.add(node.module)
    assert imported == {"__future__", "typing", "torch"}


def test_unknown_critic_names_the_known_ones() -> None:
    with pytest.raises(ValueError, match="option_heads.*afterstate.*centred.*'best'"):
        make_policy("best")


# ------------------------------------------------------------------ option values: the formulas
def test_option_heads_are_the_option_values() -> None:
    q = randn(B, N, 2, seed=3)
    critic = OptionHeadsCritic()
    th.testing.assert_close(critic.option_values(q), q)
    th.testing.assert_close(critic.option_values(q, PRICE, P_BROADCAST), q)  # the heads learn the price


def test_afterstate_values_minus_the_price_of_the_own_broadcast() -> None:
    """Q_i(s, o) = W_i(after(s, o)) - o price_i, from W of both own options (B, 2, N, 1)."""
    w = randn(B, 2, N, 1, seed=4)
    critic = AfterstateCritic()
    q = critic.option_values(w, PRICE)
    assert q.shape == (B, N, 2)
    th.testing.assert_close(q[..., 0], w[:, 0, :, 0])
    th.testing.assert_close(q[..., 1], w[:, 1, :, 0] - PRICE)
    th.testing.assert_close(critic.option_values(w)[..., 1], w[:, 1, :, 0])  # no price: zero


def test_centred_values_around_the_state_value() -> None:
    """Q_i(s, o) = V_i + (o - p_i)(D_i - price_i): mean V under the drawing probabilities, gap D - price."""
    q = randn(B, N, 2, seed=5)
    value, gap = q.unbind(-1)
    critic = CentredCritic()
    values = critic.option_values(q, PRICE, P_BROADCAST)
    for o in (0, 1):
        th.testing.assert_close(values[..., o], value + (o - P_BROADCAST) * (gap - PRICE))
    th.testing.assert_close(values[..., 1] - values[..., 0], gap - PRICE)
    th.testing.assert_close(P_BROADCAST * values[..., 1] + (1 - P_BROADCAST) * values[..., 0], value)
    with pytest.raises(ValueError, match="p_broadcast"):
        critic.option_values(q, PRICE)


@pytest.mark.parametrize("name", list(CRITICS))
def test_policy_option_values_delegate_to_its_critic(name: str) -> None:
    policy = make_policy(name)
    q = randn(B, 2, N, 1, seed=6) if CRITICS[name].reads_afterstate else randn(B, N, 2, seed=6)
    th.testing.assert_close(
        policy.option_values(q, PRICE, P_BROADCAST), CRITICS[name]().option_values(q, PRICE, P_BROADCAST)
    )


# ------------------------------------------------------------------ a fourth critic
class StateValueCritic(OptionCritic):
    """One output on the state before the options, the same value for both options (no broadcast gap)."""

    name = "state_value"
    outputs = 1
    needs_price = False

    def _option_values(self, q: th.Tensor, price: th.Tensor | float, p_broadcast: th.Tensor | None) -> th.Tensor:
        return q.expand(*q.shape[:-1], 2)


def test_a_registered_critic_is_usable_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(CRITICS, StateValueCritic.name, StateValueCritic)
    policy = make_policy("state_value", share_parameters=True)
    assert isinstance(policy.option_critic, StateValueCritic)
    assert policy.critic == "state_value"
    obs = joint_obs()
    broadcast = th.as_tensor(np.random.default_rng(3).integers(0, 2, (B, N)))
    with th.no_grad():
        value = policy.chains.run({"q": policy.critic_inputs(obs)})["q"][..., 0]
        action = policy(obs)
        evaluation = policy.evaluate_actions(obs, broadcast, action.control)
        state_values = policy.state_values(obs)
    th.testing.assert_close(action.option_values, value[..., None].expand(-1, -1, 2))
    th.testing.assert_close(evaluation.option_values, action.option_values)
    th.testing.assert_close(state_values, value)
