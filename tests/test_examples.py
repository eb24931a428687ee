"""The example of a user's own system (examples/custom_system.py): its env, its training script, rl-zoo3."""

from __future__ import annotations

import importlib
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import SubprocVecEnv

ROOT = Path(__file__).parents[1]
EXAMPLES = ROOT / "examples"
ENV_ID = "myteam/Consensus-v0"


@pytest.fixture(scope="module")
def example() -> Iterator[ModuleType]:
    """The example imported as the module ``custom_system``, as ``--gym-packages custom_system`` imports it."""
    sys.path.insert(0, str(EXAMPLES))
    try:
        yield importlib.import_module("custom_system")
    finally:
        sys.path.remove(str(EXAMPLES))


def with_examples_on_path() -> dict[str, str]:
    """The environment of a subprocess that can import ``custom_system``."""
    path = os.pathsep.join(p for p in [str(EXAMPLES), os.environ.get("PYTHONPATH", "")] if p)
    return {**os.environ, "PYTHONPATH": path}


# ----------------------------------------------------------------------------- the system and its views
def test_importing_registers_the_id(example: ModuleType) -> None:
    assert ENV_ID in gym.registry
    env = gym.make(ENV_ID, broadcast_cost=0.2, n_agents=5, max_cycles=7)
    assert env.unwrapped.network.broadcast_cost == 0.2 and env.unwrapped.n_agents == 5
    assert env.observation_space["held"].shape == (5, 1) and env.action_space["control"].shape == (5, 1)
    env.reset(seed=0)
    steps = 0
    truncated = False
    while not truncated:
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        assert not terminated and info["agent_rewards"].shape == (5,)
        steps += 1
    assert steps == 7


def test_system_passes_the_pettingzoo_api_test(example: ModuleType) -> None:
    parallel_api_test(example.HeadingConsensus(max_cycles=50), num_cycles=120)
    # a convoy that breaks up at once: terminated episodes too
    parallel_api_test(example.HeadingConsensus(max_cycles=50, max_gap=0.05), num_cycles=120)


def test_network_view_passes_the_pettingzoo_api_test(example: ModuleType) -> None:
    parallel_api_test(example.parallel_env(max_cycles=50), num_cycles=120)


def test_joint_view_passes_the_gymnasium_env_checker(example: ModuleType) -> None:
    check_env(gym.make(ENV_ID, max_cycles=50).unwrapped, skip_render_check=True)


def test_joint_view_vectorises(example: ModuleType) -> None:
    vec_env = make_vec_env(ENV_ID, n_envs=2, seed=0)
    obs = vec_env.reset()
    assert obs["local"].shape == (2, 4, 1)
    vec_env.step([vec_env.action_space.sample() for _ in range(2)])
    vec_env.close()
    # worker processes import the example themselves through gymnasium's "module:id" form
    vec_env = make_vec_env(f"custom_system:{ENV_ID}", n_envs=2, seed=0, vec_env_cls=SubprocVecEnv)
    try:
        assert vec_env.reset()["message"].shape == (2, 4, 1)
    finally:
        vec_env.close()


def test_only_the_lead_knows_the_course_and_rewards_split_the_team_cost(example: ModuleType) -> None:
    system = example.HeadingConsensus(n_agents=3, noise_std=0.0, course_change_prob=0.0, r=0.5)
    obs, _ = system.reset_arrays(seed=3)
    heading, course = system.heading.copy(), system.course
    np.testing.assert_allclose(obs.local[:, 0], [course - heading[0], 0.0, 0.0])
    np.testing.assert_allclose(obs.message[:, 0], heading)
    np.testing.assert_allclose(obs.trigger[:, 0], heading)

    turn = np.array([[1.0], [-0.5], [0.0]])
    obs, rewards, terminated, truncated, info = system.step_arrays(turn)
    after = heading + 0.2 * turn[:, 0]
    np.testing.assert_allclose(obs.message[:, 0], after)
    team_cost = (after[0] - course) ** 2 + np.sum(np.diff(after) ** 2) + 0.5 * np.sum(turn**2)
    np.testing.assert_allclose(rewards.sum(), -team_cost)
    assert not terminated and not truncated and info == {"failed": False}


def test_the_convoy_breaks_up_only_with_max_gap(example: ModuleType) -> None:
    turn = np.array([[2.0], [-2.0]])
    loose = example.HeadingConsensus(n_agents=2, max_cycles=20)
    tight = example.HeadingConsensus(n_agents=2, max_cycles=20, max_gap=1.0, breakup_penalty=7.0)
    loose.reset_arrays(seed=0)
    tight.reset_arrays(seed=0)
    for _ in range(20):
        _, loose_rewards, loose_terminated, _, _ = loose.step_arrays(turn)
        _, rewards, terminated, truncated, info = tight.step_arrays(turn)
        assert not loose_terminated
        if terminated:
            break
    assert terminated and not truncated and info["failed"]
    assert abs(np.diff(tight.heading)[0]) > 1.0
    np.testing.assert_allclose(rewards, loose_rewards - 7.0)
    assert not tight.agents  # the episode is over


def test_same_seed_same_episode(example: ModuleType) -> None:
    env = example.joint_env(max_cycles=30)
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=5)
        headings = [obs["message"]]
        for _ in range(30):
            obs, *_ = env.step({"broadcast": np.ones(4, dtype=np.int64), "control": np.full((4, 1), 0.3)})
            headings.append(obs["message"])
        runs.append(np.stack(headings))
    np.testing.assert_array_equal(runs[0], runs[1])


@pytest.mark.parametrize("kwargs", [{"n_agents": 1}, {"dt": 0.0}, {"r": -1.0}, {"course_change_prob": 2.0}])
def test_bad_parameters_are_rejected(example: ModuleType, kwargs: dict) -> None:
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        example.HeadingConsensus(**kwargs)


# ----------------------------------------------------------------------------- the script and rl-zoo3
# The envs run in MAPPOC's worker processes, which import the example by the module named in its id.
@pytest.mark.filterwarnings("error:worker processes could not make")
def test_example_trains_evaluates_and_runs_decentralised(example: ModuleType, capsys: pytest.CaptureFixture) -> None:
    example.main(["--timesteps", "1024", "--episodes", "2", "--seed", "1"])
    out = capsys.readouterr().out
    assert f"trained 1024 steps on {ENV_ID}" in out
    assert "| options | return | control return | savings |" in out
    number = r"(-?\d+\.\d+)"
    table = {
        name: tuple(float(value) for value in values)
        for name, *values in re.findall(rf"^\| ([a-z, ]+) \| {number} \| {number} \| {number} \|$", out, re.M)
    }
    assert list(table) == ["learned triggers", "random, same rate", "always broadcast"]
    assert table["always broadcast"][2] == 0.0
    for name, (episode_return, control_return, savings) in table.items():
        # Per agent and episode of 100 steps, each broadcast costs 0.05: 5 (1 - savings) in all (printed rounded).
        assert episode_return == pytest.approx(control_return - 5.0 * (1.0 - savings), abs=0.015), name
    decentralised = re.search(
        r"decentralised episode: return -?[\d.]+, (\d+) broadcasts in 100 steps \(per vessel: (.*)\)", out
    )
    assert decentralised is not None, out
    per_vessel = [int(count) for count in decentralised[2].split(", ")]
    assert len(per_vessel) == 4 and sum(per_vessel) == int(decentralised[1])
    assert all(0 <= count <= 100 for count in per_vessel)  # at most one broadcast per vessel and step


def test_example_id_trains_through_the_command_line(tmp_path: Path) -> None:
    command = [
        *(sys.executable, "-m", "sb3_detc.train", "--algo", "mappoc", "--env", ENV_ID),
        *("--gym-packages", "custom_system", "-conf", str(EXAMPLES / "custom_system.yml")),
        *("-n", "512", "-f", str(tmp_path), "--eval-freq", "-1", "--num-threads", "1", "--verbose", "0"),
    ]
    done = subprocess.run(command, cwd=ROOT, env=with_examples_on_path(), capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "mappoc" / "myteam-Consensus-v0_1" / "myteam-Consensus-v0.zip").is_file()
