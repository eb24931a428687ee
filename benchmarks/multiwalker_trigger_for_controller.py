"""A trigger learned for a controller that needs messages: MAPPOC's policies over options on a study's controllers.

On Multiwalker the controllers of the paper's random-skip baseline need their messages beyond
about 75 % savings, and there *when* matters: a message every 8th step keeps the walkers going,
random messages at the same rate do not (``benchmarks/README.md``, value of information). Can
MAPPOC's policy over options learn such timing? For every finished seed of a study algorithm
(default: ``random_skip_paper`` of ``multiwalker_paper``) the trial's final policy is loaded into
MAPPOC built from the trial's own entry (rl-zoo3's experiment manager, as the study trains it);
its control policy is frozen and only the policies over options and the critic learn
(``set_trained_policies(control_policy=False, broadcast_policy=True)``), at the communication
cost ``--broadcast-cost``, with rewards normalised afresh (as stage 2 of
:class:`~sb3_detc.callbacks.ControlFirstCallback`; ``--no-normalize-reward`` keeps the entry's
setting). The entry's callbacks (random skips, action noise schedule) are left out.

The trained policy then runs the study's evaluation protocol on the study's seeded episodes
(:func:`~sb3_detc.study.trial.evaluate_policy_modes`: learned options sampled from ``mu``,
random options at the learned rate, every step, never) and a message every ``k`` steps at the
``k`` whose savings ``1 - 1/k`` lie closest to the learned savings. The control policy is the
trial's, unchanged, so the value of information sweep of the same study
(``multiwalker_value_of_information.py``) shows the same controller under fixed triggers.

One job per seed, one after another (each trains with the entry's two rollout-worker
processes); every finished seed's row is written to ``--out`` at once and a seed already there
is not trained again (``resumable.py``). ``--save-dir`` keeps the trained policies (policy only).

    python benchmarks/multiwalker_trigger_for_controller.py benchmarks/studies/multiwalker_paper \\
        --broadcast-cost 0.25 --out benchmarks/results/multiwalker_trigger_for_controller.json
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from resumable import OutError, check_at_least_one, run_rows
from stable_baselines3.common.callbacks import BaseCallback

from sb3_detc.evaluation import evaluate_episodes
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.study.report import interval_estimates, interval_text
from sb3_detc.study.spec import StudyError, load_folder_study
from sb3_detc.study.trial import evaluate_policy_modes, read_status, replace_atomically, trial_folder
from sb3_detc.triggers import PeriodicTrigger
from sb3_detc.zoo import ExperimentManager

#: Training steps of the policies over options (500 of the paper's iterations of 2048 steps).
TIMESTEPS = 1_024_000


class Progress(BaseCallback):
    """Print the steps, the broadcast rate of the last rollout and the time every ``every`` rollouts.

    :param label: what is trained, at the start of every line
    :param every: rollouts between two lines
    """

    def __init__(self, label: str, every: int = 25) -> None:
        super().__init__()
        self.label = label
        self.every = every
        self.rollouts = 0
        self.began = time.monotonic()

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self.rollouts += 1
        if self.rollouts % self.every == 0:
            rate = float(np.mean(self.model.rollout_buffer.broadcast))
            print(
                f"{self.label}: {self.num_timesteps} steps, savings in the last rollout {1 - rate:.3f}, "
                f"{time.monotonic() - self.began:.0f} s",
                flush=True,
            )


def build(job: dict[str, Any], log_folder: Path) -> Any:
    """MAPPOC of the trial's entry on its training envs, with the trial's final policy loaded and frozen.

    :param job: ``folder`` (the study folder), ``algorithm`` (its label), ``seed``, ``broadcast_cost``,
        ``timesteps``, ``changes`` (entry settings to change) and ``normalize_reward``
    :param log_folder: where rl-zoo3's experiment manager may write
    :return: the model, ready to learn its policies over options
    :raises StudyError: if the trial is not finished
    """
    spec = load_folder_study(Path(job["folder"]))
    trial = next(t for t in spec.trials() if t.algorithm.label == job["algorithm"] and t.seed == job["seed"])
    folder = trial_folder(job["folder"], trial)
    if read_status(folder)["status"] != "done" or not (folder / "policy.pt").is_file():
        raise StudyError(f"{trial.name} of {job['folder']} has not finished (no policy.pt)")
    algorithm = trial.algorithm
    env_kwargs = {**(algorithm.entry.get("env_kwargs") or {}), "broadcast_cost": job["broadcast_cost"]}
    hyperparams = {**algorithm.hyperparams, "env_kwargs": env_kwargs, "callback": [], **job["changes"]}
    args = argparse.Namespace(algo=algorithm.algo, env=spec.env, seed=trial.seed, n_timesteps=job["timesteps"])
    manager = ExperimentManager(
        args,
        algorithm.algo,
        spec.env,
        log_folder=str(log_folder),
        n_timesteps=job["timesteps"],
        eval_freq=-1,
        save_freq=-1,
        log_interval=-1,
        hyperparams=hyperparams,
        seed=trial.seed,
        verbose=0,
        config=str(algorithm.conf),
        device="cpu",
    )
    model, _ = manager.setup_experiment()
    model.policy.load_state_dict(MlpHybridPolicy.load(str(folder / "policy.pt"), device="cpu").state_dict())
    model.set_fixed_trigger(None)
    model.set_trained_policies(control_policy=False, broadcast_policy=True)
    if job["normalize_reward"]:
        model.set_reward_normalization(True, fresh_statistics=True)
    return model


def run(job: dict[str, Any]) -> dict[str, Any]:
    """Train the policies over options for one seed's controller and evaluate them; one table row.

    :param job: as :func:`build` takes it, and ``save_dir`` (where to keep the policy; None: not kept)
    :return: the seed, the training seconds, the study protocol's metrics of the learned trigger
        (:func:`~sb3_detc.study.trial.evaluate_policy_modes`) and the control return, package travel,
        fall rate and savings of a message every ``k`` steps
    """
    th.set_num_threads(1)
    spec = load_folder_study(Path(job["folder"]))
    with tempfile.TemporaryDirectory() as log_folder:
        model = build(job, Path(log_folder))
        began = time.monotonic()
        label = f"{job['algorithm']} seed {job['seed']}"
        model.learn(job["timesteps"], callback=Progress(label))
        seconds = time.monotonic() - began
        model.env.close()
    policy = model.policy
    if job["save_dir"] is not None:
        path = Path(job["save_dir"]) / f"{job['algorithm']}_seed{job['seed']}_cost{job['broadcast_cost']:g}.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        replace_atomically(path, lambda scratch: policy.save(str(scratch)), path.stem + ".tmp.pt")
    env = gym.make(spec.env, broadcast_cost=job["broadcast_cost"])
    try:
        evaluation = evaluate_policy_modes(policy, env, spec.episodes, spec.eval_seed)
        savings = evaluation["metrics"]["savings"]
        period = max(1, round(1 / (1 - savings))) if savings < 1 else None
        periodic = None
        if period is not None:
            seeds = [spec.eval_seed + k for k in range(spec.episodes)]
            episodes = evaluate_episodes(policy, env, seeds, deterministic=True, fixed_trigger=PeriodicTrigger(period))
            periodic = {
                "period": period,
                "control_return": float(np.mean(episodes.control_returns)),
                "package_travel": float(np.nanmean(episodes.package_travel)),
                "fall_rate": float(np.mean(episodes.failed)),
                "savings": episodes.savings,
            }
    finally:
        env.close()
    return {
        "algorithm": job["algorithm"],
        "seed": job["seed"],
        "broadcast_cost": job["broadcast_cost"],
        "timesteps": job["timesteps"],
        "train_seconds": round(seconds, 1),
        "metrics": evaluation["metrics"],
        "periodic_nearest": periodic,
    }


def print_table(rows: list[dict[str, Any]]) -> None:
    """Print one line per seed and the means over seeds with 95 % bootstrap intervals.

    :param rows: the rows of :func:`run`
    """
    print(
        "| seed | savings | control return learned | random, same rate | learned minus random | every k-th step "
        "| package travel learned | fall rate learned |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        m, periodic = row["metrics"], row["periodic_nearest"]
        every = "" if periodic is None else f"{periodic['control_return']:.1f} (k = {periodic['period']})"
        cells = [
            f"{m['savings']:.3f}",
            f"{m['control_return']:.1f}",
            f"{m['random_same_rate_control_return']:.1f}",
            f"{m['learned_minus_random_control_return']:+.1f}",
            every,
            f"{m.get('package_travel', float('nan')):.2f}",
            f"{m.get('fall_rate', float('nan')):.2f}",
        ]
        print(f"| {row['seed']} | " + " | ".join(cells) + " |")
    if len(rows) < 2:
        return
    names = {
        "savings": "savings",
        "control return learned": "control_return",
        "control return random, same rate": "random_same_rate_control_return",
        "learned minus random": "learned_minus_random_control_return",
    }
    values = np.array([[row["metrics"][key] for key in names.values()] for row in rows])
    means, intervals = interval_estimates({"x": values})
    print()
    print(f"Over {len(rows)} seeds, mean [95 % bootstrap interval]:")
    for k, name in enumerate(names):
        digits = 3 if name == "savings" else 1
        print(f"- {name}: {interval_text(means['x'][k], intervals['x'][0, k], intervals['x'][1, k], digits)}")


def main() -> None:
    """Train and evaluate every seed one after another, write the rows and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="a study folder with finished trials")
    parser.add_argument("--algorithm", default="random_skip_paper", help="the study algorithm whose controllers")
    parser.add_argument("--seeds", type=int, nargs="+", help="(default: every finished seed of the algorithm)")
    parser.add_argument("--broadcast-cost", type=float, default=0.25, help="communication cost per broadcast")
    parser.add_argument("--timesteps", type=int, default=TIMESTEPS, help="training steps per seed")
    parser.add_argument("--set", type=json.loads, default={}, help="entry settings to change (JSON), e.g. MAPPOC's")
    parser.add_argument("--no-normalize-reward", action="store_true", help="keep the entry's reward normalisation")
    parser.add_argument("--out", type=Path, default=Path("multiwalker_trigger_for_controller.json"))
    parser.add_argument("--save-dir", type=Path, help="folder for the trained policies (default: not kept)")
    args = parser.parse_args()
    check_at_least_one(parser, args, "timesteps")
    if not args.broadcast_cost >= 0 or not isinstance(args.set, dict):
        parser.error("--broadcast-cost must be >= 0 and --set a JSON object")
    try:
        spec = load_folder_study(args.folder)
    except StudyError as error:
        parser.error(str(error))
    finished = {
        t.seed
        for t in spec.trials()
        if t.algorithm.label == args.algorithm and (trial_folder(args.folder, t) / "policy.pt").is_file()
    }
    if not finished:
        labels = sorted({a.label for a in spec.algorithms})
        parser.error(f"{args.folder} has no finished trial of {args.algorithm!r} (algorithms: {', '.join(labels)})")
    seeds = args.seeds or sorted(finished)
    if set(seeds) - finished:
        parser.error(f"seeds {sorted(set(seeds) - finished)} of {args.algorithm} have not finished")
    job = {
        "folder": str(args.folder),  # as given: the same key on every machine
        "algorithm": args.algorithm,
        "broadcast_cost": args.broadcast_cost,
        "timesteps": args.timesteps,
        "changes": args.set,
        "normalize_reward": not args.no_normalize_reward,
        "save_dir": None if args.save_dir is None else str(args.save_dir),
    }
    try:
        rows = run_rows(run, [{**job, "seed": seed} for seed in seeds], args.out, workers=1)
    except OutError as error:
        parser.error(str(error))
    print(
        f"{args.algorithm} of {args.folder}: policies over options trained for {args.timesteps} steps on the "
        f"frozen controllers, broadcast cost {args.broadcast_cost}; {spec.episodes} evaluation episodes from seed "
        f"{spec.eval_seed}"
    )
    print()
    print_table(rows)


if __name__ == "__main__":
    main()
