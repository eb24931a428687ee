"""Train MAPPOC and the random-skip baseline over seeds, evaluate both on the same episodes, print and plot.

``python -m sb3_detc.compare`` (``make run``) runs a study (:mod:`sb3_detc.study`) of
``mappoc`` (learned communication) and ``ppo_random_skip`` (random skips, the paper's
baseline) with the package's hyperparameter entries, for every seed (``--seeds``, default
0, 1 and 2), on Ray on this machine (the cores each entry's rollout workers need). Every final policy then runs the
same 50 seeded evaluation episodes with the training communication cost in the modes of the
package's protocol (:func:`~sb3_detc.evaluation.evaluate_policy_modes`): with its own options
(MAPPOC's sampled from its policy over options, as the entries' ``sample_options`` say, the
baseline's from its random trigger), with MAPPOC's most likely options, with random skips at its
own rate, always and never broadcasting. The default
environment is ``sb3_detc/LinearETC-LQR-v0``: the controls are LQR on held broadcasts, so
the comparison is between a learned and a random trigger for the same controller, and the
baseline, random options for a controller it cannot change, trains one iteration only. The table
gives the team-mean return per agent and episode (communication cost included), the control
return (without it) and the communication savings ``1 - broadcasts / agent-steps``, each as
the mean over seeds with a 95 % bootstrap interval, and the paired difference between the
learned options and random skips at the learned rate (same controller, same episodes). The
figure ``<dir>/curves.png`` shows the training control return and savings of both, the
control return without the communication cost for both, since the baseline trains without
paying it; ``<dir>/estimates.png`` the final policies' metrics, every seed with the mean and
its interval. Running the command again with the same settings reuses finished runs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml

from sb3_detc.cli import InputError, check_env, run_cli
from sb3_detc.evaluation import EVAL_SEED
from sb3_detc.study.report import interval_text, report_study, summarise
from sb3_detc.study.runner import prepare_folder, run_study
from sb3_detc.study.spec import load_study
from sb3_detc.triggers import FixedControl

#: The compared algorithms (rl-zoo3 names): learned communication and the random-skip baseline.
ALGOS = ("mappoc", "ppo_random_skip")

#: Row of the table: the baseline with random skips at the learned trigger's rate.
EQUAL_RATE = "ppo_random_skip at mappoc's rate"


def controls_fixed(env_id: str) -> bool:
    """Whether the env sets the controls itself (a :class:`~sb3_detc.triggers.FixedControl` wrapper).

    Then the random-skip baseline has nothing to learn: its options are random and its
    controls are the env's.

    :param env_id: environment id
    :return: True if a :class:`~sb3_detc.triggers.FixedControl` wrapper is among the env's wrappers
    """
    env = gym.make(env_id)
    try:
        while isinstance(env, gym.Wrapper):
            if isinstance(env, FixedControl):
                return True
            env = env.env
        return False
    finally:
        env.close()


def comparison_study(
    env_id: str, seeds: Sequence[int], timesteps: int | None, episodes: int, fixed: bool | None = None
) -> dict[str, Any]:
    """The study that :mod:`sb3_detc.compare` runs: both algorithms' entries of ``env_id`` over ``seeds``.

    Where the env fixes the controls (:func:`controls_fixed`), the random-skip baseline
    trains one iteration only (a budget of one step): more would change nothing it is
    evaluated with.

    :param env_id: environment id
    :param seeds: the seeds
    :param timesteps: training steps per run (None: the hyperparameter files')
    :param episodes: evaluation episodes per mode
    :param fixed: whether the env fixes the controls (None: :func:`controls_fixed`)
    :return: the study file's content
    """
    study: dict[str, Any] = {"env": env_id, "seeds": list(seeds)}
    study["checkpoint_interval"] = 100_000
    study["evaluation"] = {"episodes": episodes, "seed": EVAL_SEED}
    budgets = dict.fromkeys(ALGOS, timesteps)
    if fixed is None:
        fixed = controls_fixed(env_id)
    if fixed:
        budgets["ppo_random_skip"] = 1
    study["algorithms"] = {
        algo: {"algo": algo} if budget is None else {"algo": algo, "hyperparams": {"n_timesteps": budget}}
        for algo, budget in budgets.items()
    }
    return study


def comparison_table(summary: dict[str, Any]) -> str:
    """Markdown table of the comparison: mean and 95 % interval over seeds of return, control return and savings.

    :param summary: :func:`sb3_detc.study.report.summarise` of the comparison's study folder
    :return: the table and a line on the paired learned-minus-random difference
    """

    def cell(entry: dict[str, Any], metric: str, digits: int = 2) -> str:
        return interval_text(entry["mean"][metric], *entry["ci95"][metric], digits)

    lines = ["| algorithm | seeds | return | control return | savings |", "|---|---|---|---|---|"]
    for algo in ALGOS:
        entry = summary[algo]
        seeds = len(entry["seeds"])
        lines.append(
            f"| {algo} | {seeds} | {cell(entry, 'return')} | {cell(entry, 'control_return')} "
            f"| {cell(entry, 'savings', 3)} |"
        )
    learned = summary["mappoc"]
    lines.append(
        f"| {EQUAL_RATE} | {len(learned['seeds'])} | {cell(learned, 'random_same_rate_return')} "
        f"| {cell(learned, 'random_same_rate_control_return')} | {cell(learned, 'random_same_rate_savings', 3)} |"
    )
    differences = [seed["learned_minus_random_control_return"] for seed in learned["seeds"].values()]
    lines += [
        "",
        "Learned options minus random skips at the learned rate, same controller, paired episodes (control "
        f"return): {cell(learned, 'learned_minus_random_control_return')}; learned better in "
        f"{sum(d > 0 for d in differences)} of {len(differences)} seeds.",
    ]
    return "\n".join(lines)


def _main() -> None:
    """The comparison command: write ``<dir>/study.yml`` from ``sys.argv``, run the study, print the table.

    :raises InputError: for an unknown environment, ``--eval-episodes`` < 1, settings a study
        refuses (e.g. negative seeds) or a ``--dir`` that holds a comparison with other settings
        or other files
    :raises SystemExit: with code 1 if a run of the study did not finish
    """
    parser = argparse.ArgumentParser(prog="python -m sb3_detc.compare", description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="sb3_detc/LinearETC-LQR-v0", help="environment id")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (default: 0 1 2)")
    parser.add_argument("-n", "--n-timesteps", type=int, default=None, help="training steps (default: the files')")
    parser.add_argument("--dir", default="logs/compare", help="study folder (default: logs/compare)")
    parser.add_argument("--eval-episodes", type=int, default=50, help="evaluation episodes per mode (default: 50)")
    parser.add_argument("--address", default=None, help="address of a running Ray cluster (default: local)")
    args = parser.parse_args(sys.argv[1:])
    check_env(args.env)
    if args.eval_episodes < 1:
        raise InputError(f"--eval-episodes must be >= 1, got {args.eval_episodes}")
    folder = Path(args.dir)
    fixed = controls_fixed(args.env)
    study = comparison_study(args.env, args.seeds, args.n_timesteps, args.eval_episodes, fixed)
    text = yaml.safe_dump(study, sort_keys=False)
    path = folder / "study.yml"
    if path.is_file() and yaml.safe_load(path.read_text()) != yaml.safe_load(text):
        raise InputError(f"{folder} holds a comparison with other settings; give another --dir")
    with tempfile.TemporaryDirectory() as scratch:  # the settings are checked before the folder is touched
        draft = Path(scratch) / "study.yml"
        draft.write_text(text)
        prepare_folder(load_study(draft), folder)  # writes <dir>/study.yml (into a new or empty folder)
    print(f"Training mappoc and ppo_random_skip on {args.env}, seeds {', '.join(map(str, args.seeds))}")
    if fixed:
        print(
            f"{args.env} sets the controls and ppo_random_skip's options are random: the baseline has nothing "
            "to learn, so it trains one iteration and is evaluated as it is"
        )
    statuses = run_study(load_study(path), folder, address=args.address)
    if any(status != "done" for status in statuses.values()):
        raise SystemExit(1)
    report = report_study(folder)
    print()
    print(
        f"{args.env}, {len(args.seeds)} seeds, {args.eval_episodes} evaluation episodes per model and mode, per agent "
        "and episode; mean over seeds [95 % bootstrap interval]:"
    )
    print()
    print(comparison_table(summarise(folder)))
    print()
    print(f"Full report: python -m sb3_detc.study report {folder} ({len(report.splitlines())} lines)")
    if (folder / "curves.png").is_file():
        print(f"Figure: {folder / 'curves.png'}")
    else:
        print("No training curves: every run trained one iteration, and a curve needs two")
    print(f"Final policies: {folder / 'estimates.png'}")


def main(argv: Sequence[str] | None = None) -> None:
    """Run the comparison command line.

    :param argv: the arguments (default: ``sys.argv[1:]``)
    """
    run_cli("python -m sb3_detc.compare", _main, argv)


if __name__ == "__main__":
    main()
