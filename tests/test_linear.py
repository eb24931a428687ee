"""Tests of the coupled linear system and its LQR helpers (sb3_detc.envs.linear)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from pettingzoo.test import parallel_api_test

from sb3_detc.envs.linear import (
    LinearSystem,
    LQRController,
    lqr_cost_per_step,
    lqr_episode_cost,
    lqr_gain,
    lqr_reward_per_step,
)


def explicit_rewards(x: np.ndarray, u: np.ndarray, env: LinearSystem) -> np.ndarray:
    """Per-agent rewards written out with a loop over agents and their line neighbours."""
    n = len(x)
    out = np.zeros(n)
    for i in range(n):
        e, v = x[i]
        cost = env.q_reg * e**2 + env.q_vel * v**2 + env.r * u[i] ** 2
        for j in (i - 1, i + 1):
            if 0 <= j < n:
                cost += 0.5 * env.q_form * (x[j, 0] - e) ** 2
        out[i] = -cost
    return out


@pytest.mark.parametrize("n", [2, 3, 20])
def test_shapes_and_spaces(n: int) -> None:
    env = LinearSystem(n_agents=n)
    assert env.possible_agents == [f"agent_{i}" for i in range(n)]
    assert env.n_agents == n
    assert env.control_space.shape == (1,)
    assert env.local_space.shape == env.message_space.shape == env.trigger_space.shape == (2,)
    obs, info = env.reset_arrays(seed=1)
    assert isinstance(info, dict)
    for arr in (obs.local, obs.message, obs.trigger):
        assert arr.shape == (n, 2)
    np.testing.assert_array_equal(obs.local, obs.message)
    np.testing.assert_array_equal(obs.local, obs.trigger)
    obs, rewards, terminated, truncated, info = env.step_arrays(np.zeros((n, 1)))
    assert obs.local.shape == (n, 2) and rewards.shape == (n,)
    assert terminated is False and truncated is False
    a, b, q, r, w = env.joint_matrices()
    assert a.shape == q.shape == w.shape == (2 * n, 2 * n)
    assert b.shape == (2 * n, n) and r.shape == (n, n)
    # Dictionary API.
    d_obs, d_info = env.reset(seed=2)
    assert set(d_obs) == set(env.possible_agents)
    assert all(o.shape == (2,) and o.dtype == np.float32 for o in d_obs.values())
    d_obs, d_rew, d_term, d_trunc, _ = env.step({a_: np.array([0.1], dtype=np.float32) for a_ in env.agents})
    assert set(d_rew) == set(env.possible_agents)
    assert env.state().shape == (4 * n,)


def test_observation_is_a_copy() -> None:
    """Writing into a returned observation changes neither the state nor the messages the env keeps."""
    env = LinearSystem()
    obs, _ = env.reset_arrays(seed=0)
    obs.local[:] = 123.0
    obs.message[:] = 7.0
    obs2, *_ = env.step_arrays(np.zeros((3, 1)))
    env2 = LinearSystem()
    env2.reset_arrays(seed=0)
    ref, *_ = env2.step_arrays(np.zeros((3, 1)))  # the same step without the writes
    np.testing.assert_allclose(obs2.local, ref.local)
    np.testing.assert_allclose(obs2.message, ref.message)


@pytest.mark.parametrize("n", [2, 3, 20])
def test_rewards_sum_to_joint_cost(n: int) -> None:
    env = LinearSystem(n_agents=n, init_std=1.0, q_reg=0.7, q_vel=0.3, q_form=2.0, r=0.2)
    _, _, q, r, _ = env.joint_matrices()
    rng = np.random.default_rng(5)
    obs, _ = env.reset_arrays(seed=3)
    for _ in range(5):
        x = obs.local.copy()
        u = rng.uniform(-3.0, 3.0, size=(n, 1))
        obs, rewards, *_ = env.step_arrays(u)
        # Reward is the stage cost of the state *before* the transition and this control.
        xs = x.reshape(-1)
        joint = xs @ q @ xs + u[:, 0] @ r @ u[:, 0]
        assert rewards.sum() == pytest.approx(-joint, rel=1e-12)
        np.testing.assert_allclose(rewards, explicit_rewards(x, u[:, 0], env), rtol=1e-12)
        # It is not the cost of the state after the transition.
        xn = obs.local.reshape(-1)
        assert not np.isclose(rewards.sum(), -(xn @ q @ xn + u[:, 0] @ r @ u[:, 0]))


def test_formation_weights_in_joint_cost() -> None:
    # Hand-computed case, N=3, e = (1, 0, 3), v = 0, u = 0: q_reg*(1+0+9) + q_form*(1 + 9);
    # per agent: own q_reg e_i^2 plus half of each adjacent edge (edges cost 0.5 and 4.5).
    env = LinearSystem(n_agents=3, q_reg=2.0, q_vel=5.0, q_form=0.5)
    _, _, q, _, _ = env.joint_matrices()
    x = np.array([1.0, 0.0, 0.0, 0.0, 3.0, 0.0])
    assert x @ q @ x == pytest.approx(2.0 * 10 + 0.5 * 10)
    np.testing.assert_allclose(explicit_rewards(x.reshape(3, 2), np.zeros(3), env), [-2.25, -2.5, -20.25])


@pytest.mark.parametrize("n", [2, 20])
def test_transition_without_noise(n: int) -> None:
    dt = 0.2
    env = LinearSystem(n_agents=n, dt=dt, noise_pos=0.0, noise_vel=0.0, jump_prob=0.0, init_std=1.0)
    a, b, _, _, w = env.joint_matrices()
    assert np.all(w == 0)
    rng = np.random.default_rng(0)
    obs, _ = env.reset_arrays(seed=11)
    for _ in range(4):
        x = obs.local.copy()
        u = rng.uniform(-2.0, 2.0, size=(n, 1))
        obs, *_ = env.step_arrays(u)
        np.testing.assert_allclose(obs.local.reshape(-1), a @ x.reshape(-1) + b @ u[:, 0], rtol=1e-12)
        # The same written out for a double integrator.
        np.testing.assert_allclose(obs.local[:, 0], x[:, 0] + dt * x[:, 1] + 0.5 * dt**2 * u[:, 0])
        np.testing.assert_allclose(obs.local[:, 1], x[:, 1] + dt * u[:, 0])


def test_controls_are_clipped() -> None:
    env = LinearSystem(n_agents=2, noise_pos=0.0, noise_vel=0.0, jump_prob=0.0, u_max=2.0, dt=0.5)
    obs, _ = env.reset_arrays(seed=0)
    x = obs.local.copy()
    obs, rewards, *_ = env.step_arrays(np.array([[100.0], [-100.0]]))
    u = np.array([2.0, -2.0])
    np.testing.assert_allclose(obs.local[:, 1], x[:, 1] + 0.5 * u)
    np.testing.assert_allclose(rewards, explicit_rewards(x, u, env))


def test_noise_and_initial_statistics() -> None:
    # One step from the origin with zero control gives x1 = w; reset gives x0 ~ N(0, init_std^2).
    env = LinearSystem(n_agents=20, init_std=0.0, noise_pos=0.03, noise_vel=0.2, jump_prob=0.0)
    samples = []
    for seed in range(200):
        obs, _ = env.reset_arrays(seed=seed)
        assert np.all(obs.local == 0)
        obs, *_ = env.step_arrays(np.zeros((20, 1)))
        samples.append(obs.local)
    std = np.concatenate(samples).std(axis=0)  # 4000 samples: standard error of the std about 1.1 %
    np.testing.assert_allclose(std, [0.03, 0.2], rtol=0.05)
    env = LinearSystem(n_agents=20, init_std=0.7)
    x0 = np.concatenate([env.reset_arrays(seed=s)[0].local for s in range(200)])
    np.testing.assert_allclose(x0.std(axis=0), [0.7, 0.7], rtol=0.05)


def rollout(env: LinearSystem, seed: int | None, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    obs, _ = env.reset_arrays(seed=seed)
    states, rewards = [obs.local], []
    for u in controls:
        obs, rew, *_ = env.step_arrays(u)
        states.append(obs.local)
        rewards.append(rew)
    return np.array(states), np.array(rewards)


def test_seeding() -> None:
    controls = np.random.default_rng(0).uniform(-1, 1, size=(20, 3, 1))
    env_a, env_b = LinearSystem(), LinearSystem()
    xa, ra = rollout(env_a, 42, controls)
    xb, rb = rollout(env_b, 42, controls)
    np.testing.assert_array_equal(xa, xb)
    np.testing.assert_array_equal(ra, rb)
    # Another seed gives another episode.
    xc, _ = rollout(env_b, 43, controls)
    assert not np.allclose(xa, xc)
    # None continues the generator: a new episode, the same on both envs, and reseeding repeats.
    xa2, _ = rollout(env_a, None, controls)
    assert not np.allclose(xa2, xa)
    env_c = LinearSystem()
    rollout(env_c, 42, controls)
    xc2, _ = rollout(env_c, None, controls)
    np.testing.assert_array_equal(xa2, xc2)
    xa3, _ = rollout(env_a, 42, controls)
    np.testing.assert_array_equal(xa3, xa)
    # The dictionary API seeds the same way.
    d_obs, _ = LinearSystem().reset(seed=42)
    np.testing.assert_allclose(np.stack(list(d_obs.values())), xa[0].astype(np.float32))


def test_truncation_and_episode_end() -> None:
    env = LinearSystem(n_agents=2, max_cycles=5)
    with pytest.raises(RuntimeError):
        env.step_arrays(np.zeros((2, 1)))  # no reset yet
    env.reset_arrays(seed=0)
    for k in range(5):
        _, _, terminated, truncated, info = env.step_arrays(np.zeros((2, 1)))
        assert terminated is False
        assert truncated == (k == 4)
        assert info == {}
    assert env.agents == []
    with pytest.raises(RuntimeError):
        env.step_arrays(np.zeros((2, 1)))
    env.reset_arrays()
    assert env.agents == env.possible_agents


def test_parallel_api() -> None:
    parallel_api_test(LinearSystem(), num_cycles=100)


def test_metadata() -> None:
    assert LinearSystem.metadata == {"render_modes": [], "name": "linear_etc_v0", "is_parallelizable": True}


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"n_agents": 1}, "n_agents"),
        ({"n_agents": 0}, "n_agents"),
        ({"n_agents": 2.5}, "n_agents"),
        ({"n_agents": True}, "n_agents"),
        ({"dt": 0.0}, "dt"),
        ({"dt": -0.1}, "dt"),
        ({"q_reg": -1.0}, "q_reg"),
        ({"q_vel": -1.0}, "q_vel"),
        ({"q_form": -0.1}, "q_form"),
        ({"r": 0.0}, "r"),
        ({"noise_pos": -0.01}, "noise_pos"),
        ({"noise_vel": -0.01}, "noise_vel"),
        ({"noise_vel": float("nan")}, "noise_vel"),
        ({"init_std": -1.0}, "init_std"),
        ({"u_max": 0.0}, "u_max"),
        ({"max_cycles": 0}, "max_cycles"),
    ],
)
def test_bad_parameters(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        LinearSystem(**kwargs)


def test_zero_weights_are_allowed_but_lqr_needs_q_reg() -> None:
    env = LinearSystem(q_reg=0.0, q_vel=0.0, q_form=0.0, noise_pos=0.0, noise_vel=0.0, jump_prob=0.0, init_std=0.0)
    env.reset_arrays(seed=0)
    env.step_arrays(np.zeros((3, 1)))
    with pytest.raises(ValueError, match="q_reg"):
        lqr_gain(env)


@pytest.mark.parametrize("bad", [np.zeros(3), np.zeros((4, 1)), np.zeros((3, 2)), np.full((3, 1), np.nan)])
def test_bad_control(bad: np.ndarray) -> None:
    env = LinearSystem()
    env.reset_arrays(seed=0)
    with pytest.raises(ValueError):
        env.step_arrays(bad)


# ----------------------------------------------------------------------------- LQR
def test_lqr_gain_solves_the_riccati_equation() -> None:
    env = LinearSystem(n_agents=4)
    a, b, q, r, w = env.joint_matrices()
    k, p = lqr_gain(env)
    assert k.shape == (4, 8) and p.shape == (8, 8)
    residual = a.T @ p @ a - a.T @ p @ b @ np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a) + q - p
    assert np.abs(residual).max() < 1e-8 * np.abs(p).max()
    assert np.max(np.abs(np.linalg.eigvals(a - b @ k))) < 1.0
    # trace(P W) equals the stationary expected stage cost trace((Q + K'RK) S).
    s = scipy.linalg.solve_discrete_lyapunov(a - b @ k, w)
    assert lqr_cost_per_step(env) == pytest.approx(np.trace((q + k.T @ r @ k) @ s), rel=1e-8)
    assert lqr_reward_per_step(env) == pytest.approx(-lqr_cost_per_step(env) / 4)
    # Coupling: the gain of agent 0 depends on agent 1's position error (formation term).
    assert abs(k[0, 2]) > 1e-3
    assert lqr_cost_per_step(LinearSystem(n_agents=4, noise_pos=0.0, noise_vel=0.0, jump_prob=0.0)) == 0.0


def test_lqr_controller_matches_gain() -> None:
    env = LinearSystem(n_agents=3)
    ctrl = LQRController(env)
    k, _ = lqr_gain(env)
    x = np.random.default_rng(1).normal(size=(5, 7, 3, 2))
    u = ctrl(x)
    assert u.shape == (5, 7, 3, 1)
    np.testing.assert_allclose(u[2, 3, :, 0], -k @ x[2, 3].reshape(-1))
    assert ctrl(x[0, 0]).shape == (3, 1)
    with pytest.raises(ValueError):
        ctrl(np.zeros((4, 2)))
    with pytest.raises(ValueError):
        LQRController(env, gain=np.zeros((3, 3)))


def simulated_cost(env: LinearSystem, ctrl: LQRController, steps: int, burn_in: int, batch: int, seed: int):
    """Mean team cost per step and its standard error from batch means, simulated with the env."""
    obs, _ = env.reset_arrays(seed=seed)
    costs = np.empty(burn_in + steps)
    for k in range(burn_in + steps):
        obs, rewards, _, truncated, _ = env.step_arrays(ctrl(obs.local))
        assert not truncated
        costs[k] = -rewards.sum()
    means = costs[burn_in:].reshape(-1, batch).mean(axis=1)
    return means.mean(), means.std(ddof=1) / np.sqrt(len(means))


@pytest.mark.parametrize(("n", "steps"), [(3, 40_000), (20, 10_000)])
def test_lqr_cost_matches_simulation(n: int, steps: int) -> None:
    env = LinearSystem(n_agents=n, max_cycles=10**9)
    a, b, q, r, w = env.joint_matrices()
    theory = lqr_cost_per_step(env)
    mean, se = simulated_cost(env, LQRController(env), steps, burn_in=300, batch=500, seed=123)
    assert se < 0.05 * theory  # the test has power
    assert abs(mean - theory) < 4 * se, (mean, theory, se)

    # A detuned controller is clearly worse, in theory and in simulation.
    k, _ = lqr_gain(env)
    worse = 0.5 * k
    s = scipy.linalg.solve_discrete_lyapunov(a - b @ worse, w)
    theory_worse = np.trace((q + worse.T @ r @ worse) @ s)
    mean_w, se_w = simulated_cost(env, LQRController(env, gain=worse), steps, burn_in=300, batch=500, seed=123)
    assert abs(mean_w - theory_worse) < 4 * se_w, (mean_w, theory_worse, se_w)
    assert mean_w > theory + 10 * max(se, se_w)


def episode_costs(system: LinearSystem, controller: LQRController, seeds: range) -> np.ndarray:
    costs = []
    for seed in seeds:
        obs, _ = system.reset_arrays(seed)
        total, done = 0.0, False
        while not done:
            obs, rewards, terminated, truncated, _ = system.step_arrays(controller(obs.message))
            total -= rewards.sum()
            done = terminated or truncated
        costs.append(total)
    return np.array(costs)


def test_lqr_episode_cost_of_a_single_step_is_the_initial_stage_cost():
    system = LinearSystem(n_agents=3, max_cycles=1, init_std=0.3)
    _, _, q, _, _ = system.joint_matrices()
    assert lqr_episode_cost(system) == pytest.approx(0.09 * np.trace(q))


def test_lqr_episode_cost_bounds_simulated_episodes():
    system = LinearSystem(n_agents=3, max_cycles=40)
    bound = lqr_episode_cost(system)
    controller = LQRController(system)
    costs = episode_costs(system, controller, range(300))
    mean, sem = costs.mean(), costs.std() / np.sqrt(len(costs))
    # the stationary gain is near-optimal on a finite horizon: not below the bound, and close to it
    assert bound - 3 * sem < mean < 1.05 * bound + 3 * sem
    # a detuned controller is clearly worse, so the check can fail
    lazy = LQRController(system, gain=0.3 * controller.gain)
    assert episode_costs(system, lazy, range(100)).mean() > 1.2 * bound


def test_lqr_on_views_uses_own_state_and_held_others():
    system = LinearSystem(n_agents=3)
    controller = LQRController(system)
    rng = np.random.default_rng(4)
    held, own = rng.normal(size=(3, 2)), rng.normal(size=(3, 2))
    controls = controller.on_views(held, own)
    for i in range(3):
        view = held.copy()
        view[i] = own[i]
        np.testing.assert_allclose(controls[i, 0], -controller.gain[i] @ view.ravel())
    # with every broadcast fresh, it is the centralised law
    np.testing.assert_allclose(controller.on_views(own, own), controller(own))
