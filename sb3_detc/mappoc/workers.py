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
training is exactly on-policy, as without workers; with MAPPOC's ``overlap_rollouts`` the workers
sample the next rollout during the update instead, one update behind (see there).

Use it as the outermost wrapper of every environment, e.g.
``make_vec_env(env_id, n_envs=2, vec_env_cls=SubprocVecEnv, wrapper_class=RolloutWorker)``
(or ``env_wrapper: sb3_detc.mappoc.workers.RolloutWorker`` in an rl-zoo hyperparameter file).
"""

from __future__ import annotations

import os
import pickle
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th


def check_finite(obs: dict[str, np.ndarray]) -> None:
    """Refuse observations with NaN or infinite values (before a policy acts on them).

    :param obs: an observation (dict of arrays)
    :raises ValueError: naming the first key with a non-finite value
    """
    if np.isfinite(np.concatenate([np.ravel(value) for value in obs.values()])).all():  # one check per step
        return
    for key, value in obs.items():
        if not np.all(np.isfinite(value)):
            raise ValueError(f"the environment returned a non-finite observation in '{key}'.")


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
        niceness: int | None = None,
    ) -> dict[str, Any]:
        """Sample ``n_steps`` steps with the policy, from the observation the env is in.

        :param policy: the pickled policy when it is new to this env (None: the one sent before)
        :param state_dict: the policy's current parameters, as NumPy arrays
        :param n_steps: steps to collect
        :param action_noise_std: extra Gaussian noise on the controls (curriculum)
        :param seeds: one seed of the sampling per env of the vector env (this env uses its own)
        :param torch_compile: whether to compile the policy's sampling (read when ``policy`` is sent)
        :param triggers: one pickled fixed trigger per env of the vector env, forked for
            it (see ``MAPPOC.set_fixed_trigger``); None: options sampled from the policy
        :param niceness: lower this process's scheduling priority to at least this niceness before
            sampling (where the OS has niceness), e.g. so that a learner that updates meanwhile gets
            its core first (None: unchanged); it stays lowered
        :return: ``observations`` before every step (dict of (n_steps, N, ...)), ``broadcast``
            (n_steps, N), ``control`` (n_steps, N, m; sampled, before clipping to the bounds),
            ``dones`` (n_steps,), ``infos`` (one dict per step; at an episode end with
            ``terminal_observation`` and ``reset_info``, the info of the reset that followed) and
            ``last_obs`` (the observation after the last step)
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
        if niceness is not None and hasattr(os, "setpriority"):
            os.setpriority(os.PRIO_PROCESS, 0, max(niceness, os.getpriority(os.PRIO_PROCESS, 0)))
        self._policy.load_state_dict({key: th.as_tensor(value) for key, value in state_dict.items()})
        space = self.action_space["control"]
        low, high = space.low, space.high
        observations = {key: np.empty((n_steps, *value.shape), value.dtype) for key, value in self._obs.items()}
        broadcast = np.empty((n_steps, *self.action_space["broadcast"].shape), np.int64)
        control = np.empty((n_steps, *space.shape), np.float32)
        dones = np.empty(n_steps, bool)
        infos = []
        trigger = None if triggers is None else pickle.loads(triggers[self.worker_index])
        # The policy reads the same input tensors at every step (a batch of one): the compiled
        # sampling checks them fastest when they are the same objects.
        rows = {key: np.empty((1, *value.shape), value.dtype) for key, value in self._obs.items()}
        inputs = {key: th.from_numpy(row) for key, row in rows.items()}  # views of ``rows``
        threads = th.get_num_threads()
        # One thread: batches of one sample gain nothing from more, and several workers would fight over the cores.
        th.set_num_threads(1)
        try:
            with th.random.fork_rng(devices=[]), th.no_grad():  # in the learner's process: keep its stream
                th.manual_seed(int(seeds[self.worker_index]))
                for t in range(n_steps):
                    for key, value in self._obs.items():
                        observations[key][t] = value
                        rows[key][0] = value
                    forced = None
                    if trigger is not None:
                        forced = th.as_tensor(trigger({key: value[t : t + 1] for key, value in observations.items()}))
                    decided, controls = self._act(inputs, action_noise_std, forced)
                    broadcast[t], control[t] = decided[0].numpy(), controls[0].numpy()
                    # np.clip's result, without its dispatch on the bounds' types
                    clipped = np.minimum(np.maximum(control[t], low), high)
                    obs, _, terminated, truncated, info = self.step({"broadcast": broadcast[t], "control": clipped})
                    dones[t] = terminated or truncated
                    info["TimeLimit.truncated"] = truncated and not terminated
                    if dones[t]:
                        info["terminal_observation"] = obs
                        _, info["reset_info"] = self.reset()
                    infos.append(info)
        finally:
            th.set_num_threads(threads)
        return {
            "observations": observations,
            "broadcast": broadcast,
            "control": control,
            "dones": dones,
            "infos": infos,
            "last_obs": self._obs,
        }
