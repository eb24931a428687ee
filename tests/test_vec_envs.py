"""Vector envs around MAPPOC: worker processes that know the ids, and which VecNormalize the policy can use."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

from sb3_detc import MAPPOC

LINEAR = "sb3_detc/LinearETC-v0"


def python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, check=False)


# ----------------------------------------------------------------------------- worker processes
def test_worker_processes_know_the_ids_when_the_main_module_does_not_import_the_package(tmp_path: Path) -> None:
    code = """
def main():
    import sb3_detc  # noqa: F401  (only here: the main module itself does not import it)
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    env = make_vec_env("sb3_detc/LinearETC-v0", n_envs=2, vec_env_cls=SubprocVecEnv)
    env.reset()
    _, rewards, _, _ = env.step([env.action_space.sample() for _ in range(env.num_envs)])
    env.close()
    print("stepped", len(rewards))


main()
"""
    result = python(code, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "stepped 2" in result.stdout


def test_the_forkserver_preload_list_of_the_user_is_kept(tmp_path: Path) -> None:
    code = """
import multiprocessing
import multiprocessing.forkserver

multiprocessing.set_forkserver_preload(["json"])
import sb3_detc  # noqa: E402

print(multiprocessing.forkserver._forkserver._preload_modules)
"""
    result = python(code, tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "['json', 'sb3_detc']"


# ----------------------------------------------------------------------------- VecNormalize
def test_vec_normalize_of_the_network_observations_is_refused(tmp_path: Path) -> None:
    refused = r"normalises the observations 'message', 'held', 'age', 'trigger', 'trigger_held'"
    with pytest.raises(ValueError, match=refused + r".*norm_obs_keys=\['local'\]"):
        MAPPOC("MlpHybridPolicy", VecNormalize(make_vec_env(LINEAR)))
    with pytest.raises(ValueError, match="normalises the observations 'held'"):  # anywhere in the wrappers
        MAPPOC("MlpHybridPolicy", VecMonitor(VecNormalize(make_vec_env(LINEAR), norm_obs_keys=["local", "held"])))

    model = MAPPOC("MlpHybridPolicy", make_vec_env(LINEAR), n_steps=8, batch_size=8, policy_kwargs={"net_arch": [8]})
    with pytest.raises(ValueError, match="VecNormalize"):
        model.set_env(VecNormalize(make_vec_env(LINEAR)))
    model.save(tmp_path / "model.zip")
    with pytest.raises(ValueError, match="VecNormalize"):
        MAPPOC.load(tmp_path / "model.zip", env=VecNormalize(make_vec_env(LINEAR)))


def test_vec_normalize_of_the_local_state_or_the_rewards_is_allowed(tmp_path: Path) -> None:
    for env in (
        VecNormalize(make_vec_env(LINEAR), norm_obs_keys=["local"]),
        VecNormalize(make_vec_env(LINEAR), norm_obs=False),
    ):
        model = MAPPOC("MlpHybridPolicy", env, n_steps=8, batch_size=8, n_epochs=1, policy_kwargs={"net_arch": [8]})
        model.learn(16)
        model.set_env(env)
        model.save(tmp_path / "model.zip")
        assert MAPPOC.load(tmp_path / "model.zip", env=env).get_vec_normalize_env() is env
