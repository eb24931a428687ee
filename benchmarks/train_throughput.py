"""Training throughput: MAPPOC on the paper's Multiwalker against SB3 PPO with SuperSuit.

Both algorithms train on the same machine in the same run, alternating, with 2 worker
processes (``SubprocVecEnv``) each:

* **MAPPOC** on ``sb3_detc/MultiwalkerETC-v0`` with the paper's hyperparameters: 2048
  environment steps per iteration (2 envs x 1024), minibatch 32, 10 epochs, three agents
  with their own networks (policy over options, control policy and option-value critic,
  3 x 96 tanh each);
* **PPO + SuperSuit**, the usual PettingZoo recipe: stock ``multiwalker_v9.parallel_env()``
  turned into a vector env of agents with ``pettingzoo_env_to_vec_env_v1`` and
  ``concat_vec_envs_v1(..., 2, num_cpus=2)``, one shared 64 x 64 policy, SB3's PPO with the
  recipe's ``learning_rate=1e-3, batch_size=256`` and SB3 defaults otherwise (2048 steps
  per vector env per iteration, 10 epochs).

Throughput is counted in *environment* steps (one step of all walkers): SB3's timestep
counter counts agent steps under SuperSuit, so it is divided by the number of walkers.
A callback splits the wall time into rollout collection and updates.
"""

from __future__ import annotations

import argparse
import platform
import time
from typing import Any

import numpy as np
import supersuit as ss
import torch as th
from pettingzoo.sisl import multiwalker_v9
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import SubprocVecEnv

from sb3_detc import MAPPOC

N_WALKERS = 3


class PhaseTimer(BaseCallback):
    """Accumulate wall time spent collecting rollouts and updating."""

    def __init__(self) -> None:
        super().__init__()
        self.rollout = 0.0
        self.update = 0.0
        self._mark = 0.0

    def _on_training_start(self) -> None:
        self._mark = time.perf_counter()

    def _on_rollout_start(self) -> None:
        now = time.perf_counter()
        self.update += now - self._mark
        self._mark = now

    def _on_rollout_end(self) -> None:
        now = time.perf_counter()
        self.rollout += now - self._mark
        self._mark = now

    def _on_training_end(self) -> None:
        self.update += time.perf_counter() - self._mark

    def _on_step(self) -> bool:
        return True


def make_mappoc(seed: int) -> BaseAlgorithm:
    env = make_vec_env("sb3_detc/MultiwalkerETC-v0", n_envs=2, seed=seed, vec_env_cls=SubprocVecEnv)
    return MAPPOC("MlpHybridPolicy", env, n_steps=1024, seed=seed)


def make_ppo_supersuit(seed: int) -> BaseAlgorithm:
    env = ss.pettingzoo_env_to_vec_env_v1(multiwalker_v9.parallel_env())
    env = ss.concat_vec_envs_v1(env, 2, num_cpus=2, base_class="stable_baselines3")
    # SuperSuit's vector env cannot be seeded through SB3 (it has no seed()): seed the learner only.
    th.manual_seed(seed)
    return PPO("MlpPolicy", env, learning_rate=1e-3, batch_size=256)


def measure(name: str, model: BaseAlgorithm, iterations: int, agent_steps_per_env_step: int) -> dict[str, Any]:
    """Train for ``iterations`` rollouts and return throughput and time split."""
    per_iteration = model.n_steps * model.n_envs
    timer = PhaseTimer()
    start = time.perf_counter()
    model.learn(per_iteration * iterations, callback=timer)
    total = time.perf_counter() - start
    env_steps = model.num_timesteps / agent_steps_per_env_step
    model.get_env().close()
    return {
        "name": name,
        "env_steps": int(env_steps),
        "seconds": total,
        "steps_per_s": env_steps / total,
        "rollout_s": timer.rollout,
        "update_s": timer.update,
        "gradient_steps": model._n_updates,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=3, help="MAPPOC iterations (2048 env steps each)")
    parser.add_argument("--ppo-iterations", type=int, default=2, help="PPO iterations (4096 env steps each)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(1)

    results: dict[str, list[dict[str, Any]]] = {"MAPPOC": [], "PPO + SuperSuit": []}
    for repeat in range(args.repeats):
        seed = args.seed + repeat
        results["MAPPOC"].append(measure("MAPPOC", make_mappoc(seed), args.iterations, 1))
        results["PPO + SuperSuit"].append(
            measure("PPO + SuperSuit", make_ppo_supersuit(seed), args.ppo_iterations, N_WALKERS)
        )

    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if "model name" in line), "?")
    print(
        f"machine: {cpu}, {th.get_num_threads()} torch thread(s) in the learner, python {platform.python_version()}, "
        f"torch {th.__version__}"
    )
    print()
    print("| algorithm | env steps | seconds | env steps/s | rollout s | update s | updates logged by SB3 |")
    print("|---|---|---|---|---|---|---|")
    medians = {}
    for name, runs in results.items():
        for run in runs:
            print(
                f"| {name} | {run['env_steps']} | {run['seconds']:.1f} | {run['steps_per_s']:.0f} | "
                f"{run['rollout_s']:.1f} | {run['update_s']:.1f} | {run['gradient_steps']} |"
            )
        medians[name] = float(np.median([run["steps_per_s"] for run in runs]))
    ratio = medians["MAPPOC"] / medians["PPO + SuperSuit"]
    print()
    print(
        f"median env steps/s: MAPPOC {medians['MAPPOC']:.0f}, PPO + SuperSuit {medians['PPO + SuperSuit']:.0f}, "
        f"ratio {ratio:.2f}"
    )


if __name__ == "__main__":
    main()
