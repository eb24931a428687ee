"""The paper's modified Multiwalker behind the event-triggered network.

``parallel_env(**kwargs)`` returns the PettingZoo view, ``joint_env(**kwargs)`` the joint
Gymnasium view registered as ``sb3_detc/MultiwalkerETC-v0``.
"""

from __future__ import annotations

from sb3_detc.envs.multiwalker import MultiwalkerSystem
from sb3_detc.envs.wrappers import EventTriggeredNetwork, JointEnv
from sb3_detc.renamed import renamed_keys


def parallel_env(broadcast_cost: float = 0.25, trigger: str = "default", **kwargs) -> EventTriggeredNetwork:
    """PettingZoo parallel env of walkers that communicate through the event-triggered network.

    :param broadcast_cost: reward cost of one broadcast (0.25 environment reward units, as in the paper)
    :param trigger: features of the policy over options (see :class:`EventTriggeredNetwork`);
        the default is the package information (dx, dy, angle) now and at the last broadcast
    :param kwargs: keyword arguments of :class:`~sb3_detc.envs.multiwalker.MultiwalkerSystem`
    :return: an :class:`EventTriggeredNetwork` around a :class:`~sb3_detc.envs.multiwalker.MultiwalkerSystem`
    """
    return EventTriggeredNetwork(MultiwalkerSystem(**kwargs), broadcast_cost=broadcast_cost, trigger=trigger)


def joint_env(**kwargs) -> JointEnv:
    """Joint Gymnasium view (agent axis inside the arrays); keywords as :func:`parallel_env`.

    Also under their earlier names (``comm_cost``), as saved run configurations have them.

    :param kwargs: keyword arguments of :func:`parallel_env` (earlier names mapped to the current
        ones by :func:`~sb3_detc.renamed.renamed_keys`): ``broadcast_cost`` and ``trigger`` for
        the :class:`EventTriggeredNetwork`, everything else for
        :class:`~sb3_detc.envs.multiwalker.MultiwalkerSystem`
    :return: a :class:`JointEnv` around the network of :func:`parallel_env`
    """
    return JointEnv(parallel_env(**renamed_keys(kwargs)))
