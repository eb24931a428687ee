"""Tests of the modified Multiwalker (method.md, Sec. 5)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from pettingzoo.sisl.multiwalker import multiwalker_base as stock
from pettingzoo.test import parallel_api_test

from sb3_detc.envs.multiwalker import MultiwalkerSystem

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

VX_SCALE = 0.3 * (600 / 30) / 50  # 0.12
VY_SCALE = 0.3 * (400 / 30) / 50  # 0.08


def _run(env: MultiwalkerSystem, seed: int, n_steps: int) -> list:
    """Reset with ``seed`` and step random controls, resetting (no seed) at episode ends."""
    rng = np.random.default_rng(seed)
    obs, info = env.reset_arrays(seed=seed)
    trace = [(obs.local, obs.message, obs.trigger, info["package_x"])]
    for _ in range(n_steps):
        obs, rewards, terminated, truncated, info = env.step_arrays(rng.uniform(-1, 1, (env.n_agents, 4)))
        trace.append((obs.local, obs.message, obs.trigger, rewards, terminated, truncated, info["package_x"]))
        if terminated or truncated:
            obs, _ = env.reset_arrays()
            trace.append((obs.local, obs.message))
    return trace


def _expected_obs(env: MultiwalkerSystem) -> tuple[np.ndarray, np.ndarray]:
    """Local states and messages recomputed from the Box2D bodies."""
    physics = env.physics
    package = physics.package
    length = physics.package_length
    local, message = [], []
    for walker in physics.walkers:
        hull, joints, legs = walker.hull, walker.joints, walker.legs
        pos, vel = hull.position, hull.linearVelocity
        own = [hull.angle, 2.0 * hull.angularVelocity / 50, VX_SCALE * vel.x, VY_SCALE * vel.y]
        for joint_hip, joint_knee, foot in ((joints[0], joints[1], legs[1]), (joints[2], joints[3], legs[3])):
            own += [joint_hip.angle, joint_hip.speed / 4, joint_knee.angle + 1.0, joint_knee.speed / 6]
            own += [1.0 if foot.ground_contact else 0.0]
        package_rel = [(package.position.x - pos.x) / length, (package.position.y - pos.y) / length, package.angle]
        local.append(package_rel + own)
        message.append([pos.x / length, pos.y / length, VX_SCALE * vel.x, VX_SCALE * vel.y])
    return np.array(local), np.array(message)


@pytest.mark.parametrize("n_walkers", [2, 3, 5])
def test_shapes_and_values(n_walkers: int) -> None:
    env = MultiwalkerSystem(n_walkers=n_walkers)
    assert env.possible_agents == [f"walker_{i}" for i in range(n_walkers)]
    assert env.local_space.shape == (17,)
    assert env.message_space.shape == (4,)
    assert env.trigger_space.shape == (3,)
    assert env.control_space.shape == (4,)
    obs, _ = env.reset_arrays(seed=3)
    rng = np.random.default_rng(0)
    contacts_seen = 0.0
    for step in range(40):
        if step > 0:
            obs, _, terminated, truncated, _ = env.step_arrays(rng.uniform(-1, 1, (n_walkers, 4)))
            assert not (terminated or truncated)
        assert obs.local.shape == (n_walkers, 17)
        assert obs.message.shape == (n_walkers, 4)
        assert obs.trigger.shape == (n_walkers, 3)
        np.testing.assert_array_equal(obs.trigger, obs.local[:, :3])
        local, message = _expected_obs(env)
        np.testing.assert_allclose(obs.local, local, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(obs.message, message, rtol=1e-12, atol=1e-12)
        contacts_seen += obs.local[:, [11, 16]].sum()
    assert contacts_seen > 0  # the feet reached the ground and the flags were read


def test_message_velocity_uses_one_scale_for_both_axes() -> None:
    env = MultiwalkerSystem()
    env.reset_arrays(seed=0)
    obs, *_ = env.step_arrays(np.zeros((3, 4)))
    vel = np.array([[w.hull.linearVelocity.x, w.hull.linearVelocity.y] for w in env.physics.walkers])
    assert np.all(np.abs(vel[:, 1]) > 1e-3)  # falling onto the ground: vy is not zero
    np.testing.assert_allclose(obs.message[:, 2:], 0.12 * vel, rtol=1e-12)
    np.testing.assert_allclose(obs.local[:, 6], 0.08 * vel[:, 1], rtol=1e-12)


@pytest.mark.parametrize("action, torque", [(1.0, 120.0), (-0.5, 60.0), (3.0, 120.0)])
def test_motor_torque(action: float, torque: float) -> None:
    env = MultiwalkerSystem()
    env.reset_arrays(seed=0)
    env.step_arrays(np.full((3, 4), action))
    for walker in env.physics.walkers:
        for joint, max_speed in zip(walker.joints, (4, 6, 4, 6), strict=True):
            assert joint.GetMaxMotorTorque() == pytest.approx(torque)
            assert joint.motorSpeed == pytest.approx(np.sign(action) * max_speed)
    # The single-walker API of the stock class uses the new torque as well.
    walker = env.physics.walkers[0]
    walker.apply_action(np.array([0.25, -1.0, 0.0, 1.0]))
    torques = [joint.GetMaxMotorTorque() for joint in walker.joints]
    np.testing.assert_allclose(torques, [30.0, 120.0, 0.0, 120.0])


def test_determinism_and_fresh_episodes() -> None:
    env_a, env_b = MultiwalkerSystem(), MultiwalkerSystem()
    _run(env_a, seed=11, n_steps=30)  # some history: must not matter after reseeding
    trace_a = _run(env_a, seed=5, n_steps=150)
    trace_b = _run(env_b, seed=5, n_steps=150)
    assert len(trace_a) == len(trace_b)
    assert any(len(entry) == 2 for entry in trace_a)  # an episode ended and a new one started
    for entry_a, entry_b in zip(trace_a, trace_b, strict=True):
        for value_a, value_b in zip(entry_a, entry_b, strict=True):
            np.testing.assert_array_equal(value_a, value_b)
    # Without a new seed the generator continues: new terrain.
    terrain_a = list(env_a.physics.terrain_y)
    env_a.reset_arrays()
    assert not np.allclose(terrain_a, env_a.physics.terrain_y)
    env_b.reset_arrays(seed=5)
    env_a.reset_arrays(seed=5)
    np.testing.assert_array_equal(env_a.physics.terrain_y, env_b.physics.terrain_y)
    env_c = MultiwalkerSystem()  # no seed needed to construct and reset
    obs, _ = env_c.reset_arrays()
    assert np.all(np.isfinite(obs.local))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_walkers_get_different_initial_pushes(seed: int) -> None:
    env = MultiwalkerSystem(n_walkers=4)
    env.reset_arrays(seed=seed)
    env.step_arrays(np.zeros((4, 4)))  # the walkers are still in the air: vx comes from the push only
    vx = [walker.hull.linearVelocity.x for walker in env.physics.walkers]
    assert len(set(vx)) == 4, vx
    # ... and a new episode draws new pushes.
    env.reset_arrays()
    env.step_arrays(np.zeros((4, 4)))
    assert not np.allclose(vx, [walker.hull.linearVelocity.x for walker in env.physics.walkers])


@pytest.mark.parametrize("forward_reward, speed_penalty, seed", [(5.0, 5.0, 0), (2.0, 3.0, 4), (5.0, 0.0, 1)])
def test_reward_arithmetic_until_a_fall(forward_reward: float, speed_penalty: float, seed: int) -> None:
    env = MultiwalkerSystem(forward_reward=forward_reward, speed_penalty=speed_penalty)
    _, info = env.reset_arrays(seed=seed)
    physics = env.physics
    prev_x = physics.package.position.x
    assert info["package_x"] == prev_x
    prev_phi = np.zeros(3)  # the walkers are at rest at reset
    rng = np.random.default_rng(seed)
    for _ in range(400):
        obs, rewards, terminated, truncated, info = env.step_arrays(rng.uniform(-1, 1, (3, 4)))
        package_x = physics.package.position.x
        vx = np.array([walker.hull.linearVelocity.x for walker in physics.walkers])
        phi = -speed_penalty * np.abs(0.12 * vx)
        expected = forward_reward * 130 * (package_x - prev_x) / 30 + phi - prev_phi
        fallen = physics.fallen_walkers.copy()
        if terminated:
            break
        np.testing.assert_allclose(rewards, expected, rtol=1e-9, atol=1e-9)
        assert info["package_x"] == package_x
        prev_x, prev_phi = package_x, phi
    assert terminated and not truncated
    assert fallen.any() and not fallen.all(), "this scripted episode ends with some walkers fallen"
    np.testing.assert_allclose(rewards, expected - 100.0 - 10.0 * fallen, rtol=1e-9, atol=1e-9)
    with pytest.raises(RuntimeError, match="reset"):
        env.step_arrays(np.zeros((3, 4)))


def test_package_on_ground_or_left_of_terrain_terminates() -> None:
    env = MultiwalkerSystem()
    env.reset_arrays(seed=0)
    physics = env.physics
    # Lay the package onto the terrain far ahead of the walkers: game over, -100 for all.
    start = int(40 / stock.TERRAIN_STEP)
    top = max(physics.terrain_y[start - 16 : start + 16])
    x_before = physics.package.position.x
    physics.package.position = (start * stock.TERRAIN_STEP, top + 0.1)
    _, rewards, terminated, truncated, info = env.step_arrays(np.zeros((3, 4)))
    assert physics.game_over and not physics.fallen_walkers.any()
    assert terminated and not truncated
    vx = np.array([walker.hull.linearVelocity.x for walker in physics.walkers])
    progress = 5.0 * 130 * (info["package_x"] - x_before) / 30
    np.testing.assert_allclose(rewards, progress - 5.0 * np.abs(0.12 * vx) - 100.0, rtol=1e-9)

    env.reset_arrays(seed=0)
    x_before = physics.package.position.x
    physics.package.position = (-5.0, 20.0)  # in the air, left of the terrain
    _, rewards, terminated, _, info = env.step_arrays(np.zeros((3, 4)))
    assert terminated and info["package_x"] < 0 and not physics.game_over
    vx = np.array([walker.hull.linearVelocity.x for walker in physics.walkers])
    progress = 5.0 * 130 * (info["package_x"] - x_before) / 30
    np.testing.assert_allclose(rewards, progress - 5.0 * np.abs(0.12 * vx) - 100.0, rtol=1e-9)


def test_package_past_the_end_terminates_without_penalty() -> None:
    env = MultiwalkerSystem(terrain_length=60)
    env.reset_arrays(seed=0)
    physics = env.physics
    physics.package.position = ((60 - 10) * stock.TERRAIN_STEP + 1.0, 20.0)
    _, rewards, terminated, truncated, _ = env.step_arrays(np.zeros((3, 4)))
    assert terminated and not truncated
    assert np.all(rewards > 0)  # progress only


def test_truncation_at_max_cycles() -> None:
    env = MultiwalkerSystem(max_cycles=5)
    for seed in (0, 1):  # also after a reset
        env.reset_arrays(seed=seed)
        for step in range(1, 6):
            _, _, terminated, truncated, _ = env.step_arrays(np.zeros((3, 4)))
            assert not terminated
            assert truncated == (step == 5)
        assert env.agents == []
        with pytest.raises(RuntimeError):
            env.step_arrays(np.zeros((3, 4)))


def test_package_x_info() -> None:
    env = MultiwalkerSystem()
    _, info = env.reset_arrays(seed=0)
    assert isinstance(info["package_x"], float)
    assert info["package_x"] == pytest.approx(np.mean(env.physics.start_x))
    _, infos = env.reset(seed=0)
    assert infos["walker_1"]["package_x"] == pytest.approx(info["package_x"])
    _, _, _, _, infos = env.step({a: np.ones(4, dtype=np.float32) for a in env.agents})
    assert infos["walker_0"]["package_x"] == env.physics.package.position.x


@pytest.mark.parametrize("n_walkers", [1, 0, 41, 2.0, True, "3"])
def test_bad_n_walkers(n_walkers) -> None:
    with pytest.raises(ValueError, match="n_walkers"):
        MultiwalkerSystem(n_walkers=n_walkers)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"render_mode": "human"}, "render_mode"),
        ({"speed_penalty": -1.0}, "speed_penalty"),
        ({"max_cycles": 0}, "max_cycles"),
        ({"terrain_length": 5}, "terrain_length"),
        ({"forward_reward": float("nan")}, "forward_reward"),
    ],
)
def test_bad_arguments(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        MultiwalkerSystem(**kwargs)


def test_bad_steps() -> None:
    env = MultiwalkerSystem()
    with pytest.raises(RuntimeError):
        env.step_arrays(np.zeros((3, 4)))  # before reset
    env.reset_arrays(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step_arrays(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="shape"):
        env.step_arrays(np.zeros((3, 3)))


def test_parallel_api() -> None:
    parallel_api_test(MultiwalkerSystem(), num_cycles=200)


def test_render_rgb_array() -> None:
    env = MultiwalkerSystem(render_mode="rgb_array")
    env.reset_arrays(seed=0)
    env.step_arrays(np.ones((3, 4)))
    image = env.render()
    assert isinstance(image, np.ndarray)
    assert image.dtype == np.uint8 and image.shape == (stock.VIEWPORT_H, stock.VIEWPORT_W, 3)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 3  # sky, terrain, walkers, package
    env.close()
    assert env.render().shape == image.shape  # usable again after close
    assert MultiwalkerSystem().render() is None
