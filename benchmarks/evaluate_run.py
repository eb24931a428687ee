"""Evaluate one trained MAPPOC run at equal communication: learned options, random ones, periodic.

``python benchmarks/evaluate_run.py <run folder> --env <id>`` loads the run's final model
(as :mod:`sb3_detc.train` saves it, also when training was interrupted with Ctrl-C) and
runs the same seeded episodes, with the run's environment settings, three times: options
sampled from the learned policy over options, random options at the learned broadcast rate,
and periodic communication (every agent broadcasts every step), all with the learned
control policy (mean control). It prints the table of :func:`sb3_detc.compare.table`.

With ``--checkpoints`` it does the same for every checkpoint of the run
(``rl_model_<steps>_steps.zip``, as ``--save-freq`` writes them), in the order of their
steps, and prints one row per checkpoint as it goes: how the learned trigger compares with
random skipping at its own rate over training.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from sb3_detc.compare import evaluate_run, table
from sb3_detc.evaluation import CommunicationReport
from sb3_detc.triggers import RandomTrigger

CHECKPOINT = re.compile(r"rl_model_(\d+)_steps\.zip")


def compare(run: Path, env_id: str, episodes: int, model: Path | None = None) -> dict[str, CommunicationReport]:
    """Learned options, random options at the learned rate and periodic communication on the same episodes.

    :param run: the run folder
    :param env_id: environment id
    :param episodes: evaluation episodes per trigger
    :param model: the saved model (None: the run's final model)
    :return: trigger name -> report
    """
    learned = evaluate_run(run, env_id, episodes, model=model)
    return {
        "learned options": learned,
        "random options, same rate": evaluate_run(
            run, env_id, episodes, RandomTrigger(learned.savings, seed=0), model=model
        ),
        "periodic": evaluate_run(run, env_id, episodes, RandomTrigger(0.0), model=model),
    }


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
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes per trigger")
    parser.add_argument("--checkpoints", action="store_true", help="evaluate every checkpoint of the run")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if not args.run.is_dir():
        parser.error(f"no run folder {args.run}")
    try:
        found = checkpoints(args.run) if args.checkpoints else []
        if not args.checkpoints:
            print(table({name: [report] for name, report in compare(args.run, args.env, args.episodes).items()}))
            return
    except FileNotFoundError as error:  # no model or no checkpoints in the folder
        parser.exit(2, f"error: {error}\n")
    print("| steps | savings | control return: learned | random, same rate | periodic |")
    print("|---|---|---|---|---|")
    for steps, path in found:
        reports = compare(args.run, args.env, args.episodes, model=path)
        returns = " | ".join(f"{report.mean_control_return:.1f}" for report in reports.values())
        print(f"| {steps} | {reports['learned options'].savings:.3f} | {returns} |", flush=True)


if __name__ == "__main__":
    main()
