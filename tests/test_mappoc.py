"""MAPPOC: hybrid policies, rollout buffer, rollouts, updates and persistence (sb3_detc.mappoc)."""

from __future__ import annotations

import copy
import math
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import DummyVecEnv

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.callbacks import RandomSkipCallback
from sb3_detc.envs import linear_etc_v0
from sb3_detc.envs.wrappers import JointEnv
from sb3_detc.mappoc import MAPPOC, HybridRolloutBuffer, MlpHybridPolicy
from sb3_detc.mappoc import steps as steps_module
from sb3_detc.mappoc.batched import BatchedMLP
from sb3_detc.mappoc.critics import CRITICS
from sb3_detc.mappoc.losses import UpdateInputs, broadcast_gap_scale, clipped_surrogate_loss, greedy_broadcast_advantage
from sb3_detc.mappoc.policies import NETS
from sb3_detc.mappoc.steps import FusedGradientStep, GradientStep
from sb3_detc.triggers import RandomTrigger

ENV_ID = "sb3_detc/LinearETC-v0"
TINY = {"net_arch": [16, 16]}
CONFIGS = [(n, share) for n in (2, 3, 5) for share in (False, True)]


# --------------------------------------------------------------------------- helpers
def make_policy(env: JointEnv, seed: int = 0, **kwargs: Any) -> MlpHybridPolicy:
    th.manual_seed(seed)
    kwargs = {**TINY, **kwargs}
    return MlpHybridPolicy(env.observation_space, env.action_space, lambda _: 1e-3, **kwargs)


def joint_obs_batch(env: JointEnv, steps: int = 12, seed: int = 0) -> dict[str, th.Tensor]:
    """Joint observations (steps, N, ...) visited under random options and controls."""
    n = env.n_agents
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    visited = []
    for _ in range(steps):
        visited.append(obs)
        action = {"broadcast": rng.integers(0, 2, n), "control": rng.uniform(-1, 1, (n, 1)).astype(np.float32)}
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            obs, _ = env.reset()
    return {key: th.as_tensor(np.stack([o[key] for o in visited])) for key in visited[0]}


def random_options(steps: int, n_agents: int, seed: int) -> th.Tensor:
    """Options (steps, N) drawn uniformly at random."""
    return th.as_tensor(np.random.default_rng(seed).integers(0, 2, (steps, n_agents)))


def make_model(
    n_agents: int = 2,
    n_envs: int = 1,
    max_cycles: int = 20,
    seed: int | None = 0,
    env_kwargs: dict[str, Any] | None = None,
    policy_kwargs: dict[str, Any] | None = None,
    **kwargs: Any,
) -> MAPPOC:
    env = make_vec_env(
        ENV_ID, n_envs=n_envs, env_kwargs={"n_agents": n_agents, "max_cycles": max_cycles, **(env_kwargs or {})}
    )
    kwargs = {"n_steps": 16, "batch_size": 16, "n_epochs": 2, "learning_rate": 1e-3, **kwargs}
    return MAPPOC("MlpHybridPolicy", env, seed=seed, policy_kwargs={**TINY, **(policy_kwargs or {})}, **kwargs)


def parameters(model_or_policy: Any) -> dict[str, th.Tensor]:
    policy = getattr(model_or_policy, "policy", model_or_policy)
    return {name: p.detach().clone() for name, p in policy.state_dict().items()}


def net_slices(policy: MlpHybridPolicy, net: str) -> list[th.Tensor]:
    """Copies of all parameters of one network (all its groups)."""
    return [view.clone() for view in policy.net_parameters(net)]


def assert_padding_is_zero(policy: MlpHybridPolicy) -> None:
    for chain in policy.chains:
        first, last, last_bias = chain.weights[0], chain.weights[-1], chain.biases[-1]
        for g, (n_in, n_out) in enumerate(zip(chain.in_features, chain.out_features, strict=True)):
            assert th.all(first[g, n_in:, :] == 0)
            assert th.all(last[g, :, n_out:] == 0)
            assert th.all(last_bias[g, :, n_out:] == 0)


# ------------------------------------------------------------------ 1. shapes, sharing
@pytest.mark.parametrize("policy_samples", [False, True])
@pytest.mark.parametrize("critic", CRITICS)
@pytest.mark.parametrize(
    "modes",
    [
        {},
        {"deterministic": True},
        {"deterministic": True, "sample_options": True},
        {"sample_options": False},
    ],
)
def test_sample_actions_draws_what_forward_draws_in_every_mode(
    critic: str, modes: dict[str, bool], policy_samples: bool
) -> None:
    env = linear_etc_v0.joint_env(n_agents=3, max_cycles=50)
    policy = make_policy(env, critic=critic, sample_options=policy_samples)
    obs = joint_obs_batch(env, steps=64)
    with th.no_grad():
        th.manual_seed(5)
        action = policy(obs, **modes)
        th.manual_seed(5)
        broadcast, control = policy.sample_actions(obs, **modes)
        th.manual_seed(6)
        again, _ = policy.sample_actions(obs, **modes)
    assert th.equal(broadcast, action.broadcast)
    th.testing.assert_close(control, action.control)
    # Not given: the mode if deterministic, whatever the policy's setting (it is the evaluation protocol's)
    sampled = modes.get("sample_options", not modes.get("deterministic", False))
    assert th.equal(again, broadcast) != sampled  # modes repeat, 64 x 3 samples do not


@pytest.mark.parametrize("critic", CRITICS)
@pytest.mark.parametrize(("n_agents", "share"), CONFIGS)
def test_forward_and_evaluate_shapes(n_agents: int, share: bool, critic: str) -> None:
    env = linear_etc_v0.joint_env(n_agents=n_agents, max_cycles=50)
    policy = make_policy(env, share_parameters=share, critic=critic)
    obs = joint_obs_batch(env, steps=7)
    b, n = 7, n_agents
    with th.no_grad():
        action = policy(obs)
    assert action.broadcast.shape == (b, n) and action.broadcast.dtype == th.int64
    assert th.all((action.broadcast == 0) | (action.broadcast == 1))
    assert action.control.shape == (b, n, 1)
    assert action.log_prob_broadcast.shape == (b, n) and action.log_prob_control.shape == (b, n)
    assert th.all(action.log_prob_broadcast <= 0)
    assert action.option_values.shape == (b, n, 2)

    broadcast = th.as_tensor(np.random.default_rng(1).integers(0, 2, (b, n)))
    with th.no_grad():
        ev = policy.evaluate_actions(obs, broadcast, action.control)
    assert ev.log_prob_broadcast.shape == (b, n) and ev.entropy_broadcast.shape == (b, n)
    assert ev.log_prob_control.shape == (b, n) and ev.option_values.shape == (b, n, 2)
    assert th.all(ev.entropy_broadcast >= 0) and th.all(ev.entropy_broadcast <= math.log(2) + 1e-6)
    assert policy.state_values(obs).shape == (b, n)
    # Evaluating the sampled options gives back the sampling log-probabilities.
    with th.no_grad():
        ev_own = policy.evaluate_actions(obs, action.broadcast, action.control)
    th.testing.assert_close(ev_own.log_prob_broadcast, action.log_prob_broadcast)
    th.testing.assert_close(ev_own.log_prob_control, action.log_prob_control)
    th.testing.assert_close(ev_own.option_values, action.option_values)


@pytest.mark.parametrize(("n_agents", "share"), CONFIGS)
def test_predict_and_tiny_learn(n_agents: int, share: bool) -> None:
    u_max = 0.1  # far below the policy's standard deviation: sampled controls must be clipped
    model = make_model(n_agents, n_envs=2, env_kwargs={"u_max": u_max}, share_parameters=share)
    assert model.policy.share_parameters is share
    obs = model.env.reset()

    actions, state = model.predict(obs)
    assert state is None
    assert isinstance(actions, list) and len(actions) == 2
    controls = []
    for action in actions:
        assert set(action) == {"broadcast", "control"}
        assert action["broadcast"].shape == (n_agents,)
        assert set(np.unique(action["broadcast"])) <= {0, 1}
        assert action["control"].shape == (n_agents, 1)
        controls.append(action["control"])
    controls = np.concatenate(controls)
    assert np.all(np.abs(controls) <= np.float32(u_max))
    assert np.any(np.abs(controls) == np.float32(u_max))  # clipping happened

    single = {key: value[1] for key, value in obs.items()}
    # deterministic: the mode of mu, the same options for a single and a batched call
    action, _ = model.predict(single, deterministic=True)
    assert isinstance(action, dict)
    assert action["broadcast"].shape == (n_agents,) and action["control"].shape == (n_agents, 1)
    # The single observation gives what the batch gives for the same env.
    batch_actions, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(action["broadcast"], batch_actions[1]["broadcast"])
    np.testing.assert_allclose(action["control"], batch_actions[1]["control"], rtol=1e-5, atol=1e-7)

    before = parameters(model)
    model.learn(32)
    assert model.num_timesteps == 32
    after = parameters(model)
    assert any(not th.equal(before[k], after[k]) for k in before)
    assert all(th.all(th.isfinite(v)) for v in after.values())
    assert_padding_is_zero(model.policy)


def test_shared_parameters_do_not_grow_with_agents() -> None:
    def build(n: int, share: bool) -> MlpHybridPolicy:
        return make_policy(linear_etc_v0.joint_env(n_agents=n), share_parameters=share)

    def input_widths(policy: MlpHybridPolicy, n: int) -> dict[str, int]:
        """Feature widths the networks actually receive (plus the one-hot agent id)."""
        obs = joint_obs_batch(linear_etc_v0.joint_env(n_agents=n), steps=2)
        broadcast = th.zeros(2, n, dtype=th.int64)
        return {
            "mu": policy.option_features(obs).shape[-1] + n,
            "q": policy.critic_features(obs).shape[-1] + n,
            "pi": policy.control_features(obs, broadcast).shape[-1] + n,
        }

    shared = {n: build(n, True) for n in (2, 5)}
    shapes = {n: {k: p.shape for k, p in shared[n].named_parameters()} for n in (2, 5)}
    assert shapes[2].keys() == shapes[5].keys()
    # Only the input width of the first layers depends on N; everything else is identical.
    first_layers = {k for k in shapes[2] if k.endswith("weights.0")}
    assert first_layers
    for key in shapes[2]:
        if key not in first_layers:
            assert shapes[2][key] == shapes[5][key], key
    hidden = TINY["net_arch"][0]
    n_nets = len(NETS)
    count = {n: sum(p.numel() for p in shared[n].parameters()) for n in (2, 5)}
    widths = {n: max(input_widths(shared[n], n).values()) for n in (2, 5)}
    assert count[5] - count[2] == n_nets * hidden * (widths[5] - widths[2])

    # Without sharing every agent has its own networks: N times as many groups.
    separate = build(5, False)
    for chain in separate.chains:
        assert chain.weights[0].shape[0] == n_nets * 5
    assert separate.log_std.shape[0] == 5 and shared[5].log_std.shape[0] == 1
    assert sum(p.numel() for p in separate.parameters()) > 4 * count[5]


@pytest.mark.parametrize("critic", CRITICS)
def test_agents_have_independent_networks_without_sharing(critic: str) -> None:
    env = linear_etc_v0.joint_env(n_agents=3)
    policy = make_policy(env, learn_log_std=True, critic=critic)
    obs = joint_obs_batch(env, steps=6)
    broadcast = random_options(6, 3, seed=2)
    control = th.randn(6, 3, 1)
    ev = policy.evaluate_actions(obs, broadcast, control)
    loss = (
        ev.log_prob_broadcast[:, 0].sum()
        + ev.entropy_broadcast[:, 0].sum()
        + ev.log_prob_control[:, 0].sum()
        + ev.option_values[:, 0].sum()
    )
    loss.backward()
    for net in NETS:
        chain_idx, start, stop = policy.chains.location(net)
        chain = policy.chains[chain_idx]
        assert stop - start == 3
        for p in (*chain.weights, *chain.biases):
            grad = p.grad[start:stop]
            assert grad[0].abs().sum() > 0, net
            assert th.all(grad[1:] == 0), net
    assert th.all(policy.log_std.grad[0] != 0)
    assert th.all(policy.log_std.grad[1:] == 0)


@pytest.mark.parametrize("critic", CRITICS)
@pytest.mark.parametrize("share", [False, True])
@pytest.mark.parametrize("net_arch", [[16, 16], {"mu": [8], "q": [16, 16], "pi": [8]}])
def test_policy_outputs_match_each_agents_extracted_networks(share: bool, net_arch: Any, critic: str) -> None:
    n = 3
    env = linear_etc_v0.joint_env(n_agents=n)
    policy = make_policy(env, share_parameters=share, net_arch=net_arch, critic=critic)
    obs = joint_obs_batch(env, steps=5)
    broadcast = random_options(5, n, seed=3)
    if critic == "afterstate":  # both own options side by side on the agent axis' feature rows
        q_features = policy.afterstate_features(obs, broadcast)
    else:
        q_features = policy.critic_features(obs)
    features = {"mu": policy.option_features(obs), "q": q_features, "pi": policy.control_features(obs, broadcast)}
    with th.no_grad():
        action = policy(obs, deterministic=True, broadcast=broadcast)
        outputs = {}
        for net in NETS:
            per_agent = []
            for i in range(n):
                x = features[net][..., i, :]
                if share:
                    x = th.cat([x, th.eye(n)[i].expand(*x.shape[:-1], -1)], dim=-1)
                per_agent.append(policy.chains.extract(net, 0 if share else i)(x))
            outputs[net] = th.stack(per_agent, dim=1)
    if critic == "afterstate":  # (B, N, options, 1) -> (B, N, options)
        outputs["q"] = outputs["q"][..., 0]
    if critic == "centred":  # (V, D) -> Q(s, o) = V + (o - p) D
        p = th.softmax(outputs["mu"], dim=-1)[..., 1:]
        value, gap = outputs["q"][..., :1], outputs["q"][..., 1:]
        outputs["q"] = th.cat([value - p * gap, value + (1 - p) * gap], dim=-1)
    th.testing.assert_close(action.option_values, outputs["q"])
    th.testing.assert_close(action.control, outputs["pi"])
    log_mu = th.log_softmax(outputs["mu"], dim=-1).gather(-1, broadcast[..., None])[..., 0]
    th.testing.assert_close(action.log_prob_broadcast, log_mu)


@pytest.mark.parametrize("n_agents", [2, 3])
def test_afterstate_features_apply_the_network_rule_to_each_own_option(n_agents: int) -> None:
    env = linear_etc_v0.joint_env(n_agents=n_agents)
    policy = make_policy(env, critic="afterstate")
    obs = joint_obs_batch(env, steps=6)
    broadcast = random_options(6, n_agents, seed=4)
    features = policy.afterstate_features(obs, broadcast)
    assert features.shape == (6, 2, n_agents, policy.critic_features(obs).shape[-1])
    for i in range(n_agents):
        for option in (0, 1):
            options = broadcast.clone()
            options[:, i] = option
            held, _ = policy.network_after(obs, options)  # the one rule, applied to the whole team
            expected = policy.critic_features({**obs, "held": held})[:, i]  # ages before the options
            th.testing.assert_close(features[:, option, i], expected)
    # The taken options' afterstate: one feature row per agent, whatever the own option.
    taken = features.gather(1, broadcast[:, None, :, None].expand(-1, 1, -1, features.shape[-1]))[:, 0]
    held, _ = policy.network_after(obs, broadcast)
    th.testing.assert_close(taken, policy.critic_features({**obs, "held": held}))
    # A broadcast of what the others already hold leaves the afterstate unchanged.
    unchanged = {**obs, "held": obs["message"].clone()}
    both = policy.afterstate_features(unchanged, broadcast)
    th.testing.assert_close(both[:, 0], both[:, 1])


# -------------------------------------------------------------- 10. batched chain
def test_batched_mlp_extract_matches_batched_forward() -> None:
    th.manual_seed(0)
    ins, outs = [3, 5, 2, 4], [2, 1, 4, 3]
    chain = BatchedMLP(ins, outs, hidden=[7, 6], activation_fn=th.nn.Tanh, output_gains=[1.0, 0.5, 2.0, 1.0])
    with th.no_grad():  # non-zero biases so that they are checked too
        for bias in chain.biases:
            bias.normal_()
    batch = 9
    xs = [th.randn(batch, w) for w in ins]
    stacked = th.stack([th.nn.functional.pad(x, (0, max(ins) - x.shape[-1])) for x in xs])
    with th.no_grad():
        out = chain(stacked)
        part = chain(stacked[1:3], 1, 3)
        for g in range(len(ins)):
            net = chain.extract(g)
            assert net[0].in_features == ins[g] and net[-1].out_features == outs[g]
            expected = net(xs[g])
            th.testing.assert_close(out[g, :, : outs[g]], expected)
            if 1 <= g < 3:
                th.testing.assert_close(part[g - 1, :, : outs[g]], expected)
    # The extracted copy is independent of the chain.
    net = chain.extract(0)
    with th.no_grad():
        chain.weights[0][0].add_(1.0)
        th.testing.assert_close(net(xs[0]), out[0, :, : outs[0]])


# ------------------------------------------------------------------- 2. the one rule
@pytest.mark.parametrize("n_agents", [2, 3])
def test_policy_views_equal_the_environments(n_agents: int) -> None:
    env = linear_etc_v0.joint_env(n_agents=n_agents, max_cycles=100)
    policy = make_policy(env)
    low, high = env.action_space["control"].low, env.action_space["control"].high
    obs, _ = env.reset(seed=4)
    options, max_age = [], 0.0
    for _ in range(25):
        obs_t = {key: th.as_tensor(value)[None] for key, value in obs.items()}
        with th.no_grad():
            action = policy(obs_t)
            held, age = policy.network_after(obs_t, action.broadcast)
            features = policy.control_features(obs_t, action.broadcast)[0].numpy()
        broadcast = action.broadcast[0].numpy()
        next_obs, *_ = env.step({"broadcast": broadcast, "control": np.clip(action.control[0].numpy(), low, high)})
        np.testing.assert_array_equal(held[0].numpy(), next_obs["held"])
        np.testing.assert_array_equal(age[0].numpy(), next_obs["age"])

        # The env's own per-agent views, built from the post-broadcast network and this step's messages.
        views = env.network.agent_views({**obs, "held": next_obs["held"], "age": next_obs["age"]})
        assert features.shape[0] == n_agents
        for i, agent in enumerate(env.network.possible_agents):
            view = views[agent]
            expected = np.concatenate(
                [view["local"], view["neighbours"].ravel(), view["neighbour_age"] * np.float32(policy.age_scale)]
            )
            np.testing.assert_array_equal(features[i], expected)
        options.append(broadcast)
        max_age = max(max_age, float(next_obs["age"].max()))
        obs = next_obs
    options = np.array(options)
    assert options.min() == 0 and options.max() == 1  # both options were exercised
    assert max_age >= 2


# ------------------------------------------------------------ 3. greedy advantage
def test_greedy_broadcast_advantage_hand_computed() -> None:
    q = th.tensor([[[1.0, 3.0], [2.0, -1.0]], [[0.5, 0.5], [-2.0, 4.0]]], requires_grad=True)
    broadcast = th.tensor([[0, 0], [1, 0]])
    expected = th.tensor([[1.0 - 3.0, 0.0], [0.0, -2.0 - 4.0]])
    advantage = greedy_broadcast_advantage(q, broadcast)
    th.testing.assert_close(advantage, expected)
    assert advantage.grad_fn is None and not advantage.requires_grad
    th.testing.assert_close(greedy_broadcast_advantage(q, broadcast, offset=0.1), expected + 0.1)
    # The greedy option has advantage zero, the other option a negative one.
    greedy = q.argmax(-1)
    assert th.all(greedy_broadcast_advantage(q, greedy) == 0)
    assert th.all(greedy_broadcast_advantage(q, 1 - greedy)[th.tensor([[True, True], [False, True]])] < 0)
    # No gradient flows into Q through the advantage.
    (greedy_broadcast_advantage(q, broadcast, 0.1).sum() * 3.0 + q.sum()).backward()
    th.testing.assert_close(q.grad, th.ones_like(q))


@pytest.mark.parametrize(
    ("kind", "normalize"), [("greedy", False), ("greedy", True), ("return", False), ("return", True)]
)
def test_the_loss_takes_the_broadcast_advantage_asked_for(kind: str, normalize: bool) -> None:
    model = make_model(
        broadcast_advantage=kind,
        normalize_broadcast_advantage=normalize,
        broadcast_advantage_offset=0.1,
        normalize_advantage=False,
    )
    q = th.randn(6, 2, 2, generator=th.Generator().manual_seed(0))
    broadcast = th.randint(0, 2, (6, 2), generator=th.Generator().manual_seed(1))
    sampled = th.randn(6, 2, generator=th.Generator().manual_seed(2))
    evaluation = SimpleNamespace(option_values=q)
    data = SimpleNamespace(broadcast=broadcast, broadcast_advantages=sampled)
    greedy = greedy_broadcast_advantage(q, broadcast)
    # normalize_broadcast_advantage scales the greedy advantages only
    expected = sampled if kind == "return" else greedy / broadcast_gap_scale(q) if normalize else greedy
    th.testing.assert_close(model.loss.broadcast_advantages(evaluation, data), expected + 0.1)


def test_broadcast_gap_scale_makes_greedy_advantages_scale_free() -> None:
    q = th.randn(64, 3, 2, generator=th.Generator().manual_seed(0), dtype=th.float64)
    broadcast = th.randint(0, 2, (64, 3), generator=th.Generator().manual_seed(1))
    gap = q[..., 1] - q[..., 0]
    th.testing.assert_close(broadcast_gap_scale(q), gap.pow(2).mean(0).sqrt() + 1e-8)
    normalised = greedy_broadcast_advantage(q, broadcast) / broadcast_gap_scale(q)
    for factor in (1e-2, 7.0):  # rewards in other units: the same normalised advantages
        scaled = factor * q + 3.0
        th.testing.assert_close(
            greedy_broadcast_advantage(scaled, broadcast) / broadcast_gap_scale(scaled),
            normalised,
            rtol=1e-4,
            atol=1e-6,
        )


@pytest.mark.parametrize("n_agents", [2, 3])
def test_centred_critic_option_values(n_agents: int) -> None:
    """Q(s, o) = V + (o - p)(D - price): the gap is D - price, the mean under the drawing probabilities is V."""
    env = linear_etc_v0.joint_env(n_agents=n_agents)
    policy = make_policy(env, critic="centred")
    obs = joint_obs_batch(env, steps=7)
    broadcast = random_options(7, n_agents, seed=5)
    price = th.rand(7, n_agents, generator=th.Generator().manual_seed(2))
    p = th.rand(7, n_agents, generator=th.Generator().manual_seed(3))
    with th.no_grad():
        value, gap = policy.chains.run({"q": policy.critic_features(obs)})["q"].unbind(-1)
        q = policy.evaluate_actions(obs, broadcast, th.zeros(7, n_agents, 1), price, p).option_values
        state_values = policy.state_values(obs, price)
    th.testing.assert_close(q[..., 1] - q[..., 0], gap - price)
    th.testing.assert_close(p * q[..., 1] + (1 - p) * q[..., 0], value)
    th.testing.assert_close(state_values, value)  # under mu's own probabilities, too
    with pytest.raises(ValueError, match="p_broadcast"):
        policy.option_values(th.zeros(7, n_agents, 2), price)


@pytest.mark.parametrize("team_reward", [False, True])
def test_broadcast_price_is_what_a_broadcast_takes_from_the_learners_reward(team_reward: bool) -> None:
    """The price the critics add analytically equals the reward change of one broadcast, in the learner's units."""
    env = linear_etc_v0.joint_env(broadcast_cost=0.4)
    model = MAPPOC(
        "MlpHybridPolicy", env, n_steps=8, batch_size=8, reward_scale=0.1, team_reward=team_reward, policy_kwargs=TINY
    )
    env.reset(seed=3)
    control = np.zeros((3, 1), dtype=np.float32)
    rewards = []
    for broadcast in (np.array([0, 1, 0]), np.array([0, 0, 0])):  # agent 1 broadcasts or not, everything else equal
        _, _, _, _, info = copy.deepcopy(env).step({"broadcast": broadcast, "control": control})
        agent_rewards = model.reward_scale * np.asarray(info["agent_rewards"])
        rewards.append(np.full(3, agent_rewards.mean()) if team_reward else agent_rewards)
    price = model.reward_transform.price(np.array([0.4], dtype=np.float32))[0]
    np.testing.assert_allclose(rewards[1][1] - rewards[0][1], price[1], rtol=1e-5)


def test_centred_critic_refuses_options_of_unknown_probability() -> None:
    model = MAPPOC("MlpHybridPolicy", ENV_ID, n_steps=8, batch_size=8, policy_kwargs={**TINY, "critic": "centred"})
    with pytest.raises(ValueError, match="probabilities with which the options were drawn"):
        model.set_fixed_trigger(RandomTrigger(0.5, seed=0))
    with pytest.raises(ValueError, match="probabilities with which the options were drawn"):
        model.learn(8, callback=RandomSkipCallback(0.5))


def test_clipped_surrogate_loss_hand_computed() -> None:
    advantages = th.tensor([[1.0, -1.0], [2.0, -2.0]])
    ratio = th.tensor([[1.5, 1.5], [0.5, 0.9]])
    # Per sample min(A r, A clip(r)): 1.2, -1.5 / 1.0, -1.8; mean over the batch, sum over agents.
    expected = -((1.2 + 1.0) / 2 + (-1.5 - 1.8) / 2)
    th.testing.assert_close(clipped_surrogate_loss(advantages, ratio, 0.2), th.tensor(expected))


# ------------------------------------------------------------------------ 4. GAE
def gae_buffer(buffer_size: int, n_envs: int, gamma: float, gae_lambda: float) -> HybridRolloutBuffer:
    env = linear_etc_v0.joint_env(n_agents=2)
    return HybridRolloutBuffer(
        buffer_size, env.observation_space, env.action_space, "cpu", gamma=gamma, gae_lambda=gae_lambda, n_envs=n_envs
    )


def fill(buffer: HybridRolloutBuffer, rewards: np.ndarray, values: np.ndarray, starts: np.ndarray) -> None:
    n_envs, n = buffer.n_envs, buffer.n_agents
    obs = {key: np.zeros((n_envs, *space.shape), np.float32) for key, space in buffer.observation_space.spaces.items()}
    for t in range(buffer.buffer_size):
        zeros = np.zeros((n_envs, n), np.float32)
        option_values = np.stack([values[t], values[t] - 1.0], axis=-1)  # option 0 is the one taken
        buffer.add(
            obs, zeros.astype(np.int64), np.zeros((n_envs, n, 1)), rewards[t], starts[t], option_values, zeros, zeros
        )


def test_gae_worked_example() -> None:
    """Two steps, two envs, two agents, gamma = lambda = 0.5, numbers worked out by hand."""
    buffer = gae_buffer(2, n_envs=2, gamma=0.5, gae_lambda=0.5)
    rewards = np.array([[[1, 0], [1, 0]], [[2, 1], [2, 1]]], np.float32)  # (T, envs, N)
    values = np.array([[[0.5, 1], [0.5, 1]], [[1, 2], [1, 2]]], np.float32)
    starts = np.array([[1, 0], [0, 1]], np.float32)  # env 1: a new episode begins at t = 1
    fill(buffer, rewards, values, starts)
    buffer.compute_returns_and_advantage(last_values=np.array([[4, 0], [4, 0]], np.float32), dones=np.array([0, 1]))
    # env 0, agent 0: d1 = 2 + .5*4 - 1 = 3, A1 = 3; d0 = 1 + .5*1 - .5 = 1, A0 = 1 + .25*3 = 1.75
    # env 0, agent 1: d1 = 1 + 0 - 2 = -1, A1 = -1; d0 = 0 + .5*2 - 1 = 0, A0 = -.25
    # env 1 (episode ends after t = 0, and the env is done after t = 1):
    #   agent 0: A1 = 2 - 1 = 1; A0 = 1 - .5 = .5.  agent 1: A1 = 1 - 2 = -1; A0 = 0 - 1 = -1
    expected = np.array([[[1.75, -0.25], [0.5, -1.0]], [[3.0, -1.0], [1.0, -1.0]]], np.float32)
    np.testing.assert_allclose(buffer.advantages, expected, rtol=1e-6)
    np.testing.assert_allclose(buffer.returns, expected + values, rtol=1e-6)


def test_gae_against_explicit_discounted_sums() -> None:
    gamma, lam, size, n_envs, n = 0.9, 0.8, 5, 2, 2
    buffer = gae_buffer(size, n_envs=n_envs, gamma=gamma, gae_lambda=lam)
    rewards = np.array(
        [
            [[1.0, -0.5], [0.2, 0.3]],
            [[0.0, 2.0], [-1.0, 0.5]],
            [[0.7, 0.1], [0.4, -0.2]],
            [[-0.3, 1.5], [0.9, 0.0]],
            [[0.5, -1.0], [1.2, 0.8]],
        ],
        np.float32,
    )
    values = np.array(
        [
            [[0.1, 0.4], [-0.2, 1.0]],
            [[0.3, -0.6], [0.5, 0.2]],
            [[1.1, 0.0], [-0.4, 0.7]],
            [[-0.8, 0.9], [0.6, -0.1]],
            [[0.2, 0.5], [0.3, 0.4]],
        ],
        np.float32,
    )
    # env 0: episodes [0, 2], [3, 4] and running on; env 1: one episode that ends at the last step.
    starts = np.array([[1, 1], [0, 0], [0, 0], [1, 0], [0, 0]], np.float32)
    dones = np.array([False, True])
    last_values = np.array([[2.0, -3.0], [5.0, 7.0]], np.float32)
    fill(buffer, rewards, values, starts)
    buffer.compute_returns_and_advantage(last_values=last_values, dones=dones)

    # Reference: A_t = sum_l (gamma lam)^l delta_{t+l} over the rest of the episode inside the rollout,
    # delta_t = r_t + gamma V_{t+1} - V_t, with V_{t+1} = 0 when the episode ends after step t.
    expected = np.zeros((size, n_envs, n))
    for e in range(n_envs):
        episode_ends_after = [bool(starts[t + 1, e]) for t in range(size - 1)] + [bool(dones[e])]
        for i in range(n):
            delta = []
            for t in range(size):
                next_value = last_values[e, i] if t == size - 1 else values[t + 1, e, i]
                bootstrap = 0.0 if episode_ends_after[t] else gamma * next_value
                delta.append(rewards[t, e, i] + bootstrap - values[t, e, i])
            for t in range(size):
                total, k = 0.0, t
                while True:
                    total += (gamma * lam) ** (k - t) * delta[k]
                    if episode_ends_after[k] or k == size - 1:
                        break
                    k += 1
                expected[t, e, i] = total
    np.testing.assert_allclose(buffer.advantages, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(buffer.returns, expected + values, rtol=1e-5, atol=1e-6)


class Recorder(BaseCallback):
    """Keeps the infos of every step of a rollout."""

    def __init__(self) -> None:
        super().__init__()
        self.infos: list[list[dict[str, Any]]] = []

    def _on_step(self) -> bool:
        self.infos.append([dict(info) for info in self.locals["infos"]])
        return True


def test_truncated_episodes_bootstrap_the_terminal_value() -> None:
    # Learning rate 0: the update after the rollout leaves the critic that valued its terminal states.
    model = make_model(n_agents=2, n_envs=2, max_cycles=5, n_steps=12, gamma=0.9, reward_scale=0.5, learning_rate=0.0)
    recorder = Recorder()
    model.learn(model.n_steps * model.n_envs, callback=recorder)  # exactly one rollout
    buffer = model.rollout_buffer
    assert len(recorder.infos) == model.n_steps
    truncations = 0
    for t, infos in enumerate(recorder.infos):
        for e, info in enumerate(infos):
            expected = 0.5 * info["agent_rewards"].astype(np.float32)
            if info.get("TimeLimit.truncated", False):
                truncations += 1
                terminal = model.policy.obs_to_tensor(info["terminal_observation"])[0]
                with th.no_grad():
                    bootstrap = 0.9 * model.policy.state_values(terminal)[0].numpy()
                assert np.all(np.abs(bootstrap) > 1e-3)  # the check below can tell it apart
                expected = expected + bootstrap
                assert buffer.episode_starts[t + 1, e] == 1
            np.testing.assert_allclose(buffer.rewards[t, e], expected, rtol=1e-5, atol=1e-6)
    assert truncations == 2 * 2  # after steps 5 and 10 in both envs


# ------------------------------------------------------------------ 5. persistence
def test_save_load_round_trip(tmp_path) -> None:
    model = make_model(
        n_agents=2,
        n_envs=1,
        share_parameters=True,
        broadcast_ent_coef=0.3,
        reward_scale=0.25,
        broadcast_advantage_offset=0.1,
        clip_range_broadcast=0.15,
    )
    model.learn(16)
    path = tmp_path / "mappoc.zip"
    model.save(path)
    env = linear_etc_v0.joint_env(n_agents=2, max_cycles=20)
    loaded = MAPPOC.load(path, env=env)
    saved, restored = parameters(model), parameters(loaded)
    assert saved.keys() == restored.keys()
    for key in saved:
        assert th.equal(saved[key], restored[key]), key
    assert loaded.broadcast_ent_coef == 0.3
    assert loaded.reward_scale == 0.25
    assert loaded.broadcast_advantage_offset == 0.1
    assert loaded.clip_range_broadcast == 0.15
    assert loaded.policy.share_parameters is True
    assert loaded.policy_kwargs["share_parameters"] is True
    assert loaded.n_agents == 2

    obs = {key: v.numpy() for key, v in joint_obs_batch(env, steps=6).items()}
    th.manual_seed(1)
    expected, _ = model.predict(obs, deterministic=True)
    th.manual_seed(1)
    got, _ = loaded.predict(obs, deterministic=True)
    for a, b in zip(expected, got, strict=True):
        np.testing.assert_array_equal(a["broadcast"], b["broadcast"])
        np.testing.assert_array_equal(a["control"], b["control"])
    loaded.learn(16)  # the loaded model keeps training

    without_env = MAPPOC.load(path)
    assert all(th.equal(saved[k], v) for k, v in parameters(without_env).items())


@pytest.mark.parametrize("sample_options", [False, True])
def test_deterministic_predict_takes_the_options_as_the_policy_is_deployed(tmp_path, sample_options: bool) -> None:
    """Mean controls; the most likely options, or samples where the policy is deployed with sampled options."""
    model = make_model(n_agents=3, policy_kwargs={"broadcast_prob_init": 0.5, "sample_options": sample_options})
    path = tmp_path / "policy.pt"
    model.policy.save(str(path))
    policy = MlpHybridPolicy.load(str(path), device="cpu")
    assert policy.sample_options is sample_options  # saved with the policy
    env = linear_etc_v0.joint_env(n_agents=3, max_cycles=20)
    obs = {key: v.numpy() for key, v in joint_obs_batch(env, steps=6).items()}
    with th.no_grad():
        obs_tensor = obs_as_tensor(obs, policy.device)
        mode = policy(obs_tensor, deterministic=True).broadcast.numpy()
        logits_mode = policy.sample_actions(obs_tensor, sample_options=False)[0].numpy()
    assert (mode == logits_mode).all()
    drawn = np.array([[a["broadcast"] for a in policy.predict(obs, deterministic=True)[0]] for _ in range(20)])
    if sample_options:  # mu near 50 %: samples differ from the mode
        assert 0.2 < drawn.mean() < 0.8 and (drawn != mode).any()
    else:
        assert (drawn == mode).all()  # the most likely options, every time
    sampled = np.array([[a["broadcast"] for a in policy.predict(obs, deterministic=False)[0]] for _ in range(20)])
    assert 0.2 < sampled.mean() < 0.8 and (sampled != mode).any()  # mu near 50 %: samples differ from the mode
    controller = policy.agent_controller(0)
    assert controller.sample_options is sample_options
    decided = [controller.decide(obs["trigger"][0, 0], obs["trigger_held"][0, 0]) for _ in range(40)]
    assert len(set(decided)) == 1
    drawn_alone = [controller.decide(obs["trigger"][0, 0], obs["trigger_held"][0, 0], False) for _ in range(40)]
    assert len(set(drawn_alone)) == 2


@pytest.mark.parametrize("critic", CRITICS)
def test_a_policy_saved_alone_loads_alone(tmp_path, critic: str) -> None:
    model = make_model(n_agents=3, policy_kwargs={"critic": critic, "learn_log_std": True, "age_scale": 0.0})
    model.learn(16)
    path = tmp_path / "policy.pt"
    model.policy.save(str(path))
    loaded = MlpHybridPolicy.load(str(path), device="cpu")
    saved, restored = parameters(model.policy), parameters(loaded)
    assert saved.keys() == restored.keys()
    assert all(th.equal(saved[key], restored[key]) for key in saved)
    assert (loaded.critic, loaded.age_scale, loaded.net_arch) == (critic, 0.0, [16, 16])
    env = linear_etc_v0.joint_env(n_agents=3, max_cycles=20)
    obs = {key: v.numpy() for key, v in joint_obs_batch(env, steps=6).items()}
    th.manual_seed(1)
    expected, _ = model.predict(obs, deterministic=True)
    th.manual_seed(1)
    got, _ = loaded.predict(obs, deterministic=True)
    for a, b in zip(expected, got, strict=True):
        np.testing.assert_array_equal(a["broadcast"], b["broadcast"])
        np.testing.assert_array_equal(a["control"], b["control"])


def test_default_net_arch_is_recorded_and_survives_loading(tmp_path) -> None:
    model = make_model(policy_kwargs={"net_arch": None})
    assert model.policy.net_arch == [96, 96, 96]
    model.save(tmp_path / "model.zip")
    assert MAPPOC.load(tmp_path / "model.zip").policy.net_arch == [96, 96, 96]


def test_predict_on_a_reset_tuple_says_which_apis_are_mixed() -> None:
    model = make_model()
    env = linear_etc_v0.joint_env(n_agents=2, max_cycles=20)
    with pytest.raises(ValueError, match="mixing the Gymnasium API"):
        model.predict(env.reset(seed=0))
    obs, _ = env.reset(seed=0)
    action, _ = model.predict(obs)
    assert set(action) == {"broadcast", "control"}


# ------------------------------------------------------------------ 5b. torch.compile
def test_compiled_sampling_and_loss_match_eager(tmp_path) -> None:
    """Compiled, the policy and the loss compute what they compute eagerly; a compiled model survives save/load.

    With the afterstate critic (the option heads' compiled step is checked against the eager one below).
    """
    settings = {"torch_compile": True, "normalize_broadcast_advantage": True, "policy_kwargs": {"critic": "afterstate"}}
    model = make_model(n_agents=3, n_envs=2, **settings)
    model.learn(64)  # compiled rollouts and updates
    assert isinstance(model.gradient_step, FusedGradientStep)

    rollout = model.rollout_buffer.tensors()
    update = UpdateInputs(
        model.policy.training_inputs(rollout.observations, rollout.broadcast),
        rollout._replace(observations={}),
        th.full_like(rollout.old_log_prob_broadcast, 0.5),
        0.2,
        0.1,
        0.05,
        True,
        True,
    )
    idx = th.arange(0, 32, 3)
    results = []
    for loss_fn in (model.loss, th.compile(model.loss)):
        model.policy.optimizer.zero_grad(set_to_none=True)
        loss, step_stats = loss_fn(update, idx)
        loss.backward()
        results.append((loss.detach(), step_stats, [p.grad for p in model.policy.parameters() if p.requires_grad]))
    (eager_loss, eager_stats, eager_grads), (loss, step_stats, grads) = results
    th.testing.assert_close(loss, eager_loss)
    th.testing.assert_close(step_stats, eager_stats)
    for grad, eager_grad in zip(grads, eager_grads, strict=True):
        th.testing.assert_close(grad, eager_grad)

    obs = {key: th.as_tensor(value) for key, value in model.get_env().reset().items()}
    price = th.full((2, 3), 0.1)
    with th.no_grad():
        modes = {"deterministic": True, "sample_options": False}
        compiled = th.compile(model.policy.forward)(obs, **modes, broadcast_price=price)
        eager = model.policy(obs, **modes, broadcast_price=price)
    for got, expected in zip(compiled, eager, strict=True):
        th.testing.assert_close(got, expected)

    model.save(tmp_path / "compiled.zip")
    loaded = MAPPOC.load(tmp_path / "compiled.zip", env=model.get_env())
    assert loaded.torch_compile is True and isinstance(loaded.gradient_step, FusedGradientStep)
    loaded.learn(32)


@pytest.mark.parametrize(("max_grad_norm", "n_epochs"), [(None, 2), (0.05, 2), (None, 40)])
def test_fused_gradient_step_updates_like_backward_and_the_optimizer(
    max_grad_norm: float | None, n_epochs: int
) -> None:
    """The compiled step (loss, gradients, clipping, Adam in one graph) leaves what the eager one leaves.

    Over two updates with different learning rates; with 40 epochs an update takes more steps
    than the fused step computes Adam's scalars for at once (``ADAM_ROWS``).
    """
    model = make_model(
        n_agents=3,
        n_steps=32,
        n_epochs=n_epochs,
        torch_compile=True,
        max_grad_norm=max_grad_norm,
        policy_kwargs={"learn_log_std": True},
    )
    model.learn(32)  # a rollout and a first (fused) update: the optimizer has state
    eager = GradientStep(model.loss, model.policy.optimizer, max_grad_norm, None)
    start = parameters(model), copy.deepcopy(model.policy.optimizer.state_dict())
    results = []
    for gradient_step in (model.gradient_step, eager):
        model.policy.load_state_dict(start[0])
        model.policy.optimizer.load_state_dict(copy.deepcopy(start[1]))
        model.gradient_step = gradient_step
        th.manual_seed(1)  # the same minibatches
        model.set_learning_rate(1e-3)
        model.train()
        model.set_learning_rate(5e-4)
        model.train()
        results.append((parameters(model), model.policy.optimizer.state_dict()["state"]))
    (fused, fused_state), (unfused, unfused_state) = results
    assert any(not th.equal(fused[k], start[0][k]) for k in fused)  # the step moved the parameters
    for key in unfused:
        th.testing.assert_close(fused[key], unfused[key], rtol=1e-5, atol=1e-6)
    for i, state in unfused_state.items():
        for key, value in state.items():
            th.testing.assert_close(fused_state[i][key], value, rtol=1e-5, atol=1e-7)


class ScheduledValues(BaseCallback):
    """At every rollout start, the scheduled values that the update before it logged."""

    KEYS = ("train/broadcast_ent_coef", "train/clip_range")

    def __init__(self) -> None:
        super().__init__()
        self.values: dict[str, list[float]] = {key: [] for key in self.KEYS}

    def _on_rollout_start(self) -> None:
        logged = self.logger.name_to_value
        for key in self.KEYS:
            assert key in logged, key  # (name_to_value is a defaultdict: a missing key would read 0.0)
            self.values[key].append(logged[key])

    def _on_step(self) -> bool:
        return True


def test_fused_gradient_step_is_not_recompiled_when_schedules_change() -> None:
    # Scheduled scalars (zeta, clip ranges) enter the compiled step as tensors; were they compiled
    # in, each new value would recompile it. Compiled once, the step must serve every later update.
    th._dynamo.reset()  # forget what other tests compiled: only this model's compilations count
    model = make_model(torch_compile=True, broadcast_ent_coef=lambda p: p, clip_range=lambda p: 0.1 + 0.1 * p)
    model.set_logger(Logger(None, []))  # kept by the next learn: its first rollout start sees the first update's values
    model.learn(16)  # the first update compiles the step (at progress 0: zeta 0, clip range 0.1)
    scheduled = ScheduledValues()
    with th._dynamo.config.patch(error_on_recompile=True):
        model.learn(16 * 5, callback=scheduled, reset_num_timesteps=False)  # progress 2/3, 1/2, 1/3, 1/6, 0
    assert model.num_timesteps == 96
    zeta = [*scheduled.values["train/broadcast_ent_coef"], model.logger.name_to_value["train/broadcast_ent_coef"]]
    clip = [*scheduled.values["train/clip_range"], model.logger.name_to_value["train/clip_range"]]
    np.testing.assert_allclose(zeta, [0, 2 / 3, 1 / 2, 1 / 3, 1 / 6, 0], atol=1e-12)  # the values did change
    np.testing.assert_allclose(clip, 0.1 + 0.1 * np.array(zeta), atol=1e-12)


def test_fused_gradient_step_only_for_plain_adam_and_without_early_stopping() -> None:
    """Other optimizers, Adam variants and ``target_kl`` keep the eager step (it can stop before applying)."""
    for policy_kwargs in ({"optimizer_class": th.optim.SGD}, {"optimizer_kwargs": {"amsgrad": True}}):
        model = make_model(torch_compile=True, policy_kwargs=policy_kwargs)
        assert type(model.gradient_step) is GradientStep and model.gradient_step.loss_fn is not model.loss
    assert type(make_model(torch_compile=True, target_kl=0.01).gradient_step) is GradientStep
    assert isinstance(make_model(torch_compile=True).gradient_step, FusedGradientStep)


def test_automatic_compilation_only_for_runs_long_enough(monkeypatch: pytest.MonkeyPatch) -> None:
    model = make_model()  # torch_compile="auto"
    model.learn(16)
    assert type(model.gradient_step) is GradientStep and model.gradient_step.loss_fn is model.loss
    monkeypatch.setattr(steps_module, "COMPILE_FROM_TIMESTEPS", 0)
    model.learn(0)  # chooses the steps (compiling would start with the first step)
    assert isinstance(model.gradient_step, FusedGradientStep)
    monkeypatch.setattr(steps_module, "has_cxx_compiler", lambda: False)
    model.learn(0)  # no compiler: eager again
    assert type(model.gradient_step) is GradientStep
    assert type(make_model(torch_compile=False).learn(32).gradient_step) is GradientStep


def test_torch_compile_without_a_cxx_compiler_is_rejected() -> None:
    from torch._inductor import config

    with config.patch({"cpp.cxx": ("no-such-cxx-compiler",)}):
        with pytest.raises(RuntimeError, match="C\\+\\+ compiler"):
            make_model(torch_compile=True)
        make_model(torch_compile=False)  # the eager networks need none
    make_model(torch_compile=True)  # the compiler is found again


def test_load_with_other_number_of_agents_raises(tmp_path) -> None:
    model = make_model(n_agents=2)
    path = tmp_path / "two_agents.zip"
    model.save(path)
    with pytest.raises(ValueError, match=r"2 agents.*3"):
        MAPPOC.load(path, env=linear_etc_v0.joint_env(n_agents=3))
    with pytest.raises(ValueError, match=r"2 agents.*3"):
        MAPPOC.load(path, env=linear_etc_v0.parallel_env(n_agents=3))
    with pytest.raises(ValueError, match=r"2 agents.*3"):
        model.set_env(linear_etc_v0.parallel_env(n_agents=3))


def test_load_missing_file_raises(tmp_path) -> None:
    # SB3 also tries "<path>.zip" and then raises FileNotFoundError.
    with pytest.raises(FileNotFoundError):
        MAPPOC.load(tmp_path / "missing")
    with pytest.raises(FileNotFoundError):
        MAPPOC.load(tmp_path / "missing.zip", env=linear_etc_v0.joint_env(n_agents=2))


# --------------------------------------------------------------- 6. determinism
def test_same_seed_same_parameters_other_seed_differs() -> None:
    def run(seed: int) -> dict[str, th.Tensor]:
        model = make_model(n_agents=2, n_envs=2, seed=seed, n_steps=16, batch_size=8)
        model.learn(64)
        return parameters(model)

    first, second, other = run(7), run(7), run(8)
    for key in first:
        assert th.equal(first[key], second[key]), key
    assert any(not th.equal(first[key], other[key]) for key in first)


# ------------------------------------------------------------------ 7. bad input
@pytest.mark.parametrize("env_id", ["Pendulum-v1", "CartPole-v1"])
def test_env_without_joint_spaces_is_rejected(env_id: str) -> None:
    with pytest.raises(ValueError, match=r"Dict observation space.*(JointEnv|LinearETC)"):
        MAPPOC("MlpHybridPolicy", env_id)


@pytest.mark.parametrize("name", ["batch_size", "n_steps", "n_epochs"])
@pytest.mark.parametrize("value", [0, -4])
def test_non_positive_sizes_are_rejected(name: str, value: int) -> None:
    env = linear_etc_v0.joint_env(n_agents=2)
    kwargs = {"n_steps": 16, "batch_size": 16, "n_epochs": 1, name: value}
    with pytest.raises(ValueError, match=name):
        MAPPOC("MlpHybridPolicy", env, **kwargs)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("clip_range", -1.0),
        ("clip_range", "0.2"),
        ("clip_range_broadcast", 0.0),
        ("broadcast_ent_coef", -5.0),
        ("learning_rate", -1e-3),
    ],
)
def test_out_of_range_coefficients_are_rejected(name: str, value: object) -> None:
    env = linear_etc_v0.joint_env(n_agents=2)
    with pytest.raises(ValueError, match=f"{name} must be"):
        MAPPOC("MlpHybridPolicy", env, n_steps=16, batch_size=16, **{name: value})


def test_numpy_sizes_and_schedules_are_accepted() -> None:
    env = linear_etc_v0.joint_env(n_agents=2)
    sizes = {"n_steps": np.int64(16), "batch_size": np.int32(16)}
    model = MAPPOC("MlpHybridPolicy", env, **sizes, clip_range=lambda _: 0.1, policy_kwargs=TINY)
    assert type(model.n_steps) is int and type(model.batch_size) is int


def test_contradicting_share_parameters_are_rejected() -> None:
    env = linear_etc_v0.joint_env(n_agents=2)
    with pytest.raises(ValueError, match="share_parameters"):
        MAPPOC("MlpHybridPolicy", env, share_parameters=True, policy_kwargs={"share_parameters": False})


def test_use_sde_is_rejected() -> None:
    env = linear_etc_v0.joint_env(n_agents=2)
    with pytest.raises(ValueError, match="use_sde|gSDE"):
        MAPPOC("MlpHybridPolicy", env, n_steps=16, batch_size=16, policy_kwargs={"use_sde": True})


class InjectNaN(gym.Wrapper):
    """Puts a NaN into the observation or into one agent's reward at one step."""

    def __init__(self, env: gym.Env, where: str, at_step: int) -> None:
        super().__init__(env)
        self.where, self.at_step, self.steps = where, at_step, 0

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        if self.steps == self.at_step:
            if self.where == "obs":
                obs = {**obs, "local": obs["local"].copy()}
                obs["local"][1, 0] = np.nan
            else:
                info["agent_rewards"] = info["agent_rewards"].copy()
                info["agent_rewards"][1] = np.nan
        return obs, reward, terminated, truncated, info


@pytest.mark.parametrize(
    ("where", "max_cycles"),
    [("obs", 50), ("reward", 50), ("obs", 5)],
    ids=["observation", "reward", "terminal-observation-of-truncated-episode"],
)
def test_non_finite_rollout_data_is_rejected(where: str, max_cycles: int) -> None:
    # With max_cycles=5 the NaN observation of step 5 is the terminal observation of a truncated
    # episode: it reaches the buffer through the bootstrap gamma * V(terminal obs).
    env = InjectNaN(linear_etc_v0.joint_env(n_agents=2, max_cycles=max_cycles), where, at_step=5)
    model = MAPPOC("MlpHybridPolicy", env, n_steps=16, batch_size=16, n_epochs=1, seed=0, policy_kwargs=TINY)
    with pytest.raises(ValueError, match="non-finite"):
        model.learn(16)
    if max_cycles > 5:
        # Caught before any step of the rollout is counted or stored (an observation: the policy
        # must not act on it; rewards: checked for the whole rollout at once)
        assert model.num_timesteps == 0
    assert np.all(np.isfinite(model.rollout_buffer.rewards))
    assert all(th.all(th.isfinite(p)) for p in model.policy.parameters())


# ------------------------------------------------------------------ 8. PettingZoo
def test_pettingzoo_network_is_adapted_to_the_joint_view() -> None:
    parallel = linear_etc_v0.parallel_env(n_agents=3, max_cycles=10)
    model = MAPPOC("MlpHybridPolicy", parallel, n_steps=16, batch_size=16, n_epochs=1, seed=0, policy_kwargs=TINY)
    assert model.n_agents == 3 and model.n_control == 1
    assert isinstance(model.env, DummyVecEnv)
    assert model.env.envs[0].unwrapped.network is parallel
    model.learn(32)
    assert model.num_timesteps == 32
    views, _ = parallel.reset(seed=0)  # the wrapped PettingZoo env is still usable on its own
    assert set(views) == set(parallel.possible_agents)
    action, _ = model.predict(model.env.reset(), deterministic=True)
    assert action[0]["broadcast"].shape == (3,) and action[0]["control"].shape == (3, 1)


# ---------------------------------------------------- 9. frozen mu, fixed trigger
@pytest.mark.parametrize(
    ("train_control_policy", "train_broadcast_policy"), [(True, False), (False, True), (True, True)]
)
def test_policy_level_switches(train_control_policy: bool, train_broadcast_policy: bool) -> None:
    """A level that is switched off stays exactly as it was, also after it was trained (Adam's momentum)."""
    model = make_model(n_agents=2, n_epochs=2, batch_size=8)
    model.learn(32)  # both levels train: the optimizer has momentum for both
    model.set_trained_policies(control_policy=train_control_policy, broadcast_policy=train_broadcast_policy)
    mu_before, pi_before = net_slices(model.policy, "mu"), net_slices(model.policy, "pi")
    model.learn(32)
    for net, before, trained in (("mu", mu_before, train_broadcast_policy), ("pi", pi_before, train_control_policy)):
        unchanged = all(th.equal(a, b) for a, b in zip(before, net_slices(model.policy, net), strict=True))
        assert unchanged is (not trained), net


def test_fixed_trigger_drives_the_rollouts() -> None:
    model = make_model(n_agents=3, n_envs=2, n_steps=16)

    def send_when_ahead(obs: dict[str, np.ndarray]) -> np.ndarray:
        return (obs["local"][..., 0] > 0).astype(np.int64)

    model.set_fixed_trigger(send_when_ahead)
    model.learn(32)
    buffer = model.rollout_buffer
    expected = (buffer.observations["local"][..., 0] > 0).astype(np.int64)
    assert 0 < expected.mean() < 1  # the trigger is not constant
    np.testing.assert_array_equal(buffer.broadcast, expected)
    # The next stored observation shows the overridden options' timers (within episodes).
    age = buffer.observations["age"][..., 0]
    within = buffer.episode_starts[1:] == 0
    advanced = np.where(expected[:-1] == 1, 0, age[:-1] + 1)
    np.testing.assert_array_equal(age[1:][within], advanced[within])


def test_broadcast_advantages_subtract_the_state_value_under_mu() -> None:
    """V(s) = mu(taken) Q(taken) + mu(other) Q(other); broadcast advantage = lambda-return - V(s)."""
    buffer = gae_buffer(1, n_envs=1, gamma=0.9, gae_lambda=0.8)
    obs = {key: np.zeros((1, *space.shape), np.float32) for key, space in buffer.observation_space.spaces.items()}
    broadcast = np.array([[1, 0]])
    option_values = np.array([[[2.0, 6.0], [3.0, -1.0]]], np.float32)  # taken: 6.0 (agent 0), 3.0 (agent 1)
    log_prob = np.log(np.array([[0.25, 0.5]], np.float32))
    buffer.add(
        obs, broadcast, np.zeros((1, 2, 1)), np.array([[1.0, 1.0]]), np.array([1.0]), option_values, log_prob, log_prob
    )
    buffer.compute_returns_and_advantage(last_values=np.array([[0.0, 0.0]], np.float32), dones=np.array([1]))
    np.testing.assert_allclose(buffer.values[0, 0], [6.0, 3.0])
    np.testing.assert_allclose(buffer.state_values[0, 0], [0.25 * 6 + 0.75 * 2, 0.5 * 3 + 0.5 * -1])
    np.testing.assert_allclose(buffer.returns[0, 0], [1.0, 1.0])
    np.testing.assert_allclose(buffer.broadcast_advantages[0, 0], [1.0 - 3.0, 1.0 - 1.0])


def test_broadcast_advantage_modes() -> None:
    with pytest.raises(ValueError, match="broadcast_advantage"):
        MAPPOC("MlpHybridPolicy", "sb3_detc/LinearETC-v0", broadcast_advantage="best")
    model = MAPPOC(
        "MlpHybridPolicy",
        "sb3_detc/LinearETC-v0",
        broadcast_advantage="return",
        n_steps=32,
        batch_size=16,
        n_epochs=2,
        learning_rate=1e-3,
        seed=0,
        policy_kwargs=dict(net_arch=[16, 16]),
    )
    before = model.policy.chains.agent_weights("mu")[0].clone()
    model.learn(64)
    after = model.policy.chains.agent_weights("mu")[0]
    assert not th.equal(before, after)
    buffer = model.rollout_buffer
    np.testing.assert_allclose(buffer.broadcast_advantages, buffer.returns - buffer.state_values, rtol=1e-6)
    taken = np.take_along_axis(buffer.option_values, buffer.broadcast[..., None], axis=-1)[..., 0]
    np.testing.assert_array_equal(buffer.values, taken)


def test_evaluate_policy_runs_on_the_joint_vec_env() -> None:
    from stable_baselines3.common.evaluation import evaluate_policy

    model = MAPPOC("MlpHybridPolicy", "sb3_detc/LinearETC-v0", n_steps=16, seed=0, policy_kwargs=dict(net_arch=[8]))
    mean, std = evaluate_policy(model, model.get_env(), n_eval_episodes=2)
    assert np.isfinite(mean) and np.isfinite(std) and mean < 0


def learn_recording_rewards(n_steps: int, **kwargs: Any) -> tuple[MAPPOC, np.ndarray]:
    """One rollout on the linear env; returns the model and the env's per-agent rewards (T, envs, N)."""
    infos: list[np.ndarray] = []

    class Record(BaseCallback):
        def _on_step(self) -> bool:
            infos.append(np.stack([info["agent_rewards"] for info in self.locals["infos"]]))
            return True

    model = MAPPOC(
        "MlpHybridPolicy", "sb3_detc/LinearETC-v0", n_steps=n_steps, seed=0, policy_kwargs=dict(net_arch=[8]), **kwargs
    )
    model.learn(n_steps, callback=Record())
    return model, np.array(infos)


def test_normalize_reward_divides_by_the_running_return_std() -> None:
    model, raw = learn_recording_rewards(40, reward_scale=2.0, normalize_reward=True)
    raw = 2.0 * raw  # no truncation within 40 steps (episodes last 100)
    stored = model.rollout_buffer.rewards
    factors = stored / raw
    assert np.all(factors > 0)
    # the factor of the last step is 1 / std of the discounted returns seen so far, per agent
    np.testing.assert_allclose(factors[-1, 0], 1 / np.sqrt(model.reward_transform.return_rms.var + 1e-8), rtol=1e-4)
    returns = np.zeros_like(raw[0])
    for r in raw:
        returns = 0.99 * returns + r
    assert model.reward_transform.discounted_returns == pytest.approx(returns)
    assert not np.allclose(factors[0], factors[-1])  # the scale adapts


def test_broadcasts_are_sampled_with_mu_probabilities() -> None:
    model = MAPPOC("MlpHybridPolicy", "sb3_detc/LinearETC-v0", n_steps=8, seed=0, policy_kwargs=dict(net_arch=[8]))
    policy = model.policy
    policy.chains.agent_weights("mu")[-1].zero_()  # views into the batched chain
    bias = policy.chains.agent_biases("mu")[-1]
    bias.zero_()
    bias[:, 0, 1] = math.log(0.3 / 0.7)  # P(broadcast) = 0.3 for every agent
    obs = model.env.reset()
    batch = {key: th.as_tensor(np.repeat(value, 20000, axis=0)) for key, value in obs.items()}
    with th.no_grad():
        action = policy(batch)
    rate = action.broadcast.float().mean(0).numpy()
    np.testing.assert_allclose(rate, 0.3, atol=0.015)
    expected = np.where(action.broadcast.numpy() == 1, math.log(0.3), math.log(0.7))
    np.testing.assert_allclose(action.log_prob_broadcast.numpy(), expected, rtol=1e-5)


def test_team_reward_trains_every_agent_on_the_mean_reward() -> None:
    # episodes last 100 steps, so no timeout bootstrap within this rollout
    model, raw = learn_recording_rewards(20, reward_scale=0.5, team_reward=True)
    assert not np.allclose(raw[..., 0], raw[..., 1])  # the agents' own rewards differ
    expected = 0.5 * np.repeat(raw.mean(-1, keepdims=True), 3, axis=-1)
    np.testing.assert_allclose(model.rollout_buffer.rewards, expected, rtol=1e-5)


@pytest.mark.parametrize("share", [False, True])
@pytest.mark.parametrize("p", [0.1, 0.5, 0.8])
def test_broadcast_prob_init_sets_the_untrained_broadcast_rate(share: bool, p: float) -> None:
    kwargs = dict(net_arch=[8], broadcast_prob_init=p, share_parameters=share)
    model = MAPPOC("MlpHybridPolicy", "sb3_detc/LinearETC-v0", n_steps=8, seed=0, policy_kwargs=kwargs)
    obs = model.env.reset()
    batch = {key: th.as_tensor(np.repeat(value, 20000, axis=0)) for key, value in obs.items()}
    with th.no_grad():
        rate = model.policy(batch).broadcast.float().mean(0).numpy()
    # The output weights are small (gain 0.01), so the bias sets the rate up to a small spread.
    np.testing.assert_allclose(rate, p, atol=0.02)


@pytest.mark.parametrize("p", [0.0, 1.0, -0.2])
def test_broadcast_prob_init_outside_the_open_interval_is_rejected(p: float) -> None:
    with pytest.raises(ValueError, match="broadcast_prob_init"):
        MAPPOC("MlpHybridPolicy", "sb3_detc/LinearETC-v0", n_steps=8, policy_kwargs=dict(broadcast_prob_init=p))


@pytest.mark.parametrize("scale", [-0.1, float("nan"), float("inf")])
def test_negative_or_non_finite_age_scale_is_rejected(scale: float) -> None:
    with pytest.raises(ValueError, match="age_scale"):
        MAPPOC("MlpHybridPolicy", "sb3_detc/LinearETC-v0", n_steps=8, policy_kwargs=dict(age_scale=scale))


def test_warming_up_the_compiled_step_changes_nothing_and_the_update_reuses_it() -> None:
    """``warm_up`` compiles on copies: parameters and optimizer state stay; the first update does not recompile."""
    th._dynamo.reset()
    warmed = make_model(n_agents=3, n_steps=32, torch_compile=True)
    start = parameters(warmed), copy.deepcopy(warmed.policy.optimizer.state_dict())
    assert warmed.gradient_step.needs_warm_up
    placeholders = warmed.rollout_buffer.tensors(partial=True)  # zeros: no rollout yet
    warmed.gradient_step.warm_up(warmed.update_inputs(placeholders), th.arange(16))
    assert not warmed.gradient_step.needs_warm_up
    for key, value in parameters(warmed).items():
        assert th.equal(value, start[0][key]), key
    assert warmed.policy.optimizer.state_dict() == start[1]  # no state yet, as before a first step
    with th._dynamo.config.patch(error_on_recompile=True):
        warmed.learn(64)
    other = make_model(n_agents=3, n_steps=32, torch_compile=True).learn(64)  # compiles at its first update
    for key, value in parameters(other).items():
        th.testing.assert_close(parameters(warmed)[key], value, rtol=0, atol=0)
