"""MAPPOC: multi-agent PPO option-critic with learned event-triggered communication."""

from sb3_detc.mappoc.buffers import HybridRolloutBuffer
from sb3_detc.mappoc.decentralised import Inbox, run_decentralised_step
from sb3_detc.mappoc.mappoc import MAPPOC
from sb3_detc.mappoc.policies import AgentController, MlpHybridPolicy

__all__ = [
    "MAPPOC",
    "AgentController",
    "HybridRolloutBuffer",
    "Inbox",
    "MlpHybridPolicy",
    "run_decentralised_step",
]
