"""Train MAPPOC and the random-skip baseline through rl-zoo3, evaluate both, print a table and plot.

``python -m sb3_detc.compare`` (``make run``) trains, for every seed, ``mappoc`` (learned
communication) and ``ppo_random_skip`` (random skips, the paper's baseline) with
:mod:`sb3_detc.train` and the package's hyperparameter files, the two in parallel (one
process each; MAPPOC shows a progress bar, the baseline's output goes to
``<folder>/ppo_random_skip_seed<seed>.log``). Then both final models run the same seeded
evaluation episodes with the training communication cost: MAPPOC with options sampled from
its policy over options, the baseline with its random trigger and once more with random
skips at MAPPOC's mean rate (equal communication). The default environment is
``sb3_detc/LinearETC-LQR-v0``: the controls are LQR on held broadcasts, so the comparison
is between a learned and a random trigger for the same controller. The table gives the
team-mean return per agent and episode (communication cost included), the control return
(without it) and the communication savings ``1 - broadcasts / agent-steps``; the figure of
:mod:`sb3_detc.plot` is drawn from the runs' logs.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from huggingface_sb3 import EnvironmentName
from rl_zoo3.utils import get_callback_list, get_latest_run_id, get_saved_hyperparams

from sb3_detc.callbacks import FixedTriggerCallback
from sb3_detc.evaluation import CommunicationReport, evaluate_communication
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.mappoc import OptionOverride
from sb3_detc.plot import plot_runs
from sb3_detc.triggers import RandomTrigger
from sb3_detc.zoo import InputError, check_env, run_cli

#: The compared algorithms (rl-zoo3 names): learned communication and the random-skip baseline.
ALGOS = ("mappoc", "ppo_random_skip")

#: Row of the table: the baseline with random skips at the learned trigger's rate.
EQUAL_RATE = "ppo_random_skip at mappoc's rate"

#: Seed of the first evaluation episode (the same episodes for every model).
EVAL_SEED = 10_000


def train_command(algo: str, env_id: str, seed: int, folder: str, timesteps: int | None, progress: bool) -> list[str]:
    """The :mod:`sb3_detc.train` command line of one run (one thread, no periodic evaluation).

    :param algo: rl-zoo3 algorithm name
    :param env_id: environment id
    :param seed: the run's seed
    :param folder: log folder
    :param timesteps: training steps (None: the hyperparameter file's)
    :param progress: show a progress bar
    :return: the command
    """
    command = [sys.executable, "-m", "sb3_detc.train", "--algo", algo, "--env", env_id, "--seed", str(seed)]
    command += ["-f", folder, "--num-threads", "1", "--eval-freq", "-1", "--verbose", "0"]
    if timesteps is not None:
        command += ["-n", str(timesteps)]
    return [*command, "--progress"] if progress else command


def train_pair(env_id: str, seed: int, folder: str, timesteps: int | None) -> dict[str, Path]:
    """Train MAPPOC and the baseline with one seed in parallel; returns their run folders.

    :param env_id: environment id
    :param seed: seed of both runs
    :param folder: log folder
    :param timesteps: training steps (None: the hyperparameter files')
    :return: algorithm name -> run folder
    :raises RuntimeError: if a training process fails
    """
    Path(folder).mkdir(parents=True, exist_ok=True)
    log = Path(folder) / f"ppo_random_skip_seed{seed}.log"
    with log.open("w") as output:
        baseline = subprocess.Popen(
            train_command("ppo_random_skip", env_id, seed, folder, timesteps, progress=False),
            stdout=output,
            stderr=subprocess.STDOUT,
        )
        learned = subprocess.run(train_command("mappoc", env_id, seed, folder, timesteps, progress=True), check=False)
        baseline.wait()
    if learned.returncode != 0:
        raise RuntimeError(f"training mappoc (seed {seed}) failed")
    if baseline.returncode != 0:
        raise RuntimeError(f"training ppo_random_skip (seed {seed}) failed, see {log}")
    name = EnvironmentName(env_id)
    return {algo: Path(folder) / algo / f"{name}_{get_latest_run_id(str(Path(folder) / algo), name)}" for algo in ALGOS}


def evaluate_run(
    run: Path, env_id: str, episodes: int, trigger: OptionOverride | None = None, model: Path | None = None
) -> CommunicationReport:
    """Evaluate a run's final model or a checkpoint on seeded episodes, with the run's env settings and trigger.

    The environment gets the run's ``env_kwargs`` (so the communication cost of training is
    charged also for the baseline, which trained without it); a run trained with a fixed
    trigger (:class:`~sb3_detc.callbacks.FixedTriggerCallback`) is evaluated with that trigger.

    :param run: the run folder
    :param env_id: environment id
    :param episodes: evaluation episodes
    :param trigger: options to use instead of the run's (None: the run's own)
    :param model: the saved model to evaluate, e.g. a checkpoint ``rl_model_<steps>_steps.zip``
        (None: the run's final model ``<run>/<env name>.zip``)
    :return: the evaluation report
    :raises FileNotFoundError: if the model file does not exist
    """
    name = EnvironmentName(env_id)
    config, _ = get_saved_hyperparams(str(run / name))
    triggers = [c.trigger for c in get_callback_list(dict(config)) if isinstance(c, FixedTriggerCallback)]
    if trigger is not None:
        triggers = [trigger]
    path = run / f"{name}.zip" if model is None else model
    if not path.is_file():
        raise FileNotFoundError(f"no saved model {path}")
    env = gym.make(env_id, **(config.get("env_kwargs") or {}))
    return evaluate_communication(
        MAPPOC.load(path, device="cpu"),
        env,
        episodes,
        deterministic=True,
        deterministic_options=False,
        option_override=triggers[0] if triggers else None,
        seed=EVAL_SEED,
    )


def table(reports: dict[str, list[CommunicationReport]]) -> str:
    """Markdown table of mean (and, over several seeds, min-max) return, control return and savings.

    :param reports: algorithm name -> one report per seed
    :return: the table
    """

    def cell(values: list[float], digits: int) -> str:
        text = f"{np.mean(values):.{digits}f}"
        return text + (f" ({min(values):.{digits}f} to {max(values):.{digits}f})" if len(values) > 1 else "")

    lines = ["| algorithm | seeds | return | control return | savings |", "|---|---|---|---|---|"]
    for algo, runs in reports.items():
        returns = [r.mean_return for r in runs]
        control = [r.mean_control_return for r in runs]
        savings = [r.savings for r in runs]
        lines.append(f"| {algo} | {len(runs)} | {cell(returns, 2)} | {cell(control, 2)} | {cell(savings, 3)} |")
    return "\n".join(lines)


def _main() -> None:
    parser = argparse.ArgumentParser(prog="python -m sb3_detc.compare", description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="sb3_detc/LinearETC-LQR-v0", help="environment id")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="seeds (one run per seed and algorithm)")
    parser.add_argument("-n", "--n-timesteps", type=int, default=None, help="training steps (default: the files')")
    parser.add_argument("-f", "--folder", default="logs", help="rl-zoo3 log folder (default: logs)")
    parser.add_argument("--eval-episodes", type=int, default=50, help="evaluation episodes per model")
    parser.add_argument("-o", "--out", default=None, help="figure (default: <folder>/compare.png)")
    args = parser.parse_args(sys.argv[1:])
    check_env(args.env)
    if args.eval_episodes < 1:
        raise InputError(f"--eval-episodes must be >= 1, got {args.eval_episodes}")
    th.set_num_threads(1)
    runs: dict[str, list[Path]] = {algo: [] for algo in ALGOS}
    for seed in args.seeds:
        print(f"Training mappoc and ppo_random_skip on {args.env}, seed {seed} (the baseline in a second process)")
        for algo, run in train_pair(args.env, seed, args.folder, args.n_timesteps).items():
            runs[algo].append(run)
    reports = {algo: [evaluate_run(run, args.env, args.eval_episodes) for run in group] for algo, group in runs.items()}
    # The baseline once more with random skips at the learned trigger's rate: equal communication.
    savings = float(np.mean([report.savings for report in reports["mappoc"]]))
    reports[EQUAL_RATE] = [
        evaluate_run(run, args.env, args.eval_episodes, RandomTrigger(savings, seed=seed))
        for run, seed in zip(runs["ppo_random_skip"], args.seeds, strict=True)
    ]
    print()
    print(f"{args.env}, {args.eval_episodes} evaluation episodes per model, per agent and episode:")
    print()
    print(table(reports))
    print()
    figure = plot_runs(runs, args.out or Path(args.folder) / "compare.png", title=args.env)
    print(f"Runs: {', '.join(str(run) for group in runs.values() for run in group)}")
    print(f"Figure: {figure}")


def main(argv: Sequence[str] | None = None) -> None:
    """Run the comparison command line.

    :param argv: the arguments (default: ``sys.argv[1:]``)
    """
    run_cli("python -m sb3_detc.compare", _main, argv)


if __name__ == "__main__":
    main()
