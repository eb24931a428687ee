"""The event-triggered network wrapper and the joint Gymnasium view, on the linear system."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st
from pettingzoo.test import parallel_api_test

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.envs import linear_etc_v0
from sb3_detc.envs.linear import LinearSystem
from sb3_detc.envs.wrappers import EventTriggeredNetwork, JointEnv


def joint(**kwargs) -> JointEnv:
    return gym.make("sb3_detc/LinearETC-v0", **kwargs).unwrapped


def test_parallel_api():
    parallel_api_test(linear_etc_v0.parallel_env(max_cycles=50), num_cycles=120)


def test_gymnasium_env_checker():
    check_env(joint(max_cycles=50), skip_render_check=True)


def test_kwargs_reach_network_and_system():
    env = joint(broadcast_cost=0.7, n_agents=5, max_cycles=9)
    assert env.network.broadcast_cost == 0.7
    assert env.n_agents == 5 and env.network.system.max_cycles == 9
    assert env.observation_space["held"].shape == (5, 2)
    assert env.action_space["broadcast"].nvec.tolist() == [2] * 5


@settings(max_examples=30, deadline=None)
@given(st.data())
def test_held_age_and_cost_follow_the_broadcasts(data):
    n_agents = data.draw(st.integers(2, 5))
    n_steps = data.draw(st.integers(1, 25))
    xi = data.draw(st.floats(0.0, 2.0))
    options = np.array(
        data.draw(
            st.lists(
                st.lists(st.integers(0, 1), min_size=n_agents, max_size=n_agents), min_size=n_steps, max_size=n_steps
            )
        )
    )
    env = joint(n_agents=n_agents, broadcast_cost=xi, max_cycles=n_steps)
    obs, _ = env.reset(seed=data.draw(st.integers(0, 2**16)))
    last_sent = obs["message"].copy()  # the initial message counts as received
    last_step = np.full(n_agents, -1)
    rng = np.random.default_rng(0)
    for k, broadcast in enumerate(options):
        before = obs
        control = rng.uniform(-1, 1, size=(n_agents, 1))
        obs, reward, terminated, truncated, info = env.step({"broadcast": broadcast, "control": control})
        last_sent[broadcast == 1] = before["message"][broadcast == 1]
        last_step[broadcast == 1] = k
        np.testing.assert_array_equal(obs["held"], last_sent)
        np.testing.assert_array_equal(obs["age"][:, 0], np.where(last_step >= 0, k - last_step, k + 1))
        np.testing.assert_allclose(info["agent_rewards"], info["control_rewards"] - xi * broadcast)
        assert reward == pytest.approx(info["agent_rewards"].mean())
        np.testing.assert_array_equal(info["broadcast"], broadcast)
        np.testing.assert_array_equal(info["broadcasts"], options[: k + 1].sum(0))
    assert truncated and not terminated


def test_age_counts_steps_since_last_broadcast():
    env = joint(n_agents=2, max_cycles=10)
    env.reset(seed=0)
    ages = []
    for broadcast in ([0, 1], [0, 0], [1, 0], [0, 0]):
        obs, *_ = env.step({"broadcast": np.array(broadcast), "control": np.zeros((2, 1))})
        ages.append(obs["age"][:, 0].tolist())
    # agent 0 was last "heard" at reset; agent 1 broadcast at step 0, agent 0 at step 2
    assert ages == [[1, 0], [2, 1], [0, 2], [1, 3]]


def test_agent_views_are_relative_to_own_current_message():
    env = linear_etc_v0.parallel_env(n_agents=3)
    obs, _ = env.reset(seed=3)
    for _ in range(5):
        actions = {a: {"broadcast": 0, "control": np.array([0.5])} for a in env.agents}
        obs, *_ = env.step(actions)
    message = env.system.last_obs.message
    held = env.held
    for i, agent in enumerate(env.possible_agents):
        others = [j for j in range(3) if j != i]
        np.testing.assert_allclose(obs[agent]["neighbours"], held[others] - message[i], rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(obs[agent]["neighbour_age"], [5, 5])
        np.testing.assert_array_equal(obs[agent]["local"], message[i].astype(np.float32))


def test_same_seed_same_episode_and_new_episodes_differ():
    def rollout(env, seed):
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(1)
        out = [obs["local"]]
        for _ in range(20):
            obs, r, *_ = env.step({"broadcast": rng.integers(0, 2, 3), "control": rng.uniform(-1, 1, (3, 1))})
            out.append(obs["local"])
        return np.array(out)

    a, b = joint(), joint()
    np.testing.assert_array_equal(rollout(a, 7), rollout(b, 7))
    first = a.reset(seed=7)[0]["local"]
    assert not np.array_equal(first, a.reset()[0]["local"])


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf")])
def test_negative_or_non_finite_broadcast_cost_is_rejected(bad):
    with pytest.raises(ValueError, match="broadcast_cost"):
        linear_etc_v0.parallel_env(broadcast_cost=bad)


def test_bad_actions_are_rejected_with_clear_errors():
    env = joint(n_agents=3, max_cycles=2)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="0 \\(silent\\) or 1"):
        env.step({"broadcast": np.array([0, 2, 1]), "control": np.zeros((3, 1))})
    with pytest.raises(ValueError, match="broadcast must have shape \\(3,\\)"):
        env.step({"broadcast": np.array([0, 1]), "control": np.zeros((3, 1))})
    with pytest.raises(ValueError, match="control must have shape \\(3, 1\\)"):
        env.step({"broadcast": np.array([0, 1, 1]), "control": np.zeros((3, 2))})
    with pytest.raises(ValueError, match="NaN"):
        env.step({"broadcast": np.array([0, 1, 1]), "control": np.full((3, 1), np.nan)})
    with pytest.raises(ValueError, match="keys 'broadcast' and 'control'"):
        env.step(np.zeros(3))
    for _ in range(2):
        env.step({"broadcast": np.ones(3, dtype=int), "control": np.zeros((3, 1))})
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"broadcast": np.ones(3, dtype=int), "control": np.zeros((3, 1))})


def test_failed_step_leaves_the_network_unchanged():
    env = joint(n_agents=2)
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError):
        env.step({"broadcast": np.array([0, 1]), "control": np.full((2, 1), np.nan)})
    np.testing.assert_array_equal(env.network.held.astype(np.float32), obs["held"])
    np.testing.assert_array_equal(env.network.age, [[0], [0]])
    assert env.network.broadcasts.tolist() == [0, 0]


def test_parallel_step_rejects_missing_agents_and_malformed_actions():
    env = linear_etc_v0.parallel_env(n_agents=2)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="missing"):
        env.step({"agent_0": {"broadcast": 1, "control": np.zeros(1)}})
    with pytest.raises(ValueError, match="'broadcast' and 'control'"):
        env.step({"agent_0": np.zeros(1), "agent_1": np.zeros(1)})


def test_wrappers_reject_wrong_inputs():
    with pytest.raises(TypeError, match="CommunicatingSystem"):
        EventTriggeredNetwork(gym.make("CartPole-v1"))
    with pytest.raises(TypeError, match="EventTriggeredNetwork"):
        JointEnv(LinearSystem())
    with pytest.raises(ValueError, match="trigger"):
        linear_etc_v0.parallel_env(trigger="lidar")


def test_trigger_source_is_configurable():
    env = joint(trigger="local")
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs["trigger"], obs["local"])


def test_multiwalker_parallel_api_and_env_checker():
    from sb3_detc.envs import multiwalker_etc_v0

    parallel_api_test(multiwalker_etc_v0.parallel_env(max_cycles=60), num_cycles=150)
    env = gym.make("sb3_detc/MultiwalkerETC-v0", max_cycles=60).unwrapped
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert obs["local"].shape == (3, 17) and obs["message"].shape == (3, 4)
    assert obs["trigger"].shape == (3, 3) and obs["trigger_held"].shape == (3, 3)
    assert env.action_space["control"].shape == (3, 4)
    assert env.network.broadcast_cost == 0.25
    assert "package_x" in info
    penv = multiwalker_etc_v0.parallel_env()
    penv.reset(seed=0)
    _, rewards, _, _, infos = penv.step({a: {"broadcast": 1, "control": np.zeros(4)} for a in penv.agents})
    for agent in penv.possible_agents:
        assert infos[agent]["package_x"] == penv.system.physics.package.position.x
        assert infos[agent]["broadcast"] == 1 and infos[agent]["broadcasts"] == 1
        assert rewards[agent] == pytest.approx(infos[agent]["control_reward"] - 0.25)


def test_multiwalker_rejects_too_few_walkers():
    with pytest.raises(ValueError, match="n_walkers"):
        gym.make("sb3_detc/MultiwalkerETC-v0", n_walkers=1)
