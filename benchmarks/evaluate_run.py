"""Evaluate one trained MAPPOC run at equal communication: learned options, random ones, periodic.

``python benchmarks/evaluate_run.py <run folder> --env <id>`` loads the run's final model
(as :mod:`sb3_detc.train` saves it, also when training was interrupted with Ctrl-C) and
runs the same seeded episodes, with the run's environment settings, three times: options
sampled from the learned policy over options, random options at the learned broadcast rate,
and periodic communication (every agent broadcasts every step), all with the learned
control policy (mean control). It prints the table of :func:`sb3_detc.compare.table`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sb3_detc.compare import evaluate_run, table
from sb3_detc.triggers import RandomTrigger


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="rl-zoo3 run folder, e.g. logs/mappoc/sb3_detc-MultiwalkerETC-v0_1")
    parser.add_argument("--env", required=True, help="environment id")
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes per trigger")
    args = parser.parse_args()
    learned = evaluate_run(args.run, args.env, args.episodes)
    reports = {
        "learned options": learned,
        "random options, same rate": evaluate_run(
            args.run, args.env, args.episodes, RandomTrigger(learned.savings, seed=0)
        ),
        "periodic": evaluate_run(args.run, args.env, args.episodes, RandomTrigger(0.0)),
    }
    print(table({name: [report] for name, report in reports.items()}))


if __name__ == "__main__":
    main()
