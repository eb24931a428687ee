"""Decentralised execution (per-agent controllers and inboxes) acts exactly like the joint policy."""

import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest
import torch as th

from sb3_detc.envs import linear_etc_v0, multiwalker_etc_v0
from sb3_detc.mappoc import MAPPOC, Inbox, run_decentralised_step

ENVS = {
    "linear": (linear_etc_v0, {"max_cycles": 60}),
    "multiwalker": (multiwalker_etc_v0, {"max_cycles": 60}),
}


def fresh_model(
    module,
    kwargs: dict,
    share_parameters: bool,
    option_age_scale: float = 0.0,
    option_distance_scale: float = 0.0,
    broadcast_interval: tuple[int, int] | None = None,
    option_others_age_scale: float = 0.0,
) -> MAPPOC:
    """A model deployed with the mode of mu, so that the joint and the decentralised options agree."""
    return MAPPOC(
        "MlpHybridPolicy",
        module.joint_env(**kwargs),
        share_parameters=share_parameters,
        policy_kwargs={
            "sample_options": False,
            "option_age_scale": option_age_scale,
            "option_distance_scale": option_distance_scale,
            "broadcast_interval": broadcast_interval,
            "option_others_age_scale": option_others_age_scale,
        },
        seed=3,
        device="cpu",
    )


def sharpen_broadcast_policy(model: MAPPOC, seed: int, scale: float = 4.0) -> None:
    """Large random weights for every agent's ``mu`` (only), so its options depend more on its inputs.

    Writes into ``mu``'s views from ``net_parameters``: the control policies keep their initial
    weights, so their outputs stay small and the float32 tolerance stays meaningful. Padding
    weights only ever meet zero inputs or are sliced off, so they may be random too.
    """
    gen = th.Generator().manual_seed(seed)
    for view in model.policy.net_parameters("mu"):
        view.copy_(th.randn(view.shape, generator=gen) * scale)


def lockstep(model: MAPPOC, module, kwargs: dict, seed: int, n_steps: int = 40) -> np.ndarray:
    """Joint policy on the joint env and decentralised controllers on the PettingZoo env, side by side.

    Asserts at every step identical options, equal controls (float32 tolerance) and that every
    inbox holds what the network holds. Returns the options (steps, N).
    """
    joint, parallel = module.joint_env(**kwargs), module.parallel_env(**kwargs)
    n = parallel.n_agents
    controllers = [model.policy.agent_controller(i) for i in range(n)]
    inboxes = [Inbox(i, n) for i in range(n)]

    joint_obs, _ = joint.reset(seed=seed)
    obs, _ = parallel.reset(seed=seed)
    for inbox in inboxes:  # the network's initial state: initial messages received, age 0
        inbox.reset(parallel.system.last_obs.message)
    options = []
    for _ in range(n_steps):
        expected, _ = model.predict(joint_obs, deterministic=True)
        actions = run_decentralised_step(controllers, inboxes, obs, parallel.system.last_obs.message)
        broadcast = np.array([actions[a]["broadcast"] for a in parallel.possible_agents])
        control = np.stack([actions[a]["control"] for a in parallel.possible_agents])
        np.testing.assert_array_equal(broadcast, expected["broadcast"])
        np.testing.assert_allclose(control, expected["control"], rtol=0, atol=1e-5)
        options.append(broadcast)

        # Both envs get the same action, so tiny float differences cannot compound.
        joint_obs, _, terminated, truncated, _ = joint.step({"broadcast": broadcast, "control": control})
        obs, _, _, _, _ = parallel.step(actions)
        # Every inbox now holds what the network holds.
        messages = parallel.system.last_obs.message
        float32_error = 1e-6 * (1 + np.abs(messages).max())  # the network subtracts float32 roundings
        for i, agent in enumerate(parallel.possible_agents):
            neighbours, ages = inboxes[i].view(messages[i])
            np.testing.assert_allclose(neighbours, obs[agent]["neighbours"], rtol=0, atol=float32_error)
            np.testing.assert_array_equal(ages, obs[agent]["neighbour_age"])
        if terminated or truncated:
            break
    assert len(options) >= 30, "the episode ended too early to compare"
    return np.array(options)


@pytest.mark.parametrize(
    ("share_parameters", "option_age_scale", "option_distance_scale", "broadcast_interval", "option_others_age_scale"),
    [
        (False, 0.0, 0.0, None, 0.0),
        (True, 0.0, 0.0, None, 0.0),
        (False, 0.5, 0.0, None, 0.0),
        (True, 0.5, 2.0, (2, 5), 0.0),
        (False, 0.5, 0.0, None, 0.5),
    ],
)
@pytest.mark.parametrize("env_name", sorted(ENVS))
def test_decentralised_controllers_match_joint_policy(
    env_name: str,
    share_parameters: bool,
    option_age_scale: float,
    option_distance_scale: float,
    broadcast_interval: tuple[int, int] | None,
    option_others_age_scale: float,
) -> None:
    module, kwargs = ENVS[env_name]
    model = fresh_model(
        module,
        kwargs,
        share_parameters,
        option_age_scale,
        option_distance_scale,
        broadcast_interval,
        option_others_age_scale,
    )
    options = lockstep(model, module, kwargs, seed=11)
    # An untrained policy over options hardly depends on its inputs, so it may never broadcast
    # (or never stay silent). Until an episode has both options, also compare sharper ones.
    for weight_seed in range(10):
        if 0 < options.mean() < 1:
            break
        sharpen_broadcast_policy(model, weight_seed)
        options = lockstep(model, module, kwargs, seed=11)
    assert 0 < options.mean() < 1, "no episode had both options"


@pytest.mark.parametrize("share_parameters", [False, True])
def test_deterministic_decide_is_the_mode_of_mu(share_parameters: bool) -> None:
    module, kwargs = ENVS["linear"]
    model = fresh_model(module, kwargs, share_parameters)
    sharpen_broadcast_policy(model, seed=0)  # logits far from a tie, options that depend on the input
    policy = model.policy
    space = model.observation_space
    space.seed(0)
    batch = [space.sample() for _ in range(64)]
    obs = {key: th.as_tensor(np.stack([b[key] for b in batch])) for key in space.spaces}
    with th.no_grad():
        mode = policy(obs, deterministic=True).broadcast.numpy()  # (B, N) argmax of mu
    decided = np.array(
        [
            [policy.agent_controller(i).decide(b["trigger"][i], b["trigger_held"][i]) for i in range(policy.n_agents)]
            for b in batch
        ]
    )
    np.testing.assert_array_equal(decided, mode)
    assert 0 < mode.mean() < 1


@pytest.mark.parametrize("agent", [-1, 3, 4])
def test_controller_for_unknown_agent_raises(agent: int) -> None:
    module, kwargs = ENVS["linear"]
    model = MAPPOC("MlpHybridPolicy", module.joint_env(**kwargs), seed=0, device="cpu")
    assert model.policy.n_agents == 3
    with pytest.raises(ValueError, match="agent must be in"):
        model.policy.agent_controller(agent)
    with pytest.raises(ValueError, match="agent must be in"):
        Inbox(agent, 3)


def test_inbox_follows_the_network_rule() -> None:
    inbox = Inbox(1, 3)
    with pytest.raises(RuntimeError, match="reset"):
        inbox.receive({})
    start = np.array([[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]])
    inbox.reset(start)
    neighbours, ages = inbox.view(np.array([2.0, 3.0]))
    np.testing.assert_array_equal(neighbours, [[-2.0, -2.0], [2.0, 2.0]])
    np.testing.assert_array_equal(ages, [0, 0])
    inbox.receive({2: np.array([10.0, 10.0])})
    inbox.receive({})
    neighbours, ages = inbox.view(np.array([1.0, 1.0]))
    np.testing.assert_array_equal(neighbours, [[-1.0, 0.0], [9.0, 9.0]])
    np.testing.assert_array_equal(ages, [2, 1])
    with pytest.raises(ValueError, match="sender"):
        inbox.receive({3: np.zeros(2)})


def test_example_runs(tmp_path, capsys) -> None:
    path = Path(__file__).parents[1] / "examples" / "decentralised_multiwalker.py"
    spec = importlib.util.spec_from_file_location("decentralised_multiwalker", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    fresh_model(multiwalker_etc_v0, {}, share_parameters=False).save(tmp_path / "model.zip")
    example.main(["--model", str(tmp_path / "model.zip"), "--episodes", "1"])
    out = capsys.readouterr().out
    number = r"(-?\d+(?:\.\d+)?)"
    walkers = ", ".join(rf"walker_{i} {number} \(\d+% saved\)" for i in range(3))
    line = re.search(rf"episode 0: (\d+) steps, return {number}, package travel {number} m \| {walkers}", out)
    assert line is not None, out
    steps, team_return, travel, *walker_returns = (float(value) for value in line.groups())
    assert 0 < steps < 400  # the untrained walkers fall before the time limit of 400 steps
    # The team return is the walkers' mean (each printed to 0.1).
    assert team_return == pytest.approx(np.mean(walker_returns), abs=0.11)
    assert abs(travel) < 10  # an untrained team carries the package a few metres at most
