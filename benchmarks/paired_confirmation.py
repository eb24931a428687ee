"""A study's learned triggers against one fixed family on many more episodes, with the episodes' own noise counted.

The study protocol runs every trial on the same 50 seeded episodes, and the interval of a
learned-minus-family gap is a bootstrap over the seeds alone. The episodes are shared by the
seeds, so what they happen to favour moves every seed alike and stays in the mean, outside that
interval. This benchmark measures how much: for the given arms of a study, per finished seed,

* from the study's ``evaluation.json``: the per-episode gaps (the learned control return minus that of
  ``--family`` at exactly the learned savings, as the protocol mixes it; and ``thresholded`` minus
  it), their mean correlation between seeds, and two intervals of the mean gap: rliable's over the
  seeds (the study's) and one over seeds and episodes both (``crossed_interval`` of the study report);
* the same from a new evaluation of every final policy on ``--episodes`` episodes from ``--seed``
  (after the study's and its validation's seeds), with the same protocol and only ``--family``
  compared; every trial's result is kept as JSON beside ``--out`` and read again when present, so
  an interrupted run goes on where it stopped.

    python benchmarks/paired_confirmation.py benchmarks/studies/linear_lqr_rate \\
        --arms predictive_first_90_replayed_expected_noent_anneal_gradient --episodes 500 --seed 30000 \\
        --cpus 2 --out benchmarks/results/paired_confirmation.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_detc.evaluate import load_saved
from sb3_detc.evaluation import evaluate_policy_modes
from sb3_detc.study.report import crossed_interval, interval_estimates, paired_differences
from sb3_detc.study.spec import StudyError, load_folder_study
from sb3_detc.study.trial import read_status


def evaluate_trial(policy_path: str, family: str, episodes: int, seed: int) -> dict[str, Any]:
    """One trial's final policy in the protocol on other episodes, with one fixed family compared.

    :param policy_path: the trial's ``policy.pt``
    :param family: the fixed family compared at exactly the learned savings
    :param episodes: episodes per mode
    :param seed: seed of the first episode
    :return: what :func:`~sb3_detc.evaluation.evaluate_policy_modes` returns
    """
    saved = load_saved(policy_path)
    env = gym.make(saved.env_id, **saved.env_kwargs)
    try:
        return evaluate_policy_modes(saved.policy, env, episodes, seed, saved.trigger, fixed_families=(family,))
    finally:
        env.close()


def summary(results: list[dict[str, Any]], family: str) -> dict[str, Any]:
    """The gaps of one arm's seeds on one set of episodes, with both intervals.

    :param results: every seed's evaluation (the same episodes)
    :param family: the fixed family
    :return: per mode (learned, thresholded where every seed has it): per-seed means, the mean, rliable's
        interval over seeds, the interval over seeds and episodes, the mean correlation between seeds
        of the per-episode gaps; and the savings per seed
    """
    out: dict[str, Any] = {
        "episodes": len(results[0]["modes"]["learned"]["control_return"]),
        "savings": [result["metrics"]["savings"] for result in results],
    }
    for mode, values in paired_differences(results, family).items():
        per_seed = values.mean(axis=1)
        means, intervals = interval_estimates({"x": per_seed[:, None]})
        correlations = np.corrcoef(values)[np.triu_indices(len(values), 1)] if len(values) > 1 else np.array([])
        out[mode] = {
            "per_seed": per_seed.tolist(),
            "mean": float(means["x"][0]),
            "interval_seeds": intervals["x"][:, 0].tolist(),
            "interval_seeds_and_episodes": list(crossed_interval(values)),
            "correlation_between_seeds": float(correlations.mean()) if correlations.size else None,
        }
    return out


def main() -> None:
    """Evaluate, summarise and print every arm."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", type=Path, help="a study folder")
    parser.add_argument("--arms", nargs="+", required=True, help="labels of the study's algorithms")
    parser.add_argument("--family", default="predictive", help="the fixed family compared (default: predictive)")
    parser.add_argument("--episodes", type=int, default=500, help="episodes of the new evaluation (default: 500)")
    parser.add_argument("--seed", type=int, default=30000, help="seed of its first episode (default: 30000)")
    parser.add_argument("--cpus", type=int, default=1, help="trials evaluated at once (default: 1)")
    parser.add_argument("--out", type=Path, required=True, help="the summary (JSON); trials' results beside it")
    args = parser.parse_args()
    if args.episodes < 2:
        parser.error("--episodes must be at least 2 (the interval varies the episodes)")
    if args.cpus < 1:
        parser.error("--cpus must be at least 1")
    try:
        spec = load_folder_study(args.study)
    except StudyError as error:
        parser.error(str(error))
    seeds = {algorithm.label: algorithm.seeds for algorithm in spec.algorithms}
    unknown = sorted(set(args.arms) - set(seeds))
    if unknown:
        parser.error(f"not algorithms of {args.study}: {', '.join(unknown)}")
    if args.family not in spec.fixed_families:
        parser.error(f"{args.study} does not compare {args.family!r} (its families: {', '.join(spec.fixed_families)})")
    kept = args.out.with_suffix("")
    trials = {
        arm: [
            args.study / "trials" / arm / f"seed{seed}"
            for seed in seeds[arm]
            if read_status(args.study / "trials" / arm / f"seed{seed}")["status"] == "done"
        ]
        for arm in args.arms
    }
    todo = [
        (trial, kept / arm / f"{trial.name}.json")
        for arm, arm_trials in trials.items()
        for trial in arm_trials
        if not (kept / arm / f"{trial.name}.json").exists()
    ]
    print(f"{sum(map(len, trials.values()))} trials, {len(todo)} to evaluate on {args.episodes} episodes", flush=True)
    began = time.monotonic()
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max(1, args.cpus), mp_context=context) as pool:
        futures = {
            pool.submit(evaluate_trial, str(trial / "policy.pt"), args.family, args.episodes, args.seed): (trial, path)
            for trial, path in todo
        }
        for k, future in enumerate(as_completed(futures), 1):
            trial, path = futures[future]
            result = future.result()
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(result) + "\n")
            print(
                f"{trial.parent.name}/{trial.name}: savings {result['metrics']['savings']:.3f} "
                f"({k} of {len(todo)}, {time.monotonic() - began:.0f} s)",
                flush=True,
            )
    report: dict[str, Any] = {"family": args.family, "episodes": args.episodes, "seed": args.seed, "arms": {}}
    print(f"\nlearned (and thresholded) minus {args.family} at the same savings, per agent and episode:")
    print("| arm | episodes | seeds | savings | mean | over seeds (rliable) | over seeds and episodes | correlation |")
    print("|---|---|---|---|---|---|---|---|")
    for arm, arm_trials in trials.items():
        if not arm_trials:
            print(f"| {arm} | no finished seeds | | | | | | |")
            continue
        study = [json.loads((trial / "evaluation.json").read_text()) for trial in arm_trials]
        new = [json.loads((kept / arm / f"{trial.name}.json").read_text()) for trial in arm_trials]
        report["arms"][arm] = {
            "seeds": [trial.name for trial in arm_trials],
            "study": summary(study, args.family),
            "new": summary(new, args.family),
        }
        for which in ("study", "new"):
            entry = report["arms"][arm][which]
            for mode in ("learned", "thresholded"):
                if mode not in entry:
                    continue
                row = entry[mode]
                seeds, both = row["interval_seeds"], row["interval_seeds_and_episodes"]
                correlation = row["correlation_between_seeds"]
                print(
                    f"| {arm}{' (thresholded)' * (mode == 'thresholded')} | {entry['episodes']} | {len(arm_trials)} "
                    f"| {np.mean(entry['savings']):.3f} | {row['mean']:+.4f} | [{seeds[0]:+.4f}, {seeds[1]:+.4f}] "
                    f"| [{both[0]:+.4f}, {both[1]:+.4f}] | {'-' if correlation is None else f'{correlation:.2f}'} |"
                )
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"\n{args.out}")


if __name__ == "__main__":
    main()
