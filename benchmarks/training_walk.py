"""How far a learned trigger walks during training, against predictive triggering (linear system, LQR on predictions).

For the given arms of a study on ``LinearETC-LQR-v0`` with LQR on the receivers' predictions, per
finished seed:

* the broadcast rate of every rollout (``rollout/broadcast_rate`` of ``progress.csv.xz``) over the
  last fifth of training: its standard deviation, minimum and maximum (under a fixed trigger the
  episodes alone make it vary, as over the first ``--head`` rollouts of arms that start with a fixed
  trigger (``DeltaFirstCallback``); a policy that keeps moving adds to that);
* how sure the final policy over options is: on ``--episodes`` of the evaluation's seeded episodes
  (options sampled, as deployed), the share of the decisions whose probability of broadcasting ``p``
  lies in (0.02, 0.98), and the share of the sum of ``p (1 - p)`` (the weight of a decision's
  expected policy gradient) that the 10 % of decisions with the largest weight carry;
* the final policy's evaluation (``evaluation.json``): its control return minus that of predictive
  triggering at exactly its savings on the same episodes (the protocol's ``fixed_predictive`` mode), beside
  the protocol's learned minus the best family; per arm the mean with its 95 % interval over the seeds;
* for arms with a ``selection`` (policies evaluated on validation episodes every so many steps,
  ``selection.json``): at every evaluation, the savings and the control return minus that of
  predictive triggering at the same savings on the same validation episodes (its front over a grid
  of thresholds, ``--grid``, interpolated in the savings).

    python benchmarks/training_walk.py benchmarks/studies/linear_lqr_rate \\
        --arms predictive_first_90_replayed_noent_select predictive_first_90_replayed_expected_noent \\
        predictive_first_90_replayed_expected_noent_anneal predictive_first_90_replayed_expected_noent_anneal_gradient
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import lzma
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.study.report import interval_estimates
from sb3_detc.study.spec import StudyError, load_folder_study
from sb3_detc.triggers import PredictiveTrigger, evaluate_trigger, lqr_on_predicted_states


def rollout_rates(trial: Path) -> tuple[np.ndarray, np.ndarray]:
    """Every logged rollout's timesteps and broadcast rate of a finished trial.

    :param trial: the trial's folder (with ``progress.csv.xz``)
    :return: timesteps and rates (R,)
    """
    rows = csv.DictReader(io.StringIO(lzma.decompress((trial / "progress.csv.xz").read_bytes()).decode()))
    pairs = [
        (float(row["time/total_timesteps"]), float(row["rollout/broadcast_rate"]))
        for row in rows
        if row.get("rollout/broadcast_rate")
    ]
    steps, rates = np.array(pairs).T
    return steps, rates


def sureness(policy: MlpHybridPolicy, env: gym.Env, seeds: list[int]) -> tuple[float, float]:
    """How sure a policy over options is of its decisions on seeded episodes (options sampled).

    :param policy: the final policy
    :param env: the study's env
    :param seeds: the episodes' seeds
    :return: the share of decisions with ``p`` in (0.02, 0.98), and the share of the sum of ``p (1 - p)``
        carried by the 10 % of decisions with the largest ``p (1 - p)``
    """
    probabilities = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            with th.no_grad():
                batch = {key: th.as_tensor(np.asarray(value)[None]) for key, value in obs.items()}
                probabilities.append(policy.broadcast_probabilities(batch).numpy()[0])
            action, _ = policy.predict(obs, deterministic=True)  # options as deployed: sample_options decides
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
    p = np.concatenate(probabilities)
    weights = np.sort(p * (1 - p))[::-1]
    return float(np.mean((p > 0.02) & (p < 0.98))), float(weights[: len(weights) // 10].sum() / weights.sum())


def predictive_front(episodes: int, seed: int, deltas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Savings and control return per agent and episode of predictive triggering over ``deltas``.

    :param episodes: number of episodes
    :param seed: the first episode's seed
    :param deltas: thresholds
    :return: savings and control returns, sorted by savings
    """
    with gym.make("sb3_detc/LinearETC-v0") as env:
        control = lqr_on_predicted_states(env)
        n_agents = env.unwrapped.n_agents
        points = [evaluate_trigger(env, PredictiveTrigger(env, delta), control, episodes, seed) for delta in deltas]
    savings = np.array([p.savings for p in points])
    order = np.argsort(savings)
    return savings[order], -np.array([p.cost for p in points])[order] / n_agents


def main() -> None:
    """Print the walk of every arm's seeds."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("study", type=Path, help="the study's folder")
    parser.add_argument("--arms", nargs="+", required=True, help="labels of the arms")
    parser.add_argument("--tail", type=float, default=0.2, help="share of training at its end (default 0.2)")
    parser.add_argument("--head", type=int, default=40, help="rollouts at the start (default 40)")
    parser.add_argument("--episodes", type=int, default=10, help="episodes of the sureness (default 10)")
    parser.add_argument("--grid", type=int, default=53, help="thresholds of predictive triggering's front (default 53)")
    args = parser.parse_args()
    if not 0.0 < args.tail <= 1.0:
        parser.error(f"--tail must lie in (0, 1], got {args.tail}")
    if args.head < 2:
        parser.error(f"--head must be at least 2, got {args.head}")
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    if args.grid < 2:
        parser.error(f"--grid must be at least 2, got {args.grid}")
    try:
        study = load_folder_study(args.study)
    except StudyError as error:
        parser.error(str(error))
    known = {a.label: a for a in study.algorithms}
    unknown = [arm for arm in args.arms if arm not in known]
    if unknown:
        parser.error(f"no such arms in {args.study}: {', '.join(unknown)}")
    fronts: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    grid = np.linspace(0.10, 0.36, args.grid)
    for arm in args.arms:
        print(f"## {arm}")
        matched = []
        for trial in sorted((args.study / "trials" / arm).glob("seed*")):
            if not (trial / "evaluation.json").exists():
                continue
            metrics = json.loads((trial / "evaluation.json").read_text())["metrics"]
            gap = metrics["control_return"] - metrics["fixed_predictive_control_return"]
            matched.append(gap)
            steps, rates = rollout_rates(trial)
            tail = rates[steps >= steps.max() * (1.0 - args.tail)]
            print(
                f"{trial.name}: broadcast rate over the last {args.tail:.0%} of training: mean {tail.mean():.3f}, "
                f"sd {tail.std():.3f}, range [{tail.min():.3f}, {tail.max():.3f}] ({len(tail)} rollouts); "
                f"over the first {args.head} rollouts: sd {rates[: args.head].std():.3f}"
            )
            with gym.make(study.env, **known[arm].hyperparams.get("env_kwargs", {})) as env:
                undecided, top = sureness(
                    MlpHybridPolicy.load(trial / "policy.pt"),
                    env,
                    list(range(study.eval_seed, study.eval_seed + args.episodes)),
                )
            print(
                f"  final policy: p in (0.02, 0.98) at {undecided:.1%} of decisions; "
                f"top 10 % carry {top:.1%} of p (1 - p); savings {metrics['savings']:.3f}, control return minus "
                f"predictive triggering's at the same savings {gap:+.4f} (the protocol's learned minus the best "
                f"family: {metrics['learned_minus_best_fixed_control_return']:+.4f})"
            )
            selection = known[arm].selection
            if selection is None:
                continue
            key = (selection.episodes, study.validation_seeds(selection.episodes, selection.seed)[0])
            if key not in fronts:
                fronts[key] = predictive_front(*key, grid)
            savings, returns = fronts[key]
            walk = json.loads((trial / "selection.json").read_text())["evaluations"]
            points = [
                f"{e['timesteps'] // 1000}k {e['savings']:.3f} "
                f"{e['control_return'] - np.interp(e['savings'], savings, returns):+.3f}"
                for e in walk
            ]
            print(
                "  at every evaluation on validation episodes, savings and control return minus predictive "
                "triggering's at the same savings: " + ", ".join(points)
            )
            print(f"  savings range [{min(e['savings'] for e in walk):.3f}, {max(e['savings'] for e in walk):.3f}]")
        if len(matched) > 1:
            means, intervals = interval_estimates({"x": np.array(matched)[:, None]})
            low, high = intervals["x"][:, 0]
            print(
                f"{arm}: control return minus predictive triggering's at the same savings over {len(matched)} seeds: "
                f"{means['x'][0]:+.4f} [{low:+.4f}, {high:+.4f}]"
            )


if __name__ == "__main__":
    main()
