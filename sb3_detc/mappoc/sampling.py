"""Sampling of rollouts: one step loop, run by the learner or inside the rollout workers.

Per step (same-step delivery, Sec. 2 of the method): all options are sampled from ``mu``
or taken from a fixed trigger, the broadcasts are delivered, then all controls are sampled
from ``pi`` on the updated views; the envs receive the controls clipped to their bounds.
:func:`run_steps` is that loop, written once; what differs between the places that run it
is only how a batch of observations becomes actions (``act``) and how the envs step
(``env_step``).

:class:`RolloutSampler` is the learner's side. Where the training env is a plain vector
env of :class:`~sb3_detc.mappoc.workers.RolloutWorker` envs, every env samples its part of
the rollout with a copy of the policy, in parallel (in its own process with
``SubprocVecEnv``), and returns it in one message; otherwise the learner runs the loop
itself over the vector env. Either way the learner gets a :class:`Rollout` of all envs.
"""

from __future__ import annotations

import functools
import pickle
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from sb3_detc.mappoc.replays import (
    REPLAY_CHOICES,
    Replays,
    copyable_env,
    replay,
    replayed_observations,
    snapshot,
)

#: Signature of a fixed trigger: a batch of joint observations (B, N, ...) -> options (B, N). A trigger
#: with ``broadcast_probability(obs)`` (B, N) (without side effects, as :mod:`sb3_detc.triggers` have)
#: gives the learner its probabilities of broadcasting for the values at the rollout's end and at
#: truncations; for any other the learner takes ``mu``'s. In rollout workers a trigger runs only if it
#: has ``fork(seed)`` (an independent copy, like :meth:`sb3_detc.triggers.RandomTrigger.fork`): one
#: fork per env and rollout; any other keeps the rollout in the learner's process.
FixedTrigger = Callable[[dict[str, np.ndarray]], np.ndarray]

#: How a batch of joint observations (B, N, ...) and the options a fixed trigger forces (B, N) (None:
#: ``mu`` decides) become options (B, N) and sampled controls (B, N, m), as NumPy arrays.
Act = Callable[[dict[str, np.ndarray], "np.ndarray | None"], tuple[np.ndarray, np.ndarray]]

#: How B envs step with options (B, N) and clipped controls (B, N, m): the observations after the
#: step (the next episode's first at an episode end), the episode ends (B,) and the B infos (at an
#: episode end with ``terminal_observation``, ``TimeLimit.truncated`` and ``reset_info``).
EnvStep = Callable[[np.ndarray, np.ndarray], tuple[dict[str, np.ndarray], np.ndarray, list[dict[str, Any]]]]


class Rollout(NamedTuple):
    """Steps of B envs as sampled, before the learner takes them in (T steps).

    :param observations: joint observations before every step, (T, B, N, ...) per key
    :param broadcast: options (T, B, N)
    :param control: sampled controls (T, B, N, m), before clipping to the bounds
    :param dones: episode ends (T, B)
    :param infos: T lists of B infos; at an episode end also ``"reset_info"``
    :param last_obs: joint observations after the last step, (B, N, ...) per key
    :param replays: the rollout's replayed decisions (:class:`ReplayingSampler`; None: none)
    """

    observations: dict[str, np.ndarray]
    broadcast: np.ndarray
    control: np.ndarray
    dones: np.ndarray
    infos: list[list[dict[str, Any]]]
    last_obs: dict[str, np.ndarray]
    replays: Replays | None = None

    def flat_tensors(self, device: th.device | str) -> tuple[dict[str, th.Tensor], th.Tensor, th.Tensor]:
        """Observations, options and controls of all steps as one batch (T * B, ...), step by step.

        :param device: where the tensors go
        :return: observations (T * B, N, ...) per key, options (T * B, N), controls (T * B, N, m)
        """
        flat = self.dones.size
        return (
            obs_as_tensor({k: v.reshape(flat, *v.shape[2:]) for k, v in self.observations.items()}, device),
            th.as_tensor(self.broadcast.reshape(flat, -1), device=device),
            th.as_tensor(self.control.reshape(flat, *self.control.shape[2:]), device=device),
        )  # type: ignore[return-value]


class StepsTaken(NamedTuple):
    """What the learner took of a rollout's steps, in order (T steps, n_envs envs, N agents).

    :param rewards: the learner's rewards (T, n_envs, N); the bootstraps of truncated episodes are added later
    :param price: the price of a broadcast in the learner's reward units at every step (T, n_envs, N)
    :param last_price: the price after the last step (n_envs, N)
    :param truncated: every episode a time limit cut, as ``(step, env index, terminal observation)``
    :param episode_starts: whether every step's observation starts an episode (T, n_envs)
    """

    rewards: np.ndarray
    price: np.ndarray
    last_price: np.ndarray
    truncated: list[tuple[int, int, dict[str, np.ndarray]]]
    episode_starts: np.ndarray


def run_steps(
    act: Act,
    env_step: EnvStep,
    obs: dict[str, np.ndarray],
    n_steps: int,
    trigger: FixedTrigger | None,
    low: np.ndarray,
    high: np.ndarray,
) -> Rollout:
    """The step loop: ``n_steps`` steps of B envs from the observations ``obs``.

    :param act: options and sampled controls from a batch of observations (see :data:`Act`)
    :param env_step: steps the envs (see :data:`EnvStep`)
    :param obs: the envs' current observations, (B, N, ...) per key
    :param n_steps: steps to take (>= 1)
    :param trigger: the fixed trigger that takes the options (None: ``mu``)
    :param low: lower bounds of the controls (N, m)
    :param high: upper bounds of the controls (N, m)
    :return: the steps
    """
    observations = {key: np.empty((n_steps, *value.shape), value.dtype) for key, value in obs.items()}
    broadcast: np.ndarray | None = None
    control: np.ndarray | None = None
    dones = np.empty((n_steps, len(obs["age"])), bool)
    infos = []
    for t in range(n_steps):
        for key, value in obs.items():
            observations[key][t] = value
        options, controls = act(obs, None if trigger is None else trigger(obs))
        if broadcast is None or control is None:
            broadcast = np.empty((n_steps, *options.shape), np.int64)
            control = np.empty((n_steps, *controls.shape), np.float32)
        broadcast[t], control[t] = options, controls
        # np.clip's result, without its dispatch on the bounds' types
        obs, dones[t], step_infos = env_step(options, np.minimum(np.maximum(controls, low), high))
        infos.append(step_infos)
    return Rollout(observations, broadcast, control, dones, infos, obs)  # type: ignore[arg-type]


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


def truncated_episodes(infos: list[dict[str, Any]], dones: np.ndarray) -> list[tuple[int, dict[str, np.ndarray]]]:
    """The envs whose episode was cut by a time limit in this step, with their last observations (checked).

    :param infos: every env's info of the step (n_envs,)
    :param dones: episode ends of the step (n_envs,)
    :return: ``(env index, terminal observation)`` of every truncated episode
    :raises ValueError: if a terminal observation is not finite
    """
    cut = []
    for idx, (info, done) in enumerate(zip(infos, dones, strict=True)):
        if done and info.get("TimeLimit.truncated", False) and "terminal_observation" in info:
            check_finite(info["terminal_observation"])
            cut.append((idx, info["terminal_observation"]))
    return cut


def has_rollout_workers(env: VecEnv) -> bool:
    """Whether ``env`` is a plain SB3 vector env of :class:`~sb3_detc.mappoc.workers.RolloutWorker` envs.

    Vector env wrappers (e.g. ``VecNormalize``) change what the policy sees: those keep the rollout in
    the learner's process.

    :param env: the training env
    :return: True if it is a ``DummyVecEnv`` or ``SubprocVecEnv`` whose envs have ``collect_rollout``
    """
    return isinstance(env, (DummyVecEnv, SubprocVecEnv)) and env.has_attr("collect_rollout")


class RolloutSampler:
    """The learner's sampling: in the rollout workers where the env has them, else in this process.

    :param policy: the policy that samples (:class:`~sb3_detc.mappoc.policies.MlpHybridPolicy`)
    :param compiled: compile the sampling with ``torch.compile`` (here and in the workers)
    """

    def __init__(self, policy: Any, compiled: bool) -> None:
        self.policy = policy
        self.compiled = compiled
        sample = policy.sample_actions
        self._sample_actions: Callable[..., tuple[th.Tensor, th.Tensor]] = th.compile(sample) if compiled else sample
        self._workers_hold: VecEnv | None = None  # the vector env whose workers hold a copy of the policy
        #: whether the last rollout was sampled inside rollout workers (None: no rollout yet)
        self.last_in_workers: bool | None = None

    def in_workers(self, env: VecEnv, trigger: FixedTrigger | None) -> bool:
        """Whether a rollout with this trigger can be sampled in ``env``'s rollout workers.

        :param env: the training env
        :param trigger: the fixed trigger (None: ``mu``)
        :return: True for an env of rollout workers and a trigger that runs in them (or none)
        """
        return (trigger is None or hasattr(trigger, "fork")) and has_rollout_workers(env)

    def sample(
        self,
        env: VecEnv,
        obs: dict[str, np.ndarray],
        n_steps: int,
        action_noise_std: float,
        trigger: FixedTrigger | None,
        meanwhile: Callable[[], None] | None = None,
    ) -> Rollout:
        """Sample ``n_steps`` steps of every env with the policy's current parameters.

        :param env: the training env (a vector env)
        :param obs: the envs' current observations (what the learner last saw)
        :param n_steps: steps per env
        :param action_noise_std: extra Gaussian noise on the controls (curriculum)
        :param trigger: the fixed trigger that takes the options (None: ``mu``)
        :param meanwhile: work for the learner while worker processes sample (e.g. compiling its
            gradient step); called once per rollout in worker processes, never otherwise
        :return: the steps of all envs
        """
        self.last_in_workers = self.in_workers(env, trigger)
        if not self.last_in_workers:
            return run_steps(
                self._here(action_noise_std), self._vec_env_step(env), obs, n_steps, trigger, *self._bounds()
            )
        collect = self._in_workers(env, n_steps, action_noise_std, trigger)
        if meanwhile is None or not isinstance(env, SubprocVecEnv):
            return collect()
        with ThreadPoolExecutor(max_workers=1) as waiter:  # the worker processes sample; the learner works
            collected = waiter.submit(collect)
            meanwhile()
            return collected.result()

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The control bounds, (N, m) each."""
        space = self.policy.action_space["control"]
        return space.low, space.high

    def _here(self, action_noise_std: float, sample: Callable[..., tuple[th.Tensor, th.Tensor]] | None = None) -> Act:
        """Actions of the policy in this process.

        :param action_noise_std: extra Gaussian noise on the controls
        :param sample: the policy's sampling to use (None: the sampler's, compiled where it compiles)
        :return: the ``act`` of :func:`run_steps`
        """
        device = self.policy.device
        sample_actions = self._sample_actions if sample is None else sample

        def act(obs: dict[str, np.ndarray], forced: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
            with th.no_grad():
                broadcast, control = sample_actions(
                    obs_as_tensor(obs, device),  # type: ignore[arg-type]
                    action_noise_std,
                    None if forced is None else th.as_tensor(forced, device=device),
                )
            return broadcast.cpu().numpy(), control.cpu().numpy()

        return act

    @staticmethod
    def _vec_env_step(env: VecEnv) -> EnvStep:
        """SB3's vector env step, with every episode end's reset info (as the workers report it).

        :param env: the vector env
        :return: the ``env_step`` of :func:`run_steps`
        """

        def env_step(broadcast: np.ndarray, control: np.ndarray) -> tuple[dict, np.ndarray, list[dict[str, Any]]]:
            obs, _, dones, infos = env.step(
                [{"broadcast": c, "control": u} for c, u in zip(broadcast, control, strict=True)]
            )
            check_finite(obs)  # before the policy acts on them
            reset_infos = getattr(env, "reset_infos", None)
            for idx in np.flatnonzero(dones) if reset_infos is not None else ():
                infos[idx]["reset_info"] = reset_infos[idx]  # the VecEnv keeps the latest only
            return obs, dones, infos

        return env_step

    def _in_workers(
        self, env: VecEnv, n_steps: int, action_noise_std: float, trigger: FixedTrigger | None
    ) -> Callable[[], Rollout]:
        """What lets every env sample ``n_steps`` steps with the policy's current parameters (in parallel).

        The policy (if new to the workers), its parameters, the settings and the seeds are taken
        now; the returned call sends them and waits for the steps (also from another thread).

        :param env: the training env (of rollout workers)
        :param n_steps: steps per env
        :param action_noise_std: extra Gaussian noise on the controls
        :param trigger: the fixed trigger (None: ``mu``), forked once per env
        :return: the call that returns the rollout of all envs
        """
        n_envs = env.num_envs
        new_policy = self._workers_hold is not env
        if new_policy:
            for index in range(n_envs):
                env.env_method("set_worker_index", index, indices=index)
        seeds = th.randint(2**31 - 1, (n_envs,)).tolist()
        collect = functools.partial(
            env.env_method,
            "collect_rollout",
            pickle.dumps(self.policy) if new_policy else None,
            {key: value.detach().cpu().numpy() for key, value in self.policy.state_dict().items()},
            n_steps,
            action_noise_std,
            seeds,
            self.compiled,
            None if trigger is None else [pickle.dumps(trigger.fork(seed)) for seed in seeds],  # type: ignore[attr-defined]
        )
        self._workers_hold = env
        return lambda: joined(collect())


class ReplayingSampler(RolloutSampler):
    """The learner's sampling with replayed decisions, for ``broadcast_advantage="replayed"``.

    Rollouts of ``mu``'s options run in this process (the envs must be copied, so a ``DummyVecEnv``);
    at every step, ``choice`` picks at most one agent's decision per env (``share`` per env and step in
    the mean), the env is copied before the step, and the decision is replayed after the rollout
    (:func:`~sb3_detc.mappoc.replays.replay`) with the policy's parameters of the rollout. Rollouts of
    a fixed trigger, from which ``mu`` does not learn, are sampled as :class:`RolloutSampler` samples them.

    :param policy: the policy that samples
    :param compiled: compile the rollout's sampling (the replays' batches change size: they run eagerly)
    :param share: mean number of replayed decisions per env and step, in (0, 1]
    :param horizon: steps of a replay (>= 1)
    :param gamma: discount factor of the replayed rewards
    :param choice: how a step's decisions are chosen, a key of :data:`~sb3_detc.mappoc.replays.REPLAY_CHOICES`
        (``"uniform"``: one agent at random; ``"gradient"``: by ``mu``'s ``p (1 - p)``, an extra pass of ``mu``
        per step)
    """

    def __init__(
        self, policy: Any, compiled: bool, share: float, horizon: int, gamma: float, choice: str = "uniform"
    ) -> None:
        super().__init__(policy, compiled)
        self.share, self.horizon, self.gamma = share, horizon, gamma
        self.choose = REPLAY_CHOICES[choice]

    def in_workers(self, env: VecEnv, trigger: FixedTrigger | None) -> bool:
        """Whether a rollout can be sampled in rollout workers: only a fixed trigger's.

        :param env: the training env
        :param trigger: the fixed trigger (None: ``mu``)
        :return: True for a fixed trigger that runs in ``env``'s rollout workers
        """
        return trigger is not None and super().in_workers(env, trigger)

    def sample(
        self,
        env: VecEnv,
        obs: dict[str, np.ndarray],
        n_steps: int,
        action_noise_std: float,
        trigger: FixedTrigger | None,
        meanwhile: Callable[[], None] | None = None,
    ) -> Rollout:
        """Sample ``n_steps`` steps of every env, and replay some of ``mu``'s decisions.

        :param env: the training env (a ``DummyVecEnv`` for rollouts of ``mu``)
        :param obs: the envs' current observations
        :param n_steps: steps per env
        :param action_noise_std: extra Gaussian noise on the controls, in the rollout and in the replays
        :param trigger: the fixed trigger that takes the options (None: ``mu``)
        :param meanwhile: as for :meth:`RolloutSampler.sample`
        :return: the steps of all envs, with the replays of ``mu``'s rollouts
        :raises ValueError: if the envs of a rollout of ``mu`` are not in this process or cannot be copied
        """
        if trigger is not None:
            return super().sample(env, obs, n_steps, action_noise_std, trigger, meanwhile)
        if not isinstance(env, DummyVecEnv):
            raise ValueError(
                "broadcast_advantage='replayed' copies the training envs, so they must run in the learner's "
                f"process (a DummyVecEnv), got {type(env).__name__}."
            )
        self.last_in_workers = False
        envs, bounds = [copyable_env(e) for e in env.envs], self._bounds()
        seed = int(th.randint(2**31 - 1, ()).item())
        rng = np.random.default_rng(seed)
        chosen, chances = np.full((n_steps, env.num_envs), -1), np.zeros((n_steps, env.num_envs))
        copies: list[Any] = []
        here, vec_env_step, step = self._here(action_noise_std), self._vec_env_step(env), 0

        def act(obs: dict[str, np.ndarray], forced: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
            chosen[step], chances[step] = self.choose(self.policy, obs, self.share, rng)
            return here(obs, forced)

        def env_step(broadcast: np.ndarray, control: np.ndarray) -> tuple[dict, np.ndarray, list[dict[str, Any]]]:
            nonlocal step
            copies.extend(snapshot(envs[idx]) for idx in np.flatnonzero(chosen[step] >= 0))  # before the step
            step += 1
            return vec_env_step(broadcast, control)

        rollout = run_steps(act, env_step, obs, n_steps, None, *bounds)
        steps, env_index = np.nonzero(chosen >= 0)  # step by step, the envs in order: as the copies were taken
        agents = chosen[steps, env_index]
        n_agents = rollout.broadcast.shape[-1]
        rewards, broadcasts = np.zeros((len(agents), n_agents)), np.zeros((len(agents), n_agents))
        if len(agents):
            act_replays = self._here(action_noise_std, self.policy.sample_actions)
            observed = replayed_observations(rollout.observations, steps, env_index)
            rewards, broadcasts = replay(act_replays, copies, observed, agents, self.horizon, self.gamma, *bounds, seed)
        replays = Replays(steps, env_index, agents, rewards, broadcasts, chances[steps, env_index])
        return rollout._replace(replays=replays)


def joined(rollouts: list[Rollout]) -> Rollout:
    """One rollout of all envs from the rollouts of every env (or group of envs), side by side.

    :param rollouts: rollouts of the same number of steps, in the order of the envs
    :return: their steps, the envs in that order
    """
    return Rollout(
        {key: np.concatenate([r.observations[key] for r in rollouts], axis=1) for key in rollouts[0].observations},
        np.concatenate([r.broadcast for r in rollouts], axis=1),
        np.concatenate([r.control for r in rollouts], axis=1),
        np.concatenate([r.dones for r in rollouts], axis=1),
        [[info for r in rollouts for info in r.infos[t]] for t in range(len(rollouts[0].infos))],
        {key: np.concatenate([r.last_obs[key] for r in rollouts], axis=0) for key in rollouts[0].last_obs},
    )
