"""Coupled linear agents behind the event-triggered network.

``parallel_env(**kwargs)`` returns the PettingZoo view, ``joint_env(**kwargs)`` the joint
Gymnasium view registered as ``sb3_detc/LinearETC-v0``, and ``lqr_joint_env(**kwargs)`` the
joint view whose controls are LQR on held broadcasts, registered as ``sb3_detc/LinearETC-LQR-v0``.
"""

from __future__ import annotations

import gymnasium as gym

from sb3_detc.envs.linear import LinearSystem
from sb3_detc.envs.wrappers import EventTriggeredNetwork, JointEnv
from sb3_detc.renamed import renamed_keys


def parallel_env(broadcast_cost: float = 0.01, trigger: str = "default", **kwargs) -> EventTriggeredNetwork:
    """PettingZoo parallel env of linear agents that communicate through the event-triggered network.

    :param broadcast_cost: reward cost of one broadcast (default 0.01: about what one broadcast is
        worth to the team's quadratic cost when send-on-delta with the LQR controller keeps
        70 to 85 % savings on the default system, so that the trade-off matters)
    :param trigger: features of the policy over options (see :class:`EventTriggeredNetwork`);
        the default is the own state (position error and velocity)
    :param kwargs: keyword arguments of :class:`~sb3_detc.envs.linear.LinearSystem`
    :return: an :class:`EventTriggeredNetwork` around a :class:`~sb3_detc.envs.linear.LinearSystem`
    """
    return EventTriggeredNetwork(LinearSystem(**kwargs), broadcast_cost=broadcast_cost, trigger=trigger)


def joint_env(**kwargs) -> JointEnv:
    """Joint Gymnasium view (agent axis inside the arrays); keywords as :func:`parallel_env`.

    Also under their earlier names (``comm_cost``), as saved run configurations have them.

    :param kwargs: keyword arguments of :func:`parallel_env` (earlier names mapped to the current
        ones by :func:`~sb3_detc.renamed.renamed_keys`): ``broadcast_cost`` and ``trigger`` for
        the :class:`EventTriggeredNetwork`, everything else for
        :class:`~sb3_detc.envs.linear.LinearSystem`
    :return: a :class:`JointEnv` around the network of :func:`parallel_env`
    """
    return JointEnv(parallel_env(**renamed_keys(kwargs)))


def lqr_joint_env(prediction: bool = False, predicted_held: bool = False, **kwargs) -> gym.Env:
    """Joint view in which every agent's control is its row of the LQR gain on its view of held broadcasts.

    Only *when* to communicate is left to learn (the classic event-triggered setting, in
    which send-on-delta is the reference); the action's ``control`` entry is ignored (see
    :class:`~sb3_detc.triggers.FixedControl`). Keywords as :func:`parallel_env`.

    :param prediction: act on the receivers' predictions of the held states instead
        (:func:`~sb3_detc.triggers.lqr_on_predicted_states`, the controller of predictive
        triggering) rather than on the held states themselves
    :param predicted_held: with ``prediction``, show the receivers' prediction of every agent's
        state as what they hold of it (``held`` and ``trigger_held``,
        :class:`~sb3_detc.triggers.ReceiverPredictions`), so that a learned trigger reads the
        prediction error that predictive triggering triggers on, and a critic the belief itself
    :param kwargs: keyword arguments of :func:`joint_env`, which passes them on to
        :func:`parallel_env` (``broadcast_cost`` and ``trigger`` for the
        :class:`EventTriggeredNetwork`, everything else for
        :class:`~sb3_detc.envs.linear.LinearSystem`; earlier names accepted)
    :return: a :class:`~sb3_detc.triggers.FixedControl` around the env of :func:`joint_env`, its
        controls from :func:`~sb3_detc.triggers.lqr_on_held_states` (or ``lqr_on_predicted_states``),
        inside a :class:`~sb3_detc.triggers.ReceiverPredictions` with ``predicted_held``
    :raises ValueError: if ``predicted_held`` is asked for without ``prediction``
    """
    from sb3_detc import triggers  # builds on the envs

    if predicted_held and not prediction:
        raise ValueError("predicted_held=True needs prediction=True: the receivers predict only with it.")
    joint = joint_env(**kwargs)
    env = triggers.FixedControl(joint, "lqr_on_predicted_states" if prediction else "lqr_on_held_states")
    return triggers.ReceiverPredictions(env) if predicted_held else env
