"""Rollouts sampled inside the envs (RolloutWorker) fill the buffer as rollouts sampled in the learner do."""

from __future__ import annotations

import os
import subprocess
import sys
from typing import Any

import numpy as np
import pytest
import torch as th
from logged import capture_logger  # tests/logged.py
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.callbacks import CommMetricsCallback
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.sampling import has_rollout_workers
from sb3_detc.mappoc.workers import RolloutWorker, check_finite
from sb3_detc.triggers import DitheredTrigger, PeriodicTrigger, RandomTrigger

ENV_ID = "sb3_detc/LinearETC-v0"
#: Nearly deterministic policies: broadcast with probability 1 - 1e-6, control noise exp(-30).
CERTAIN = {"net_arch": [16, 16], "broadcast_prob_init": 1 - 1e-6, "log_std_init": -30.0, "critic": "afterstate"}


def always_broadcast(obs: dict[str, np.ndarray]) -> np.ndarray:
    """A fixed trigger: every agent broadcasts (options for the batch of joint observations)."""
    return np.ones(obs["age"].shape[:-1], np.int64)


def make(workers: bool, vec_env_cls: type = DummyVecEnv, **kwargs: Any) -> MAPPOC:
    env = make_vec_env(
        ENV_ID,
        n_envs=2,
        seed=3,
        env_kwargs={"n_agents": 3, "max_cycles": 20, "broadcast_cost": 0.05},
        vec_env_cls=vec_env_cls,
        wrapper_class=RolloutWorker if workers else None,
    )
    settings = {"n_steps": 48, "batch_size": 32, "n_epochs": 1, "policy_kwargs": CERTAIN, **kwargs}
    return MAPPOC("MlpHybridPolicy", env, seed=0, **settings)


@pytest.mark.parametrize("normalize_reward, periodic", [(False, False), (True, False), (False, True)])
def test_worker_rollouts_fill_the_buffer_like_rollouts_in_the_learner(normalize_reward: bool, periodic: bool) -> None:
    """Same observations, options, controls, rewards (with truncation bootstrap), values, returns, logs.

    The control noise differs (other random streams), and with it the log-probabilities of the
    controls, so the updates would differ: learning rate 0 keeps the policies equal.
    """
    settings = {"normalize_reward": normalize_reward, "team_reward": True, "learning_rate": 0.0}
    models = [make(workers, **settings) for workers in (False, True)]
    assert [has_rollout_workers(model.get_env()) for model in models] == [False, True]
    if periodic:  # a fixed trigger that the workers run themselves
        for model in models:
            model.set_fixed_trigger(PeriodicTrigger(3))
    captures = [capture_logger(model) for model in models]
    for model in models:
        model.learn(192, callback=CommMetricsCallback())  # two rollouts; the second starts mid-episode
    plain, worker = (model.rollout_buffer for model in models)
    assert plain.episode_starts[1:].any()  # episodes of 20 steps ended inside the rollout
    for key in plain.observations:
        np.testing.assert_allclose(worker.observations[key], plain.observations[key], atol=1e-5)
    np.testing.assert_array_equal(worker.broadcast, plain.broadcast)
    assert not periodic or 0.6 < 1 - worker.broadcast.mean() < 0.7  # broadcasts at every third step
    for name in ("control", "rewards", "values", "returns", "advantages", "log_prob_broadcast", "broadcast_price"):
        np.testing.assert_allclose(getattr(worker, name), getattr(plain, name), rtol=1e-4, atol=1e-5, err_msg=name)
    np.testing.assert_array_equal(worker.episode_starts, plain.episode_starts)
    a, b = models
    assert a.num_timesteps == b.num_timesteps == 192
    assert [info["r"] for info in a.ep_info_buffer] == pytest.approx([info["r"] for info in b.ep_info_buffer])
    plain_rows, worker_rows = (capture.rows for capture in captures)
    assert len(plain_rows) == len(worker_rows) == 2  # one dump per rollout
    for plain_row, worker_row in zip(plain_rows, worker_rows, strict=True):
        comm = {key for key in plain_row if key.startswith("comm/")}
        assert {"comm/savings", "comm/inter_event_time_mean", "comm/episodes"} <= comm  # the rollout's metrics
        assert {key for key in worker_row if key.startswith("comm/")} == comm
        for key in comm:
            np.testing.assert_allclose(np.asarray(worker_row[key]), np.asarray(plain_row[key]), rtol=1e-6, err_msg=key)
    assert [model.sampler.last_in_workers for model in models] == [False, True]
    np.testing.assert_allclose(b.last_obs["local"], a.last_obs["local"], atol=1e-5)


def test_worker_processes_train_and_take_the_new_policy_after_loading(tmp_path) -> None:
    """In SubprocVecEnv workers: training runs, and a loaded model sends its own policy to the workers."""
    model = make(True, vec_env_cls=SubprocVecEnv, policy_kwargs={"net_arch": [16, 16]})
    model.learn(96)
    assert model.sampler.last_in_workers
    model.save(tmp_path / "model.zip")
    loaded = MAPPOC.load(tmp_path / "model.zip", env=model.get_env(), learning_rate=0.0)
    with th.no_grad():  # the loaded policy always broadcasts, the workers' copy of the saved one does not
        loaded.policy.net_parameters("mu")[-1][..., 1] = 30.0
    loaded.learn(96, reset_num_timesteps=False)
    assert loaded.sampler.last_in_workers and loaded.rollout_buffer.broadcast.all()
    assert loaded.num_timesteps == 2 * 96  # one more iteration of 2 x 48 steps
    model.get_env().close()


def test_random_skips_run_in_the_workers_with_one_fork_per_env_and_rollout() -> None:
    """Each env skips at random with its own stream, a new one every rollout, at the trigger's rate."""
    model = make(True, policy_kwargs={"net_arch": [16, 16]})
    model.set_fixed_trigger(RandomTrigger(0.5, seed=0))
    rollout_broadcasts = []
    for _ in range(2):
        model.learn(96, reset_num_timesteps=False)
        rollout_broadcasts.append(model.rollout_buffer.broadcast.copy())
    assert model.sampler.last_in_workers
    assert not np.array_equal(rollout_broadcasts[0][:, 0], rollout_broadcasts[0][:, 1])  # the two envs
    assert not np.array_equal(rollout_broadcasts[0], rollout_broadcasts[1])  # the two rollouts
    assert 0.35 < np.mean(rollout_broadcasts) < 0.65


def test_a_dithered_schedule_runs_in_the_workers_with_its_own_deviations_per_env() -> None:
    """A schedule with random skips forks into the workers: each env skips its own scheduled messages."""
    model = make(True, policy_kwargs={"net_arch": [16, 16]})
    model.set_fixed_trigger(DitheredTrigger(PeriodicTrigger(2), skip_prob=0.5, extra_prob=0.0, seed=0))
    model.learn(96)
    broadcast = model.rollout_buffer.broadcast
    assert model.sampler.last_in_workers
    assert not np.array_equal(broadcast[:, 0], broadcast[:, 1])  # the two envs
    # every other step due, half of those skipped (a skip makes the next step due again): about 1 in 3
    assert 0.2 < np.mean(broadcast) < 0.45


def test_other_triggers_and_vec_env_wrappers_keep_the_rollout_in_the_learner() -> None:
    """A trigger without fork() draws its options in the learner; a VecNormalize changes what the policy sees."""
    model = make(True)
    model.set_fixed_trigger(always_broadcast)
    model.learn(48)
    assert model.sampler.last_in_workers is False and model.rollout_buffer.broadcast.all()
    assert not has_rollout_workers(VecNormalize(model.get_env()))


def test_collect_rollout_needs_a_reset_and_a_policy() -> None:
    env = RolloutWorker(make(True).get_env().envs[0].unwrapped)
    with pytest.raises(RuntimeError, match="Reset the env"):
        env.collect_rollout(None, {}, 4, 0.0, [0])
    env.reset(seed=0)
    with pytest.raises(RuntimeError, match="needs the policy"):
        env.collect_rollout(None, {}, 4, 0.0, [0])


def test_a_callback_can_stop_a_worker_rollout() -> None:
    """Stopping mid-rollout ends training there; the learner's last observations are where the envs are."""

    class StopAt20(BaseCallback):
        def _on_step(self) -> bool:
            return self.num_timesteps < 20

    model = make(True)
    model.learn(960, callback=StopAt20())
    assert model.num_timesteps == 20  # 10 steps of 2 envs
    for index, env in enumerate(model.get_env().envs):
        for key, value in env.observation.items():
            np.testing.assert_array_equal(model.last_obs[key][index], value)


def test_a_non_finite_observation_is_named_by_its_key() -> None:
    check_finite({"held": np.zeros((2, 3), np.float32), "age": np.ones((2, 1), np.float32)})  # finite: passes
    with pytest.raises(ValueError, match="non-finite observation in 'age'"):
        check_finite({"held": np.zeros((2, 3), np.float32), "age": np.array([[0.0], [np.inf]], np.float32)})


class WarmAtRolloutEnd(BaseCallback):
    """Records at every rollout's end whether the model's gradient step still has to be compiled."""

    def __init__(self) -> None:
        super().__init__()
        self.needs_warm_up: list[bool] = []

    def _on_rollout_end(self) -> None:
        self.needs_warm_up.append(self.model.gradient_step.needs_warm_up)

    def _on_step(self) -> bool:
        return True


def test_worker_processes_sample_while_the_learner_compiles_its_step() -> None:
    """With worker processes the step is compiled during the first rollout; training is as with in-process workers."""
    results = []
    for vec_env_cls in (SubprocVecEnv, DummyVecEnv):
        model = make(True, vec_env_cls=vec_env_cls, torch_compile=True, policy_kwargs={"net_arch": [16, 16]})
        callback = WarmAtRolloutEnd()
        model.learn(192, callback=callback)
        model.get_env().close()
        results.append((callback.needs_warm_up, {k: v.clone() for k, v in model.policy.state_dict().items()}))
    (in_processes, trained), (in_learner, expected) = results
    assert in_processes == [False, False] and in_learner == [True, False]
    for key, value in expected.items():
        th.testing.assert_close(trained[key], value, rtol=0, atol=0)


def test_a_script_fed_on_standard_input_trains_with_one_warning_and_no_worker_tracebacks() -> None:
    """Worker processes import the main script from its file; ``python - <<EOF`` has none (``<stdin>``)."""
    script = (
        "import warnings\n"
        "from sb3_detc import MAPPOC\n"
        "if __name__ == '__main__':\n"
        "    with warnings.catch_warnings(record=True) as caught:\n"
        "        warnings.simplefilter('always')\n"
        "        model = MAPPOC('MlpHybridPolicy', 'sb3_detc/LinearETC-v0', n_envs=2, n_steps=8, batch_size=8,\n"
        "                       policy_kwargs={'net_arch': [8]}, torch_compile=False)\n"
        "        model.learn(16)\n"
        "    print('WARNINGS', [str(w.message) for w in caught if 'standard input' in str(w.message)])\n"
        "    print('ENV', type(model.get_env()).__name__, model.num_timesteps)\n"
    )
    done = subprocess.run(
        [sys.executable, "-"], input=script, capture_output=True, text=True, timeout=300, env=dict(os.environ)
    )
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    warned = next(line for line in done.stdout.splitlines() if line.startswith("WARNINGS"))
    assert warned.count("standard input") == 1 and "<stdin>" in warned
    assert "ENV DummyVecEnv 16" in done.stdout
