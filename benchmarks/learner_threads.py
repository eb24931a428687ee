"""Learner threads and OpenMP's waiting: the training speed of a saved MAPPOC model with rollout workers.

A study trial's learner and its rollout workers take turns on the same cores, so the learner's
torch threads and how OpenMP's idle threads wait (``OMP_WAIT_POLICY``: ``PASSIVE`` sleeps at
once, the default spins a while first) set the speed of its updates. For every setting and
repeat this script starts a fresh Python process (OpenMP reads its policy once, and a compiled
gradient step is compiled again for another thread count), which loads the model with its
rollout workers (``n_envs`` of the model), trains one untimed iteration (worker start,
compilation) and then times ``--iterations`` iterations. It prints the environment steps per
second, median over the repeats, per setting:

    python benchmarks/learner_threads.py benchmarks/studies/multiwalker_rate/trials/joint_9375/seed1/checkpoint.zip
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: The settings compared: (torch threads of the learner, ``OMP_WAIT_POLICY`` or None for OpenMP's default).
SETTINGS = ((1, "PASSIVE"), (2, "PASSIVE"), (1, None), (2, None))


def measure(model_path: str, env_id: str, threads: int, iterations: int, seed: int) -> dict[str, float]:
    """Train the saved model for one untimed and ``iterations`` timed iterations, in this process.

    :param model_path: the saved model (``MAPPOC.save`` or a study trial's ``checkpoint.zip``)
    :param env_id: the environment id its rollout workers run
    :param threads: torch threads of the learner
    :param iterations: timed iterations
    :param seed: seed of the rollout workers
    :return: ``steps_per_s`` (environment steps per second) and ``warm_up_s``
    """
    import torch as th

    from sb3_detc import MAPPOC

    th.set_num_threads(threads)
    model = MAPPOC.load(model_path, env=env_id, device="cpu", torch_compile=True)  # the saved number of workers
    try:
        model.set_random_seed(seed)
        per_iteration = model.n_steps * model.n_envs
        began = time.perf_counter()
        model.learn(per_iteration, reset_num_timesteps=False)
        warm_up = time.perf_counter() - began
        began = time.perf_counter()
        model.learn(iterations * per_iteration, reset_num_timesteps=False)
        return {"steps_per_s": iterations * per_iteration / (time.perf_counter() - began), "warm_up_s": warm_up}
    finally:
        model.get_env().close()


def main(argv: list[str] | None = None) -> None:
    """Run every setting ``--repeats`` times in fresh processes and print the table.

    :param argv: the arguments (default: ``sys.argv[1:]``)
    """
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="saved MAPPOC model (a study trial's checkpoint.zip)")
    parser.add_argument("--env", default="sb3_detc/MultiwalkerETC-v0", help="environment id of the rollout workers")
    parser.add_argument("--iterations", type=int, default=3, help="timed iterations per measurement (default: 3)")
    parser.add_argument("--repeats", type=int, default=2, help="measurements per setting (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the rollout workers")
    parser.add_argument("--one", type=int, metavar="THREADS", help=argparse.SUPPRESS)  # a measurement, as JSON
    args = parser.parse_args(argv)
    if not Path(args.model).is_file():
        parser.error(f"{args.model} is not a saved model")
    for name in ("iterations", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1")
    if args.one is not None:
        print(json.dumps(measure(args.model, args.env, args.one, args.iterations, args.seed)))
        return
    rates: dict[tuple[int, str | None], list[float]] = {setting: [] for setting in SETTINGS}
    for repeat in range(args.repeats):
        for threads, policy in SETTINGS:
            env = {key: value for key, value in os.environ.items() if key != "OMP_WAIT_POLICY"}
            if policy is not None:
                env["OMP_WAIT_POLICY"] = policy
            command = [sys.executable, __file__, args.model, "--env", args.env, "--one", str(threads)]
            command += ["--iterations", str(args.iterations), "--seed", str(args.seed)]
            done = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
            result = json.loads(done.stdout.strip().splitlines()[-1])
            rates[threads, policy].append(result["steps_per_s"])
            print(
                f"repeat {repeat}: {threads} thread(s), OMP_WAIT_POLICY={policy or '(default)'}: "
                f"{result['steps_per_s']:.0f} env steps/s (warm-up {result['warm_up_s']:.0f} s)",
                flush=True,
            )
    print()
    print(f"{args.model}, {args.iterations} timed iterations per measurement, {args.repeats} repeats:")
    print()
    print("| learner threads | OMP_WAIT_POLICY | env steps/s (median) |")
    print("|---:|---|---:|")
    for (threads, policy), values in rates.items():
        print(f"| {threads} | {policy or '(default)'} | {statistics.median(values):.0f} |")


if __name__ == "__main__":
    main()
