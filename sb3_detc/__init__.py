"""sb3-detc: learned distributed event-triggered communication and control for Stable-Baselines3.

Importing the package registers the Gymnasium ids ``sb3_detc/MultiwalkerETC-v0`` and
``sb3_detc/LinearETC-v0`` (joint views of the event-triggered environments), and
``sb3_detc/LinearETC-LQR-v0`` (the linear agents with LQR on held broadcasts as their
controller: only when to communicate is learned).

Worker processes (SB3's ``SubprocVecEnv``) need the ids too. SB3 starts them with the
``forkserver`` method where it exists (Linux, macOS), and importing the package adds it to
the modules the fork server imports (``multiprocessing.set_forkserver_preload``; a list set
before is kept), so workers know the ids even if the main module imports the package only
inside a function. Limits: a fork server started before the package was imported keeps
what it had (import ``sb3_detc`` before the first worker process starts), and a preload
list set after the import replaces this one (include ``"sb3_detc"`` in it). With the
``spawn`` method (Windows, or ``start_method="spawn"``) workers import only the main
module, so they know the ids if a script imports ``sb3_detc`` at its top level; elsewhere
(``python -c``, notebooks) name the env ``"sb3_detc:sb3_detc/LinearETC-v0"``, which makes
Gymnasium import the package first.
"""

import multiprocessing

import gymnasium

__version__ = "0.2.0"

_ENV_IDS = {
    "sb3_detc/MultiwalkerETC-v0": "sb3_detc.envs.multiwalker_etc_v0:joint_env",
    "sb3_detc/LinearETC-v0": "sb3_detc.envs.linear_etc_v0:joint_env",
    "sb3_detc/LinearETC-LQR-v0": "sb3_detc.envs.linear_etc_v0:lqr_joint_env",
}
for _env_id, _entry_point in _ENV_IDS.items():
    if _env_id not in gymnasium.registry:
        gymnasium.register(id=_env_id, entry_point=_entry_point)


def _preload_in_forkserver() -> None:
    """Add the package to the modules that the fork server imports, keeping the ones set before."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return
    from multiprocessing import forkserver

    # The preload list has no getter: read the fork server's (its default is ["__main__"]).
    preload = list(getattr(forkserver._forkserver, "_preload_modules", ["__main__"]))
    if __name__ not in preload:
        multiprocessing.set_forkserver_preload([*preload, __name__])


_preload_in_forkserver()

from sb3_detc.mappoc import MAPPOC, MlpHybridPolicy  # noqa: E402  (after the env ids are registered)

__all__ = ["MAPPOC", "MlpHybridPolicy", "__version__"]
