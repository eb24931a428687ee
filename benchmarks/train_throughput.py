"""Training throughput: MAPPOC on the paper's Multiwalker against SB3 PPO with SuperSuit.

Both algorithms train on the same machine in the same run, alternating, with 2 worker
processes (``SubprocVecEnv``) each:

* **MAPPOC, one-liner**: what a user gets from ``MAPPOC("MlpHybridPolicy",
  "sb3_detc/MultiwalkerETC-v0").learn(6_144_000)`` with every default (MAPPOC builds its
  rollout workers from the id and compiles for a run that long), timed over its first
  iterations; its warm-up is everything from the constructor to the end of the first
  iteration (worker start, compilation), with its parts in the JSON of ``--one``: the start
  (constructor and set-up), the first rollout (the workers compile their sampling) and the
  first update (the learner compiles its gradient step); with ``--baseline DIR`` also the
  one-liner of the package in another source tree (e.g. a git worktree of an earlier commit),
  alternating with this one's, to measure what a change costs;
* **MAPPOC** on ``sb3_detc/MultiwalkerETC-v0`` with the paper's hyperparameters: 2048
  environment steps per iteration (2 envs x 1024), minibatch 32, 10 epochs, three agents
  with their own networks (policy over options, control policy and option-value critic,
  3 x 96 tanh each), eager and with ``torch_compile=True``, with SB3's workers (the learner
  evaluates the policy and exchanges messages with the workers at every step) and with
  :class:`~sb3_detc.mappoc.workers.RolloutWorker` envs in the same 2 worker processes (each
  worker samples its whole rollout with a copy of the policy; one message per iteration),
  and for comparison also compiled with both envs in the learner's process (``DummyVecEnv``,
  no worker processes);
* **PPO + SuperSuit**, the usual PettingZoo recipe: stock ``multiwalker_v9.parallel_env()``
  turned into a vector env of agents with ``pettingzoo_env_to_vec_env_v1`` and
  ``concat_vec_envs_v1(..., 2, num_cpus=2)``, one shared 64 x 64 policy, SB3's PPO with the
  recipe's ``learning_rate=1e-3, batch_size=256`` and SB3 defaults otherwise (2048 steps
  per vector env per iteration, 10 epochs);
* **PPO + SuperSuit, equal gradient steps**: the same vector env, with MAPPOC's samples and
  gradient steps per update: 1024 steps per vector env (2048 environment steps, 6144 agent
  samples per iteration), minibatch 96 (32 per walker), 10 epochs, policy and value networks
  of 3 x 96 tanh each (SB3's PPO learning rate: it does not change the time).

Throughput is counted in *environment* steps (one step of all walkers): SB3's timestep
counter counts agent steps under SuperSuit, so it is divided by the number of walkers.
A callback splits the wall time into rollout collection and updates. For the floor of the
rollouts, the joint env alone is also stepped with pre-sampled random actions, with the same 2
worker processes and in-process. For the floor of the updates, the matrix products of one
gradient step alone are timed: for every layer of MAPPOC's agent-batched networks, the
forward product and the two of its backward pass on a minibatch of 32 (no activations,
optimizer or Python around them). Every model first
trains one untimed iteration (warm-up: worker start, compilation), reported separately.
Every measurement runs in a fresh Python process (SuperSuit is imported only by PPO's:
its module ``__getattr__`` raises ``ImportError`` for unknown names, which breaks
``torch.compile``'s cache-key pickling once worker processes have run).

    python benchmarks/train_throughput.py --only "MAPPOC, one-liner" "PPO + SuperSuit" --repeats 3 --iterations 4
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from pettingzoo.sisl import multiwalker_v9
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_detc import MAPPOC
from sb3_detc.mappoc.workers import RolloutWorker
from sb3_detc.study.sweep import check_at_least_one

N_WALKERS = 3


class PhaseTimer(BaseCallback):
    """Accumulate wall time spent collecting rollouts and updating, and count the updates.

    Every rollout is followed by one update (``train``), which starts when the rollout ends.
    """

    def __init__(self) -> None:
        super().__init__()
        self.rollout = 0.0
        self.update = 0.0
        self.updates = 0
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
        self.updates += 1
        self._mark = now

    def _on_training_end(self) -> None:
        self.update += time.perf_counter() - self._mark

    def _on_step(self) -> bool:
        return True


def make_mappoc(seed: int, torch_compile: bool, envs: str) -> BaseAlgorithm:
    """MAPPOC with the paper's settings; ``envs``: "workers", "rollout workers" or "in-process".

    :param seed: seed of the envs and the model
    :param torch_compile: compile the gradient step (MAPPOC's ``torch_compile``)
    :param envs: "workers": 2 envs in SB3's worker processes (``SubprocVecEnv``); "rollout workers": the
        same, each wrapped in :class:`~sb3_detc.mappoc.workers.RolloutWorker`; "in-process": both envs in
        the learner's process (``DummyVecEnv``)
    :return: the model, 2 envs x 1024 steps per iteration
    """
    vec_env_cls = DummyVecEnv if envs == "in-process" else SubprocVecEnv
    wrapper_class = RolloutWorker if envs == "rollout workers" else None
    env = make_vec_env(
        "sb3_detc/MultiwalkerETC-v0", n_envs=2, seed=seed, vec_env_cls=vec_env_cls, wrapper_class=wrapper_class
    )
    return MAPPOC("MlpHybridPolicy", env, n_steps=1024, seed=seed, torch_compile=torch_compile)


class IterationTimer(BaseCallback):
    """Note when every rollout starts and ends, and stop training when rollout ``stop_at`` starts.

    :param stop_at: number (from 0) of the rollout at whose start training stops
    """

    def __init__(self, stop_at: int) -> None:
        super().__init__()
        self.stop_at = stop_at
        self.starts: list[float] = []
        self.ends: list[float] = []

    def _on_rollout_start(self) -> None:
        self.starts.append(time.perf_counter())

    def _on_rollout_end(self) -> None:
        self.ends.append(time.perf_counter())

    def _on_step(self) -> bool:
        return len(self.starts) <= self.stop_at


def measure_one_liner(name: str, seed: int, iterations: int) -> dict[str, Any]:
    """The documented one-liner with the paper's budget, timed over ``iterations`` iterations after the first.

    :param name: the row's name (:data:`ONE_LINER`)
    :param seed: the model's seed
    :param iterations: timed iterations, after the first (the warm-up)
    :return: the warm-up and its parts in seconds, timed env steps, seconds, env steps/s, rollout and
        update seconds, epochs and ms per minibatch gradient step, the number of envs and the class
        of the gradient step (compiled or not)
    """
    start = time.perf_counter()
    model = MAPPOC("MlpHybridPolicy", "sb3_detc/MultiwalkerETC-v0", seed=seed)
    timer = IterationTimer(stop_at=iterations + 1)
    model.learn(PAPER_TIMESTEPS, callback=timer)
    model.get_env().close()
    timed = range(1, iterations + 1)
    seconds = timer.starts[iterations + 1] - timer.starts[1]
    rollout = sum(timer.ends[i] - timer.starts[i] for i in timed)
    gradient_steps = iterations * model.n_epochs * -(-model.n_steps * model.n_envs // model.batch_size)
    return {
        "name": name,
        "warm_up_s": timer.starts[1] - start,
        # the warm-up's parts: constructor and learn() set-up (workers start), the first rollout
        # (the workers compile their sampling), the first update (the learner compiles its step)
        "start_s": timer.starts[0] - start,
        "first_rollout_s": timer.ends[0] - timer.starts[0],
        "first_update_s": timer.starts[1] - timer.ends[0],
        "env_steps": iterations * model.n_steps * model.n_envs,
        "seconds": seconds,
        "steps_per_s": iterations * model.n_steps * model.n_envs / seconds,
        "rollout_s": rollout,
        "update_s": seconds - rollout,
        "epochs": iterations * model.n_epochs,
        "ms_per_gradient_step": 1e3 * (seconds - rollout) / gradient_steps,
        "n_envs": model.n_envs,
        "compiled": type(model.gradient_step).__name__,
    }


def make_ppo_supersuit(seed: int, equal_gradient_steps: bool) -> BaseAlgorithm:
    """PPO + SuperSuit: the usual recipe, or with MAPPOC's samples and gradient steps per update.

    :param seed: seed of PyTorch (the learner only: the SuperSuit vector env cannot be seeded through SB3)
    :param equal_gradient_steps: 1024 steps per vector env, minibatch 96 and 3 x 96 networks (MAPPOC's
        samples and gradient steps per update); False: the recipe's ``learning_rate=1e-3, batch_size=256``
    :return: the model, on 2 stock Multiwalker envs of 3 walkers as 6 vector envs of agents
    """
    import supersuit as ss

    env = ss.pettingzoo_env_to_vec_env_v1(multiwalker_v9.parallel_env())
    env = ss.concat_vec_envs_v1(env, 2, num_cpus=2, base_class="stable_baselines3")
    # SuperSuit's vector env cannot be seeded through SB3 (it has no seed()): seed the learner only.
    th.manual_seed(seed)
    if equal_gradient_steps:
        net_arch = dict(pi=[96, 96, 96], vf=[96, 96, 96])
        return PPO("MlpPolicy", env, n_steps=1024, batch_size=96, policy_kwargs=dict(net_arch=net_arch))
    return PPO("MlpPolicy", env, learning_rate=1e-3, batch_size=256)


def measure(name: str, model: BaseAlgorithm, iterations: int, agent_steps_per_env_step: int) -> dict[str, Any]:
    """Train one warm-up iteration, then ``iterations`` timed ones; return throughput and time split.

    :param name: the row's name
    :param model: the model to train (its env is closed afterwards)
    :param iterations: timed iterations
    :param agent_steps_per_env_step: the model's timesteps per environment step (the number of walkers
        under SuperSuit, which counts agent steps; 1 for MAPPOC)
    :return: the warm-up seconds, timed env steps, seconds, env steps/s, rollout and update seconds,
        epochs and ms per minibatch gradient step
    :raises ValueError: if the model may stop an update's epochs early (``target_kl``): its epochs are not counted
    """
    if model.target_kl is not None:
        raise ValueError(f"{name}: every update must run all its epochs (target_kl None), got {model.target_kl}")
    per_iteration = model.n_steps * model.n_envs
    start = time.perf_counter()
    model.learn(per_iteration)
    warm_up = time.perf_counter() - start
    minibatches = -(-model.n_steps * model.n_envs // model.batch_size)  # per epoch
    timer = PhaseTimer()
    start = time.perf_counter()
    model.learn(per_iteration * iterations, callback=timer, reset_num_timesteps=False)
    total = time.perf_counter() - start
    env_steps = (model.num_timesteps - per_iteration) / agent_steps_per_env_step
    model.get_env().close()
    return {
        "name": name,
        "warm_up_s": warm_up,
        "env_steps": int(env_steps),
        "seconds": total,
        "steps_per_s": env_steps / total,
        "rollout_s": timer.rollout,
        "update_s": timer.update,
        "epochs": timer.updates * model.n_epochs,
        "ms_per_gradient_step": 1e3 * timer.update / (timer.updates * model.n_epochs * minibatches),
    }


def env_only(name: str, workers: bool, vec_steps: int, seed: int) -> dict[str, Any]:
    """Environment steps per second of the joint env stepped with pre-sampled random actions (no learner).

    :param name: the row's name
    :param workers: 2 envs in worker processes (``SubprocVecEnv``); False: both in this process (``DummyVecEnv``)
    :param vec_steps: steps of the vector env (2 environment steps each)
    :param seed: seed of the envs and of the action sampling
    :return: env steps, seconds and env steps/s
    """
    vec_env_cls = SubprocVecEnv if workers else DummyVecEnv
    env = make_vec_env("sb3_detc/MultiwalkerETC-v0", n_envs=2, seed=seed, vec_env_cls=vec_env_cls)
    env.action_space.seed(seed)
    actions = [[env.action_space.sample() for _ in range(env.num_envs)] for _ in range(vec_steps)]
    env.reset()
    start = time.perf_counter()
    for action in actions:
        env.step(action)
    seconds = time.perf_counter() - start
    env.close()
    return {"name": name, "env_steps": vec_steps * 2, "seconds": seconds, "steps_per_s": vec_steps * 2 / seconds}


def matmul_floor(name: str, seed: int, repeats: int = 500) -> dict[str, Any]:
    """Seconds of the matrix products of one MAPPOC gradient step (paper settings), nothing else.

    Per layer with weights ``(groups, in, out)``: ``x @ W`` forward, ``g @ W^T`` and ``x^T @ g``
    backward, on ``(groups, 32, in)`` inputs; the best of ``repeats`` timings of all layers.

    :param name: the row's name
    :param seed: seed of PyTorch and of the MAPPOC model whose layer shapes are used
    :param repeats: timings of all layers; the fastest counts
    :return: ms per gradient step, GFLOP/s, and gradient steps per environment step (epochs / minibatch size)
    """
    th.manual_seed(seed)
    model = make_mappoc(seed, torch_compile=False, envs="in-process")
    batch = model.batch_size
    shapes = [tuple(weight.shape) for chain in model.policy.chains for weight in chain.weights]
    model.get_env().close()
    tensors = [(th.randn(g, batch, i), th.randn(g, i, o), th.randn(g, batch, o)) for g, i, o in shapes]
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for x, weight, grad in tensors:
            th.bmm(x, weight)
            th.bmm(grad, weight.transpose(1, 2))
            th.bmm(x.transpose(1, 2), grad)
        best = min(best, time.perf_counter() - start)
    flops = sum(3 * 2 * g * batch * i * o for g, i, o in shapes)
    gradient_steps_per_env_step = model.n_epochs / batch  # every sample is in one minibatch per epoch
    return {
        "name": name,
        "ms_per_gradient_step": 1e3 * best,
        "gflops": flops / best / 1e9,
        "gradient_steps_per_env_step": gradient_steps_per_env_step,
    }


ONE_LINER = "MAPPOC, one-liner"
#: The one-liner of the package in the source tree given with ``--baseline``.
BASELINE = "MAPPOC, one-liner, baseline"
#: The paper's budget: 3000 iterations of 2048 environment steps.
PAPER_TIMESTEPS = 6_144_000
MAPPOC_VARIANTS = {  # name -> (torch_compile, envs)
    "MAPPOC": (False, "workers"),
    "MAPPOC, compiled": (True, "workers"),
    "MAPPOC, compiled, in-process envs": (True, "in-process"),
    "MAPPOC, rollout workers": (False, "rollout workers"),
    "MAPPOC, compiled, rollout workers": (True, "rollout workers"),
    "MAPPOC, compiled, rollout workers, 2 threads": (True, "rollout workers"),
}
#: Variants whose learner runs 2 torch threads (the others 1): the second core is idle during updates.
TWO_THREADS = ("MAPPOC, compiled, rollout workers, 2 threads", "PPO + SuperSuit, 2 threads")
ENV_ONLY = {"joint env only, 2 worker processes": True, "joint env only, in-process": False}
MATMUL_FLOOR = "MAPPOC gradient step, matrix products only"
PPO_EQUAL = "PPO + SuperSuit, equal gradient steps"
#: PPO + SuperSuit variants: name -> with MAPPOC's samples and gradient steps per update
PPO_VARIANTS = {"PPO + SuperSuit": False, "PPO + SuperSuit, 2 threads": False, PPO_EQUAL: True}
ALGORITHMS = (ONE_LINER, *MAPPOC_VARIANTS, *PPO_VARIANTS, *ENV_ONLY, MATMUL_FLOOR)


def measure_one(name: str, seed: int, iterations: int, ppo_iterations: int) -> dict[str, Any]:
    """One measurement of ``name`` (one of :data:`ALGORITHMS`) in this process.

    :param name: the algorithm to measure
    :param seed: seed of the measurement
    :param iterations: timed iterations of MAPPOC and of equal-gradient-steps PPO (2048 env steps each);
        the env-only rows step 1024 x ``iterations`` times
    :param ppo_iterations: timed iterations of the PPO recipe (4096 env steps each)
    :return: the measurement (:func:`measure_one_liner`, :func:`measure`, :func:`env_only` or :func:`matmul_floor`)
    """
    if name == ONE_LINER:  # as a user runs it: PyTorch's default threads
        return measure_one_liner(name, seed, iterations)
    th.set_num_threads(2 if name in TWO_THREADS else 1)  # PPO: its faster setting on 2 cores
    if name in ENV_ONLY:
        return env_only(name, ENV_ONLY[name], 1024 * iterations, seed)
    if name == MATMUL_FLOOR:
        return matmul_floor(name, seed)
    if name in PPO_VARIANTS:
        # The equal-gradient-steps variant's iteration is MAPPOC's (2048 env steps): as many iterations.
        timed = iterations if PPO_VARIANTS[name] else ppo_iterations
        return measure(name, make_ppo_supersuit(seed, PPO_VARIANTS[name]), timed, N_WALKERS)
    return measure(name, make_mappoc(seed, *MAPPOC_VARIANTS[name]), iterations, 1)


def main() -> None:
    """Measure one algorithm in this process (``--one``, as JSON), or each in fresh processes and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--iterations", type=int, default=3, help="MAPPOC and equal-gradient-steps PPO iterations (2048 env steps each)"
    )
    parser.add_argument("--ppo-iterations", type=int, default=2, help="PPO recipe iterations (4096 env steps each)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--one", choices=ALGORITHMS, help="measure only this algorithm, in this process (JSON)")
    parser.add_argument("--only", nargs="+", choices=ALGORITHMS, help="measure only these (default: all)")
    parser.add_argument(
        "--baseline",
        type=Path,
        help="also measure the one-liner with this source tree's package and its own train_throughput.py (e.g. a "
        "git worktree of an earlier commit), right after this tree's in every repeat",
    )
    args = parser.parse_args()
    check_at_least_one(parser, args, "iterations", "ppo_iterations", "repeats")
    if args.baseline is not None and not (args.baseline / "benchmarks" / "train_throughput.py").is_file():
        parser.error(
            f"--baseline {args.baseline} is not a source tree of the package (no benchmarks/train_throughput.py)."
        )
    if args.one is not None:
        print(json.dumps(measure_one(args.one, args.seed, args.iterations, args.ppo_iterations)))
        return

    names = [name for name in ALGORITHMS if args.only is None or name in args.only]
    runs = [(name, None) for name in names]
    if args.baseline is not None and ONE_LINER in names:
        runs.insert(names.index(ONE_LINER) + 1, (BASELINE, args.baseline.resolve()))
    results: dict[str, list[dict[str, Any]]] = {name: [] for name, _ in runs}
    for repeat in range(args.repeats):
        for name, tree in runs:
            script = tree / "benchmarks" / "train_throughput.py" if tree else Path(__file__)  # the tree's own script
            command = [
                sys.executable,
                str(script),
                "--one",
                ONE_LINER if tree else name,
                "--seed",
                str(args.seed + repeat),
            ]
            command += ["--iterations", str(args.iterations), "--ppo-iterations", str(args.ppo_iterations)]
            environment = dict(os.environ, PYTHONPATH=str(tree)) if tree else None  # the other tree's package
            print(f"[repeat {repeat + 1} of {args.repeats}] {name}", file=sys.stderr, flush=True)
            # in the tree: worker processes start from a fork server that looks in its working directory first
            done = subprocess.run(command, stdout=subprocess.PIPE, text=True, env=environment, cwd=tree)  # stderr shows
            if done.returncode != 0:
                sys.exit(f"measuring {name} failed (exit status {done.returncode}; its error is above): {command}")
            results[name].append({**json.loads(done.stdout.strip().splitlines()[-1]), "name": name})

    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if "model name" in line), "?")
    threads = "1 torch thread in the learner (2 where named; the one-liner: torch's default)"
    print(f"machine: {cpu}, {threads}, python {platform.python_version()}, torch {th.__version__}")
    print()
    print(
        "| algorithm | warm-up s | env steps | seconds | env steps/s | rollout s | update s | epochs "
        "| ms per gradient step |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    medians = {}
    for name, runs in results.items():
        for run in runs:
            if name == MATMUL_FLOOR:
                cells = f"| | | | | | | {run['ms_per_gradient_step']:.2f} ({run['gflops']:.0f} GFLOP/s) |"
            elif name in ENV_ONLY:
                cells = f"| {run['env_steps']} | {run['seconds']:.1f} | {run['steps_per_s']:.0f} | | | | |"
            else:
                cells = (
                    f"{run['warm_up_s']:.1f} | {run['env_steps']} | {run['seconds']:.1f} | {run['steps_per_s']:.0f} | "
                    f"{run['rollout_s']:.1f} | {run['update_s']:.1f} | {run['epochs']} | "
                    f"{run['ms_per_gradient_step']:.2f} |"
                )
            print(f"| {name} | {cells}")
        if name != MATMUL_FLOOR:
            medians[name] = float(np.median([run["steps_per_s"] for run in runs]))
    print()
    print("median env steps/s: " + ", ".join(f"{name} {value:.0f}" for name, value in medians.items()))
    for reference in (name for name in PPO_VARIANTS if name in results):
        for name in (name for name in (ONE_LINER, *MAPPOC_VARIANTS) if name in results):
            pairs = zip(results[name], results[reference], strict=True)
            per_repeat = ", ".join(f"{a['steps_per_s'] / b['steps_per_s']:.2f}" for a, b in pairs)
            print(f"ratio {name} / {reference}: {medians[name] / medians[reference]:.2f} (per repeat: {per_repeat})")
    if BASELINE in results and ONE_LINER in results:
        pairs = zip(results[ONE_LINER], results[BASELINE], strict=True)
        per_repeat = ", ".join(f"{a['steps_per_s'] / b['steps_per_s']:.3f}" for a, b in pairs)
        ratio = medians[ONE_LINER] / medians[BASELINE]
        print(f"ratio {ONE_LINER} / baseline ({args.baseline}): {ratio:.3f} (per repeat: {per_repeat})")
    if MATMUL_FLOOR not in results or "PPO + SuperSuit" not in results:
        return
    floor = min(results[MATMUL_FLOOR], key=lambda run: run["ms_per_gradient_step"])
    update_s = floor["gradient_steps_per_env_step"] * floor["ms_per_gradient_step"] / 1e3
    for name in (name for name in ENV_ONLY if name in results):
        bound = 1 / (1 / medians[name] + update_s)
        print(
            f"bound with the {name.removeprefix('joint env only, ')} env and only the updates' matrix products: "
            f"{bound:.0f} env steps/s ({bound / medians['PPO + SuperSuit']:.2f} x PPO + SuperSuit)"
        )


if __name__ == "__main__":
    main()
