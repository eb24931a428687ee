"""Rollouts collected where the environments run: one message per iteration instead of two per step.

With SB3's worker processes (``SubprocVecEnv``) the learner normally evaluates the policy
and exchanges one message with every worker per step. For networks as small as the
method's, that exchange and the waiting around it cost more than the environment step
itself. :class:`RolloutWorker` is a Gymnasium wrapper that lets
:class:`~sb3_detc.mappoc.mappoc.MAPPOC` send a copy of its policy to every environment
once per iteration; each environment then samples options and controls and steps itself
for the whole rollout, in parallel with the others, and returns the trajectory. The
learner evaluates log-probabilities and option values of the whole rollout in one batch
and then goes through the steps in order (rewards, callbacks, episode statistics), so
training is exactly on-policy, as without workers. The step loop is
:func:`sb3_detc.mappoc.sampling.run_steps`, the same as the learner's own.

Use it as the outermost wrapper of every environment, e.g.
``make_vec_env(env_id, n_envs=2, vec_env_cls=SubprocVecEnv, wrapper_class=RolloutWorker)``
(or ``env_wrapper: sb3_detc.mappoc.workers.RolloutWorker`` in an rl-zoo hyperparameter file).
"""

from __future__ import annotations

import os
import pickle
import sys
import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from sb3_detc.mappoc.sampling import Rollout, check_finite, run_steps


def default_n_envs() -> int:
    """Envs that MAPPOC builds from an env id: one rollout worker per available CPU core, at most 8.

    A power of two (the largest not above the cores), so that the paper's iteration of 2048
    steps divides evenly among the workers.

    :return: the number of envs: 1, 2, 4 or 8
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 1 << (max(1, min(cores, 8)).bit_length() - 1)


def main_script_without_file() -> str | None:
    """The main script's name if worker processes cannot import it: it has no file (e.g. a script read from stdin).

    Worker processes (``forkserver`` or ``spawn``) import the main script from its file before they
    run; a script fed on standard input (``python - <<EOF``) is named ``<stdin>`` and has none.

    :return: the script's ``__file__`` if that is not a file, else None (a file, or no main script to import)
    """
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    return main_file if main_file is not None and not os.path.isfile(main_file) else None


def make_rollout_workers(env_id: str, n_envs: int, seed: int | None = None) -> VecEnv:
    """The fast setting for a registered joint env: ``n_envs`` :class:`RolloutWorker` envs.

    Each env runs in its own process (``SubprocVecEnv``) when there are several, and samples
    whole rollouts itself. Worker processes must find the id: the package's ids always, one's own
    where the module that registers it is the main script or is imported by the worker (see
    :mod:`sb3_detc`). Where they cannot, or where the main script has no file for them to import
    (a script on standard input), the envs run in this process instead, with a warning.

    :param env_id: a registered joint env id, e.g. ``"sb3_detc/MultiwalkerETC-v0"``
    :param n_envs: number of envs (>= 1)
    :param seed: seed of the envs (None: random)
    :return: a ``SubprocVecEnv`` of the envs when there are several and the worker processes could make them,
        else a ``DummyVecEnv``
    """
    stdin_script = main_script_without_file() if n_envs > 1 else None
    if stdin_script is not None:
        warnings.warn(
            f"the main script {stdin_script!r} has no file that worker processes could import (a script fed on "
            f"standard input), so the {n_envs} envs of {env_id!r} run in this process; save the script to a file "
            "to run them in worker processes.",
            stacklevel=3,
        )
    elif n_envs > 1:
        try:
            return make_vec_env(
                env_id, n_envs=n_envs, seed=seed, vec_env_cls=SubprocVecEnv, wrapper_class=RolloutWorker
            )
        except (EOFError, ConnectionError) as error:  # a worker died while making its env
            warnings.warn(
                f"worker processes could not make {env_id!r} ({type(error).__name__}; the worker's traceback is "
                f"above), so its {n_envs} envs run in this process. A script that starts training when it is "
                "imported needs `if __name__ == '__main__':` (worker processes import the main script); an id "
                "registered in another module needs that module named in the id ('module:namespace/Name-v0').",
                stacklevel=3,
            )
    return make_vec_env(env_id, n_envs=n_envs, seed=seed, vec_env_cls=DummyVecEnv, wrapper_class=RolloutWorker)


class RolloutWorker(gym.Wrapper):
    """Collects whole rollouts of a joint sb3_detc env with a copy of MAPPOC's policy (see the module).

    Steps the wrapped env exactly as SB3's vector envs do: ``info["TimeLimit.truncated"]``,
    ``info["terminal_observation"]`` and an automatic reset at the end of every episode. The
    copy of the policy runs on the CPU with one thread (batches of one sample).

    :param env: a joint env (Dict observations with an agent axis, ``broadcast`` x ``control`` actions)
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self._obs: dict[str, np.ndarray] | None = None
        self._policy: Any = None
        self._act: Any = None
        self.worker_index = 0

    def reset(self, **kwargs: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Reset the env and remember the observation the next rollout starts from.

        :param kwargs: passed to the wrapped env's ``reset`` (``seed``, ``options``)
        :return: the wrapped env's first observation and info
        """
        obs, info = self.env.reset(**kwargs)
        check_finite(obs)
        self._obs = obs
        return obs, info

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Step the env and remember the observation.

        :param action: joint action, passed to the wrapped env (``{"broadcast": (N,), "control": (N, m)}``)
        :return: the wrapped env's observation, reward, terminated, truncated and info
        """
        obs, reward, terminated, truncated, info = self.env.step(action)
        check_finite(obs)
        self._obs = obs
        return obs, reward, terminated, truncated, info

    @property
    def observation(self) -> dict[str, np.ndarray] | None:
        """The observation the env is in (None before the first reset)."""
        return self._obs

    def set_worker_index(self, index: int) -> None:
        """Tell this env its index in the vector env (it picks its own seed of a rollout by it).

        :param index: position of this env in the vector env
        """
        self.worker_index = index

    def collect_rollout(
        self,
        policy: bytes | None,
        state_dict: dict[str, np.ndarray],
        n_steps: int,
        action_noise_std: float,
        seeds: list[int],
        torch_compile: bool = False,
        triggers: list[bytes] | None = None,
    ) -> Rollout:
        """Sample ``n_steps`` steps with the policy, from the observation the env is in.

        :param policy: the pickled policy when it is new to this env (None: the one sent before)
        :param state_dict: the policy's current parameters, as NumPy arrays
        :param n_steps: steps to collect
        :param action_noise_std: extra Gaussian noise on the controls (curriculum)
        :param seeds: one seed of the sampling per env of the vector env (this env uses its own)
        :param torch_compile: whether to compile the policy's sampling (read when ``policy`` is sent)
        :param triggers: one pickled fixed trigger per env of the vector env, forked for
            it (see ``MAPPOC.set_fixed_trigger``); None: options sampled from the policy
        :return: the steps as a rollout of one env (:class:`~sb3_detc.mappoc.sampling.Rollout`, B = 1); at an
            episode end the info has ``terminal_observation`` and ``reset_info`` (the info of the reset that
            followed)
        """
        if self._obs is None:
            raise RuntimeError("Reset the env before collecting a rollout.")
        if policy is not None:
            self._policy = pickle.loads(policy).to("cpu")
            self._policy.set_training_mode(False)
            self._act = self._policy.sample_actions
            if torch_compile:  # a C++ wrapper around the kernels: a third faster for single samples
                self._act = th.compile(self._act, options={"cpp_wrapper": True})
        if self._policy is None:
            raise RuntimeError("collect_rollout needs the policy on its first call.")
        self._policy.load_state_dict({key: th.as_tensor(value) for key, value in state_dict.items()})
        space = self.action_space["control"]
        trigger = None if triggers is None else pickle.loads(triggers[self.worker_index])
        # The policy reads the same input tensors at every step (a batch of one): the compiled
        # sampling checks them fastest when they are the same objects.
        rows = {key: np.empty((1, *value.shape), value.dtype) for key, value in self._obs.items()}
        inputs = {key: th.from_numpy(row) for key, row in rows.items()}  # views of ``rows``

        def act(obs: dict[str, np.ndarray], forced: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
            for key, row in rows.items():
                row[...] = obs[key]
            decided, controls = self._act(inputs, action_noise_std, None if forced is None else th.as_tensor(forced))
            return decided.numpy(), controls.numpy()

        def env_step(broadcast: np.ndarray, control: np.ndarray) -> tuple[dict, np.ndarray, list[dict[str, Any]]]:
            obs, _, terminated, truncated, info = self.step({"broadcast": broadcast[0], "control": control[0]})
            done = terminated or truncated
            info["TimeLimit.truncated"] = truncated and not terminated
            if done:
                info["terminal_observation"] = obs
                _, info["reset_info"] = self.reset()
            return batch_of_one(self._obs), np.array([done]), [info]

        threads = th.get_num_threads()
        # One thread: batches of one sample gain nothing from more, and several workers would fight over the cores.
        th.set_num_threads(1)
        try:
            with th.random.fork_rng(devices=[]), th.no_grad():  # in the learner's process: keep its stream
                th.manual_seed(int(seeds[self.worker_index]))
                return run_steps(act, env_step, batch_of_one(self._obs), n_steps, trigger, space.low, space.high)
        finally:
            th.set_num_threads(threads)


def batch_of_one(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """An observation with a batch axis of size one (views).

    :param obs: a joint observation, (N, ...) per key
    :return: the same arrays shaped (1, N, ...)
    """
    return {key: value[None] for key, value in obs.items()}
