"""MAPPOC: multi-agent PPO option-critic for learned event-triggered communication and control."""

from __future__ import annotations

import copy
import functools
import numbers
import os
import pathlib
import pickle
import warnings
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import Any, ClassVar, NamedTuple, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import FloatSchedule, explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, unwrap_vec_normalize

from sb3_detc.envs.wrappers import EventTriggeredNetwork, JointEnv
from sb3_detc.mappoc.buffers import HybridRolloutBuffer, HybridRolloutSamples
from sb3_detc.mappoc.critics import CRITICS
from sb3_detc.mappoc.losses import BROADCAST_ADVANTAGES, STEP_STATS, MAPPOCLoss, UpdateInputs
from sb3_detc.mappoc.policies import MlpHybridPolicy, check_joint_spaces, drawn_broadcast_probability
from sb3_detc.mappoc.rewards import RewardTransform, agent_rewards
from sb3_detc.mappoc.steps import FusedGradientStep, GradientStep, fusable_adam
from sb3_detc.mappoc.workers import RolloutWorker, check_finite
from sb3_detc.renamed import RENAMED, renamed_action_space, renamed_keys

SelfMAPPOC = TypeVar("SelfMAPPOC", bound="MAPPOC")

#: Observation keys that the policy turns into the network's state with the broadcast rule (the
#: message copied into ``held``, ``age`` reset to 0) or that feed the policy over options: a
#: ``VecNormalize`` must pass them on as the environment returns them.
NETWORK_KEYS = ("message", "held", "age", "trigger", "trigger_held")

#: Signature of a fixed trigger: a batch of joint observations (B, N, ...) -> options (B, N). A trigger
#: with ``broadcast_probability(obs)`` (B, N) (without side effects, as :mod:`sb3_detc.triggers` have)
#: gives the learner its probabilities of broadcasting for the values at the rollout's end and at
#: truncations; for any other the learner takes ``mu``'s.
#: With rollout workers (:mod:`sb3_detc.mappoc.workers`) a trigger that has ``fork(seed)``
#: (an independent copy, like :meth:`sb3_detc.triggers.RandomTrigger.fork`) runs in the workers,
#: one fork per env and rollout; any other keeps the rollout in the learner's process.
FixedTrigger = Callable[[dict[str, np.ndarray]], np.ndarray]

#: Environment steps per iteration of the paper (all envs together), MAPPOC's default.
PAPER_ITERATION = 2048

#: With ``overlap_rollouts``: how much lower the rollout workers' scheduling priority is than the learner's while
#: they sample during its update (niceness), so that the learner's one thread keeps its core.
WORKER_NICENESS = 5

#: With ``torch_compile="auto"``: the shortest ``learn`` that compiles (compiling takes tens of
#: seconds, minutes with a cold compile cache).
COMPILE_FROM_TIMESTEPS = 200_000


class Rollout(NamedTuple):
    """Steps of all envs as sampled, before the learner takes them in (T steps, n_envs envs).

    :param observations: joint observations before every step, (T, n_envs, N, ...) per key
    :param broadcast: options (T, n_envs, N)
    :param control: sampled controls (T, n_envs, N, m), before clipping to the bounds
    :param dones: episode ends (T, n_envs)
    :param infos: T lists of n_envs infos; at an episode end also ``"reset_info"``
    :param last_obs: joint observations after the last step, (n_envs, N, ...) per key
    """

    observations: dict[str, np.ndarray]
    broadcast: np.ndarray
    control: np.ndarray
    dones: np.ndarray
    infos: list[list[dict[str, Any]]]
    last_obs: dict[str, np.ndarray]


class PendingRollout(NamedTuple):
    """A rollout that the rollout workers sample while the learner updates (``overlap_rollouts``).

    :param rollout: the workers' steps, once they are done
    :param behaviour: the policy's parameters that sample it (a copy)
    :param trigger: the fixed trigger that takes its options (None: mu)
    """

    rollout: Future[Rollout]
    behaviour: dict[str, th.Tensor]
    trigger: FixedTrigger | None


def default_n_envs() -> int:
    """Envs that MAPPOC builds from an env id: one rollout worker per available CPU core, at most 8.

    A power of two (the largest not above the cores), so that the paper's iteration of 2048
    steps divides evenly among the workers.

    :return: the number of envs: 1, 2, 4 or 8
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 1 << (max(1, min(cores, 8)).bit_length() - 1)


def make_rollout_workers(env_id: str, n_envs: int, seed: int | None = None) -> VecEnv:
    """The fast setting for a registered joint env: ``n_envs`` :class:`RolloutWorker` envs.

    Each env runs in its own process (``SubprocVecEnv``) when there are several, and samples
    whole rollouts itself (:mod:`sb3_detc.mappoc.workers`).

    Worker processes must find the id: the package's ids always, one's own where the module that
    registers it is the main script or is imported by the worker (see :mod:`sb3_detc`). Where they
    cannot, the envs run in this process instead, with a warning.

    :param env_id: a registered joint env id, e.g. ``"sb3_detc/MultiwalkerETC-v0"``
    :param n_envs: number of envs (>= 1)
    :param seed: seed of the envs (None: random)
    :return: a ``SubprocVecEnv`` of the envs when there are several and the worker processes could make them,
        else a ``DummyVecEnv``
    """
    if n_envs > 1:
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


def _as_joint_env(env: GymEnv | str | EventTriggeredNetwork | None) -> GymEnv | str | None:
    """Adapt a PettingZoo event-triggered env to the joint Gymnasium view.

    :param env: an env id, a Gymnasium or vector env, a PettingZoo :class:`EventTriggeredNetwork`, or None
    :return: a :class:`JointEnv` of an :class:`EventTriggeredNetwork`, anything else as given
    """
    return JointEnv(env) if isinstance(env, EventTriggeredNetwork) else env


class MAPPOC(OnPolicyAlgorithm):
    """Multi-agent PPO option-critic (Kesper, Trimpe and Baumann, L4DC 2023), with the paper's defaults.

    Every agent learns a policy over options (broadcast or stay silent, every step), a
    Gaussian control policy on its networked observation, and a centralised option-value
    critic used only in training. Both policy levels are trained with PPO's clipped
    surrogate: the control policy on GAE advantages of the taken option, the policy over
    options on the greedy advantage ``Q(o) - max_o' Q(o')`` (Sec. 3 of the method reference).

    :param policy: the policy model (``"MlpHybridPolicy"`` or a subclass of :class:`MlpHybridPolicy`)
    :param env: the joint env: a registered id such as ``"sb3_detc/MultiwalkerETC-v0"``,
        from which MAPPOC builds the fast setting (``n_envs`` rollout workers, each in its own
        process, :func:`make_rollout_workers`); a VecEnv or Gymnasium env, used as given (wrap
        the envs in :class:`~sb3_detc.mappoc.workers.RolloutWorker` for the fast rollouts); or a
        PettingZoo :class:`EventTriggeredNetwork`, adapted to the joint view. A ``VecNormalize``
        in its wrappers may normalise the ``local`` observations (``norm_obs_keys=["local"]``), not the keys of
        :data:`NETWORK_KEYS` (see :func:`check_observation_normalization`); its reward
        normalisation leaves the per-agent rewards MAPPOC learns from (``info["agent_rewards"]``)
        as they are, ``normalize_reward`` normalises those
    :param learning_rate: learning rate, constant or a schedule of the remaining progress (paper: 3e-5)
    :param n_steps: steps per environment per rollout (None: the paper's 2048 steps per
        iteration, divided over the environments)
    :param batch_size: minibatch size (paper: 32)
    :param n_epochs: epochs per rollout (paper: 10)
    :param gamma: discount factor
    :param gae_lambda: GAE factor
    :param clip_range: clipping parameter of the control policy ``pi`` (constant or schedule)
    :param clip_range_broadcast: clipping parameter of the policy over options ``mu`` (constant or schedule)
    :param broadcast_ent_coef: coefficient ``zeta`` of the mean entropy of ``mu`` (constant or
        schedule; the paper's code sums over minibatches of 32, so its final 0.02 is 0.64 here)
    :param vf_coef: coefficient of the critic's squared error
    :param max_grad_norm: maximum gradient norm, or None for no clipping (paper: none)
    :param action_noise_std: standard deviation of extra Gaussian noise on the controls
        (the curriculum changes it during training); log-probabilities refer to the noisy controls
    :param broadcast_advantage: advantage of the taken option in ``mu``'s loss: ``"greedy"``
        (the paper: ``Q(o) - max_o' Q(o')`` with the current critic) or ``"return"`` (the
        lambda-return minus ``V(s) = sum_o mu(o) Q(s, o)`` at collection time, standardised
        per agent like the control advantages if ``normalize_advantage``: a sampled advantage
        that does not rely on the critic telling the two options apart)
    :param broadcast_advantage_offset: constant added to the greedy broadcast advantage (the
        paper's code used a 0.1 "deliberation" offset; the paper and the default use 0)
    :param normalize_broadcast_advantage: divide every agent's greedy broadcast advantages by the
        root mean square of its critic's broadcast gap ``Q(1) - Q(0)`` over the minibatch, so
        that ``mu`` moves towards the better option at a rate set by the learning rate and
        the clip range, not by the (often tiny) scale of the value of a single broadcast,
        just as the control advantages are standardised (the paper: raw advantages)
    :param reward_scale: factor applied to rewards for learning only (paper: 0.1)
    :param normalize_reward: divide every agent's (scaled) reward by a running standard
        deviation of its discounted return, clipped to [-10, 10], as SB3's ``VecNormalize``
        does for single-agent rewards (which it cannot do here: per-agent rewards travel in
        ``info``); useful where returns span orders of magnitude during training
    :param team_reward: train every agent on the team's mean reward instead of its own (the
        paper: own rewards). A broadcast mostly helps the *others* act, so with own rewards the
        sender sees only part of its value
    :param normalize_advantage: standardise the control advantages per agent and minibatch (and
        the broadcast advantages with ``broadcast_advantage="return"``)
    :param target_kl: stop the epochs of an update early when the control policy's
        approximate KL divergence exceeds ``1.5 * target_kl`` (None: never)
    :param share_parameters: one network set for all agents with an agent-id input
        (added to ``policy_kwargs``; default off, as in the paper)
    :param train_control_policy: whether ``pi`` (and its log standard deviation) is trained;
        switch it off to learn only when to communicate for a trained controller
    :param train_broadcast_policy: whether ``mu`` is trained (baselines with fixed
        communication switch it off)
    :param torch_compile: compile the rollout's sampling and every gradient step with
        ``torch.compile`` (needs a C++ compiler); with the default Adam optimizer and no
        ``target_kl``, a gradient step (loss, gradients, clipping, Adam update) is one
        compiled graph (:mod:`sb3_detc.mappoc.steps`). On a CPU about twice the gradient
        steps per second and faster rollouts (``benchmarks/results/train_throughput.log``), for a one-off
        compilation of tens of seconds with a warm compile cache, about a minute with a cold one (and a
        few seconds whenever a new variant appears, e.g. a first fixed trigger), so worth it for
        long runs. ``"auto"``: compile
        when a C++ compiler is found, the device is the CPU and ``learn`` runs at least
        :data:`COMPILE_FROM_TIMESTEPS` steps
    :param overlap_rollouts: let the rollout workers (in worker processes) sample the next rollout
        while the learner updates on the last one, with the parameters from before that update,
        instead of waiting for the update: the learner then trains with one thread and workers
        and learner share the cores. The update corrects for the one update the samples lag
        behind: PPO's ratio and clipping refer to the policy at the update's start, and every
        sample's surrogate is weighted by its probability under that policy over its probability
        under the policy that sampled it (the decoupled objective of Hilton, Cobbe and Schulman,
        2022, "Batch size-invariance for policy optimization"; the critic's error and the
        entropy are not weighted). Settings that callbacks change in ``on_rollout_start`` (noise,
        fixed trigger) reach the sampling one rollout later. The logger's ``rollout/sampler_kl_pi``
        and ``rollout/sampler_kl_mu`` estimate the KL divergence from the sampling policy to the
        update's start (per agent and step). Without worker processes (or with a
        fixed trigger that cannot run in them) rollouts are sampled in turn, as without it. About
        1.12x the steps per second on Multiwalker with 2 cores, but there it learned worse over 5
        seeds (study ``multiwalker_paper``, ``benchmarks/README.md``), so no entry turns it on.
    :param n_envs: number of envs built from an env id (None: :func:`default_n_envs`, one
        per CPU core rounded down to a power of two, at most 8); only for an env id
    :param fixed_trigger: take the options from this trigger instead of ``mu`` (see
        :meth:`set_fixed_trigger`; None: from ``mu``)
    :param stats_window_size: window size of the rollout logging (episodes)
    :param tensorboard_log: log location for TensorBoard (None: no logging)
    :param policy_kwargs: additional arguments of the policy on creation
    :param verbose: verbosity level: 0 no output, 1 info messages, 2 debug messages
    :param seed: seed of the pseudo random generators
    :param device: device (cpu, cuda, ...) on which the code runs
    :param _init_setup_model: whether to build the network at the creation of the instance

    The loss's and the rewards' settings (``vf_coef``, ``broadcast_advantage*``,
    ``normalize_advantage``, ``max_grad_norm``, ``target_kl``, ``gamma``, ``reward_scale``,
    ``team_reward``) are read when the model is built or loaded (``MAPPOC.load(path, key=value)``
    changes them); what callbacks switch during training goes through the ``set_*`` methods.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpHybridPolicy": MlpHybridPolicy}
    policy: MlpHybridPolicy
    rollout_buffer: HybridRolloutBuffer  # type: ignore[assignment]

    def __init__(
        self,
        policy: str | type[MlpHybridPolicy],
        env: GymEnv | str | EventTriggeredNetwork,
        learning_rate: float | Schedule = 3e-5,
        n_steps: int | None = None,
        batch_size: int = 32,
        n_epochs: int = 10,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        clip_range: float | Schedule = 0.2,
        clip_range_broadcast: float | Schedule = 0.2,
        broadcast_ent_coef: float | Schedule = 0.64,
        vf_coef: float = 1.0,
        max_grad_norm: float | None = None,
        action_noise_std: float = 0.0,
        broadcast_advantage: str = "greedy",
        broadcast_advantage_offset: float = 0.0,
        normalize_broadcast_advantage: bool = False,
        reward_scale: float = 0.1,
        normalize_reward: bool = False,
        team_reward: bool = False,
        normalize_advantage: bool = True,
        target_kl: float | None = None,
        share_parameters: bool = False,
        train_control_policy: bool = True,
        train_broadcast_policy: bool = True,
        torch_compile: bool | str = "auto",
        overlap_rollouts: bool = False,
        n_envs: int | None = None,
        fixed_trigger: FixedTrigger | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        if not isinstance(overlap_rollouts, bool):
            raise ValueError(f"overlap_rollouts must be True or False, got {overlap_rollouts!r}.")
        if torch_compile not in (True, False, "auto"):
            raise ValueError(f"torch_compile must be True, False or 'auto', got {torch_compile!r}.")
        if broadcast_advantage not in BROADCAST_ADVANTAGES:
            raise ValueError(f"broadcast_advantage must be 'greedy' or 'return', got {broadcast_advantage!r}.")
        if n_envs is not None:
            if not isinstance(env, str):
                raise ValueError(
                    "n_envs is the number of envs MAPPOC builds from an env id; pass an env id, not an env."
                )
            if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
                raise ValueError(f"n_envs must be a positive integer, got {n_envs!r}.")
        env = _as_joint_env(env)
        if isinstance(env, str):
            n_envs = n_envs or default_n_envs()
        if n_steps is None:
            n_envs_given = n_envs if isinstance(env, str) else env.num_envs if isinstance(env, VecEnv) else 1
            n_steps = max(1, PAPER_ITERATION // n_envs_given)
        check_hyperparameters(
            learning_rate=learning_rate,
            n_steps=n_steps,
            batch_size=batch_size,
            n_epochs=n_epochs,
            gamma=gamma,
            gae_lambda=gae_lambda,
            clip_range=clip_range,
            clip_range_broadcast=clip_range_broadcast,
            broadcast_ent_coef=broadcast_ent_coef,
            vf_coef=vf_coef,
            max_grad_norm=max_grad_norm,
            action_noise_std=action_noise_std,
            reward_scale=reward_scale,
            target_kl=target_kl,
            normalize_advantage=normalize_advantage,
        )
        if isinstance(env, str):  # after the checks: no worker processes for a model that cannot be built
            env = make_rollout_workers(env, n_envs, seed)  # type: ignore[arg-type]
        n_steps, batch_size, n_epochs = int(n_steps), int(batch_size), int(n_epochs)  # e.g. from numpy
        policy_kwargs = dict(policy_kwargs or {})
        if share_parameters and not policy_kwargs.get("share_parameters", True):
            raise ValueError("share_parameters=True contradicts policy_kwargs['share_parameters']=False: give one.")
        policy_kwargs.setdefault("share_parameters", share_parameters)
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            n_steps=n_steps,
            gamma=gamma,
            gae_lambda=gae_lambda,
            ent_coef=0.0,
            vf_coef=vf_coef,
            max_grad_norm=max_grad_norm,  # type: ignore[arg-type]
            use_sde=False,
            sde_sample_freq=-1,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            device=device,
            seed=seed,
            _init_setup_model=False,
            supported_action_spaces=None,
        )
        if self.env is not None:  # without an env (loading), the spaces are checked in _setup_model
            check_joint_spaces(self.observation_space, self.action_space)
            _check_vec_normalize(self.env)  # also on load(path, env): SB3's load builds the model with the env
        self.batch_size = batch_size
        self.n_epochs = n_epochs
        self.clip_range = clip_range
        self.clip_range_broadcast = clip_range_broadcast
        self.broadcast_ent_coef = broadcast_ent_coef
        self.action_noise_std = action_noise_std
        self.broadcast_advantage = broadcast_advantage
        self.broadcast_advantage_offset = broadcast_advantage_offset
        self.normalize_broadcast_advantage = normalize_broadcast_advantage
        self.reward_scale = reward_scale
        self.normalize_reward = normalize_reward
        self.team_reward = team_reward
        self.normalize_advantage = normalize_advantage
        self.target_kl = target_kl
        self.train_control_policy = train_control_policy
        self.train_broadcast_policy = train_broadcast_policy
        self.torch_compile = torch_compile
        self.overlap_rollouts = overlap_rollouts
        #: the rollout the workers sample during the update (``overlap_rollouts``), None between ``learn`` calls
        #: unless ``learn`` stopped on an error with one sampled, which the next ``learn`` takes
        self._pending: PendingRollout | None = None
        self._waiter: ThreadPoolExecutor | None = None
        self._learner_threads: int | None = None  # the learner's threads while a rollout is pending
        self._behaviour_hold: tuple[MlpHybridPolicy, MlpHybridPolicy] | None = None  # (policy, its spare copy)
        self.fixed_trigger: FixedTrigger | None = fixed_trigger  # checked by set_fixed_trigger in _setup_model
        #: the fixed trigger that took the options of the rollout being collected or in the buffer (None: ``mu``);
        #: with ``overlap_rollouts`` the one set when the rollout started, which a callback may have changed since
        self._rollout_trigger: FixedTrigger | None = fixed_trigger
        self._action_noise_terms: dict[Hashable, float] = {}
        #: whether the last rollout was sampled inside rollout workers (None: no rollout yet)
        self.last_rollout_in_workers: bool | None = None
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        self.n_agents, self.n_control = check_joint_spaces(self.observation_space, self.action_space)
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        self.policy_kwargs = renamed_keys(self.policy_kwargs)  # also a model saved under earlier names
        self.policy = self.policy_class(  # type: ignore[assignment]
            self.observation_space, self.action_space, self.lr_schedule, **self.policy_kwargs
        )
        self.policy = self.policy.to(self.device)
        self.rollout_buffer = HybridRolloutBuffer(
            self.n_steps,
            self.observation_space,  # type: ignore[arg-type]
            self.action_space,  # type: ignore[arg-type]
            device=self.device,
            gamma=self.gamma,
            gae_lambda=self.gae_lambda,
            n_envs=self.n_envs,
        )
        # The settings are the model's (load(..., normalize_reward=True) changes them); a loaded model brings the
        # statistics: in its saved transform, or as reward_rms if it was saved before RewardTransform existed.
        saved = self.__dict__.pop("reward_transform", None)
        saved_rms = self.__dict__.pop("reward_rms", None)
        for old in RENAMED:  # a model saved under earlier names (MAPPOC.load took the values)
            self.__dict__.pop(old, None)
        self.reward_transform = RewardTransform(
            self.n_agents, self.gamma, self.reward_scale, self.team_reward, self.normalize_reward
        )
        self.reward_transform.return_rms = saved.return_rms if saved is not None else saved_rms
        self.loss = MAPPOCLoss(
            self.policy,
            self.vf_coef,
            self.broadcast_advantage,
            self.broadcast_advantage_offset,
            self.normalize_broadcast_advantage,
            self.normalize_advantage,
        )
        control_space = self.action_space["control"]  # type: ignore[index]
        self._control_low, self._control_high = control_space.low, control_space.high
        self._setup_steps(self.torch_compile is True)
        self.set_fixed_trigger(self.fixed_trigger)

    def _setup_steps(self, compiled: bool) -> None:
        """Choose the sampling function and the gradient step: eager, or compiled (and fused where it can be).

        :param compiled: whether to compile them
        """
        if compiled and self.device.type == "cpu":
            check_cxx_compiler()
        self._compiled = compiled
        # The rollout workers compile their copy of the policy (or not) when they receive it: send it again.
        self._workers_hold: tuple[MlpHybridPolicy, VecEnv] | None = None
        sample = self.policy.sample_actions
        self._sample_actions: Callable[..., tuple[th.Tensor, th.Tensor]] = th.compile(sample) if compiled else sample
        optimizer = self.policy.optimizer
        self.gradient_step: GradientStep | FusedGradientStep
        # Early stopping looks at a step's statistics before applying it: only the unfused step can.
        if compiled and fusable_adam(optimizer) and self.target_kl is None:
            self.gradient_step = FusedGradientStep(self.loss, optimizer, self.max_grad_norm)
        else:
            self.gradient_step = GradientStep(
                self.loss, optimizer, self.max_grad_norm, self.target_kl, compile_loss=compiled
            )

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        if self.torch_compile == "auto":
            compiled = self.device.type == "cpu" and total_timesteps >= COMPILE_FROM_TIMESTEPS and has_cxx_compiler()
            if compiled != self._compiled:
                self._setup_steps(compiled)
        if reset_num_timesteps or self._last_obs is None:  # the envs are reset: a kept rollout started elsewhere
            self._pending = None
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "fixed_trigger",
            "loss",
            "gradient_step",
            "_sample_actions",
            "_workers_hold",
            "_action_noise_terms",
            "_compiled",
            "_pending",
            "_waiter",
            "_learner_threads",
            "_behaviour_hold",
            "_rollout_trigger",
        ]

    # ------------------------------------------------------------------ modes
    def set_fixed_trigger(self, trigger: FixedTrigger | None) -> None:
        """Take every rollout's options from a fixed trigger instead of ``mu`` (None: from ``mu`` again).

        ``mu`` is not trained on the rollouts whose options a fixed trigger took (with
        ``overlap_rollouts`` also the one sampled before the trigger was set off). The values at
        the rollout's end and at truncations average the option values under the trigger's
        ``broadcast_probability(obs)`` if it has one (the triggers of :mod:`sb3_detc.triggers`
        do), else under ``mu``. Not saved with the model.

        :param trigger: callable batch of joint observations (B, N, ...) -> options (B, N), e.g.
            from :mod:`sb3_detc.triggers`; with rollout workers, a trigger with ``fork(seed)``
            runs in the workers (one fork per env and rollout), any other keeps the rollout in
            this process
        :raises ValueError: for a trigger that is not callable, or with a critic that needs the
            probabilities with which ``mu`` drew the options
        """
        if trigger is not None and not callable(trigger):
            raise ValueError(f"a fixed trigger must be callable (joint observations -> options), got {trigger!r}.")
        if trigger is not None and self.policy.option_critic.needs_draw_probabilities:
            usable = " or ".join(repr(name) for name, critic in CRITICS.items() if not critic.needs_draw_probabilities)
            raise ValueError(
                f"critic={self.policy.critic!r} needs the probabilities with which the options were drawn, which a "
                f"fixed trigger does not give; use critic={usable} with a fixed trigger."
            )
        self.fixed_trigger = trigger

    def set_trained_policies(self, control_policy: bool, broadcast_policy: bool) -> None:
        """Choose which policy levels the updates train (the critic always learns).

        :param control_policy: whether ``pi`` (and its log standard deviation, if learned) is trained
        :param broadcast_policy: whether ``mu`` is trained (never while a fixed trigger decides)
        """
        self.train_control_policy = bool(control_policy)
        self.train_broadcast_policy = bool(broadcast_policy)

    def set_action_noise_std(self, std: float | None, source: Hashable = None) -> None:
        """Set one source's extra Gaussian noise on the controls; the noise used is the largest of all sources.

        Schedules (e.g. the curriculum's phases I and III) each own one term; a source that
        sets None withdraws its term (the noise keeps its value until another term changes it).

        :param std: the source's standard deviation (>= 0), or None to withdraw it
        :param source: who sets it (any hashable, e.g. the callback itself)
        :raises ValueError: for a negative ``std``
        """
        if std is None:
            self._action_noise_terms.pop(source, None)
            return
        if not std >= 0:
            raise ValueError(f"action_noise_std must be >= 0, got {std!r}.")
        self._action_noise_terms[source] = float(std)
        self.action_noise_std = max(self._action_noise_terms.values())

    def set_learning_rate(self, learning_rate: float | Schedule) -> None:
        """Use another learning rate (a number, or a schedule of the remaining progress) from the next update on.

        :param learning_rate: the new learning rate
        """
        self.learning_rate = learning_rate
        self._setup_lr_schedule()

    def set_reward_normalization(self, normalize: bool, fresh_statistics: bool = False) -> None:
        """Switch the normalisation of the learner's rewards (see ``normalize_reward``) on or off.

        :param normalize: whether to divide rewards by the running spread of the returns
        :param fresh_statistics: forget the spread measured so far, so that it is measured on the
            rewards from now on (e.g. when the policies that learn change and their returns are of
            another size than the earlier ones)
        """
        self.normalize_reward = bool(normalize)
        self.reward_transform.normalize = self.normalize_reward
        if fresh_statistics:
            self.reward_transform.return_rms = None
            self.reward_transform.discounted_returns = None

    # ------------------------------------------------------------------ rollouts
    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """Collect ``n_rollout_steps`` steps per environment with the current policies.

        Per step: all options are sampled from ``mu`` (or taken from the fixed trigger), the
        broadcasts are delivered, then all controls are sampled from ``pi`` on the updated
        views (same-step delivery), with :attr:`action_noise_std` extra noise; the env receives
        the controls clipped to their bounds. The steps are sampled first, inside rollout
        workers where the env has them (:mod:`sb3_detc.mappoc.workers`), else here; then every
        step goes through :meth:`_record_rollout` in order. With ``overlap_rollouts`` the steps
        were sampled by the workers during the last update, and the workers start on the next
        rollout before this one returns (unless ``learn`` ends with it).

        :param env: the training environment
        :param callback: callback called at each step (and at the beginning and end of the rollout)
        :param rollout_buffer: the buffer to fill (a :class:`HybridRolloutBuffer`)
        :param n_rollout_steps: number of steps to collect per environment
        :return: True if the rollout was completed, False if a callback stopped it
        """
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)
        rollout_buffer.reset()
        pending = self._wait_for_pending()  # before the callbacks: the workers' pipes are free again
        self._pending = None
        callback.on_rollout_start()  # callbacks may change the mode, the noise or the cost here
        behaviour = None
        # The options of a rollout sampled during the last update are those of the trigger set then.
        self._rollout_trigger = self.fixed_trigger if pending is None else pending.trigger
        if pending is not None:
            rollout, behaviour = pending.rollout.result(), pending.behaviour
            self.last_rollout_in_workers = True
        elif self._in_workers(env):
            rollout = self._sample_in_workers(env, n_rollout_steps)
            self.last_rollout_in_workers = True
        else:
            rollout = self._sample_here(env, n_rollout_steps)
            self.last_rollout_in_workers = False
        if not self._record_rollout(rollout, env, callback, rollout_buffer, behaviour, self._rollout_trigger):  # type: ignore[arg-type]
            return False
        another_follows = self.num_timesteps < self._total_timesteps  # learn's loop goes on
        if self.overlap_rollouts and another_follows and self._in_workers(env, processes=True):
            self._start_pending(env, n_rollout_steps)
        return True

    @property
    def has_pending_rollout(self) -> bool:
        """Whether the workers hold a rollout sampled for the next ``learn`` (``overlap_rollouts``).

        Only after a ``learn`` stopped by an error during an update; a ``learn`` that resets the
        envs (``reset_num_timesteps=True``) or :meth:`set_env` drops it.
        """
        return self._pending is not None

    def _in_workers(self, env: VecEnv, processes: bool = False) -> bool:
        """Whether the next rollout can be sampled in rollout workers (in worker processes, if ``processes``).

        :param env: the training env
        :param processes: whether the workers must run in processes of their own
        """
        trigger = self.fixed_trigger
        in_workers = (trigger is None or hasattr(trigger, "fork")) and has_rollout_workers(env)
        return in_workers and (isinstance(env, SubprocVecEnv) or not processes)

    def _start_pending(self, env: VecEnv, n_steps: int) -> None:
        """Let the workers sample the next rollout with a copy of the current parameters; the learner goes on.

        :param env: the training env (of rollout workers in worker processes)
        :param n_steps: steps per env
        """
        behaviour = {key: value.detach().clone() for key, value in self.policy.state_dict().items()}
        # The learner trains with one thread meanwhile: it keeps its core, the workers take what is left.
        niceness = os.getpriority(os.PRIO_PROCESS, 0) + WORKER_NICENESS if hasattr(os, "getpriority") else None
        sample = self._worker_rollout(env, n_steps, behaviour, niceness)
        if self._waiter is None:
            self._waiter = ThreadPoolExecutor(max_workers=1, thread_name_prefix="rollout")
        self._pending = PendingRollout(self._waiter.submit(sample), behaviour, self.fixed_trigger)
        self._learner_threads = th.get_num_threads()
        th.set_num_threads(1)

    def _wait_for_pending(self) -> PendingRollout | None:
        """Wait until the pending rollout (if any) is sampled and give the learner its threads back.

        :return: the pending rollout, still :attr:`_pending`
        """
        if self._pending is not None:
            wait([self._pending.rollout])
        if self._learner_threads is not None:
            th.set_num_threads(self._learner_threads)
            self._learner_threads = None
        return self._pending

    def _sample_here(self, env: VecEnv, n_steps: int) -> Rollout:
        """Sample and step ``n_steps`` steps of every env in this process.

        :param env: the training env
        :param n_steps: steps per env
        :return: the sampled steps, starting from :attr:`_last_obs`
        """
        obs = self._last_obs
        steps = []
        for _ in range(n_steps):
            with th.no_grad():
                forced = None
                if self.fixed_trigger is not None:
                    forced = th.as_tensor(self.fixed_trigger(obs), device=self.device)  # type: ignore[arg-type]
                broadcast, control = self._sample_actions(
                    obs_as_tensor(obs, self.device),  # type: ignore[arg-type]
                    self.action_noise_std,
                    forced,
                )
            broadcast, control = broadcast.cpu().numpy(), control.cpu().numpy()
            clipped = np.clip(control, self._control_low, self._control_high)
            new_obs, _, dones, infos = env.step(
                [{"broadcast": c, "control": u} for c, u in zip(broadcast, clipped, strict=True)]
            )
            check_finite(new_obs)  # before the policy acts on them
            reset_infos = getattr(env, "reset_infos", None)
            for idx in np.flatnonzero(dones) if reset_infos is not None else ():
                infos[idx]["reset_info"] = reset_infos[idx]  # as workers report it (the VecEnv keeps the latest only)
            steps.append((obs, broadcast, control, dones, infos))
            obs = new_obs
        observations, broadcast, control, dones, infos = zip(*steps, strict=True)
        return Rollout(
            _stack_dicts(list(observations), axis=0),
            np.stack(broadcast),
            np.stack(control),
            np.stack(dones),
            list(infos),
            obs,
        )  # type: ignore[arg-type]

    def _sample_in_workers(self, env: VecEnv, n_steps: int) -> Rollout:
        """Let every env sample and step ``n_steps`` steps with a copy of the current policy (in parallel).

        While worker processes sample, the learner compiles its gradient step if it needs to.

        :param env: the training env (of rollout workers)
        :param n_steps: steps per env
        :return: the sampled steps
        """
        sample = self._worker_rollout(env, n_steps, self.policy.state_dict())
        if self.gradient_step.needs_warm_up and isinstance(env, SubprocVecEnv):
            # The learner waits for the worker processes: compile its gradient step meanwhile.
            with ThreadPoolExecutor(max_workers=1) as waiter:
                collected = waiter.submit(sample)
                self._warm_up_gradient_step()
                return collected.result()
        return sample()

    def _worker_rollout(
        self, env: VecEnv, n_steps: int, state: dict[str, th.Tensor], niceness: int | None = None
    ) -> Callable[[], Rollout]:
        """What lets every env sample and step ``n_steps`` steps with the policy's parameters ``state`` (in parallel).

        The policy (if new to the workers), the settings and the seeds are taken now; the returned
        call sends them and waits for the steps (also from another thread: it reads nothing of
        the model).

        :param env: the training env (of rollout workers)
        :param n_steps: steps per env
        :param state: the parameters to sample with, unchanged until the call returns
        :param niceness: the workers' scheduling priority, at least (see ``RolloutWorker.collect_rollout``)
        """
        n_envs = env.num_envs
        new_policy = self._workers_hold != (self.policy, env)
        if new_policy:
            for index in range(n_envs):
                env.env_method("set_worker_index", index, indices=index)
        seeds = th.randint(2**31 - 1, (n_envs,)).tolist()
        trigger = self.fixed_trigger
        collect = functools.partial(
            env.env_method,
            "collect_rollout",
            pickle.dumps(self.policy) if new_policy else None,
            {key: value.detach().cpu().numpy() for key, value in state.items()},
            n_steps,
            self.action_noise_std,
            seeds,
            self._compiled,
            None if trigger is None else [pickle.dumps(trigger.fork(seed)) for seed in seeds],  # type: ignore[attr-defined]
            niceness,
        )
        self._workers_hold = (self.policy, env)

        def sample() -> Rollout:
            trajectories = collect()

            def stacked(key: str) -> Any:  # (steps, n_envs, ...)
                return np.stack([trajectory[key] for trajectory in trajectories], axis=1)

            return Rollout(
                _stack_dicts([trajectory["observations"] for trajectory in trajectories], axis=1),
                stacked("broadcast"),
                stacked("control"),
                stacked("dones"),
                [[trajectory["infos"][step] for trajectory in trajectories] for step in range(n_steps)],
                _stack_dicts([trajectory["last_obs"] for trajectory in trajectories], axis=0),
            )

        return sample

    def _record_rollout(
        self,
        rollout: Rollout,
        env: VecEnv,
        callback: BaseCallback,
        buffer: HybridRolloutBuffer,
        behaviour: dict[str, th.Tensor] | None = None,
        trigger: FixedTrigger | None = None,
    ) -> bool:
        """Take sampled steps into training, in order, whoever sampled them.

        Per step: the learner's rewards (:class:`~sb3_detc.mappoc.rewards.RewardTransform`) and
        the price of a broadcast, ``num_timesteps``, the callbacks, the episode statistics and
        the truncated episodes; then, for the whole rollout in one batch, log-probabilities and
        option values of the current policy, the bootstrap of truncated episodes and of the
        rollout's end with ``V(s_T) = sum_o p(o) Q(s_T, o)`` (as SB3 does for PPO) under the
        options' probabilities ``p`` of what took them: ``mu``, or a fixed trigger that tells its
        ``broadcast_probability``; the buffer, GAE and ``on_rollout_end``. The envs are at the
        rollout's end whether or not a callback stops on the way.

        :param rollout: the sampled steps
        :param env: the training environment
        :param callback: callback called at each step and at the end of the rollout
        :param buffer: the buffer to fill
        :param behaviour: the parameters that sampled the steps if they are not the current ones
            (``overlap_rollouts``), for the log-probabilities of the behaviour policy
        :param trigger: the fixed trigger that took the steps' options (None: ``mu``)
        :return: True if the rollout was completed, False if a callback stopped it
        """
        n_steps, n_envs = rollout.dones.shape
        episode_starts = np.concatenate([np.asarray(self._last_episode_starts)[None], rollout.dones[:-1]])
        self._last_obs, self._last_episode_starts = rollout.last_obs, rollout.dones[-1]  # type: ignore[assignment]
        broadcast_cost = self._broadcast_costs(env)
        prices, all_rewards, truncated = [], [], []
        env_rewards = agent_rewards([info for infos in rollout.infos for info in infos]).reshape(n_steps, n_envs, -1)
        for step in range(n_steps):
            infos, dones = rollout.infos[step], rollout.dones[step]
            new_obs = (
                rollout.last_obs if step == n_steps - 1 else {k: v[step + 1] for k, v in rollout.observations.items()}
            )
            prices.append(self.reward_transform.price(broadcast_cost))
            rewards = self.reward_transform(env_rewards[step], dones)
            self.num_timesteps += n_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            truncated += [(step, idx, terminal_obs) for idx, terminal_obs in _truncated(infos, dones)]
            all_rewards.append(rewards)

        price = np.stack(prices)
        flat = n_steps * n_envs
        steps = (
            obs_as_tensor({k: v.reshape(flat, *v.shape[2:]) for k, v in rollout.observations.items()}, self.device),
            th.as_tensor(rollout.broadcast.reshape(flat, -1), device=self.device),
            th.as_tensor(rollout.control.reshape(flat, *rollout.control.shape[2:]), device=self.device),
            th.as_tensor(price.reshape(flat, -1), device=self.device),
        )
        with th.no_grad():
            sampled, drawn = None, None  # drawn: the probabilities of broadcasting with which the options were drawn
            if behaviour is not None:
                sampled = self._behaviour_policy(behaviour).evaluate_actions(*steps)
                drawn = drawn_broadcast_probability(steps[1], sampled.log_prob_broadcast)
            evaluation = self.policy.evaluate_actions(*steps, drawn)
            if sampled is not None:  # how far the update's start has moved from the sampler (k3 estimate of the KL)
                for name, now, then in (
                    ("pi", evaluation.log_prob_control, sampled.log_prob_control),
                    ("mu", evaluation.log_prob_broadcast, sampled.log_prob_broadcast),
                ):
                    log_weight = now - then
                    self.logger.record(f"rollout/sampler_kl_{name}", float((th.expm1(log_weight) - log_weight).mean()))
            probability = getattr(trigger, "broadcast_probability", None)

            def state_values(obs: dict[str, np.ndarray], prices: np.ndarray) -> th.Tensor:
                p = None if probability is None else probability(obs)
                return self.policy.state_values(
                    obs_as_tensor(obs, self.device),  # type: ignore[arg-type]
                    th.as_tensor(prices, device=self.device),
                    None if p is None else th.as_tensor(p, dtype=th.float32, device=self.device),
                )

            if truncated:
                at = [(step, idx) for step, idx, _ in truncated]
                terminal = _stack_dicts([obs for _, _, obs in truncated], axis=0)
                values = state_values(terminal, np.stack([price[s, i] for s, i in at]))
                for (step, idx), value in zip(at, values.cpu().numpy(), strict=True):
                    all_rewards[step][idx] += self.gamma * value
            last_values = state_values(rollout.last_obs, self.reward_transform.price(broadcast_cost))  # type: ignore[arg-type]

        def per_step(x: th.Tensor) -> np.ndarray:
            return x.cpu().numpy().reshape(n_steps, n_envs, *x.shape[1:])

        buffer.extend(
            rollout.observations,
            rollout.broadcast,
            rollout.control,
            np.stack(all_rewards),
            episode_starts,
            per_step(evaluation.option_values),
            per_step(evaluation.log_prob_broadcast),
            per_step(evaluation.log_prob_control),
            price,
            None if sampled is None else (per_step(sampled.log_prob_broadcast), per_step(sampled.log_prob_control)),
        )
        buffer.compute_returns_and_advantage(last_values=last_values.cpu().numpy(), dones=rollout.dones[-1])
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def _behaviour_policy(self, state: dict[str, th.Tensor]) -> MlpHybridPolicy:
        """A spare copy of the policy with the parameters ``state`` (of a rollout sampled earlier).

        :param state: the parameters
        """
        if self._behaviour_hold is None or self._behaviour_hold[0] is not self.policy:
            self._behaviour_hold = (self.policy, copy.deepcopy(self.policy))
        spare = self._behaviour_hold[1]
        spare.load_state_dict(state)
        spare.set_training_mode(False)
        return spare

    # ------------------------------------------------------------------ updates
    def train(self) -> None:
        """Update every agent's ``pi``, ``mu`` and ``Q`` with PPO on the collected rollout (Sec. 3)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        update = self.update_inputs(self.rollout_buffer.tensors())
        clip_pi, clip_mu, zeta, train_mu = update.clip_pi, update.clip_mu, update.zeta, update.train_mu
        # Networks sharing a batched chain with trained ones get zero gradients, but Adam's momentum
        # from earlier training would still move them: restore them after every step instead.
        frozen = [net for net, trained in (("pi", self.train_control_policy), ("mu", train_mu)) if not trained]
        frozen_views = [view for net in frozen for view in self.policy.net_parameters(net)]
        frozen_values = [view.clone() for view in frozen_views]

        stats: dict[str, list[float]] = {name: [] for name in STEP_STATS}
        continue_training = True
        for epoch in range(self.n_epochs):
            for idx in self.rollout_buffer.minibatch_indices(self.batch_size):
                step_stats, continue_training = self.gradient_step(update, idx)
                for name, value in zip(STEP_STATS, step_stats.tolist(), strict=True):
                    stats[name].append(value)
                if not continue_training:
                    if self.verbose >= 1:
                        print(f"Early stopping at epoch {epoch} due to reaching max kl: {stats['kl_pi'][-1]:.2f}")
                    break
                for view, value in zip(frozen_views, frozen_values, strict=True):
                    view.copy_(value)
            self._n_updates += 1
            if not continue_training:
                break

        buffer = self.rollout_buffer
        for name, values in stats.items():
            self.logger.record(f"train/{name}", float(np.mean(values)) if values else float("nan"))
        self.logger.record(
            "train/explained_variance_q", explained_variance(buffer.values.ravel(), buffer.returns.ravel())
        )
        self.logger.record("train/std", float(th.exp(self.policy.log_std.detach()).mean()))
        self.logger.record("train/clip_range", clip_pi)
        self.logger.record("train/clip_range_broadcast", clip_mu)
        self.logger.record("train/broadcast_ent_coef", zeta)
        self.logger.record("train/action_noise_std", self.action_noise_std)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("rollout/broadcast_rate", float(buffer.broadcast.mean()))

    def update_inputs(self, rollout: HybridRolloutSamples) -> UpdateInputs:
        """What every gradient step of an update needs of the rollout and of the update's settings now.

        The settings (clip ranges, broadcast entropy coefficient, which levels train) are constants
        or schedules of the remaining progress; callbacks (e.g. the curriculum) may change them
        between updates.

        :param rollout: the rollout buffer's samples (:meth:`HybridRolloutBuffer.tensors`)
        :return: the inputs of :attr:`gradient_step`
        """
        progress = self._current_progress_remaining
        return UpdateInputs(
            # The networks' inputs depend on stored observations and options only: built once.
            self.policy.training_inputs(rollout.observations, rollout.broadcast),
            rollout._replace(observations={}),
            # probability of broadcasting with which the options were drawn (the centred critic's p_i)
            drawn_broadcast_probability(rollout.broadcast, rollout.behaviour_log_prob_broadcast),
            FloatSchedule(self.clip_range)(progress),
            FloatSchedule(self.clip_range_broadcast)(progress),
            FloatSchedule(self.broadcast_ent_coef)(progress),
            self.train_control_policy,
            self.train_broadcast_policy and self._rollout_trigger is None,  # mu learns from its own options only
        )

    def _warm_up_gradient_step(self) -> None:
        """Compile the gradient step before the first update, on inputs of the update's shapes and settings."""
        update = self.update_inputs(self.rollout_buffer.tensors(partial=True))
        samples = self.rollout_buffer.buffer_size * self.rollout_buffer.n_envs
        # the first minibatch's shape; not drawn at random: the update's minibatches stay as they were
        self.gradient_step.warm_up(update, th.arange(min(self.batch_size, samples), device=self.device))

    def _broadcast_costs(self, env: VecEnv) -> np.ndarray:
        """The communication cost ``xi`` of every environment, (n_envs,); zeros unless the critic needs it.

        :param env: the training env
        :return: the cost of a broadcast in every env, float32 (n_envs,)
        :raises ValueError: if the critic needs the cost and the envs have no ``broadcast_cost``
        """
        if not self.policy.option_critic.needs_price:
            return np.zeros(env.num_envs, dtype=np.float32)  # such critics learn it from the rewards
        try:
            return np.asarray(env.get_attr("broadcast_cost"), dtype=np.float32)
        except AttributeError as err:
            raise ValueError(
                f"critic={self.policy.critic!r} needs the environment's communication cost (attribute "
                "'broadcast_cost', as the sb3_detc envs have) to add it to its option values."
            ) from err

    def learn(
        self: SelfMAPPOC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "MAPPOC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMAPPOC:
        """Train for ``total_timesteps`` environment steps (summed over environments).

        :param total_timesteps: number of environment steps to train for
        :param callback: callback(s) called at every step
        :param log_interval: iterations between two logs
        :param tb_log_name: name of the run for TensorBoard logging
        :param reset_num_timesteps: whether to reset the current timestep number (used in logging)
        :param progress_bar: display a progress bar using tqdm and rich
        :return: the trained model
        """
        try:
            return super().learn(
                total_timesteps=int(total_timesteps),
                callback=callback,
                log_interval=log_interval,
                tb_log_name=tb_log_name,
                reset_num_timesteps=reset_num_timesteps,
                progress_bar=progress_bar,
            )
        finally:
            # Stopped by an error during an update (``overlap_rollouts``): the workers finish their rollout, which
            # the next learn (without reset_num_timesteps) takes if it was sampled.
            pending = self._wait_for_pending()
            if pending is not None and pending.rollout.exception() is not None:
                self._pending = None
            if self._waiter is not None:  # its thread is idle now (a kept rollout stays in its future)
                self._waiter.shutdown()
                self._waiter = None

    def set_env(self, env: GymEnv | EventTriggeredNetwork, force_reset: bool = True) -> None:
        """Use a new environment (a PettingZoo event-triggered env is adapted to the joint view).

        :param env: the new environment, with the same spaces (and no ``VecNormalize`` of the
            network's observations, see :func:`check_observation_normalization`)
        :param force_reset: force a reset of the environment before the next ``learn``
        :raises ValueError: if the environment has another number of agents than the model or
            normalises the network's observations
        """
        env = _as_joint_env(env)
        _check_same_agents(env, self.n_agents)  # type: ignore[arg-type]
        _check_vec_normalize(env)  # type: ignore[arg-type]
        self._pending = None  # a rollout kept from an interrupted learn (overlap_rollouts) is of the old env
        super().set_env(env, force_reset=force_reset)  # type: ignore[arg-type]

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfMAPPOC],
        path: str | pathlib.Path,
        env: GymEnv | EventTriggeredNetwork | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfMAPPOC:
        """Load a saved model, optionally with an environment (checked for the same number of agents).

        :param path: path to the saved file
        :param env: environment to attach (must have the spaces the model was trained with); from
            an env id, MAPPOC builds as many rollout workers as the model was trained with
        :param device: device on which the code runs
        :param custom_objects: objects to replace on load, see :meth:`BaseAlgorithm.load`
        :param print_system_info: print the system info of the saved model and the current one
        :param force_reset: force a reset of the environment before the next ``learn``
        :param kwargs: attributes to change on the loaded model
        :return: the loaded model (with ``env`` attached, if given)
        :raises FileNotFoundError: if there is no file at ``path``
        :raises ValueError: if the environment has another number of agents than the model or
            normalises the network's observations (see :func:`check_observation_normalization`)
        """
        env = _as_joint_env(env)
        data, _, _ = load_from_zip_file(path, device="cpu", custom_objects=custom_objects, load_data=True)
        data = data or {}
        if isinstance(env, str):  # the fast setting, with the saved number of envs (n_steps is per env)
            env = make_rollout_workers(env, int(data.get("n_envs", 1)))
        if "action_space" in data:
            action_space = renamed_action_space(data["action_space"])
            if action_space is not data["action_space"]:  # saved under an earlier name (sb3_detc.renamed)
                custom_objects = {"action_space": action_space, **(custom_objects or {})}
            if env is not None:
                _check_same_agents(env, len(action_space["broadcast"].nvec))  # type: ignore[arg-type]
        # Attributes saved under earlier names become the current ones unless given here (as custom objects or
        # keyword arguments, also under earlier names); _setup_model drops the old names.
        saved = {RENAMED[key]: value for key, value in data.items() if key in RENAMED}
        given = {key: value for key, value in (custom_objects or {}).items() if key in saved}
        kwargs = {**saved, **given, **renamed_keys(kwargs)}
        return super().load(  # type: ignore[return-value]
            path,
            env=env,  # type: ignore[arg-type]
            device=device,
            custom_objects=custom_objects,
            print_system_info=print_system_info,
            force_reset=force_reset,
            **kwargs,
        )


def has_cxx_compiler() -> bool:
    """Whether ``torch.compile`` finds a C++ compiler for CPU code.

    :return: True if a compiler is found
    """
    from torch._inductor import cpp_builder, exc

    try:
        cpp_builder.get_cpp_compiler()
    except exc.InvalidCxxCompiler:
        return False
    return True


def check_cxx_compiler() -> None:
    """``torch.compile`` builds C++ code for the CPU: fail at once, and clearly, without a compiler.

    :raises RuntimeError: if no C++ compiler is found
    """
    if not has_cxx_compiler():
        raise RuntimeError(
            "torch_compile=True needs a C++ compiler on the CPU (g++ or clang++ on PATH, or the CXX "
            "environment variable); install one or use torch_compile=False."
        )


def has_rollout_workers(env: VecEnv) -> bool:
    """Whether ``env`` is a plain SB3 vector env of :class:`~sb3_detc.mappoc.workers.RolloutWorker` envs.

    Vector env wrappers (e.g. ``VecNormalize``) change what the policy sees: those keep the rollout in
    the learner's process.

    :param env: the training env
    :return: True if it is a ``DummyVecEnv`` or ``SubprocVecEnv`` whose envs have ``collect_rollout``
    """
    return isinstance(env, (DummyVecEnv, SubprocVecEnv)) and env.has_attr("collect_rollout")


def _stack_dicts(dicts: list[dict[str, np.ndarray]], axis: int) -> dict[str, np.ndarray]:
    """Stack same-keyed dicts of arrays key by key along a new ``axis``.

    :param dicts: the dicts (at least one), each key with arrays of the same shape in all of them
    :param axis: position of the new axis (0: steps of one rollout; 1: the envs' trajectories, (T, n_envs, ...))
    :return: key -> stacked array
    """
    return {key: np.stack([d[key] for d in dicts], axis=axis) for key in dicts[0]}


def _truncated(infos: list[dict[str, Any]], dones: np.ndarray) -> list[tuple[int, dict[str, np.ndarray]]]:
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


def _check_same_agents(env: GymEnv, n_agents: int) -> None:
    """Check that a joint env has ``n_agents`` agents (if its action space is a joint one; the rest is checked later).

    :param env: the joint env (Gymnasium or vector env)
    :param n_agents: number of agents N of the model
    :raises ValueError: if the env's ``broadcast`` action has another number of agents
    """
    action_space = env.action_space
    if isinstance(action_space, spaces.Dict) and "broadcast" in action_space.spaces:
        n_env = len(action_space["broadcast"].nvec)
        if n_env != n_agents:
            raise ValueError(f"the model controls {n_agents} agents but the environment has {n_env}.")


#: Hyperparameter checks: name -> (rule, what the rule needs).
_HYPERPARAMETER_RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "learning_rate": (lambda v: callable(v) or v >= 0, ">= 0 or a schedule"),
    "n_steps": (lambda v: isinstance(v, numbers.Integral) and v > 0, "a positive integer"),
    "batch_size": (lambda v: isinstance(v, numbers.Integral) and v > 0, "a positive integer"),
    "n_epochs": (lambda v: isinstance(v, numbers.Integral) and v > 0, "a positive integer"),
    "gamma": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "gae_lambda": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "clip_range": (lambda v: callable(v) or v > 0, "> 0 or a schedule"),
    "clip_range_broadcast": (lambda v: callable(v) or v > 0, "> 0 or a schedule"),
    "broadcast_ent_coef": (lambda v: callable(v) or v >= 0, ">= 0 or a schedule"),
    "vf_coef": (lambda v: v >= 0, ">= 0"),
    "max_grad_norm": (lambda v: v is None or v > 0, "None or > 0"),
    "action_noise_std": (lambda v: v >= 0, ">= 0"),
    "reward_scale": (lambda v: v > 0, "> 0"),
    "target_kl": (lambda v: v is None or v > 0, "None or > 0"),
}


def check_hyperparameters(**values: Any) -> None:
    """Check the values of MAPPOC's numeric hyperparameters (before anything is built).

    :param values: every hyperparameter of :data:`_HYPERPARAMETER_RULES` and ``normalize_advantage``
    :raises ValueError: on the first value out of its range (or of the wrong type)
    """
    for name, (rule, needs) in _HYPERPARAMETER_RULES.items():
        value = values[name]
        try:
            valid = not isinstance(value, bool) and bool(rule(value))
        except TypeError:  # e.g. a string where a number belongs
            valid = False
        if not valid:
            raise ValueError(f"{name} must be {needs}, got {value!r}.")
    if values["normalize_advantage"] and values["batch_size"] == 1:
        raise ValueError("batch_size must be > 1 when normalize_advantage=True (a single advantage has no spread).")


def check_observation_normalization(norm_obs: bool, norm_obs_keys: Sequence[str] | None) -> None:
    """Refuse a ``VecNormalize`` that would normalise observations of :data:`NETWORK_KEYS`.

    ``VecNormalize`` keeps separate statistics per key, while the policy applies the broadcast
    rule (copy the message into ``held``, reset ``age`` to 0) to the values it is given: with
    normalised ``message``, ``held`` and ``age`` the network state it computes is no longer the
    environment's. Normalising only the local state (``norm_obs_keys=["local"]``) or no
    observations (``norm_obs=False``) is fine.

    :param norm_obs: whether the ``VecNormalize`` normalises observations
    :param norm_obs_keys: the keys it normalises (None: all of them)
    :raises ValueError: if it would normalise one of :data:`NETWORK_KEYS`
    """
    if not norm_obs:
        return
    keys = [key for key in NETWORK_KEYS if norm_obs_keys is None or key in norm_obs_keys]
    if keys:
        raise ValueError(
            f"MAPPOC cannot use a VecNormalize that normalises the observations {', '.join(map(repr, keys))}: "
            "VecNormalize scales every key with its own statistics, while the policy copies the message into "
            "'held' and resets 'age' to 0 on a broadcast, so its view of the network would differ from the "
            "environment's. Normalise only the local state with VecNormalize(env, norm_obs_keys=['local']), "
            "or no observations with norm_obs=False (the per-agent rewards MAPPOC learns from are normalised "
            "by normalize_reward=True, not by VecNormalize)."
        )


def _check_vec_normalize(env: GymEnv | None) -> None:
    """Apply :func:`check_observation_normalization` to a ``VecNormalize`` anywhere in ``env``'s vector wrappers.

    :param env: the training env (only a vector env can have a ``VecNormalize``), or None
    :raises ValueError: if the ``VecNormalize`` normalises one of :data:`NETWORK_KEYS`
    """
    vec_normalize = unwrap_vec_normalize(env) if isinstance(env, VecEnv) else None
    if vec_normalize is not None:
        check_observation_normalization(vec_normalize.norm_obs, vec_normalize.norm_obs_keys)
