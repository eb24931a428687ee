"""Evaluate one trained MAPPOC run, or every checkpoint of it, with the package's evaluation protocol.

``python benchmarks/evaluate_run.py <run folder> --env <id>`` loads the run's final model
(as :mod:`sb3_detc.train` saves it, also when training was interrupted with Ctrl-C) and
runs the protocol (:func:`sb3_detc.evaluation.evaluate_policy_modes`) on seeded episodes with
the run's environment settings: the learned options, the most likely options, random options at
the learned rate, periodic communication and none, all with the learned control policy (mean
control). It prints the table of ``python -m sb3_detc.evaluate`` (which does this for any saved model).

With ``--checkpoints`` it does the same for every checkpoint of the run
(``rl_model_<steps>_steps.zip``, as ``--save-freq`` writes them), in the order of their
steps, and prints one row per checkpoint as it goes: how the learned trigger compares with
random skipping at its own rate over training.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

import gymnasium as gym
from huggingface_sb3 import EnvironmentName

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.cli import InputError
from sb3_detc.evaluate import load_saved, modes_table
from sb3_detc.evaluation import EVAL_SEED, evaluate_policy_modes

CHECKPOINT = re.compile(r"rl_model_(\d+)_steps\.zip")


def evaluate(model: Path, episodes: int) -> dict[str, Any]:
    """The protocol on a saved model of a run, with the run's env settings and trigger.

    :param model: the saved model in its run folder
    :param episodes: evaluation episodes per mode
    :return: what :func:`~sb3_detc.evaluation.evaluate_policy_modes` returns
    """
    saved = load_saved(model)
    with gym.make(saved.env_id, **saved.env_kwargs) as env:
        return evaluate_policy_modes(saved.policy, env, episodes, EVAL_SEED, saved.trigger)


def checkpoints(run: Path) -> list[tuple[int, Path]]:
    """The run's checkpoints as (steps, path), by steps.

    :param run: the run folder
    :return: the checkpoints
    :raises FileNotFoundError: if the run has none
    """
    found = sorted((int(m.group(1)), path) for path in run.iterdir() if (m := CHECKPOINT.fullmatch(path.name)))
    if not found:
        raise FileNotFoundError(f"no checkpoints rl_model_<steps>_steps.zip in {run} (train with --save-freq)")
    return found


def main() -> None:
    """Evaluate the run (or every checkpoint of it, with ``--checkpoints``) and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="rl-zoo3 run folder, e.g. logs/mappoc/sb3_detc-MultiwalkerETC-v0_1")
    parser.add_argument("--env", required=True, help="environment id")
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes per mode")
    parser.add_argument("--checkpoints", action="store_true", help="evaluate every checkpoint of the run")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if not args.run.is_dir():
        parser.error(f"no run folder {args.run}")
    final = args.run / f"{EnvironmentName(args.env)}.zip"
    try:
        if not args.checkpoints:
            if not final.is_file():
                raise FileNotFoundError(f"no saved model {final}")
            print(modes_table(evaluate(final, args.episodes)))
            return
        found = checkpoints(args.run)
    except (FileNotFoundError, InputError) as error:  # no model or checkpoints in the folder, or not a run's
        parser.exit(2, f"error: {error}\n")
    print("| steps | savings | control return: learned | random, same rate | periodic |")
    print("|---|---|---|---|---|")
    for steps, path in found:
        metrics = evaluate(path, args.episodes)["metrics"]
        returns = " | ".join(
            f"{metrics[key]:.1f}"
            for key in ("control_return", "random_same_rate_control_return", "periodic_control_return")
        )
        print(f"| {steps} | {metrics['savings']:.3f} | {returns} |", flush=True)


if __name__ == "__main__":
    main()
