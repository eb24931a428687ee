"""MAPPOC: multi-agent PPO option-critic for learned event-triggered communication and control."""

from __future__ import annotations

import contextlib
import pathlib
from collections.abc import Hashable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import FloatSchedule, explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from sb3_detc.envs.wrappers import EventTriggeredNetwork, as_joint_env
from sb3_detc.mappoc.buffers import HybridRolloutBuffer, HybridRolloutSamples
from sb3_detc.mappoc.checks import (
    check_fixed_trigger,
    check_hyperparameters,
    check_n_envs,
    check_price_rule,
    check_rate_target,
    check_same_agents,
    check_vec_normalize,
)
from sb3_detc.mappoc.losses import REPLAYED_ADVANTAGES, STEP_STATS, MAPPOCLoss, UpdateInputs
from sb3_detc.mappoc.policies import MlpHybridPolicy, check_joint_spaces, drawn_broadcast_probability
from sb3_detc.mappoc.replays import Replays
from sb3_detc.mappoc.rewards import PRICE_RULES, RewardTransform, agent_rewards, broadcast_costs
from sb3_detc.mappoc.sampling import (
    FixedTrigger,
    ReplayingSampler,
    Rollout,
    RolloutSampler,
    StepsTaken,
    truncated_episodes,
)
from sb3_detc.mappoc.steps import FusedGradientStep, GradientStep, compiles, make_gradient_step
from sb3_detc.mappoc.workers import default_n_envs, make_rollout_workers
from sb3_detc.network import interval_window
from sb3_detc.renamed import REMOVED, RENAMED, renamed_action_space, renamed_keys, renamed_saved_data

SelfMAPPOC = TypeVar("SelfMAPPOC", bound="MAPPOC")

#: Environment steps per iteration of the paper (all envs together), MAPPOC's default.
PAPER_ITERATION = 2048


def training_envs(env_id: str, n_envs: int, seed: int | None, broadcast_advantage: str) -> VecEnv:
    """The training envs MAPPOC builds from an env id (in ``__init__`` and ``load``).

    Rollout workers (the fast setting), or, for a replayed ``broadcast_advantage``, which copies the
    envs at replayed decisions, a ``DummyVecEnv`` in this process.

    :param env_id: a registered env id
    :param n_envs: number of envs
    :param seed: seed of the envs (None: unseeded)
    :param broadcast_advantage: the model's kind of broadcast advantage
    :return: the vectorised envs
    """
    if broadcast_advantage in REPLAYED_ADVANTAGES:
        return make_vec_env(env_id, n_envs=n_envs, seed=seed, vec_env_cls=DummyVecEnv)
    return make_rollout_workers(env_id, n_envs, seed)


class MAPPOC(OnPolicyAlgorithm):
    """Multi-agent PPO option-critic (Kesper, Trimpe and Baumann, L4DC 2023), with the paper's defaults.

    Every agent learns a policy over options (broadcast or stay silent, every step), a
    Gaussian control policy on its networked observation, and a centralised option-value
    critic used only in training. Both policy levels are trained with PPO's clipped
    surrogate: the control policy on GAE advantages of the taken option, the policy over
    options on the greedy advantage ``Q(o) - max_o' Q(o')`` (Sec. 3 of the method reference).

    :param policy: the policy model (``"MlpHybridPolicy"`` or a subclass of :class:`MlpHybridPolicy`)
    :param env: the joint env: a registered id (MAPPOC builds ``n_envs`` rollout workers,
        :func:`~sb3_detc.mappoc.workers.make_rollout_workers`), a VecEnv or Gymnasium env (used as
        given), or a PettingZoo :class:`EventTriggeredNetwork` (adapted to the joint view). A
        ``VecNormalize`` may normalise the ``local`` observations only
        (:func:`~sb3_detc.mappoc.checks.check_observation_normalization`)
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
        (the paper: ``Q(o) - max_o' Q(o')`` with the current critic), ``"return"`` (the
        lambda-return minus ``V(s) = sum_o mu(o) Q(s, o)`` at collection time) or ``"replayed"``
        (measured: at some of the decisions, ``replay_share`` per step of an env, chosen as ``replay_choice``
        says, the decision is replayed in two
        copies of the env, broadcasting and silent, with the same noise, :mod:`sb3_detc.mappoc.replays`;
        ``mu`` learns from those decisions only, with the advantage ``(o - p) (Q(1) - Q(0))``, ``p``
        its probability of broadcasting, weighted by the inverse of the probability with which the decision
        was chosen, ``N / replay_share`` for ``replay_choice="uniform"``), ``"replayed_expected"`` (the same
        replays, with the advantage ``(o - (1 - p)) (Q(1) - Q(0))``: the gradient of the broadcast logit is
        then ``p (1 - p) (Q(1) - Q(0))`` whichever option was drawn, until clipped; see
        :meth:`replayed_advantages`) or
        ``"replayed_value"`` (the same
        replays; ``mu``'s broadcast logit ``log mu(1) - log mu(0)`` is fitted by least squares to the value
        of a broadcast divided by ``replay_temperature``: a regression, which weighs every replayed decision
        alike, where the policy gradient weighs them by ``p (1 - p)``, most near ``mu``'s threshold). The
        replayed kinds need envs that can be copied, in the learner's process (a ``DummyVecEnv``; MAPPOC
        builds one from an env id)
    :param broadcast_advantage_offset: constant added to the greedy and the sampled broadcast advantage
        (the paper's code used a 0.1 "deliberation" offset; the paper and the default use 0)
    :param replay_share: with a replayed ``broadcast_advantage``, the mean number of replayed decisions per
        step of an env (at most one), in (0, 1]
    :param replay_choice: with a replayed ``broadcast_advantage``, how the replayed decisions are chosen:
        ``"uniform"`` (at a share ``replay_share`` of the steps of every env, one agent at random) or
        ``"gradient"`` (in proportion to ``p (1 - p)``, ``p`` the decision's probability of broadcasting,
        which weighs its expected gradient: the replays go where ``mu`` is undecided instead of where it
        is sure, :func:`~sb3_detc.mappoc.replays.gradient_choice`; the policy-gradient kinds weigh every
        replayed decision by the inverse of its chance, so the gradient stays the same in expectation,
        while ``"replayed_value"`` fits the logit where the decisions were chosen)
    :param replay_horizon: with a replayed ``broadcast_advantage``, the steps a replay follows (at most to the
        episode's end); the value of a broadcast after them is left out
    :param replay_temperature: with ``broadcast_advantage="replayed_value"``, the value of a broadcast (in the
        learner's units, or in root mean squares with ``normalize_broadcast_advantage``) at which ``mu``
        broadcasts with probability ``1 / (1 + e^-1)``; smaller is sharper
    :param normalize_broadcast_advantage: divide every agent's greedy broadcast advantages by the
        root mean square of its critic's broadcast gap ``Q(1) - Q(0)`` over the minibatch (the
        paper: raw advantages), or its replayed values of a broadcast by their root mean square over
        the rollout
    :param reward_scale: factor applied to rewards for learning only (paper: 0.1)
    :param normalize_reward: divide every agent's (scaled) reward by a running standard
        deviation of its discounted return, clipped to [-10, 10], as ``VecNormalize`` does
    :param team_reward: train every agent on the team's mean reward instead of its own (the
        paper: own rewards)
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
    :param torch_compile: compile the sampling and every gradient step with ``torch.compile``
        (needs a C++ compiler; :mod:`sb3_detc.mappoc.steps`): on a CPU about twice the gradient
        steps per second, for a one-off compilation of tens of seconds. ``"auto"``: compile on
        the CPU with a C++ compiler for a ``learn`` of at least
        :data:`~sb3_detc.mappoc.steps.COMPILE_FROM_TIMESTEPS` steps
    :param n_envs: number of envs built from an env id (None: one per CPU core,
        :func:`~sb3_detc.mappoc.workers.default_n_envs`); only for an env id
    :param fixed_trigger: take the options from this trigger instead of ``mu`` (see
        :meth:`set_fixed_trigger`; None: from ``mu``)
    :param target_savings: communication savings the policy over options is to settle at, in (0, 1)
        (None: no target). A price per broadcast, :attr:`broadcast_price` in the learner's reward
        units (a subsidy below zero), is charged on top of the environment's cost and moved after
        every update by ``broadcast_price_rule``; logged as ``train/broadcast_price``, saved with
        the model. Not with a fixed trigger
    :param broadcast_price_lr: step size of the ``"dual"`` rule (> 0), in reward units per unit of rate
    :param broadcast_price_rule: ``"dual"`` (dual ascent on ``mu``'s rate, after rollouts of ``mu``'s
        options) or ``"quantile"`` (where the critic's greedy options on the rollout's states meet the
        target), see :data:`~sb3_detc.mappoc.rewards.PRICE_RULES`
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
        replay_share: float = 0.25,
        replay_choice: str = "uniform",
        replay_horizon: int = 60,
        replay_temperature: float = 0.1,
        reward_scale: float = 0.1,
        normalize_reward: bool = False,
        team_reward: bool = False,
        normalize_advantage: bool = True,
        target_kl: float | None = None,
        share_parameters: bool = False,
        train_control_policy: bool = True,
        train_broadcast_policy: bool = True,
        torch_compile: bool | str = "auto",
        n_envs: int | None = None,
        fixed_trigger: FixedTrigger | None = None,
        target_savings: float | None = None,
        broadcast_price_lr: float = 0.05,
        broadcast_price_rule: str = "dual",
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        if torch_compile not in (True, False, "auto"):
            raise ValueError(f"torch_compile must be True, False or 'auto', got {torch_compile!r}.")
        check_rate_target(target_savings, fixed_trigger, broadcast_price_rule)
        check_n_envs(env, n_envs)
        env = as_joint_env(env)
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
            broadcast_price_lr=broadcast_price_lr,
            broadcast_advantage=broadcast_advantage,
            replay_share=replay_share,
            replay_choice=replay_choice,
            replay_horizon=replay_horizon,
            replay_temperature=replay_temperature,
        )
        policy_kwargs = dict(policy_kwargs or {})
        if share_parameters and not policy_kwargs.get("share_parameters", True):
            raise ValueError("share_parameters=True contradicts policy_kwargs['share_parameters']=False: give one.")
        policy_kwargs.setdefault("share_parameters", share_parameters)
        owns_env = isinstance(env, str)
        if owns_env:  # after the checks: no worker processes for a model that cannot be built
            env = training_envs(env, n_envs, seed, broadcast_advantage)  # type: ignore[arg-type]
        try:  # a model refused from here on (e.g. for its policy_kwargs) ends the workers it started
            n_steps, batch_size, n_epochs = int(n_steps), int(batch_size), int(n_epochs)  # e.g. from numpy
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
                check_vec_normalize(self.env)  # also on load(path, env): SB3's load builds the model with the env
            self.batch_size = batch_size
            self.n_epochs = n_epochs
            self.clip_range = clip_range
            self.clip_range_broadcast = clip_range_broadcast
            self.broadcast_ent_coef = broadcast_ent_coef
            self.action_noise_std = action_noise_std
            self.broadcast_advantage = broadcast_advantage
            self.broadcast_advantage_offset = broadcast_advantage_offset
            self.normalize_broadcast_advantage = normalize_broadcast_advantage
            self.replay_share = float(replay_share)
            self.replay_choice = replay_choice
            self.replay_horizon = int(replay_horizon)
            self.replay_temperature = float(replay_temperature)
            self.reward_scale = reward_scale
            self.normalize_reward = normalize_reward
            self.team_reward = team_reward
            self.normalize_advantage = normalize_advantage
            self.target_kl = target_kl
            self.train_control_policy = train_control_policy
            self.train_broadcast_policy = train_broadcast_policy
            self.torch_compile = torch_compile
            self.target_savings = None if target_savings is None else float(target_savings)
            self.broadcast_price_lr = float(broadcast_price_lr)
            self.broadcast_price_rule = broadcast_price_rule
            #: the price per broadcast of the rate target, in the learner's reward units (0 without a target)
            self.broadcast_price = 0.0
            self.fixed_trigger: FixedTrigger | None = fixed_trigger  # checked by set_fixed_trigger in _setup_model
            #: the fixed trigger that took the options of the rollout in the buffer (None: ``mu``)
            self._rollout_trigger: FixedTrigger | None = fixed_trigger
            self._action_noise_terms: dict[Hashable, float] = {}
            if _init_setup_model:
                self._setup_model()
        except BaseException:
            if owns_env:
                with contextlib.suppress(Exception):  # the refusal is what the user needs to see
                    env.close()
            raise

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
        # The settings are the model's; a loaded model brings the statistics (as reward_rms before RewardTransform).
        saved, saved_rms = self.__dict__.pop("reward_transform", None), self.__dict__.pop("reward_rms", None)
        for old in (*RENAMED, *REMOVED):  # a model saved under earlier names (MAPPOC.load took the values)
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
        check_price_rule(self.broadcast_price_rule, self.target_savings, self.policy.option_critic)
        self._setup_steps(compiles(self.torch_compile, self.device))
        self.set_fixed_trigger(self.fixed_trigger)

    def _setup_steps(self, compiled: bool) -> None:
        """Build the sampler and the gradient step: eager, or compiled (and fused where it can be).

        :param compiled: whether to compile them
        """
        self._compiled = compiled
        self.sampler = (
            ReplayingSampler(
                self.policy, compiled, self.replay_share, self.replay_horizon, self.gamma, self.replay_choice
            )
            if self.broadcast_advantage in REPLAYED_ADVANTAGES
            else RolloutSampler(self.policy, compiled)
        )
        self.gradient_step: GradientStep | FusedGradientStep = make_gradient_step(
            self.loss, self.policy.optimizer, self.max_grad_norm, self.target_kl, compiled
        )

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        if self.torch_compile == "auto" and compiles("auto", self.device, total_timesteps) != self._compiled:
            self._setup_steps(not self._compiled)
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "fixed_trigger",
            "loss",
            "gradient_step",
            "sampler",
            "_action_noise_terms",
            "_compiled",
            "_rollout_trigger",
        ]

    @property
    def n_updates(self) -> int:
        """Gradient epochs done so far (what the logger's ``train/n_updates`` shows)."""
        return self._n_updates

    @property
    def last_obs(self) -> dict[str, np.ndarray] | None:
        """The joint observation of every env that the next rollout starts from (None before ``learn`` sets up)."""
        return self._last_obs  # type: ignore[return-value]

    # ------------------------------------------------------------------ modes
    def set_fixed_trigger(self, trigger: FixedTrigger | None) -> None:
        """Take every rollout's options from a fixed trigger instead of ``mu`` (None: from ``mu`` again).

        ``mu`` is not trained on the rollouts whose options a fixed trigger took. The values at
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
        check_fixed_trigger(trigger, self.policy.critic)
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
        self.reward_transform.switch(self.normalize_reward, fresh_statistics)

    # ------------------------------------------------------------------ rollouts
    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """Collect ``n_rollout_steps`` steps per environment with the current policies.

        The steps are sampled first (:mod:`sb3_detc.mappoc.sampling`), inside rollout workers where the
        env has them; the learner then goes through them in order (:meth:`_take_steps`) and stores them
        with their values (:meth:`_store_rollout`).

        :param env: the training environment
        :param callback: called at every step with SB3's locals ``infos``, ``dones``, ``new_obs`` and
            ``rewards`` (the learner's per-agent rewards (n_envs, N) with the rate target's price, before a
            truncation's bootstrap), and at the beginning and end of the rollout
        :param rollout_buffer: the buffer to fill (a :class:`HybridRolloutBuffer`)
        :param n_rollout_steps: number of steps to collect per environment
        :return: True if the rollout was completed, False if a callback stopped it
        """
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)
        rollout_buffer.reset()
        callback.on_rollout_start()  # callbacks may change the mode, the noise or the cost here
        self._rollout_trigger = self.fixed_trigger
        warm_up = self._warm_up_gradient_step if self.gradient_step.needs_warm_up else None
        rollout = self.sampler.sample(
            env, self._last_obs, n_rollout_steps, self.action_noise_std, self.fixed_trigger, meanwhile=warm_up
        )  # type: ignore[arg-type]
        taken = self._take_steps(rollout, env, callback)
        if taken is None:
            return False
        self._store_rollout(rollout, taken, rollout_buffer)  # type: ignore[arg-type]
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def _take_steps(self, rollout: Rollout, env: VecEnv, callback: BaseCallback) -> StepsTaken | None:
        """Go through sampled steps in order, as SB3's rollout loop does after every step.

        Per step: the learner's rewards and the price of a broadcast in the same units (with the rate
        target's price), ``num_timesteps``, the callbacks, the episode statistics and the truncations.

        :param rollout: the sampled steps
        :param env: the training environment
        :param callback: callback called at each step
        :return: what the learner took of the steps, None if a callback stopped
        """
        n_steps, n_envs = rollout.dones.shape
        episode_starts = np.concatenate([np.asarray(self._last_episode_starts)[None], rollout.dones[:-1]])
        self._last_obs, self._last_episode_starts = rollout.last_obs, rollout.dones[-1]  # type: ignore[assignment]
        broadcast_cost = broadcast_costs(env, self.policy.option_critic.needs_price, self.policy.critic)
        prices, all_rewards, truncated = [], [], []
        env_rewards = agent_rewards([info for infos in rollout.infos for info in infos]).reshape(n_steps, n_envs, -1)
        for step in range(n_steps):
            infos, dones = rollout.infos[step], rollout.dones[step]
            new_obs = (
                rollout.last_obs if step == n_steps - 1 else {k: v[step + 1] for k, v in rollout.observations.items()}
            )
            prices.append(self.reward_transform.price(broadcast_cost) + self.broadcast_price)
            rewards = self.reward_transform(env_rewards[step], dones) - self.broadcast_price * rollout.broadcast[step]
            self.num_timesteps += n_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return None
            self._update_info_buffer(infos, dones)
            truncated += [(step, idx, terminal_obs) for idx, terminal_obs in truncated_episodes(infos, dones)]
            all_rewards.append(rewards)
        last_price = self.reward_transform.price(broadcast_cost) + self.broadcast_price
        return StepsTaken(np.stack(all_rewards), np.stack(prices), last_price, truncated, episode_starts)

    def _store_rollout(self, rollout: Rollout, taken: StepsTaken, buffer: HybridRolloutBuffer) -> None:
        """Evaluate the rollout with the current policy in one batch and store it with its advantages.

        The bootstraps of truncations and of the rollout's end are ``V(s) = sum_o p(o) Q(s, o)`` under
        the options' probabilities of what took them: ``mu``, or a fixed trigger's ``broadcast_probability``.

        :param rollout: the sampled steps
        :param taken: what the learner took of them (:meth:`_take_steps`)
        :param buffer: the buffer to fill
        """
        n_steps, n_envs = rollout.dones.shape
        rewards, price, truncated = taken.rewards, taken.price, taken.truncated
        steps = (
            *rollout.flat_tensors(self.device),
            th.as_tensor(price.reshape(n_steps * n_envs, -1), device=self.device),
        )
        probability = getattr(self._rollout_trigger, "broadcast_probability", None)

        def state_values(obs: dict[str, np.ndarray], prices: np.ndarray) -> np.ndarray:
            p = None if probability is None else probability(obs)
            return (
                self.policy.state_values(
                    obs_as_tensor(obs, self.device),  # type: ignore[arg-type]
                    th.as_tensor(prices, device=self.device),
                    None if p is None else th.as_tensor(p, dtype=th.float32, device=self.device),
                )
                .cpu()
                .numpy()
            )

        with th.no_grad():
            evaluation = self.policy.evaluate_actions(*steps)
            if truncated:
                terminal = {key: np.stack([obs[key] for _, _, obs in truncated]) for key in truncated[0][2]}
                values = state_values(terminal, np.stack([price[step, idx] for step, idx, _ in truncated]))
                for (step, idx, _), value in zip(truncated, values, strict=True):
                    rewards[step, idx] += self.gamma * value
            last_values = state_values(rollout.last_obs, taken.last_price)

        def per_step(x: th.Tensor) -> np.ndarray:
            return x.cpu().numpy().reshape(n_steps, n_envs, *x.shape[1:])

        buffer.extend(
            rollout.observations,
            rollout.broadcast,
            rollout.control,
            rewards,
            taken.episode_starts,
            per_step(evaluation.option_values),
            per_step(evaluation.log_prob_broadcast),
            per_step(evaluation.log_prob_control),
            price,
        )
        buffer.compute_returns_and_advantage(last_values=last_values, dones=rollout.dones[-1])
        replays = rollout.replays
        if replays is None:
            if self.broadcast_advantage == "replayed_value":  # a fixed trigger's rollout: no targets
                nowhere = np.zeros(0, np.int64)
                buffer.set_broadcast_advantages(nowhere, nowhere, nowhere, np.zeros(0), elsewhere=np.nan)
            return
        if self.broadcast_advantage == "replayed_value":  # mu's targets; no target where nothing was replayed
            targets = self.replayed_logit_targets(rollout)
            buffer.set_broadcast_advantages(replays.steps, replays.envs, replays.agents, targets, elsewhere=np.nan)
        else:
            advantages = self.replayed_advantages(rollout, buffer.log_prob_broadcast)
            buffer.set_broadcast_advantages(replays.steps, replays.envs, replays.agents, advantages)

    def replayed_values(self, replays: Replays) -> np.ndarray:
        """The values of a broadcast ``Q(1) - Q(0)`` at a rollout's replayed decisions, in the learner's units.

        The replayed difference of the learner's rewards (the environment's through
        :meth:`RewardTransform.converted`), minus the rate target's price per own broadcast. With
        ``normalize_broadcast_advantage`` divided by every agent's root mean square value over the replays.

        :param replays: a rollout's replays (:class:`~sb3_detc.mappoc.replays.Replays`)
        :return: values (K,), in the order of the replays
        """
        rows = np.arange(len(replays.agents))
        value = self.reward_transform.converted(replays.rewards)[rows, replays.agents]
        value -= self.broadcast_price * replays.broadcasts[rows, replays.agents]
        if self.normalize_broadcast_advantage:  # every agent's values over the rollout, as the greedy gap's
            square = np.bincount(replays.agents, value**2, self.n_agents) / np.maximum(
                np.bincount(replays.agents, minlength=self.n_agents), 1
            )
            value = value / (np.sqrt(square)[replays.agents] + 1e-8)
        return value

    def replayed_logit_targets(self, rollout: Rollout) -> np.ndarray:
        """The targets of ``mu``'s broadcast logit at a rollout's replayed decisions (``"replayed_value"``).

        :meth:`replayed_values` divided by ``replay_temperature``; NaN (no target) at decisions that the
        policy's window of broadcast intervals forces (``broadcast_interval``), whose logit is pinned.

        :param rollout: a rollout with its replays (:class:`~sb3_detc.mappoc.replays.Replays`)
        :return: targets (K,), in the order of the replays
        """
        replays: Replays = rollout.replays  # type: ignore[assignment]
        targets = self.replayed_values(replays) / self.replay_temperature
        if self.policy.broadcast_interval is not None:
            age = rollout.observations["age"][replays.steps, replays.envs]
            silent, broadcast = interval_window(age, *self.policy.broadcast_interval)
            rows = np.arange(len(replays.agents))
            targets[(silent | broadcast)[rows, replays.agents]] = np.nan
        return targets

    def replayed_advantages(self, rollout: Rollout, log_prob_broadcast: np.ndarray) -> np.ndarray:
        """``mu``'s advantages of the taken options at a rollout's replayed decisions, in the learner's units.

        With ``broadcast_advantage="replayed"`` the taken option ``o`` gets ``(o - p) (Q(1) - Q(0))``
        (:meth:`replayed_values`) with ``p`` the probability of broadcasting it was drawn with; with
        ``"replayed_expected"`` it gets ``(o - (1 - p)) (Q(1) - Q(0))``: ``p (Q(1) - Q(0))`` for a broadcast,
        ``-(1 - p) (Q(1) - Q(0))`` for silence, so that the gradient of the broadcast logit is
        ``p (1 - p) (Q(1) - Q(0))`` whichever option was drawn (its expectation over the option under
        ``"replayed"``, without the variance of the draw), until PPO clips the ratio. Weighted by the inverse
        of the probability with which every decision was chosen (``N / replay_share`` for
        ``replay_choice="uniform"``): over the rollout, the gradient of every decision's advantage in expectation.

        :param rollout: a rollout with its replays (:class:`~sb3_detc.mappoc.replays.Replays`)
        :param log_prob_broadcast: the log-probabilities of the rollout's taken options, (T, n_envs, N)
        :return: advantages (K,), in the order of the replays
        """
        replays: Replays = rollout.replays  # type: ignore[assignment]
        value = self.replayed_values(replays)
        taken = rollout.broadcast[replays.steps, replays.envs, replays.agents]
        p_taken = np.exp(log_prob_broadcast[replays.steps, replays.envs, replays.agents])
        p_broadcast = np.where(taken == 1, p_taken, 1.0 - p_taken)
        centre = 1.0 - p_broadcast if self.broadcast_advantage == "replayed_expected" else p_broadcast
        return (taken - centre) * value / replays.chances

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
        rate = float(buffer.broadcast.mean())
        self.logger.record("rollout/broadcast_rate", rate)
        if self.target_savings is not None:  # the rule with the settings as they are now (callbacks may change them)
            rule = PRICE_RULES[self.broadcast_price_rule](self.target_savings, self.broadcast_price_lr)
            self.broadcast_price = rule.updated(self.broadcast_price, buffer.broadcast, buffer.option_values, train_mu)
            self.logger.record("train/broadcast_price", self.broadcast_price)

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
            rollout._replace(observations={"age": rollout.observations["age"]}),  # what option_logits reads
            # probability of broadcasting with which the options were drawn (the centred critic's p_i)
            drawn_broadcast_probability(rollout.broadcast, rollout.old_log_prob_broadcast),
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
        return super().learn(
            total_timesteps=int(total_timesteps),
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def set_env(self, env: GymEnv | EventTriggeredNetwork, force_reset: bool = True) -> None:
        """Use a new environment (a PettingZoo event-triggered env is adapted to the joint view).

        :param env: the new environment, with the same spaces (and no ``VecNormalize`` of the
            network's observations, see :func:`check_observation_normalization`)
        :param force_reset: force a reset of the environment before the next ``learn``
        :raises ValueError: if the environment has another number of agents than the model or
            normalises the network's observations
        """
        env = as_joint_env(env)
        check_same_agents(env, self.n_agents)  # type: ignore[arg-type]
        check_vec_normalize(env)  # type: ignore[arg-type]
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
            an env id, MAPPOC builds as many rollout workers as the model was trained with (envs in a
            ``DummyVecEnv`` for a replayed ``broadcast_advantage``, which copies them)
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
        env = as_joint_env(env)
        data, _, _ = load_from_zip_file(path, device="cpu", custom_objects=custom_objects, load_data=True)
        data = data or {}
        if isinstance(env, str):  # with the saved number of envs (n_steps is per env)
            env = training_envs(env, int(data.get("n_envs", 1)), None, data.get("broadcast_advantage", "greedy"))
        custom_objects, kwargs = renamed_saved_data(data, custom_objects, kwargs)
        if env is not None and "action_space" in data:
            check_same_agents(env, len(renamed_action_space(data["action_space"])["broadcast"].nvec))  # type: ignore[arg-type]
        return super().load(  # type: ignore[return-value]
            path,
            env=env,  # type: ignore[arg-type]
            device=device,
            custom_objects=custom_objects,
            print_system_info=print_system_info,
            force_reset=force_reset,
            **kwargs,
        )
