"""Which states a learned trigger ranks first, against predictive triggering, on the linear system.

Predictive triggering broadcasts where the receivers' prediction of an agent is off the most.
For every finished seed of the given arms of a study on ``LinearETC-LQR-v0`` with the receivers'
predictions shown (``predicted_held``), this script runs predictive triggering (send-on-delta on
the shown predictions, the ``DeltaFirstCallback``'s trigger) on seeded episodes and, at every
agent-step, sets three rankings side by side: the prediction error (what predictive triggering
thresholds), the trained critic's broadcast gap ``Q_i(s, 1) - Q_i(s, 0)`` (without the price: what
the greedy option advantages move ``mu`` toward), and ``mu``'s probability of broadcasting. Per
arm it prints, mean [min, max] over seeds:

* the rank correlation (Spearman) of the critic's gap and of ``mu``'s probability with the error;
* the overlap at the target: the share of the agent-steps with the largest 10 % of the critic's gap
  (or of ``mu``'s probability) that are among those with the largest 10 % of the error (1.0: the
  same states; 0.1: unrelated).

    python benchmarks/critic_gap_ranking.py benchmarks/studies/linear_lqr_rate \\
        --arms predictive_imitated_90 predictive_first_90 predictive_first_90_quantile predicted_held_90_distance
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from scipy.stats import spearmanr
from stable_baselines3.common.utils import obs_as_tensor

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.study.spec import StudyError, load_folder_study
from sb3_detc.triggers import SendOnDelta

#: The threshold of send-on-delta on the shown predictions at 90 % savings (the study's DeltaFirstCallback).
DELTA = 0.21


def predictive_states(env_kwargs: dict[str, Any], episodes: int, seed: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Every step's joint observation and options under predictive triggering, stacked over the episodes.

    :param env_kwargs: the arm's env settings (``predicted_held=True``)
    :param episodes: number of episodes, seeded ``seed``, ``seed + 1``, ...
    :param seed: the first episode's seed
    :return: observations (T, N, ...) by key, and the options taken (T, N)
    """
    trigger = SendOnDelta(DELTA)
    observations: list[dict[str, np.ndarray]] = []
    options: list[np.ndarray] = []
    with gym.make("sb3_detc/LinearETC-LQR-v0", **env_kwargs) as env:
        control = np.zeros(env.action_space["control"].shape, dtype=np.float32)  # LQR acts (FixedControl)
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            done = False
            while not done:
                broadcast = trigger({key: value[None] for key, value in obs.items()})[0]
                observations.append(obs)
                options.append(broadcast)
                obs, _, terminated, truncated, _ = env.step({"broadcast": broadcast, "control": control})
                done = terminated or truncated
    stacked = {key: np.stack([obs[key] for obs in observations]) for key in observations[0]}
    return stacked, np.stack(options)


def top_overlap(score: np.ndarray, reference: np.ndarray, share: float) -> float:
    """The share of the entries with the largest ``share`` of ``score`` that are among the largest of ``reference``.

    :param score: a ranking's scores (flat)
    :param reference: the reference's scores (flat, same length)
    :param share: the share of the entries on top (equal scores are ordered at random, seeded)
    :return: the overlap, in [0, 1]
    """
    k = max(1, round(share * len(score)))
    ties = np.random.default_rng(0).random(len(score))  # equal scores (a saturated mu) in random order

    def top(values: np.ndarray) -> set[int]:
        return set(np.lexsort((ties, -values))[:k].tolist())

    return len(top(score) & top(reference)) / k


def rankings(policy: MlpHybridPolicy, obs: dict[str, np.ndarray], options: np.ndarray) -> dict[str, float]:
    """How the policy's critic and ``mu`` rank the agent-steps against the prediction error.

    :param policy: a trained policy
    :param obs: observations (T, N, ...) by key
    :param options: the options taken (T, N) (the others' options that an afterstate critic reads)
    :return: rank correlations and top-10 % overlaps of the critic's gap and of ``mu``'s probability
    """
    error = SendOnDelta(DELTA).distance(obs).ravel()
    with th.no_grad():
        tensors = obs_as_tensor(obs, policy.device)
        broadcast = th.as_tensor(options, device=policy.device)
        control = th.zeros((*options.shape, policy.action_space["control"].shape[-1]), device=policy.device)
        values = policy.evaluate_actions(tensors, broadcast, control).option_values.cpu().numpy()
        probability = policy.broadcast_probabilities(tensors).cpu().numpy().ravel()
    gap = (values[..., 1] - values[..., 0]).ravel()
    return {
        "gap_spearman": float(spearmanr(gap, error).statistic),
        "mu_spearman": float(spearmanr(probability, error).statistic),
        "gap_top10": top_overlap(gap, error, 0.1),
        "mu_top10": top_overlap(probability, error, 0.1),
    }


def main() -> None:
    """Print every arm's rankings against predictive triggering's error, over its finished seeds."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path, help="a study folder on LinearETC-LQR-v0")
    parser.add_argument("--arms", nargs="+", required=True, help="labels of arms with predicted_held=True")
    parser.add_argument("--episodes", type=int, default=20, help="seeded episodes (default 20)")
    parser.add_argument("--seed", type=int, default=10000, help="the first episode's seed (default 10000)")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    try:
        study = load_folder_study(args.folder)
    except StudyError as err:
        parser.error(str(err))
    arms = {spec.label: spec for spec in study.algorithms}
    unknown = [arm for arm in args.arms if arm not in arms]
    if unknown:
        parser.error(f"no arms {unknown} in {args.folder}; it has {sorted(arms)}")
    print("metric: mean [min, max] over seeds; overlap: share of the top 10 % that is predictive's top 10 %")
    print("| arm | seeds | gap rank corr. | mu rank corr. | gap top-10 % overlap | mu top-10 % overlap |")
    print("|---|---:|---:|---:|---:|---:|")
    for arm in args.arms:
        spec = arms[arm]
        env_kwargs = spec.entry.get("env_kwargs", {})
        if not env_kwargs.get("predicted_held"):
            parser.error(f"arm {arm!r} does not show the receivers' predictions (predicted_held)")
        obs, options = predictive_states(env_kwargs, args.episodes, args.seed)
        rows = []
        for seed in spec.seeds:
            path = args.folder / "trials" / arm / f"seed{seed}" / "policy.pt"
            if path.exists():
                rows.append(rankings(MlpHybridPolicy.load(str(path), device="cpu"), obs, options))
        if not rows:
            print(f"| {arm} | 0 | | | | |")
            continue
        cells = []
        for key in ("gap_spearman", "mu_spearman", "gap_top10", "mu_top10"):
            values = np.array([row[key] for row in rows])
            cells.append(f"{values.mean():.2f} [{values.min():.2f}, {values.max():.2f}]")
        print(f"| {arm} | {len(rows)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
