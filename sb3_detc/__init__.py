"""sb3-detc: learned distributed event-triggered communication and control for Stable-Baselines3.

Importing the package registers the Gymnasium ids ``sb3_detc/MultiwalkerETC-v0`` and
``sb3_detc/LinearETC-v0`` (joint views of the event-triggered environments), and
``sb3_detc/LinearETC-LQR-v0`` (the linear agents with LQR on held broadcasts as their
controller: only when to communicate is learned).
"""

import gymnasium

__version__ = "0.1.0"

_ENV_IDS = {
    "sb3_detc/MultiwalkerETC-v0": "sb3_detc.envs.multiwalker_etc_v0:joint_env",
    "sb3_detc/LinearETC-v0": "sb3_detc.envs.linear_etc_v0:joint_env",
    "sb3_detc/LinearETC-LQR-v0": "sb3_detc.envs.linear_etc_v0:lqr_joint_env",
}
for _env_id, _entry_point in _ENV_IDS.items():
    if _env_id not in gymnasium.registry:
        gymnasium.register(id=_env_id, entry_point=_entry_point)

from sb3_detc.mappoc import MAPPOC, MlpHybridPolicy  # noqa: E402  (after the env ids are registered)

__all__ = ["MAPPOC", "MlpHybridPolicy", "__version__"]
