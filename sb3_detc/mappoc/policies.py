"""MlpHybridPolicy: per agent a policy over options, a control policy and an option-value critic.

For every agent ``i`` (Sec. 3 of the method reference):

* ``mu_i(o_i | trigger_i, trigger_held_i)``: categorical over {silent, broadcast}
  (policy over options, re-sampled every step: option termination ``beta = 1``);
* ``pi_i(u_i | x^_i)``: Gaussian control policy with a state-independent log standard
  deviation, evaluated on the networked observation ``x^_i`` *after* this step's
  broadcasts (same-step delivery);
* ``Q_i(s, o)``: option-value critic, centralised during training only (it also sees the
  true messages of all agents); how its network's outputs become both options' values is
  one of the critics of :mod:`sb3_detc.mappoc.critics` (the paper's option heads, an
  afterstate critic or a centred one).

This module builds the networks' features (the hold rule of :mod:`sb3_detc.network`
applied to the options), samples and evaluates hybrid actions, and gives each agent's
standalone controller (:class:`AgentController`). The networks of all agents are evaluated
by agent-batched layers (:class:`~sb3_detc.mappoc.batched.AgentBatchedNetworks`: one batched
matmul per layer, weights shaped (groups, in, out)); no Python loop over agents on the hot path.
"""

from __future__ import annotations

import inspect
import math
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.common.utils import get_device
from torch import nn
from torch.nn import functional as F

from sb3_detc.envs.wrappers import JOINT_KEYS
from sb3_detc.mappoc.batched import AgentBatchedNetworks, ChainInput, NetSpec
from sb3_detc.mappoc.critics import CRITICS, OptionCritic
from sb3_detc.network import (
    advance_timer,
    hold,
    interval_window,
    others_ages,
    others_index,
    relative_to_receivers,
    relative_views,
)
from sb3_detc.renamed import renamed_action_space, renamed_keys

#: Order of the networks inside the batched chains: ``mu`` (and a critic that reads the state
#: before the options) do not depend on this step's options and run before the options are
#: sampled, ``pi`` (and a critic that reads the afterstate) run after.
NETS = ("mu", "q", "pi")
#: Orthogonal-init gains of the networks' output layers.
OUTPUT_GAINS = {"mu": 0.01, "q": 1.0, "pi": 0.01}
#: How far below the other option's logit an option that a broadcast interval closes is pinned:
#: its probability underflows to zero, and its log-probability stays finite (no NaN in entropies).
CLOSED_LOGIT = 1e4


def option_inputs(
    trigger: th.Tensor,
    trigger_held: th.Tensor,
    own_age: th.Tensor,
    age_scale: float,
    distance_scale: float,
    others_age: th.Tensor | None,
    others_age_scale: float,
) -> th.Tensor:
    """Inputs of a policy over options ``mu_i``, for the joint policy and the decentralised controllers alike.

    The trigger features now and at the own last broadcast; with ``age_scale`` > 0 the own age
    (steps since the own last broadcast) times it; with ``distance_scale`` > 0 the Euclidean
    distance between both feature vectors (what send-on-delta thresholds,
    :meth:`~sb3_detc.triggers.SendOnDelta.distance`) times it; with ``others_age_scale`` > 0 the
    ages of the others' held broadcasts (steps since their last broadcasts, before this step's
    options) times it.

    :param trigger: trigger features now (..., n_trig)
    :param trigger_held: trigger features at the own last broadcast (..., n_trig)
    :param own_age: the own age (..., 1)
    :param age_scale: factor of the own age (0: not an input)
    :param distance_scale: factor of the distance (0: not an input)
    :param others_age: the others' ages, others in increasing order (..., N - 1); read only with
        ``others_age_scale`` > 0 (else None will do)
    :param others_age_scale: factor of the others' ages (0: not an input)
    :return: (..., 2 n_trig), then the scaled own age, distance and others' ages where they are inputs
    """
    parts = [trigger, trigger_held]
    if age_scale > 0:
        parts.append(own_age * age_scale)
    if distance_scale > 0:
        parts.append(th.linalg.vector_norm(trigger - trigger_held, dim=-1, keepdim=True) * distance_scale)
    if others_age_scale > 0:
        parts.append(others_age * others_age_scale)
    return th.cat(parts, dim=-1)


def pin_options(logits: th.Tensor, silent: th.Tensor, broadcast: th.Tensor) -> th.Tensor:
    """Logits of ``mu`` with the options that a window of broadcast intervals decides pinned.

    Where the window forces an option, the logits become constants that give it probability
    one: the option is drawn and is the mode, its log-probability is zero whatever the
    parameters (so PPO's ratio is one and no gradient flows from that decision), and the entropy is zero.

    :param logits: outputs of ``mu``, (..., 2): the logits of silent (0) and broadcast (1)
    :param silent: where the agent must stay silent (...), from :func:`~sb3_detc.network.interval_window`
    :param broadcast: where it must broadcast (...)
    :return: the logits, pinned where either mask is set, (..., 2)
    """
    pinned = th.stack([broadcast, silent], dim=-1).to(logits.dtype) * -CLOSED_LOGIT
    return th.where((silent | broadcast)[..., None], pinned, logits)


def check_broadcast_interval(window: Any) -> tuple[int, int]:
    """A window of broadcast intervals as two integers, checked.

    :param window: ``(min_interval, max_interval)``
    :return: the window as a tuple of two ints
    :raises ValueError: unless it is two integers with ``1 <= min_interval <= max_interval``
    """
    values = tuple(window) if isinstance(window, (list, tuple)) else ()
    if not (
        len(values) == 2
        and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in values)
        and 1 <= values[0] <= values[1]
    ):
        raise ValueError(
            "broadcast_interval must be two integers (min_interval, max_interval) with 1 <= min <= max, "
            f"got {window!r}."
        )
    return int(values[0]), int(values[1])


def options_sampled(sample_options: bool, deterministic: bool) -> bool:
    """Whether a trigger runs with options sampled from ``mu``: the one rule of every prediction and evaluation.

    A stochastic call samples them; a deterministic one (mean controls) samples them too where
    the trigger is meant to run sampled (``sample_options``), and takes the most likely ones
    otherwise.

    :param sample_options: how the trigger is meant to run when deployed (a policy's or a
        controller's ``sample_options``)
    :param deterministic: whether the call asks for the deterministic policy
    :return: True to sample the options, False to take the most likely ones
    """
    return sample_options or not deterministic


def broadcast_probability(logits: th.Tensor) -> th.Tensor:
    """Probability of broadcasting under ``mu`` from its logits (..., 2): ``sigmoid(logit_1 - logit_0)``.

    :param logits: outputs of ``mu``, (..., 2): the logits of silent (0) and broadcast (1)
    :return: probabilities of broadcasting, (...)
    """
    return th.sigmoid(logits[..., 1] - logits[..., 0])


def drawn_broadcast_probability(broadcast: th.Tensor, log_prob_broadcast: th.Tensor) -> th.Tensor:
    """Probability of broadcasting with which options were drawn, from the log-probabilities of the drawn ones.

    :param broadcast: the drawn options (...)
    :param log_prob_broadcast: their log-probabilities (...)
    :return: probabilities of broadcasting, (...)
    """
    taken = log_prob_broadcast.exp()
    return th.where(broadcast.bool(), taken, 1 - taken)


class HybridAction(NamedTuple):
    """One joint hybrid action of all agents with what training needs about it.

    :param broadcast: options (B, N), int64
    :param control: controls (B, N, m), with any extra exploration noise, unclipped
    :param log_prob_broadcast: ``log mu_i(o_i)`` (B, N)
    :param log_prob_control: ``log pi_i(u_i)`` (B, N)
    :param option_values: ``Q_i(s, o)`` for both options (B, N, 2)
    """

    broadcast: th.Tensor
    control: th.Tensor
    log_prob_broadcast: th.Tensor
    log_prob_control: th.Tensor
    option_values: th.Tensor


class HybridEvaluation(NamedTuple):
    """Log-probabilities, broadcast entropy and option values of stored hybrid actions.

    :param log_prob_broadcast: ``log mu_i(o_i)`` of the stored options under the current ``mu`` (B, N)
    :param entropy_broadcast: entropy of every agent's current ``mu`` (B, N)
    :param log_prob_control: ``log pi_i(u_i)`` of the stored controls under the current ``pi`` (B, N)
    :param option_values: ``Q_i(s, o)`` for both options under the current critic (B, N, 2)
    :param broadcast_logit: ``log mu_i(1) - log mu_i(0)`` under the current ``mu`` (B, N)
    """

    log_prob_broadcast: th.Tensor
    entropy_broadcast: th.Tensor
    log_prob_control: th.Tensor
    option_values: th.Tensor
    broadcast_logit: th.Tensor


def gaussian_log_prob(x: th.Tensor, mean: th.Tensor, log_std: th.Tensor) -> th.Tensor:
    """Log-density of a diagonal Gaussian, summed over the last axis.

    :param x: points at which to evaluate the density (..., m)
    :param mean: means (..., m), broadcastable against ``x``
    :param log_std: log standard deviations (..., m), broadcastable against ``x``
    :return: log-densities (...)
    """
    z = (x - mean) * th.exp(-log_std)
    return (-0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)


class MlpHybridPolicy(BasePolicy):
    """Per-agent policy over options, Gaussian control policy and centralised option-value critic.

    :param observation_space: joint observation space of an event-triggered env (Dict with
        keys ``local``, ``message``, ``held``, ``age``, ``trigger``, ``trigger_held``)
    :param action_space: joint action space (Dict with ``broadcast`` MultiDiscrete and ``control`` Box)
    :param lr_schedule: learning rate schedule (None: a constant placeholder, for a policy
        loaded on its own with :meth:`load` to act, not to train)
    :param net_arch: hidden layer sizes, either one list for all networks or a dict with keys
        ``mu``, ``pi`` and ``q`` (None: three layers of 96 units, as in the paper)
    :param activation_fn: activation function of the hidden layers
    :param log_std_init: initial log standard deviation of the control policies (paper: -0.7)
    :param learn_log_std: whether the log standard deviation is trained (the paper keeps it constant)
    :param share_parameters: one network set for all agents with a one-hot agent id input
        (default: every agent has its own networks, as in the paper)
    :param age_scale: factor applied to ages of information (in steps) before they enter a network
        (>= 0; 0: no network sees the ages)
    :param option_age_scale: factor applied to the age of the agent's own last broadcast (in steps)
        before it enters its policy over options as an extra input (>= 0; 0, the default: no such
        input, as in the paper). With it, ``mu`` can represent every periodic schedule in phase
        and every send-on-delta rule with a maximum age, not only send-on-delta
    :param option_distance_scale: factor applied to the Euclidean distance between the agent's
        trigger features now and at its own last broadcast before it enters its policy over
        options as an extra input (>= 0; 0, the default: no such input). With it, a send-on-delta
        rule is a threshold on one input; where the held features are the receivers' predictions
        (``LinearETC-LQR-v0(prediction=True, predicted_held=True)``) the distance is the prediction
        error, and predictive triggering is such a threshold
    :param option_others_age_scale: factor applied to the ages of the others' held broadcasts (steps
        since their last broadcasts, as every agent knows them from what it received, before this
        step's options) before they enter the policy over options as extra inputs (>= 0; 0, the
        default: no such inputs). With it and ``option_age_scale``, ``mu`` can represent the
        periodic schedules staggered over the agents as well as those in phase, and keep its
        messages apart from the others' or together with them
    :param broadcast_interval: a window ``(min_interval, max_interval)`` of steps between two
        broadcasts of an agent (integers, ``1 <= min_interval <= max_interval``), or None (the
        default: ``mu`` decides at every step). With it an agent stays silent while its interval
        would be shorter than ``min_interval``, broadcasts once it reaches ``max_interval``, and
        ``mu`` decides in between (:func:`~sb3_detc.network.interval_window`): no silence lasts
        longer than the window, whatever ``mu`` learns. ``(P, P)`` is the periodic schedule of
        period ``P``, all agents in phase. Decisions the window takes carry no gradient
    :param broadcast_prob_init: probability of broadcasting of the untrained policies over
        options (through the bias of their output layer; 0.5: undecided). A low value lets
        training start where every broadcast carries information that would otherwise stay
        stale for several steps, so its value stands out from the noise of the returns
    :param critic: name of the option-value critic, a key of
        :data:`~sb3_detc.mappoc.critics.CRITICS`: ``"option_heads"`` (the paper: one output per
        option on the state before the options), ``"afterstate"`` (one output that values the
        network state after the options, with the price of the own broadcast added
        analytically) or ``"centred"`` (a state value and a broadcast gap on the state before the
        options, centred on the probabilities the options were drawn with); see the classes of
        :mod:`sb3_detc.mappoc.critics`. The critic object is :attr:`option_critic`
    :param ortho_init: orthogonal initialisation (otherwise PyTorch's default init)
    :param sample_options: how this policy's trigger is meant to run when it is deployed: options
        sampled from the policy over options (True) or its most likely option (False, default).
        Saved with the policy; :meth:`predict` with ``deterministic=True`` (mean controls) and the
        package's evaluation protocol (:mod:`sb3_detc.evaluation`) run the trigger this way, the
        protocol shows the most likely option as a mode of its own. A policy over options that an
        entropy bonus keeps stochastic (the paper's ends near 50 %) has a mode that is another
        trigger, one it was never trained with: on Multiwalker the paper's policies fall in nearly
        every episode with it, so the paper's entries set ``sample_options=True``; their
        deterministic predictions repeat under the same state of PyTorch's generator
        (``th.manual_seed``)
    :param use_sde: not supported, must be False (present for SB3 compatibility)
    :param optimizer_class: optimizer class
    :param optimizer_kwargs: optimizer keyword arguments, excluding the learning rate
        (default ``eps=1e-5`` as in the paper's code, and PyTorch's fused Adam kernel)
    :param normalize_images: unused (no image inputs); present for SB3 compatibility, it is
        among the constructor parameters that SB3 saves with a policy

    :ivar chains: the agent-batched networks of ``mu``, ``q`` and ``pi``
        (:class:`~sb3_detc.mappoc.batched.AgentBatchedNetworks`)
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Dict,
        lr_schedule: Schedule | None = None,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.Tanh,
        log_std_init: float = -0.7,
        learn_log_std: bool = False,
        share_parameters: bool = False,
        age_scale: float = 0.1,
        option_age_scale: float = 0.0,
        option_distance_scale: float = 0.0,
        option_others_age_scale: float = 0.0,
        broadcast_interval: tuple[int, int] | None = None,
        broadcast_prob_init: float = 0.5,
        critic: str = "option_heads",
        ortho_init: bool = True,
        sample_options: bool = False,
        use_sde: bool = False,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
    ) -> None:
        if use_sde:
            raise ValueError("MlpHybridPolicy does not support gSDE (use_sde=True).")
        n_agents, n_control = check_joint_spaces(observation_space, action_space)
        if not 0.0 < broadcast_prob_init < 1.0:
            raise ValueError(f"broadcast_prob_init must be in (0, 1), got {broadcast_prob_init}.")
        if not (np.isfinite(age_scale) and age_scale >= 0):
            raise ValueError(f"age_scale must be a finite number >= 0 (0: the networks ignore ages), got {age_scale}.")
        if not (np.isfinite(option_age_scale) and option_age_scale >= 0):
            raise ValueError(
                f"option_age_scale must be a finite number >= 0 (0: mu ignores its own age), got {option_age_scale}."
            )
        if not (np.isfinite(option_distance_scale) and option_distance_scale >= 0):
            raise ValueError(
                "option_distance_scale must be a finite number >= 0 (0: mu does not read the distance), "
                f"got {option_distance_scale}."
            )
        if not (np.isfinite(option_others_age_scale) and option_others_age_scale >= 0):
            raise ValueError(
                "option_others_age_scale must be a finite number >= 0 (0: mu ignores the others' ages), "
                f"got {option_others_age_scale}."
            )
        if broadcast_interval is not None:
            broadcast_interval = check_broadcast_interval(broadcast_interval)
        if critic not in CRITICS:
            raise ValueError(f"critic must be one of {tuple(CRITICS)}, got {critic!r}.")
        if optimizer_kwargs is None:
            # The paper's epsilon (for optimizers that have one); the fused Adam kernel saves about
            # 12 % of an eager update step here.
            optimizer_kwargs = {"eps": 1e-5} if "eps" in inspect.signature(optimizer_class).parameters else {}
            if optimizer_class is th.optim.Adam:
                optimizer_kwargs["fused"] = True
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=False,
            normalize_images=normalize_images,
        )
        self.n_agents = n_agents
        self.n_control = n_control
        self.net_arch = [96, 96, 96] if net_arch is None else net_arch
        self.activation_fn = activation_fn
        self.log_std_init = log_std_init
        self.learn_log_std = learn_log_std
        self.share_parameters = share_parameters
        self.age_scale = age_scale
        self.option_age_scale = float(option_age_scale)
        self.option_distance_scale = float(option_distance_scale)
        self.option_others_age_scale = float(option_others_age_scale)
        self.broadcast_interval = broadcast_interval
        self.broadcast_prob_init = broadcast_prob_init
        self.critic = critic
        self.option_critic: OptionCritic = CRITICS[critic]()
        self.ortho_init = ortho_init
        self.sample_options = bool(sample_options)

        n_local = observation_space["local"].shape[1]
        n_msg = observation_space["message"].shape[1]
        n_trig = observation_space["trigger"].shape[1]
        n = n_agents
        self.register_buffer("others", th.as_tensor(others_index(n)), persistent=False)
        self.register_buffer("everyone", th.arange(n).repeat(n, 1), persistent=False)
        self.register_buffer("agent_id", th.eye(n), persistent=False)
        self.register_buffer("control_low", th.as_tensor(action_space["control"].low), persistent=False)
        self.register_buffer("control_high", th.as_tensor(action_space["control"].high), persistent=False)
        in_features = {
            "mu": 2 * n_trig
            + (self.option_age_scale > 0)
            + (self.option_distance_scale > 0)
            + (n - 1) * (self.option_others_age_scale > 0),
            "q": n_local + n * (n_msg + 1) + (n - 1) * n_msg,
            "pi": n_local + (n - 1) * (n_msg + 1),
        }
        out_features = {"mu": 2, "q": self.option_critic.outputs, "pi": n_control}
        self._build(lr_schedule, in_features, out_features)

    # ------------------------------------------------------------------ building
    def _arch(self, net: str) -> tuple[int, ...]:
        """Hidden layer sizes of network ``net`` from ``net_arch``.

        :param net: one of :data:`NETS`
        :raises ValueError: for a malformed ``net_arch``
        """
        arch = self.net_arch
        if isinstance(arch, dict):
            if set(arch) != set(NETS):
                raise ValueError(f"net_arch as a dict needs exactly the keys {sorted(NETS)}, got {sorted(arch)}.")
            arch = arch[net]
        if not all(isinstance(h, int) and h > 0 for h in arch):
            raise ValueError(f"net_arch must list positive layer sizes, got {arch!r}.")
        return tuple(arch)

    def _build(self, lr_schedule: Schedule | None, in_features: dict[str, int], out_features: dict[str, int]) -> None:
        """Create the networks, the log standard deviation and the optimizer.

        :param lr_schedule: learning rate schedule (None: learning rate 0)
        :param in_features: input width of every network (without a one-hot agent id)
        :param out_features: output width of every network
        """
        groups = 1 if self.share_parameters else self.n_agents
        specs = {net: NetSpec(in_features[net], out_features[net], self._arch(net), OUTPUT_GAINS[net]) for net in NETS}
        self.chains = AgentBatchedNetworks(
            specs, self.n_agents, self.share_parameters, self.activation_fn, self.ortho_init
        )
        # mu's output layer: logit(broadcast) - logit(silent) = log(p / (1 - p)) at initialisation.
        self.chains.agent_biases("mu")[-1][:, 0, 1] = math.log(
            self.broadcast_prob_init / (1.0 - self.broadcast_prob_init)
        )
        log_std = th.full((groups, self.n_control), float(self.log_std_init))
        self.log_std = nn.Parameter(log_std, requires_grad=self.learn_log_std)
        params = [p for p in self.parameters() if p.requires_grad]
        learning_rate = 0.0 if lr_schedule is None else lr_schedule(1)
        self.optimizer = self.optimizer_class(params, lr=learning_rate, **self.optimizer_kwargs)

    @classmethod
    def load(cls, path: str, device: th.device | str = "auto") -> MlpHybridPolicy:  # type: ignore[override]
        """Load a policy saved with :meth:`save`, also one saved under earlier names (:mod:`sb3_detc.renamed`).

        A policy saved before ``sample_options`` (or its earlier opposite ``deterministic_options``)
        existed sampled its options in every evaluation: it loads with ``sample_options=True``.

        :param path: the file
        :param device: where the policy runs
        :return: the policy
        """
        device = get_device(device)
        saved = th.load(path, map_location=device, weights_only=False)  # the spaces are pickled gymnasium objects
        data = renamed_keys({**saved["data"], "action_space": renamed_action_space(saved["data"]["action_space"])})
        data.setdefault("sample_options", True)  # saved before the setting existed: it sampled its options
        policy = cls(**data)
        policy.load_state_dict(saved["state_dict"])
        return policy.to(device)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            log_std_init=self.log_std_init,
            learn_log_std=self.learn_log_std,
            share_parameters=self.share_parameters,
            age_scale=self.age_scale,
            option_age_scale=self.option_age_scale,
            option_distance_scale=self.option_distance_scale,
            option_others_age_scale=self.option_others_age_scale,
            broadcast_interval=self.broadcast_interval,
            broadcast_prob_init=self.broadcast_prob_init,
            critic=self.critic,
            ortho_init=self.ortho_init,
            sample_options=self.sample_options,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data

    def constructor_parameters(self) -> dict[str, Any]:
        """The arguments this policy was built with, as :meth:`save` stores them and :meth:`load` rebuilds it from.

        :return: the constructor's keyword arguments by name (the spaces and the learning-rate schedule included)
        """
        return self._get_constructor_parameters()

    def net_parameters(self, net: str) -> list[th.Tensor]:
        """Every agent's parameters of one network: views into the batched chain (``pi`` includes ``log_std``).

        :param net: one of ``"mu"``, ``"q"``, ``"pi"``
        :return: detached views (writing into them changes the network)
        """
        views = [*self.chains.agent_weights(net), *self.chains.agent_biases(net)]
        return [*views, self.log_std.detach()] if net == "pi" else views

    # ------------------------------------------------------------------ features
    def network_after(self, obs: PyTorchObs, broadcast: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Held broadcasts and timers after this step's options (the rule of :mod:`sb3_detc.network`).

        :param obs: joint observation, tensors shaped (B, N, ...)
        :param broadcast: broadcast decisions (B, N)
        :return: held broadcasts (B, N, n_msg) and timers (B, N, 1)
        """
        broadcast = broadcast.to(obs["held"].dtype)
        return hold(obs["held"], obs["message"], broadcast), advance_timer(obs["age"], broadcast)

    def option_features(self, obs: PyTorchObs) -> th.Tensor:
        """Inputs of ``mu_i``: trigger features now and at the own last broadcast, ages and distance where read.

        :param obs: joint observation (B, N, ...); reads ``trigger``, ``trigger_held`` and ``age``
        :return: (B, N, 2 n_trig), then the own age times ``option_age_scale``, the distance times
            ``option_distance_scale`` and the others' ages times ``option_others_age_scale`` where they
            are inputs (:func:`option_inputs`)
        """
        return option_inputs(
            obs["trigger"],
            obs["trigger_held"],
            obs["age"],
            self.option_age_scale,
            self.option_distance_scale,
            others_ages(obs["age"], self.others) if self.option_others_age_scale > 0 else None,  # none per step unread
            self.option_others_age_scale,
        )

    def option_logits(self, logits: th.Tensor, age: th.Tensor | None) -> th.Tensor:
        """The logits the options are drawn from: ``mu``'s, pinned where :attr:`broadcast_interval` decides.

        :param logits: outputs of the ``mu`` networks (B, N, 2)
        :param age: every agent's timer before this step's decisions (B, N, 1); read only with a
            broadcast interval
        :return: (B, N, 2), ``logits`` itself without a broadcast interval
        :raises ValueError: with a broadcast interval and no ``age``
        """
        if self.broadcast_interval is None:
            return logits
        if age is None:
            raise ValueError("A policy with a broadcast_interval needs the agents' ages to evaluate its options.")
        return pin_options(logits, *interval_window(age, *self.broadcast_interval))

    def mu_logits(self, features: th.Tensor, age: th.Tensor | None) -> th.Tensor:
        """The logits the options are drawn from, for given features of ``mu`` (only ``mu`` runs).

        :param features: inputs of the policy over options (B, N, ...), :meth:`option_features`
        :param age: every agent's timer before this step's decisions (B, N, 1), see :meth:`option_logits`
        :return: (B, N, 2)
        """
        return self.option_logits(self.chains.run({"mu": features})["mu"], age)

    def control_features(self, obs: PyTorchObs, broadcast: th.Tensor) -> th.Tensor:
        """Inputs of ``pi_i``: networked observation ``x^_i`` after this step's broadcasts.

        Own local state, the others' held broadcasts relative to the own current message
        and their ages (Sec. 2, networked observation).

        :param obs: joint observation (B, N, ...)
        :param broadcast: broadcast decisions (B, N)
        :return: (B, N, n_local + (N - 1) (n_msg + 1))
        """
        held, age = self.network_after(obs, broadcast)
        views = relative_views(held, obs["message"], self.others).flatten(2)
        ages = others_ages(age, self.others) * self.age_scale
        return th.cat([obs["local"], views, ages], dim=-1)

    def critic_features(self, obs: PyTorchObs) -> th.Tensor:
        """Inputs of a critic that reads the network state before this step's options (option heads, centred).

        Own local state, every agent's held broadcast (the own one included: what the
        others believe about agent ``i``) relative to the own message, every age, and the
        others' true current messages relative to the own one (centralised training).

        :param obs: joint observation (B, N, ...)
        :return: (B, N, n_local + N (n_msg + 1) + (N - 1) n_msg)
        """
        return self._centralised_features(obs, obs["held"][:, self.everyone], obs["age"][:, self.everyone])

    def afterstate_features(self, obs: PyTorchObs, broadcast: th.Tensor) -> th.Tensor:
        """Inputs of the afterstate critic ``W_i`` for both own options, the others' as in ``broadcast``.

        The features of :meth:`critic_features` with the held broadcasts after this step's
        broadcasts: variant ``v`` of agent ``i`` applies the hold rule (:func:`hold`, as
        :meth:`network_after` does) to the options ``broadcast`` with agent ``i``'s own option
        replaced by ``v``. The ages stay those before the options, the same for both
        variants: a broadcast is worth the information it delivers, and an age reset that
        differs between the options in every state, whatever the broadcast carries, would let
        the critic credit "age 0" with the average value of broadcasting everywhere (it
        then valued broadcasting far above what the returns showed, and ``mu`` learned to
        broadcast at every step even when a broadcast cost more than any information).

        :param obs: joint observation (B, N, ...) from before the options
        :param broadcast: broadcast decisions (B, N)
        :return: (B, 2, N, features): ``[:, v, i]`` feeds ``W_i`` for ``o_i = v``
        """
        n = self.n_agents
        own = self.agent_id.bool()  # (N receivers, N agents): the receiver's own option
        age = obs["age"][:, None].expand(-1, n, -1, -1)  # every critic sees all ages before the options
        variants = []
        for option in (0, 1):
            # row i: everyone's options with agent i's own replaced by `option`, (B, N, N)
            variant = th.where(own, option, broadcast[:, None, :].expand(-1, n, -1)).to(obs["held"].dtype)
            held = hold(obs["held"][:, None], obs["message"][:, None], variant)
            variants.append(self._centralised_features(obs, held, age))
        return th.stack(variants, dim=1)

    def critic_inputs(self, obs: PyTorchObs, broadcast: th.Tensor | None = None) -> th.Tensor:
        """Inputs of the critic network for what :attr:`option_critic` reads (its ``reads_afterstate``).

        :param obs: joint observation (B, N, ...) from before the options
        :param broadcast: this step's options (B, N); needed by a critic that reads the
            afterstates, unused otherwise
        :return: :meth:`afterstate_features` (B, 2, N, features) for a critic that reads the
            afterstates, else :meth:`critic_features` (B, N, features)
        :raises ValueError: if the critic reads the afterstates and ``broadcast`` is None
        """
        if not self.option_critic.reads_afterstate:
            return self.critic_features(obs)
        if broadcast is None:
            raise ValueError(f"The {self.critic} critic reads this step's options (broadcast).")
        return self.afterstate_features(obs, broadcast)

    def _centralised_features(self, obs: PyTorchObs, held: th.Tensor, age: th.Tensor) -> th.Tensor:
        """Critic inputs from what every agent's critic sees of everyone's held broadcasts.

        :param obs: joint observation (B, N, ...)
        :param held: row ``i`` holds all agents' held broadcasts seen by agent ``i``'s critic, (B, N, N, n_msg)
        :param age: their ages, (B, N, N, 1)
        :return: (B, N, n_local + N (n_msg + 1) + (N - 1) n_msg)
        """
        views = relative_to_receivers(held, obs["message"]).flatten(2)
        true = relative_views(obs["message"], obs["message"], self.others).flatten(2)
        return th.cat([obs["local"], views, age[..., 0] * self.age_scale, true], dim=-1)

    def broadcast_probabilities(self, obs: PyTorchObs) -> th.Tensor:
        """Every agent's probability of broadcasting under ``mu`` (draws nothing; only ``mu`` runs).

        :param obs: joint observation (B, N, ...)
        :return: probabilities of broadcasting (B, N)
        """
        return broadcast_probability(self.mu_logits(self.option_features(obs), obs["age"]))

    def imitate_options(
        self,
        obs: PyTorchObs,
        options: th.Tensor,
        gradient_steps: int = 500,
        batch_size: int = 256,
        learning_rate: float = 1e-3,
    ) -> float:
        """Fit ``mu`` to given options by cross-entropy (behaviour cloning), e.g. to start it as a fixed trigger.

        Only ``mu``'s parameters change (Adam of its own, which leaves the other networks'
        parameters where they get no gradient); the training optimizer's state is not touched.

        :param obs: joint observations (B, N, ...)
        :param options: the options to imitate (B, N), 0 or 1
        :param gradient_steps: Adam steps, each on ``batch_size`` samples drawn at random
        :param batch_size: samples per gradient step
        :param learning_rate: Adam's step size
        :return: the share of agent decisions whose most likely option equals the given one afterwards
        :raises ValueError: for options whose shape differs from the observations' (B, N)
        """
        features = self.option_features(obs).detach()
        age = obs["age"]
        targets = th.as_tensor(options, device=features.device).long()
        if targets.shape != features.shape[:2]:
            raise ValueError(
                f"options must be shaped (B, N) = {tuple(features.shape[:2])}, got {tuple(targets.shape)}."
            )
        optimizer = th.optim.Adam(self.chains.parameters(), lr=learning_rate)
        training = self.training
        self.set_training_mode(True)
        for _ in range(gradient_steps):
            idx = th.randint(len(targets), (min(batch_size, len(targets)),), device=features.device)
            logits = self.mu_logits(features[idx], age[idx])
            loss = F.cross_entropy(logits.reshape(-1, 2), targets[idx].reshape(-1))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        self.set_training_mode(training)
        with th.no_grad():
            mode = self._sample_options(self.mu_logits(features, age), True)
        return float((mode == targets).float().mean())

    def option_values(
        self, q: th.Tensor, broadcast_price: th.Tensor | None = None, p_broadcast: th.Tensor | None = None
    ) -> th.Tensor:
        """Both options' values from the critic's outputs: :meth:`.OptionCritic.option_values` of :attr:`option_critic`.

        :param q: outputs of the critic network
        :param broadcast_price: what a broadcast costs agent ``i`` in the learner's reward units (B, N);
            read by critics that add it analytically (None: zero)
        :param p_broadcast: probability of broadcasting ``p_i`` with which the options were
            drawn (B, N); needed by the centred critic only
        :return: ``Q_i(s, o)``, (B, N, 2)
        """
        return self.option_critic.option_values(q, broadcast_price, p_broadcast)

    def training_inputs(self, obs: PyTorchObs, broadcast: th.Tensor) -> list[ChainInput]:
        """Stacked inputs of all networks for stored observations and options (no parameters involved).

        :param obs: joint observations (B, N, ...) from before the options
        :param broadcast: stored options (B, N)
        :return: the inputs of ``mu``, ``q`` and ``pi`` arranged for the batched chains, one
            :class:`~sb3_detc.mappoc.batched.ChainInput` per run of networks (see
            :meth:`~sb3_detc.mappoc.batched.AgentBatchedNetworks.stack`)
        """
        return self.chains.stack(
            {
                "mu": self.option_features(obs),
                "q": self.critic_inputs(obs, broadcast),
                "pi": self.control_features(obs, broadcast),
            }
        )

    # ------------------------------------------------------------------ acting
    def forward(
        self,
        obs: PyTorchObs,
        deterministic: bool = False,
        broadcast: th.Tensor | None = None,
        action_noise_std: float = 0.0,
        sample_options: bool | None = None,
        broadcast_price: th.Tensor | None = None,
    ) -> HybridAction:
        """Sample all options, deliver the broadcasts, then sample all controls (same-step delivery).

        :param obs: joint observation (B, N, ...)
        :param deterministic: mean of ``pi`` instead of samples, and the most likely options
            unless ``sample_options`` says otherwise
        :param broadcast: broadcast decisions to use instead of sampling them from ``mu`` (e.g. a baseline's)
        :param action_noise_std: standard deviation of extra Gaussian exploration noise added
            to the sampled controls (curriculum); log-probabilities refer to the noisy controls
        :param sample_options: options sampled from ``mu`` (True) or its mode (False) whatever
            ``deterministic`` says (None: the mode if ``deterministic``, else a sample)
        :param broadcast_price: cost of a broadcast in the learner's reward units (B, N), see
            :meth:`option_values`
        :return: the hybrid action with its log-probabilities and the option values
        """
        out, broadcast, control = self._sample(obs, deterministic, broadcast, action_noise_std, sample_options, True)
        log_std = self.log_std.expand(self.n_agents, -1)
        log_prob_broadcast = F.log_softmax(out["mu"], dim=-1).gather(-1, broadcast[..., None])[..., 0]
        return HybridAction(
            broadcast,
            control,
            log_prob_broadcast,
            gaussian_log_prob(control, out["pi"], log_std),
            self.option_values(out["q"], broadcast_price, broadcast_probability(out["mu"])),
        )

    def sample_actions(
        self,
        obs: PyTorchObs,
        action_noise_std: float = 0.0,
        broadcast: th.Tensor | None = None,
        deterministic: bool = False,
        sample_options: bool | None = None,
    ) -> tuple[th.Tensor, th.Tensor]:
        """The options and controls :meth:`forward` samples, without evaluating the critic.

        What a :class:`~sb3_detc.mappoc.workers.RolloutWorker` and an evaluation need: it
        draws the same random numbers as :meth:`forward`; the learner evaluates
        probabilities and values later.

        :param obs: joint observation (B, N, ...)
        :param action_noise_std: extra Gaussian noise on the controls (see :meth:`forward`)
        :param broadcast: broadcast decisions to use instead of sampling them (a fixed trigger)
        :param deterministic: mean of ``pi`` instead of samples, and the most likely options
            unless ``sample_options`` says otherwise
        :param sample_options: options sampled from ``mu`` (True) or its mode (False) whatever
            ``deterministic`` says (None: the mode if ``deterministic``, else a sample; unlike
            :meth:`predict`, the policy's own :attr:`sample_options` is not consulted)
        :return: options (B, N) and controls (B, N, m)
        """
        _, broadcast, control = self._sample(obs, deterministic, broadcast, action_noise_std, sample_options, False)
        return broadcast, control

    def _sample(
        self,
        obs: PyTorchObs,
        deterministic: bool,
        broadcast: th.Tensor | None,
        action_noise_std: float,
        sample_options: bool | None,
        with_critic: bool,
    ) -> tuple[dict[str, th.Tensor], th.Tensor, th.Tensor]:
        """Options, then the broadcasts delivered, then controls; with the networks' outputs.

        :param obs: joint observation (B, N, ...)
        :param deterministic: mean of ``pi`` instead of samples
        :param broadcast: broadcast decisions to use instead of sampling them (None: sample)
        :param action_noise_std: extra Gaussian noise on the controls
        :param sample_options: a sample (True) or the mode (False) of ``mu`` (None: the mode if
            ``deterministic``, else a sample)
        :param with_critic: whether to evaluate the critic too (output ``q``)
        :return: the outputs of ``mu`` (left out where ``broadcast`` is given and the critic is
            not needed), ``pi`` (and ``q``), the options, the controls
        """
        reads_afterstate = self.option_critic.reads_afterstate
        before = {"mu": self.option_features(obs)} if broadcast is None or with_critic else {}  # mu decides
        if with_critic and not reads_afterstate:
            before["q"] = self.critic_inputs(obs)
        out = self.chains.run(before) if before else {}
        if "mu" in out:
            out["mu"] = self.option_logits(out["mu"], obs["age"])
        if sample_options is None:
            sample_options = not deterministic
        if broadcast is None:
            broadcast = self._sample_options(out["mu"], not sample_options)
        broadcast = broadcast.long()
        after = {"pi": self.control_features(obs, broadcast)}
        if with_critic and reads_afterstate:
            after["q"] = self.critic_inputs(obs, broadcast)
        out.update(self.chains.run(after))
        mean = out["pi"]
        control = mean
        if not deterministic:
            control = mean + th.randn_like(mean) * self.log_std.expand(self.n_agents, -1).exp()
        if action_noise_std > 0:
            control = control + th.randn_like(mean) * action_noise_std
        return out, broadcast, control

    @staticmethod
    def _sample_options(logits: th.Tensor, deterministic: bool) -> th.Tensor:
        """Options from the logits of ``mu``: the mode, or a sample (B, N).

        :param logits: outputs of ``mu``, (B, N, 2): the logits of silent (0) and broadcast (1)
        :param deterministic: the most likely option instead of a sample
        :return: options (B, N), 1 for a broadcast
        """
        if deterministic:
            return logits.argmax(-1)
        p_broadcast = broadcast_probability(logits)
        return (th.rand_like(p_broadcast) < p_broadcast).long()

    def evaluate_actions(
        self,
        obs: PyTorchObs,
        broadcast: th.Tensor,
        control: th.Tensor,
        broadcast_price: th.Tensor | None = None,
        p_broadcast: th.Tensor | None = None,
    ) -> HybridEvaluation:
        """Evaluate stored hybrid actions with the current networks (one pass through all chains).

        :param obs: joint observations (B, N, ...) from before the options
        :param broadcast: stored options (B, N)
        :param control: stored controls (B, N, m)
        :param broadcast_price: cost of a broadcast in the learner's reward units (B, N), see :meth:`option_values`
        :param p_broadcast: probabilities of broadcasting with which ``broadcast`` was drawn (B, N),
            see :meth:`option_values` (None: those of the current ``mu``)
        :return: log-probabilities, broadcast entropy, option values and broadcast logits, as
            :class:`HybridEvaluation`
        """
        return self.evaluate_inputs(
            self.training_inputs(obs, broadcast), broadcast, control, broadcast_price, p_broadcast, obs["age"]
        )

    def evaluate_inputs(
        self,
        stacked: list[ChainInput],
        broadcast: th.Tensor,
        control: th.Tensor,
        broadcast_price: th.Tensor | None = None,
        p_broadcast: th.Tensor | None = None,
        age: th.Tensor | None = None,
    ) -> HybridEvaluation:
        """Like :meth:`evaluate_actions`, from inputs prepared by :meth:`training_inputs`.

        :param stacked: stacked inputs of the same samples as ``broadcast`` and ``control``
        :param broadcast: stored options (B, N)
        :param control: stored controls (B, N, m)
        :param broadcast_price: cost of a broadcast in the learner's reward units (B, N), see :meth:`option_values`
        :param p_broadcast: probabilities of broadcasting with which ``broadcast`` was drawn (B, N),
            see :meth:`option_values` (None: those of the current ``mu``)
        :param age: the agents' timers before the options (B, N, 1); needed with a :attr:`broadcast_interval` only
        :return: log-probabilities, broadcast entropy, option values and broadcast logits, as
            :class:`HybridEvaluation`
        """
        out = self.chains.evaluate(stacked)
        log_p = F.log_softmax(self.option_logits(out["mu"], age), dim=-1)
        log_prob_broadcast = log_p.gather(-1, broadcast.long()[..., None])[..., 0]
        entropy = -(log_p.exp() * log_p).sum(-1)
        log_std = self.log_std.expand(self.n_agents, -1)
        control_log_prob = gaussian_log_prob(control, out["pi"], log_std)
        if p_broadcast is None:
            p_broadcast = log_p[..., 1].exp().detach()
        option_values = self.option_values(out["q"], broadcast_price, p_broadcast)
        logit = log_p[..., 1] - log_p[..., 0]
        return HybridEvaluation(log_prob_broadcast, entropy, control_log_prob, option_values, logit)

    def state_values(
        self, obs: PyTorchObs, broadcast_price: th.Tensor | None = None, p_broadcast: th.Tensor | None = None
    ) -> th.Tensor:
        """Option-value critic averaged under the policy over options, ``V_i(s) = sum_o mu_i(o) Q_i(s, o)``.

        A critic that reads the afterstate takes the others' options from one sample of their policies.
        Under a fixed trigger's probabilities of broadcasting ``p`` instead of ``mu``'s:
        ``V_i(s) = p_i Q_i(s, 1) + (1 - p_i) Q_i(s, 0)``, the others' options sampled from ``p``.

        :param obs: joint observation (B, N, ...)
        :param broadcast_price: cost of a broadcast in the learner's reward units (B, N), see :meth:`option_values`
        :param p_broadcast: probabilities of broadcasting (B, N) to average under (None: ``mu``'s)
        :return: values (B, N)
        """
        reads_afterstate = self.option_critic.reads_afterstate
        before = {"mu": self.option_features(obs)}
        if not reads_afterstate:
            before["q"] = self.critic_inputs(obs)
        out = self.chains.run(before)
        out["mu"] = self.option_logits(out["mu"], obs["age"])
        if reads_afterstate:
            if p_broadcast is None:
                broadcast = self._sample_options(out["mu"], deterministic=False)
            else:
                broadcast = th.bernoulli(p_broadcast).long()
            out.update(self.chains.run({"q": self.critic_inputs(obs, broadcast)}))
        q = self.option_values(out["q"], broadcast_price, broadcast_probability(out["mu"]))
        if p_broadcast is None:
            return (F.softmax(out["mu"], dim=-1) * q).sum(-1)
        return (1 - p_broadcast) * q[..., 0] + p_broadcast * q[..., 1]

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        """Options and controls side by side, (B, N, 1 + m); :meth:`predict` returns them as a Dict.

        :param observation: joint observation (B, N, ...)
        :param deterministic: mean controls and the options as :attr:`sample_options` says (else
            samples of both)
        """
        sampled = options_sampled(self.sample_options, deterministic)
        broadcast, control = self.sample_actions(observation, deterministic=deterministic, sample_options=sampled)
        return th.cat([broadcast[..., None].to(control.dtype), control], dim=-1)

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[dict[str, np.ndarray] | list[dict[str, np.ndarray]], tuple[np.ndarray, ...] | None]:
        """Joint hybrid action(s) for joint observation(s).

        :param observation: one joint observation or a batch of them (from a VecEnv)
        :param state: unused (no recurrent state), returned as is
        :param episode_start: unused
        :param deterministic: mean of ``pi`` and the options as the trigger is deployed: the most
            likely ones (the mode of ``mu``), the same every call, or samples where
            :attr:`sample_options` is set; else samples of both
        :return: ``{"broadcast": (N,), "control": (N, m)}`` for one observation, or a list of
            such dicts, one per environment, for a batch (what a VecEnv's ``step`` takes);
            controls are clipped to the action bounds
        :raises ValueError: for the ``(obs, info)`` tuple of a Gymnasium env's ``reset``
        """
        if isinstance(observation, tuple) and len(observation) == 2 and isinstance(observation[1], dict):
            raise ValueError(
                "predict() got an (obs, info) tuple instead of an observation: you are probably mixing the "
                "Gymnasium API (`obs, info = env.reset()`) with the SB3 VecEnv API (`obs = vec_env.reset()`); "
                "pass `obs` alone."
            )
        self.set_training_mode(False)
        obs_tensor, vectorized = self.obs_to_tensor(observation)
        with th.no_grad():
            joint = self._predict(obs_tensor, deterministic=deterministic)
        broadcast = joint[..., 0].long().cpu().numpy()
        control = th.clamp(joint[..., 1:], self.control_low, self.control_high).cpu().numpy()
        actions = [{"broadcast": c, "control": u} for c, u in zip(broadcast, control, strict=True)]
        return (actions if vectorized else actions[0]), state

    def agent_controller(self, agent: int) -> AgentController:
        """Agent ``agent``'s policy over options and control policy as a small standalone controller.

        :param agent: index of the agent
        :return: a controller that needs only what the agent itself receives
        """
        if not 0 <= agent < self.n_agents:
            raise ValueError(f"agent must be in [0, {self.n_agents}), got {agent}.")
        group = 0 if self.share_parameters else agent
        return AgentController(
            option_net=self.chains.extract("mu", group),
            control_net=self.chains.extract("pi", group),
            log_std=self.log_std[group].detach().clone(),
            agent=agent,
            n_agents=self.n_agents,
            age_scale=self.age_scale,
            option_age_scale=self.option_age_scale,
            option_distance_scale=self.option_distance_scale,
            option_others_age_scale=self.option_others_age_scale,
            broadcast_interval=self.broadcast_interval,
            agent_id=self.agent_id[agent].clone() if self.share_parameters else None,
            control_low=self.control_low[agent].clone(),
            control_high=self.control_high[agent].clone(),
            sample_options=self.sample_options,
        )


class AgentController(nn.Module):
    """One agent's executable policies, fed only with what this agent receives.

    Decentralised execution in two phases per step: :meth:`decide` whether to broadcast
    (from the own trigger features), then, after the step's broadcasts were exchanged,
    :meth:`act` on the own local state and the others' held broadcasts relative to the own
    message, with their ages. The controller keeps no state.

    :param option_net: the agent's ``mu`` network (:func:`option_inputs` -> 2 logits)
    :param control_net: the agent's ``pi`` mean network
    :param log_std: log standard deviation of the control policy (m,)
    :param agent: index of the agent
    :param n_agents: number of agents N
    :param age_scale: factor applied to ages before they enter the network
    :param option_age_scale: factor applied to the own age before it enters ``mu`` (0: ``mu`` does not read it)
    :param option_distance_scale: factor applied to the distance of the trigger features from those at
        the own last broadcast before it enters ``mu`` (0: ``mu`` does not read it)
    :param option_others_age_scale: factor applied to the others' ages before they enter ``mu`` (0:
        ``mu`` does not read them)
    :param broadcast_interval: the policy's window of broadcast intervals, which decides the
        options outside it (None: ``mu`` decides at every step)
    :param agent_id: one-hot id input for shared-parameter policies, else None
    :param control_low: lower control bounds (m,)
    :param control_high: upper control bounds (m,)
    :param sample_options: how the trigger is meant to run when deployed, copied from the
        policy's ``sample_options`` (read by whoever runs the controller, e.g.
        :func:`~sb3_detc.mappoc.decentralised.run_decentralised_step`)
    """

    def __init__(
        self,
        option_net: nn.Module,
        control_net: nn.Module,
        log_std: th.Tensor,
        agent: int,
        n_agents: int,
        age_scale: float,
        agent_id: th.Tensor | None,
        control_low: th.Tensor,
        control_high: th.Tensor,
        sample_options: bool = False,
        option_age_scale: float = 0.0,
        option_distance_scale: float = 0.0,
        option_others_age_scale: float = 0.0,
        broadcast_interval: tuple[int, int] | None = None,
    ) -> None:
        super().__init__()
        self.sample_options = sample_options
        self.broadcast_interval = broadcast_interval
        self.option_age_scale = option_age_scale
        self.option_distance_scale = option_distance_scale
        self.option_others_age_scale = option_others_age_scale
        self.option_net = option_net
        self.control_net = control_net
        self.agent = agent
        self.n_agents = n_agents
        self.age_scale = age_scale
        self.register_buffer("log_std", log_std)
        self.register_buffer("agent_id", agent_id if agent_id is not None else th.zeros(0))
        self.register_buffer("control_low", control_low)
        self.register_buffer("control_high", control_high)

    def _with_id(self, x: th.Tensor) -> th.Tensor:
        """A network input with the one-hot agent id appended (shared parameters; else as it is).

        :param x: the agent's features, 1-D
        :return: the network's input, 1-D
        """
        return th.cat([x, self.agent_id.to(x.dtype)])

    @th.no_grad()
    def decide(
        self,
        trigger: np.ndarray,
        trigger_held: np.ndarray,
        deterministic: bool = True,
        own_age: float | None = None,
        others_age: np.ndarray | None = None,
    ) -> bool:
        """Whether to broadcast now.

        :param trigger: own trigger features now (n_trig,)
        :param trigger_held: own trigger features at the own last broadcast (n_trig,)
        :param deterministic: the most likely option instead of a sample
        :param own_age: steps since the own last broadcast, before this step's decision; needed
            where the controller reads it (``option_age_scale`` > 0 or a ``broadcast_interval``)
        :param others_age: the ages of the others' held broadcasts before this step's exchange, others
            in increasing order (N - 1,); needed where the controller reads them (``option_others_age_scale`` > 0)
        :return: True to broadcast, False to stay silent
        :raises ValueError: without ``own_age`` or ``others_age`` where the controller reads it
        """
        if own_age is None:
            if self.option_age_scale > 0 or self.broadcast_interval is not None:
                raise ValueError(
                    "This controller reads its own age (option_age_scale > 0 or a broadcast_interval): pass own_age."
                )
            own_age = 0.0
        if others_age is None:
            if self.option_others_age_scale > 0:
                raise ValueError(
                    "This controller reads the others' ages (option_others_age_scale > 0): pass others_age."
                )
        x = option_inputs(
            th.as_tensor(trigger, dtype=th.float32),
            th.as_tensor(trigger_held, dtype=th.float32),
            th.tensor([own_age], dtype=th.float32),
            self.option_age_scale,
            self.option_distance_scale,
            None if others_age is None else th.as_tensor(others_age, dtype=th.float32),
            self.option_others_age_scale,
        )
        logits = self.option_net(self._with_id(x))
        if self.broadcast_interval is not None:
            logits = pin_options(logits, *interval_window(th.tensor([own_age]), *self.broadcast_interval))
        if deterministic:
            return bool(logits.argmax() == 1)
        return bool(th.distributions.Categorical(logits=logits).sample() == 1)

    @th.no_grad()
    def act(
        self, local: np.ndarray, neighbours: np.ndarray, neighbour_age: np.ndarray, deterministic: bool = True
    ) -> np.ndarray:
        """Control from the own state and the others' held broadcasts after this step's exchange.

        :param local: own local state (n_local,)
        :param neighbours: the others' held broadcasts minus the own current message (N - 1, n_msg)
        :param neighbour_age: the others' ages of information in steps (N - 1,)
        :param deterministic: the mean control instead of a sample
        :return: control (m,), clipped to the bounds
        """
        x = np.concatenate([local, np.ravel(neighbours), np.asarray(neighbour_age) * self.age_scale])
        mean = self.control_net(self._with_id(th.as_tensor(x, dtype=th.float32)))
        control = mean if deterministic else mean + th.randn_like(mean) * self.log_std.exp()
        return th.clamp(control, self.control_low, self.control_high).numpy()


def check_joint_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> tuple[int, int]:
    """Check that the spaces are those of a joint event-triggered env.

    :param observation_space: observation space to check
    :param action_space: action space to check
    :return: number of agents N and control dimension m
    :raises ValueError: naming what does not fit
    """
    hint = "use an env from sb3_detc (e.g. 'sb3_detc/LinearETC-v0') or wrap a system in JointEnv"
    if not isinstance(observation_space, spaces.Dict) or set(observation_space.spaces) != set(JOINT_KEYS):
        keys = sorted(observation_space.spaces) if isinstance(observation_space, spaces.Dict) else observation_space
        raise ValueError(f"expected a Dict observation space with keys {sorted(JOINT_KEYS)}, got {keys}; {hint}.")
    if (
        not isinstance(action_space, spaces.Dict)
        or set(action_space.spaces) != {"broadcast", "control"}
        or not isinstance(action_space["broadcast"], spaces.MultiDiscrete)
        or not isinstance(action_space["control"], spaces.Box)
    ):
        raise ValueError(
            "expected a Dict action space with 'broadcast' (MultiDiscrete) and 'control' (Box), "
            f"got {action_space}; {hint}."
        )
    n_agents = len(action_space["broadcast"].nvec)
    if not np.all(action_space["broadcast"].nvec == 2):
        raise ValueError(f"'broadcast' must be MultiDiscrete([2] * N), got nvec {action_space['broadcast'].nvec}.")
    control = action_space["control"]
    if control.shape[0] != n_agents or len(control.shape) != 2:
        raise ValueError(f"'control' must have shape (N={n_agents}, m), got {control.shape}.")
    for key, space in observation_space.spaces.items():
        if not isinstance(space, spaces.Box) or len(space.shape) != 2 or space.shape[0] != n_agents:
            raise ValueError(f"observation '{key}' must be a Box of shape (N={n_agents}, features), got {space}.")
    if observation_space["age"].shape[1] != 1:
        raise ValueError(f"observation 'age' must have shape (N, 1), got {observation_space['age'].shape}.")
    return n_agents, control.shape[1]
