"""Communicating multi-agent systems and the event-triggered network around them."""

from sb3_detc.envs.system import CommunicatingSystem, SystemObs
from sb3_detc.envs.wrappers import EventTriggeredNetwork, JointEnv

__all__ = ["CommunicatingSystem", "EventTriggeredNetwork", "JointEnv", "SystemObs"]
