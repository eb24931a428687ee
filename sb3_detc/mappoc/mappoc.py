"""MAPPOC: multi-agent PPO option-critic for learned event-triggered communication and control."""

from __future__ import annotations

import pathlib
import pickle
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import FloatSchedule, explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, unwrap_vec_normalize

from sb3_detc.envs.wrappers import EventTriggeredNetwork, JointEnv
from sb3_detc.mappoc.buffers import HybridRolloutBuffer, HybridRolloutSamples
from sb3_detc.mappoc.fused import adam_state, adam_update_, clip_by_total_norm, fusable_adam
from sb3_detc.mappoc.policies import ChainInput, HybridAction, MlpHybridPolicy, check_joint_spaces

SelfMAPPOC = TypeVar("SelfMAPPOC", bound="MAPPOC")

#: Statistics of every gradient step, in the order :meth:`MAPPOC._losses` returns them (logged as ``train/<name>``).
STEP_STATS = ("pi_loss", "mu_loss", "q_loss", "entropy_mu", "clip_pi", "clip_mu", "kl_pi", "kl_mu")

#: Observation keys that the policy turns into the network's state with the broadcast rule (the
#: message copied into ``held``, ``age`` reset to 0) or that feed the policy over options: a
#: ``VecNormalize`` must pass them on as the environment returns them.
NETWORK_KEYS = ("message", "held", "age", "trigger", "trigger_held")

#: Signature of an option override: joint observations (n_envs, N, ...) -> options (n_envs, N).
#: With rollout workers (:mod:`sb3_detc.mappoc.workers`) an override that has ``fork(seed)``
#: (an independent copy, like :meth:`sb3_detc.triggers.RandomTrigger.fork`) runs in the workers,
#: one fork per env and rollout; any other override keeps the step-by-step rollout.
OptionOverride = Callable[[dict[str, np.ndarray]], np.ndarray]


def _as_joint_env(env: GymEnv | str | EventTriggeredNetwork | None) -> GymEnv | str | None:
    """Adapt a PettingZoo event-triggered env to the joint Gymnasium view."""
    return JointEnv(env) if isinstance(env, EventTriggeredNetwork) else env


class MAPPOC(OnPolicyAlgorithm):
    """Multi-agent PPO option-critic (Kesper, Trimpe and Baumann, L4DC 2023), with the paper's defaults.

    Every agent learns a policy over options (broadcast or stay silent, every step), a
    Gaussian control policy on its networked observation, and a centralised option-value
    critic used only in training. Both policy levels are trained with PPO's clipped
    surrogate: the control policy on GAE advantages of the taken option, the policy over
    options on the greedy advantage ``Q(o) - max_o' Q(o')`` (Sec. 3 of the method reference).

    :param policy: the policy model (``"MlpHybridPolicy"`` or a subclass of :class:`MlpHybridPolicy`)
    :param env: the joint env (Gymnasium env, VecEnv or registered id such as
        ``"sb3_detc/MultiwalkerETC-v0"``) or a PettingZoo :class:`EventTriggeredNetwork`,
        which is adapted to the joint view. A ``VecNormalize`` in its wrappers may normalise
        the ``local`` observations (``norm_obs_keys=["local"]``), not the keys of
        :data:`NETWORK_KEYS` (see :func:`check_observation_normalization`); its reward
        normalisation leaves the per-agent rewards MAPPOC learns from (``info["agent_rewards"]``)
        as they are, ``normalize_reward`` normalises those
    :param learning_rate: learning rate, constant or a schedule of the remaining progress (paper: 3e-5)
    :param n_steps: steps per environment per rollout (paper: 2048 in total per iteration)
    :param batch_size: minibatch size (paper: 32)
    :param n_epochs: epochs per rollout (paper: 10)
    :param gamma: discount factor
    :param gae_lambda: GAE factor
    :param clip_range: clipping parameter of the control policy ``pi`` (constant or schedule)
    :param clip_range_option: clipping parameter of the policy over options ``mu`` (constant or schedule)
    :param option_ent_coef: coefficient ``zeta`` of the mean entropy of ``mu`` (constant or
        schedule; the paper's code sums over minibatches of 32, so its final 0.02 is 0.64 here)
    :param vf_coef: coefficient of the critic's squared error
    :param max_grad_norm: maximum gradient norm, or None for no clipping (paper: none)
    :param action_noise_std: standard deviation of extra Gaussian noise on the controls
        (the curriculum changes it during training); log-probabilities refer to the noisy controls
    :param option_advantage: advantage of the taken option in ``mu``'s loss: ``"greedy"``
        (the paper: ``Q(o) - max_o' Q(o')`` with the current critic) or ``"return"`` (the
        lambda-return minus ``V(s) = sum_o mu(o) Q(s, o)`` at collection time, standardised
        per agent like the control advantages: a sampled advantage that does not rely on the
        critic telling the two options apart)
    :param option_advantage_offset: constant added to the greedy option advantage (the
        paper's code used a 0.1 "deliberation" offset; the paper and the default use 0)
    :param normalize_option_advantage: divide every agent's greedy option advantages by the
        root mean square of its critic's option gap ``Q(1) - Q(0)`` over the minibatch, so
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
    :param normalize_advantage: standardise the control advantages per agent and minibatch
    :param target_kl: stop the epochs of an update early when the control policy's
        approximate KL divergence exceeds ``1.5 * target_kl`` (None: never)
    :param share_parameters: one network set for all agents with an agent-id input
        (added to ``policy_kwargs``; default off, as in the paper)
    :param train_control_policy: whether ``pi`` (and its log standard deviation) is trained;
        switch it off to learn only when to communicate for a trained controller
    :param train_option_policy: whether ``mu`` is trained (baselines with fixed
        communication switch it off)
    :param torch_compile: compile the rollout's forward pass and every gradient step with
        ``torch.compile`` (needs a C++ compiler); with the default Adam optimizer and no
        ``target_kl``, a gradient step (loss, gradients, clipping, Adam update) is one
        compiled graph (:mod:`sb3_detc.mappoc.fused`). On a CPU about twice the gradient
        steps per second and faster rollouts (benchmarks/README.md), for a one-off
        compilation of some tens of seconds (and a few seconds whenever a new variant
        appears, e.g. a first option override), so worth it for long runs
    :param stats_window_size: window size of the rollout logging (episodes)
    :param tensorboard_log: log location for TensorBoard (None: no logging)
    :param policy_kwargs: additional arguments of the policy on creation
    :param verbose: verbosity level: 0 no output, 1 info messages, 2 debug messages
    :param seed: seed of the pseudo random generators
    :param device: device (cpu, cuda, ...) on which the code runs
    :param _init_setup_model: whether to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpHybridPolicy": MlpHybridPolicy}
    policy: MlpHybridPolicy
    rollout_buffer: HybridRolloutBuffer  # type: ignore[assignment]

    def __init__(
        self,
        policy: str | type[MlpHybridPolicy],
        env: GymEnv | str | EventTriggeredNetwork,
        learning_rate: float | Schedule = 3e-5,
        n_steps: int = 2048,
        batch_size: int = 32,
        n_epochs: int = 10,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        clip_range: float | Schedule = 0.2,
        clip_range_option: float | Schedule = 0.2,
        option_ent_coef: float | Schedule = 0.64,
        vf_coef: float = 1.0,
        max_grad_norm: float | None = None,
        action_noise_std: float = 0.0,
        option_advantage: str = "greedy",
        option_advantage_offset: float = 0.0,
        normalize_option_advantage: bool = False,
        reward_scale: float = 0.1,
        normalize_reward: bool = False,
        team_reward: bool = False,
        normalize_advantage: bool = True,
        target_kl: float | None = None,
        share_parameters: bool = False,
        train_control_policy: bool = True,
        train_option_policy: bool = True,
        torch_compile: bool = False,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        check_hyperparameters(
            n_steps=n_steps,
            batch_size=batch_size,
            n_epochs=n_epochs,
            gamma=gamma,
            gae_lambda=gae_lambda,
            vf_coef=vf_coef,
            max_grad_norm=max_grad_norm,
            action_noise_std=action_noise_std,
            reward_scale=reward_scale,
            target_kl=target_kl,
            normalize_advantage=normalize_advantage,
        )
        policy_kwargs = dict(policy_kwargs or {})
        policy_kwargs.setdefault("share_parameters", share_parameters)
        super().__init__(
            policy,
            _as_joint_env(env),
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
        self.clip_range_option = clip_range_option
        self.option_ent_coef = option_ent_coef
        self.action_noise_std = action_noise_std
        if option_advantage not in ("greedy", "return"):
            raise ValueError(f"option_advantage must be 'greedy' or 'return', got {option_advantage!r}.")
        self.option_advantage = option_advantage
        self.option_advantage_offset = option_advantage_offset
        self.normalize_option_advantage = normalize_option_advantage
        self.reward_scale = reward_scale
        self.normalize_reward = normalize_reward
        self.team_reward = team_reward
        self.reward_rms: RunningMeanStd | None = None
        self._discounted_returns: np.ndarray | None = None
        self.normalize_advantage = normalize_advantage
        self.target_kl = target_kl
        self.train_control_policy = train_control_policy
        self.train_option_policy = train_option_policy
        self.torch_compile = torch_compile
        self.option_override: OptionOverride | None = None
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        self.n_agents, self.n_control = check_joint_spaces(self.observation_space, self.action_space)
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
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
        control_space = self.action_space["control"]  # type: ignore[index]
        self._control_low, self._control_high = control_space.low, control_space.high
        self._act: Callable[..., HybridAction] = self.policy
        self._step_losses: Callable[..., tuple[th.Tensor, th.Tensor]] = self._losses
        self._gradient_step: Callable[..., th.Tensor] | None = None
        self._workers_hold: tuple[MlpHybridPolicy, VecEnv] | None = None  # what the rollout workers have
        if self.torch_compile:
            if self.device.type == "cpu":
                _check_cxx_compiler()
            self._act = th.compile(self.policy.forward)
            self._step_losses = th.compile(self._losses)
            if fusable_adam(self.policy.optimizer):
                self._loss_module = _PolicyLoss(self.policy, self._losses)
                self._gradient_step = th.compile(self._fused_gradient_step)

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "option_override",
            "_discounted_returns",
            "_act",
            "_step_losses",
            "_gradient_step",
            "_loss_module",
            "_workers_hold",
        ]

    # ------------------------------------------------------------------ rollouts
    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """Collect ``n_rollout_steps`` steps per environment with the current policies.

        Per step: all options are sampled from ``mu`` (or taken from
        :attr:`option_override`), the broadcasts are delivered, then all controls are
        sampled from ``pi`` on the updated views (same-step delivery), with
        :attr:`action_noise_std` extra noise; the env receives the controls clipped to
        their bounds. Per-agent rewards come from ``info["agent_rewards"]``.

        :param env: the training environment
        :param callback: callback called at each step (and at the beginning and end of the rollout)
        :param rollout_buffer: the buffer to fill (a :class:`HybridRolloutBuffer`)
        :param n_rollout_steps: number of steps to collect per environment
        :return: True if the rollout was completed, False if a callback stopped it
        """
        assert self._last_obs is not None, "No previous observation was provided"
        if self.option_override is not None and self.policy.critic == "centred":
            raise ValueError(
                "critic='centred' needs the probabilities with which the options were drawn, which an "
                "option override does not give; use critic='option_heads' or 'afterstate' with fixed options."
            )
        buffer: HybridRolloutBuffer = rollout_buffer  # type: ignore[assignment]
        self.policy.set_training_mode(False)
        n_steps = 0
        buffer.reset()
        callback.on_rollout_start()
        # Overrides run in the workers when they can be forked for them (the package's triggers).
        if (self.option_override is None or hasattr(self.option_override, "fork")) and _has_rollout_workers(env):
            return self._collect_in_workers(env, callback, buffer, n_rollout_steps)
        comm_cost = self._comm_costs(env)  # callbacks may change it between rollouts
        new_obs, dones = self._last_obs, self._last_episode_starts
        while n_steps < n_rollout_steps:
            obs = self._last_obs
            price = self._comm_prices(comm_cost)
            price_tensor = th.as_tensor(price, device=self.device)
            with th.no_grad():
                override = None
                if self.option_override is not None:
                    override = th.as_tensor(self.option_override(obs), device=self.device)  # type: ignore[arg-type]
                action = self._act(
                    obs_as_tensor(obs, self.device),  # type: ignore[arg-type]
                    comm=override,
                    action_noise_std=self.action_noise_std,
                    comm_price=price_tensor,
                )
            comm = action.comm.cpu().numpy()
            control = action.control.cpu().numpy()
            clipped = np.clip(control, self._control_low, self._control_high)
            new_obs, _, dones, infos = env.step([{"comm": c, "control": u} for c, u in zip(comm, clipped, strict=True)])
            rewards = self._step_rewards(infos, dones, new_obs)
            self.num_timesteps += env.num_envs

            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            n_steps += 1

            # Bootstrap truncated episodes with V(s_T) = sum_o mu(o) Q(s_T, o), as SB3 does for PPO.
            for idx, terminal_obs in _truncated(infos, dones):
                with th.no_grad():
                    value = self.policy.state_values(
                        self.policy.obs_to_tensor(terminal_obs)[0], price_tensor[idx : idx + 1]
                    )
                rewards[idx] += self.gamma * value[0].cpu().numpy()

            buffer.add(
                obs,  # type: ignore[arg-type]
                comm,
                control,
                rewards,
                self._last_episode_starts,  # type: ignore[arg-type]
                action.option_values.cpu().numpy(),
                action.log_prob_comm.cpu().numpy(),
                action.log_prob_control.cpu().numpy(),
                price,
            )
            self._last_obs = new_obs  # type: ignore[assignment]
            self._last_episode_starts = dones

        with th.no_grad():
            last_values = self.policy.state_values(
                obs_as_tensor(new_obs, self.device),  # type: ignore[arg-type]
                th.as_tensor(self._comm_prices(comm_cost), device=self.device),
            )
        buffer.compute_returns_and_advantage(last_values=last_values.cpu().numpy(), dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def _step_rewards(
        self, infos: list[dict[str, Any]], dones: np.ndarray, new_obs: dict[str, np.ndarray] | None = None
    ) -> np.ndarray:
        """The learner's rewards of one step of all envs (n_envs, N): scaled, shared, normalised.

        :param infos: the step's infos, with ``agent_rewards`` (checked for NaN)
        :param dones: episode ends of the step
        :param new_obs: observations after the step, to check for NaN (None: checked elsewhere)
        """
        rewards = self.reward_scale * _agent_rewards(infos)
        _check_finite({} if new_obs is None else new_obs, rewards)
        if self.team_reward:
            rewards = np.repeat(rewards.mean(axis=1, keepdims=True), self.n_agents, axis=1)
        if self.normalize_reward:
            rewards = self._normalized_rewards(rewards, dones)
        return rewards

    def _collect_in_workers(
        self, env: VecEnv, callback: BaseCallback, buffer: HybridRolloutBuffer, n_rollout_steps: int
    ) -> bool:
        """:meth:`collect_rollouts` with the sampling inside the envs (:mod:`sb3_detc.mappoc.workers`).

        Every env samples and steps ``n_rollout_steps`` times with a copy of the current policy;
        then the steps go through the learner in order, as in :meth:`collect_rollouts`: rewards,
        callbacks, episode statistics, bootstrapping of truncated episodes; log-probabilities and
        option values come from one batched evaluation of the same policy.

        :param env: the training environment (a ``DummyVecEnv`` or ``SubprocVecEnv`` of
            :class:`~sb3_detc.mappoc.workers.RolloutWorker` envs)
        :param callback: callback called at each step (and at the end of the rollout)
        :param buffer: the buffer to fill
        :param n_rollout_steps: number of steps to collect per environment
        :return: True if the rollout was completed, False if a callback stopped it
        """
        n_envs = env.num_envs
        new_policy = self._workers_hold != (self.policy, env)
        if new_policy:
            for index in range(n_envs):
                env.env_method("set_worker_index", index, indices=index)
        state = {key: value.detach().cpu().numpy() for key, value in self.policy.state_dict().items()}
        seeds = th.randint(2**31 - 1, (n_envs,)).tolist()
        override = self.option_override
        trajectories = env.env_method(
            "collect_rollout",
            pickle.dumps(self.policy) if new_policy else None,
            state,
            n_rollout_steps,
            self.action_noise_std,
            seeds,
            self.torch_compile,
            None if override is None else [pickle.dumps(override.fork(seed)) for seed in seeds],  # type: ignore[attr-defined]
        )
        self._workers_hold = (self.policy, env)

        def stacked(key: str) -> Any:  # (steps, n_envs, ...)
            return np.stack([trajectory[key] for trajectory in trajectories], axis=1)

        observations = _stack_dicts([trajectory["observations"] for trajectory in trajectories], axis=1)
        last_obs = _stack_dicts([trajectory["last_obs"] for trajectory in trajectories], axis=0)
        comm, control, all_dones = stacked("comm"), stacked("control"), stacked("dones")
        _check_finite(observations)
        _check_finite(last_obs)
        # The envs are at the rollout's end now, whether or not a callback stops on the way.
        episode_starts = np.concatenate([np.asarray(self._last_episode_starts)[None], all_dones[:-1]])
        self._last_obs, self._last_episode_starts = last_obs, all_dones[-1]  # type: ignore[assignment]
        comm_cost = self._comm_costs(env)
        prices, all_rewards, truncated = [], [], []
        for step in range(n_rollout_steps):
            infos = [trajectory["infos"][step] for trajectory in trajectories]
            dones = all_dones[step]
            new_obs = last_obs if step == n_rollout_steps - 1 else {k: v[step + 1] for k, v in observations.items()}
            prices.append(self._comm_prices(comm_cost))
            rewards = self._step_rewards(infos, dones)
            self.num_timesteps += n_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            truncated += [(step, idx, terminal_obs) for idx, terminal_obs in _truncated(infos, dones)]
            all_rewards.append(rewards)

        price = np.stack(prices)
        flat = n_rollout_steps * n_envs
        with th.no_grad():
            evaluation = self.policy.evaluate_actions(
                obs_as_tensor({k: v.reshape(flat, *v.shape[2:]) for k, v in observations.items()}, self.device),
                th.as_tensor(comm.reshape(flat, -1), device=self.device),
                th.as_tensor(control.reshape(flat, *control.shape[2:]), device=self.device),
                th.as_tensor(price.reshape(flat, -1), device=self.device),
            )
            # Bootstrap truncated episodes with V(s_T) = sum_o mu(o) Q(s_T, o), as SB3 does for PPO.
            if truncated:
                terminal = _stack_dicts([obs for _, _, obs in truncated], axis=0)
                at = [(step, idx) for step, idx, _ in truncated]
                values = self.policy.state_values(
                    obs_as_tensor(terminal, self.device),
                    th.as_tensor(np.stack([price[s, i] for s, i in at]), device=self.device),
                )
                for (step, idx), value in zip(at, values.cpu().numpy(), strict=True):
                    all_rewards[step][idx] += self.gamma * value

        def per_step(x: th.Tensor) -> np.ndarray:
            return x.cpu().numpy().reshape(n_rollout_steps, n_envs, *x.shape[1:])

        option_values, log_prob_comm = per_step(evaluation.option_values), per_step(evaluation.log_prob_comm)
        log_prob_control = per_step(evaluation.log_prob_control)
        buffer.extend(
            observations,
            comm,
            control,
            np.stack(all_rewards),
            episode_starts,
            option_values,
            log_prob_comm,
            log_prob_control,
            price,
        )
        with th.no_grad():
            last_values = self.policy.state_values(
                obs_as_tensor(last_obs, self.device), th.as_tensor(self._comm_prices(comm_cost), device=self.device)
            )
        buffer.compute_returns_and_advantage(last_values=last_values.cpu().numpy(), dones=all_dones[-1])
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    # ------------------------------------------------------------------ updates
    def train(self) -> None:
        """Update every agent's ``pi``, ``mu`` and ``Q`` with PPO on the collected rollout (Sec. 3)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        progress = self._current_progress_remaining
        # Constants or schedules; callbacks (e.g. the curriculum) may replace them between updates.
        clip_pi = FloatSchedule(self.clip_range)(progress)
        clip_mu = FloatSchedule(self.clip_range_option)(progress)
        zeta = FloatSchedule(self.option_ent_coef)(progress)
        train_mu = self.train_option_policy and self.option_override is None
        # Networks sharing a batched chain with trained ones get zero gradients, but Adam's momentum
        # from earlier training would still move them: restore them after every step instead.
        frozen = [net for net, trained in (("pi", self.train_control_policy), ("mu", train_mu)) if not trained]
        frozen_views = [view for net in frozen for view in self.policy.net_parameters(net)]
        frozen_values = [view.clone() for view in frozen_views]

        stats: dict[str, list[float]] = {name: [] for name in STEP_STATS}
        continue_training = True
        rollout = self.rollout_buffer.tensors()
        # The networks' inputs depend on stored observations and options only: build them once.
        inputs = self.policy.training_inputs(rollout.observations, rollout.comm)
        samples = rollout._replace(observations={})
        # probability of broadcasting with which the options were drawn (the centred critic's p_i)
        taken = rollout.old_log_prob_comm.exp()
        p_broadcast = th.where(rollout.comm.bool(), taken, 1 - taken)
        # Early stopping looks at a step's statistics before applying it: only the unfused path can.
        fused = self._gradient_step is not None and self.target_kl is None
        if fused:
            optimizer = self.policy.optimizer
            adam = (optimizer.param_groups[0]["params"], *adam_state(optimizer))
            names = self._loss_module.names_of(adam[0])
            lr = th.tensor(optimizer.param_groups[0]["lr"], device=self.device)
        scalars = (clip_pi, clip_mu, zeta)
        if fused:  # as tensors: a float would be compiled in, and every new value of a schedule recompile the step
            scalars = tuple(th.tensor(value, dtype=th.float64, device=self.device) for value in scalars)
        train_pi = self.train_control_policy
        for epoch in range(self.n_epochs):
            for idx in self.rollout_buffer.minibatch_indices(self.batch_size):
                loss_args = (inputs, samples, p_broadcast, idx, *scalars, train_pi, train_mu)
                if fused:
                    step_stats = self._gradient_step(adam, names, lr, loss_args)  # type: ignore[misc]
                else:
                    loss, step_stats = self._step_losses(*loss_args)
                for name, value in zip(STEP_STATS, step_stats.tolist(), strict=True):
                    stats[name].append(value)
                if not fused:
                    kl_pi = stats["kl_pi"][-1]
                    if self.target_kl is not None and kl_pi > 1.5 * self.target_kl:
                        continue_training = False
                        if self.verbose >= 1:
                            print(f"Early stopping at epoch {epoch} due to reaching max kl: {kl_pi:.2f}")
                        break
                    self.policy.optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    if self.max_grad_norm is not None:
                        th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                    self.policy.optimizer.step()
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
        self.logger.record("train/clip_range_option", clip_mu)
        self.logger.record("train/option_ent_coef", zeta)
        self.logger.record("train/action_noise_std", self.action_noise_std)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("rollout/broadcast_rate", float(buffer.comm.mean()))

    def _fused_gradient_step(
        self,
        adam: tuple[list[th.Tensor], list[th.Tensor], list[th.Tensor], list[th.Tensor]],
        names: list[str],
        lr: th.Tensor,
        loss_args: tuple[Any, ...],
    ) -> th.Tensor:
        """One gradient step as one function, compiled whole (:mod:`sb3_detc.mappoc.fused`).

        Equal to :meth:`_losses`, ``backward()``, optional gradient clipping and ``optimizer.step()``.

        :param adam: the optimizer's parameters and their ``step``, ``exp_avg`` and ``exp_avg_sq``
        :param names: the names of the parameters in :class:`_PolicyLoss`
        :param lr: learning rate (0-d tensor)
        :param loss_args: the arguments of :meth:`_losses`
        :return: the statistics named in :data:`STEP_STATS`
        """
        params, steps, exp_avgs, exp_avg_sqs = adam

        def loss_of(values: tuple[th.Tensor, ...]) -> tuple[th.Tensor, th.Tensor]:
            return th.func.functional_call(self._loss_module, dict(zip(names, values, strict=True)), loss_args)

        grads, (_, step_stats) = th.func.grad_and_value(loss_of, has_aux=True)(tuple(params))
        if self.max_grad_norm is not None:
            grads = clip_by_total_norm(grads, self.max_grad_norm)
        group = self.policy.optimizer.param_groups[0]
        adam_update_(params, grads, steps, exp_avgs, exp_avg_sqs, lr, group["betas"], group["eps"])
        return step_stats

    def _losses(
        self,
        inputs: list[ChainInput],
        samples: HybridRolloutSamples,
        p_broadcast: th.Tensor,
        idx: th.Tensor,
        clip_pi: float,
        clip_mu: float,
        zeta: float,
        train_pi: bool,
        train_mu: bool,
    ) -> tuple[th.Tensor, th.Tensor]:
        """The loss of one gradient step on the minibatch ``idx`` and its statistics (Sec. 3).

        :param inputs: stacked network inputs of the whole rollout (:meth:`MlpHybridPolicy.training_inputs`)
        :param samples: the rollout's tensors (observations not needed)
        :param p_broadcast: probabilities of broadcasting with which the options were drawn (B, N)
        :param idx: indices of the minibatch's samples
        :param clip_pi: clip range of ``pi``
        :param clip_mu: clip range of ``mu``
        :param zeta: option entropy coefficient
        :param train_pi: whether ``pi``'s loss is part of the loss
        :param train_mu: whether ``mu``'s loss and entropy bonus are part of the loss
        :return: the loss, and the statistics named in :data:`STEP_STATS` as one tensor
        """
        data = samples.select(idx)
        evaluation = self.policy.evaluate_inputs(
            [x.select(idx) for x in inputs], data.comm, data.control, data.comm_price, p_broadcast[idx]
        )

        # Control policy: PPO clipped surrogate on GAE advantages of the taken option.
        advantages = self._normalized(data.advantages)
        log_ratio_pi = evaluation.log_prob_control - data.old_log_prob_control
        ratio_pi = th.exp(log_ratio_pi)
        pi_loss = clipped_surrogate_loss(advantages, ratio_pi, clip_pi)

        # Critic: squared error of Q(s, o_taken) against the lambda-return.
        q = evaluation.option_values
        q_taken = q.gather(-1, data.comm[..., None])[..., 0]
        q_loss = (data.returns - q_taken).pow(2).mean(0).sum()
        loss = self.vf_coef * q_loss
        if train_pi:
            loss = loss + pi_loss

        # Options: PPO clipped surrogate on the greedy advantage Q(o) - max_o' Q(o'), no gradient into Q.
        if self.option_advantage == "greedy":
            advantages_mu = greedy_option_advantage(q, data.comm)
            if self.normalize_option_advantage:
                advantages_mu = advantages_mu / option_gap_scale(q)
            advantages_mu = advantages_mu + self.option_advantage_offset
        else:
            advantages_mu = self._normalized(data.option_advantages) + self.option_advantage_offset
        log_ratio_mu = evaluation.log_prob_comm - data.old_log_prob_comm
        ratio_mu = th.exp(log_ratio_mu)
        mu_loss = clipped_surrogate_loss(advantages_mu, ratio_mu, clip_mu)
        entropy_mu = evaluation.entropy_comm.mean(0).sum()
        if train_mu:
            loss = loss + mu_loss - zeta * entropy_mu

        with th.no_grad():
            step_stats = th.stack(
                [
                    pi_loss,
                    mu_loss,
                    q_loss,
                    entropy_mu / self.n_agents,
                    ((ratio_pi - 1).abs() > clip_pi).float().mean(),
                    ((ratio_mu - 1).abs() > clip_mu).float().mean(),
                    ((ratio_pi - 1) - log_ratio_pi).mean(),
                    ((ratio_mu - 1) - log_ratio_mu).mean(),
                ]
            )
        return loss, step_stats

    def _comm_costs(self, env: VecEnv) -> np.ndarray:
        """The communication cost ``xi`` of every environment, (n_envs,); zeros unless the critic needs it."""
        if self.policy.critic == "option_heads":
            return np.zeros(env.num_envs, dtype=np.float32)  # the option heads learn it from the rewards
        try:
            return np.asarray(env.get_attr("comm_cost"), dtype=np.float32)
        except AttributeError as err:
            raise ValueError(
                f"critic={self.policy.critic!r} needs the environment's communication cost (attribute "
                "'comm_cost', as the sb3_detc envs have) to add it to its option values."
            ) from err

    def _comm_prices(self, comm_cost: np.ndarray) -> np.ndarray:
        """What an agent's own broadcast costs in the learner's reward units, (n_envs, N).

        The communication cost through the same transformation as the rewards: scaled,
        shared by the team (``team_reward``) and divided by the running return spread
        (``normalize_reward``; the clipping to [-10, 10] is ignored).

        :param comm_cost: communication cost of every environment (n_envs,)
        """
        price = np.repeat(comm_cost[:, None] * self.reward_scale, self.n_agents, axis=1)
        if self.team_reward:
            price = price / self.n_agents
        if self.normalize_reward and self.reward_rms is not None:
            price = price / np.sqrt(self.reward_rms.var + 1e-8)
        return price.astype(np.float32)

    def _normalized_rewards(self, rewards: np.ndarray, dones: np.ndarray) -> np.ndarray:
        """Rewards divided by the running standard deviation of the discounted returns, per agent."""
        if self.reward_rms is None:
            self.reward_rms = RunningMeanStd(shape=(self.n_agents,))
        if self._discounted_returns is None or self._discounted_returns.shape != rewards.shape:
            self._discounted_returns = np.zeros_like(rewards, dtype=np.float64)
        self._discounted_returns = self._discounted_returns * self.gamma + rewards
        self.reward_rms.update(self._discounted_returns)
        self._discounted_returns[np.asarray(dones, dtype=bool)] = 0.0
        return np.clip(rewards / np.sqrt(self.reward_rms.var + 1e-8), -10.0, 10.0).astype(np.float32)

    def _normalized(self, advantages: th.Tensor) -> th.Tensor:
        """Standardise advantages per agent over the minibatch (if ``normalize_advantage``)."""
        if self.normalize_advantage and len(advantages) > 1:
            return (advantages - advantages.mean(0)) / (advantages.std(0) + 1e-8)
        return advantages

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
        env = _as_joint_env(env)
        _check_same_agents(env, self.n_agents)  # type: ignore[arg-type]
        _check_vec_normalize(env)  # type: ignore[arg-type]
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
        :param env: environment to attach (must have the spaces the model was trained with)
        :param device: device on which the code runs
        :param custom_objects: objects to replace on load, see :meth:`BaseAlgorithm.load`
        :param print_system_info: print the system info of the saved model and the current one
        :param force_reset: force a reset of the environment before the next ``learn``
        :param kwargs: attributes to change on the loaded model
        :raises FileNotFoundError: if there is no file at ``path``
        :raises ValueError: if the environment has another number of agents than the model or
            normalises the network's observations (see :func:`check_observation_normalization`)
        """
        env = _as_joint_env(env)
        if env is not None:
            data, _, _ = load_from_zip_file(path, device="cpu", custom_objects=custom_objects, load_data=True)
            if data is not None and "action_space" in data:
                _check_same_agents(env, len(data["action_space"]["comm"].nvec))  # type: ignore[arg-type]
        return super().load(  # type: ignore[return-value]
            path,
            env=env,  # type: ignore[arg-type]
            device=device,
            custom_objects=custom_objects,
            print_system_info=print_system_info,
            force_reset=force_reset,
            **kwargs,
        )


class _PolicyLoss(th.nn.Module):
    """The loss of a gradient step as a module holding the policy, for :func:`torch.func.functional_call`.

    :param policy: the policy whose parameters the loss depends on
    :param losses: the loss function (:meth:`MAPPOC._losses`)
    """

    def __init__(self, policy: MlpHybridPolicy, losses: Callable[..., tuple[th.Tensor, th.Tensor]]) -> None:
        super().__init__()
        self.policy = policy
        self._losses = losses

    def names_of(self, params: list[th.Tensor]) -> list[str]:
        """The names under which this module holds ``params``."""
        names = {id(param): name for name, param in self.named_parameters()}
        return [names[id(param)] for param in params]

    def forward(self, *args: Any) -> tuple[th.Tensor, th.Tensor]:
        """The loss and the statistics of :meth:`MAPPOC._losses`."""
        return self._losses(*args)


def greedy_option_advantage(option_values: th.Tensor, comm: th.Tensor, offset: float = 0.0) -> th.Tensor:
    """Greedy advantage of the taken options, ``A_mu = Q(o) - max_o' Q(o') + offset`` (Sec. 3).

    Evaluated with the current critic and detached: no gradient flows into ``Q``.

    :param option_values: ``Q_i(s, o)`` for both options, (B, N, 2)
    :param comm: taken options (B, N)
    :param offset: constant added to the advantage (the paper's code: 0.1, the paper: 0)
    :return: advantages (B, N), at most ``offset``
    """
    q = option_values.detach()
    return q.gather(-1, comm.long()[..., None])[..., 0] - q.max(-1).values + offset


def option_gap_scale(option_values: th.Tensor) -> th.Tensor:
    """Every agent's root mean square option gap ``Q(1) - Q(0)`` over a batch, detached, (N,).

    :param option_values: ``Q_i(s, o)`` for both options, (B, N, 2)
    """
    gap = option_values.detach()[..., 1] - option_values.detach()[..., 0]
    return gap.pow(2).mean(0).sqrt() + 1e-8


def clipped_surrogate_loss(advantages: th.Tensor, ratio: th.Tensor, clip: float) -> th.Tensor:
    """PPO's clipped surrogate loss, averaged over the batch and summed over agents.

    Summing over agents keeps every agent's gradient what it would be if it trained alone.

    :param advantages: advantages (B, N)
    :param ratio: probability ratios new / old (B, N)
    :param clip: clipping parameter epsilon
    :return: scalar loss
    """
    surrogate = th.min(advantages * ratio, advantages * th.clamp(ratio, 1 - clip, 1 + clip))
    return -surrogate.mean(0).sum()


def _agent_rewards(infos: list[dict[str, Any]]) -> np.ndarray:
    try:
        return np.stack([info["agent_rewards"] for info in infos]).astype(np.float32)
    except KeyError as err:
        raise ValueError(
            "MAPPOC needs per-agent rewards in info['agent_rewards']: use a joint sb3_detc env (JointEnv)."
        ) from err


def _check_cxx_compiler() -> None:
    """``torch.compile`` builds C++ code for the CPU: fail at once, and clearly, without a compiler."""
    from torch._inductor import cpp_builder, exc

    try:
        cpp_builder.get_cpp_compiler()
    except exc.InvalidCxxCompiler as error:
        raise RuntimeError(
            "torch_compile=True needs a C++ compiler on the CPU (g++ or clang++ on PATH, or the CXX "
            "environment variable); install one or use torch_compile=False."
        ) from error


def _has_rollout_workers(env: VecEnv) -> bool:
    """Whether ``env`` is a plain SB3 vector env of :class:`~sb3_detc.mappoc.workers.RolloutWorker` envs.

    Vector env wrappers (e.g. ``VecNormalize``) change what the policy sees: those keep the step-by-step path.
    """
    return isinstance(env, (DummyVecEnv, SubprocVecEnv)) and env.has_attr("collect_rollout")


def _stack_dicts(dicts: list[dict[str, np.ndarray]], axis: int) -> dict[str, np.ndarray]:
    """Stack same-keyed dicts of arrays key by key along a new ``axis``."""
    return {key: np.stack([d[key] for d in dicts], axis=axis) for key in dicts[0]}


def _truncated(infos: list[dict[str, Any]], dones: np.ndarray) -> list[tuple[int, dict[str, np.ndarray]]]:
    """The envs whose episode was cut by a time limit in this step, with their last observations (checked)."""
    cut = []
    for idx, (info, done) in enumerate(zip(infos, dones, strict=True)):
        if done and info.get("TimeLimit.truncated", False) and "terminal_observation" in info:
            _check_finite(info["terminal_observation"])
            cut.append((idx, info["terminal_observation"]))
    return cut


def _check_finite(obs: dict[str, np.ndarray], rewards: np.ndarray | None = None) -> None:
    if rewards is not None and not np.all(np.isfinite(rewards)):
        raise ValueError(f"the environment returned non-finite rewards: {rewards.tolist()}.")
    for key, value in obs.items():
        if not np.all(np.isfinite(value)):
            raise ValueError(f"the environment returned a non-finite observation in '{key}'.")


def _check_same_agents(env: GymEnv, n_agents: int) -> None:
    action_space = env.action_space
    if isinstance(action_space, spaces.Dict) and "comm" in action_space.spaces:
        n_env = len(action_space["comm"].nvec)
        if n_env != n_agents:
            raise ValueError(f"the model controls {n_agents} agents but the environment has {n_env}.")


#: Hyperparameter checks: name -> (rule, what the rule needs).
_HYPERPARAMETER_RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "n_steps": (lambda v: isinstance(v, int) and v > 0, "a positive integer"),
    "batch_size": (lambda v: isinstance(v, int) and v > 0, "a positive integer"),
    "n_epochs": (lambda v: isinstance(v, int) and v > 0, "a positive integer"),
    "gamma": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "gae_lambda": (lambda v: 0 <= v <= 1, "in [0, 1]"),
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
    """Apply :func:`check_observation_normalization` to a ``VecNormalize`` anywhere in ``env``'s vector wrappers."""
    vec_normalize = unwrap_vec_normalize(env) if isinstance(env, VecEnv) else None
    if vec_normalize is not None:
        check_observation_normalization(vec_normalize.norm_obs, vec_normalize.norm_obs_keys)
