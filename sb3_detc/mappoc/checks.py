"""Checks of MAPPOC's settings and environments, before anything is built: one clear line per mistake."""

from __future__ import annotations

import numbers
from collections.abc import Callable, Sequence
from typing import Any

from gymnasium import spaces
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.vec_env import VecEnv, unwrap_vec_normalize

from sb3_detc.mappoc.critics import CRITICS, OptionCritic
from sb3_detc.mappoc.losses import BROADCAST_ADVANTAGES
from sb3_detc.mappoc.replays import REPLAY_CHOICES
from sb3_detc.mappoc.rewards import PRICE_RULES
from sb3_detc.validation import is_integer

#: Observation keys that the policy turns into the network's state with the broadcast rule (the
#: message copied into ``held``, ``age`` reset to 0) or that feed the policy over options: a
#: ``VecNormalize`` must pass them on as the environment returns them.
NETWORK_KEYS = ("message", "held", "age", "trigger", "trigger_held")


def check_same_agents(env: GymEnv, n_agents: int) -> None:
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
    "n_steps": (lambda v: is_integer(v, 1), "a positive integer"),
    "batch_size": (lambda v: is_integer(v, 1), "a positive integer"),
    "n_epochs": (lambda v: is_integer(v, 1), "a positive integer"),
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
    "broadcast_price_lr": (lambda v: v > 0, "> 0"),
    "broadcast_advantage": (lambda v: v in BROADCAST_ADVANTAGES, " or ".join(map(repr, BROADCAST_ADVANTAGES))),
    "replay_share": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "replay_choice": (lambda v: v in REPLAY_CHOICES, " or ".join(map(repr, REPLAY_CHOICES))),
    "replay_horizon": (lambda v: is_integer(v, 1), "a positive integer"),
    "replay_temperature": (lambda v: v > 0, "> 0"),
}


def check_hyperparameters(**values: Any) -> None:
    """Check the values of MAPPOC's hyperparameters (before anything is built).

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


def check_vec_normalize(env: GymEnv | None) -> None:
    """Apply :func:`check_observation_normalization` to a ``VecNormalize`` anywhere in ``env``'s vector wrappers.

    :param env: the training env (only a vector env can have a ``VecNormalize``), or None
    :raises ValueError: if the ``VecNormalize`` normalises one of :data:`NETWORK_KEYS`
    """
    vec_normalize = unwrap_vec_normalize(env) if isinstance(env, VecEnv) else None
    if vec_normalize is not None:
        check_observation_normalization(vec_normalize.norm_obs, vec_normalize.norm_obs_keys)


def check_rate_target(target_savings: float | None, fixed_trigger: Any, price_rule: str = "dual") -> None:
    """Check a rate target of the policy over options (``target_savings``) and the rule of its price.

    :param target_savings: the savings to settle at, or None
    :param fixed_trigger: the fixed trigger given with it, or None
    :param price_rule: how the price follows the target, a key of :data:`~sb3_detc.mappoc.rewards.PRICE_RULES`
    :raises ValueError: for an unknown price rule, a target outside (0, 1), or one with a fixed trigger
    """
    _check_price_rule_name(price_rule)
    if target_savings is None:
        return
    if isinstance(target_savings, bool) or not isinstance(target_savings, numbers.Real) or not 0 < target_savings < 1:
        raise ValueError(
            f"target_savings must be a number in (0, 1) (the share of silent steps), got {target_savings!r}."
        )
    if fixed_trigger is not None:
        raise ValueError(
            "target_savings sets the rate of the policy over options, but a fixed trigger takes the options instead; "
            "give one of target_savings and fixed_trigger."
        )


def _check_price_rule_name(price_rule: Any) -> None:
    """Refuse a price rule that is not a key of :data:`~sb3_detc.mappoc.rewards.PRICE_RULES`, with one line.

    :param price_rule: the rule's name
    :raises ValueError: if it is not one of the rules' names
    """
    if not isinstance(price_rule, str) or price_rule not in PRICE_RULES:
        raise ValueError(f"broadcast_price_rule must be one of {sorted(PRICE_RULES)}, got {price_rule!r}.")


def check_price_rule(price_rule: str, target_savings: float | None, critic: OptionCritic) -> None:
    """Check that the critic gives what the rate target's price rule needs.

    :param price_rule: a key of :data:`~sb3_detc.mappoc.rewards.PRICE_RULES`
    :param target_savings: the savings to settle at, or None (then no rule runs)
    :param critic: the policy's option critic
    :raises ValueError: for an unknown rule, or one that needs option values that take the price
        analytically with a critic that learns the price from the rewards
    """
    _check_price_rule_name(price_rule)
    if target_savings is not None and PRICE_RULES[price_rule].needs_price and not critic.needs_price:
        raise ValueError(
            f"broadcast_price_rule={price_rule!r} needs a critic that adds the price of a broadcast to its option "
            f"values; the {critic.name!r} critic learns it from the rewards: use another critic or the 'dual' rule."
        )


def check_n_envs(env: Any, n_envs: int | None) -> None:
    """Check MAPPOC's ``n_envs``: the number of envs it builds from an env id.

    :param env: the env given to MAPPOC
    :param n_envs: the number of envs, or None
    :raises ValueError: for ``n_envs`` with an env that is not an id, or one that is not a positive integer
    """
    if n_envs is None:
        return
    if not isinstance(env, str):
        raise ValueError("n_envs is the number of envs MAPPOC builds from an env id; pass an env id, not an env.")
    if not is_integer(n_envs, 1):
        raise ValueError(f"n_envs must be a positive integer, got {n_envs!r}.")


def check_fixed_trigger(trigger: Any, critic: str) -> None:
    """Check a fixed trigger for MAPPOC's ``set_fixed_trigger``.

    :param trigger: the trigger, or None
    :param critic: the name of the policy's critic (a key of :data:`~sb3_detc.mappoc.critics.CRITICS`)
    :raises ValueError: for a trigger that is not callable, or with a critic that needs the probabilities
        with which ``mu`` drew the options
    """
    if trigger is None:
        return
    if not callable(trigger):
        raise ValueError(f"a fixed trigger must be callable (joint observations -> options), got {trigger!r}.")
    if CRITICS[critic].needs_draw_probabilities:
        usable = " or ".join(repr(name) for name, kind in CRITICS.items() if not kind.needs_draw_probabilities)
        raise ValueError(
            f"critic={critic!r} needs the probabilities with which the options were drawn, which a fixed trigger "
            f"does not give; use critic={usable} with a fixed trigger."
        )
