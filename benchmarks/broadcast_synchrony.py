"""Do the agents of a learned trigger broadcast together, apart, or independently of each other?

A periodic schedule with all agents in phase sends every message together with the others'; one
staggered over the agents never does. This script runs saved policies (read as ``python -m
sb3_detc.evaluate`` reads them: the env and its settings from the study trial or rl-zoo3 run they are
in, or ``--env``) on seeded episodes with their options as they are deployed (sampled for
``sample_options=True``) and mean controls, and prints per policy the broadcast rate of every agent,
the share of broadcasts sent in a step in which another agent broadcast too (*together*), and that
share if every agent broadcast independently at its own rate (*independent*: for agent ``i``,
``1 - prod_{j != i} (1 - rate_j)``, weighted by the agents' broadcasts).

    python benchmarks/broadcast_synchrony.py benchmarks/results/multiwalker_trigger_window_9375/*.pt \\
        --env sb3_detc/MultiwalkerETC-v0 --env-kwargs '{"broadcast_cost": 0.25}' --episodes 20
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.cli import InputError
from sb3_detc.evaluate import load_saved
from sb3_detc.evaluation import EVAL_SEED
from sb3_detc.mappoc.policies import MlpHybridPolicy


def synchrony(broadcasts: np.ndarray) -> dict[str, float | list[float]]:
    """How often the agents' broadcasts fall in the same step, against independent timing at the same rates.

    :param broadcasts: every step's options, (steps, N) of 0 and 1
    :return: ``rates`` (per agent), ``together`` (share of the broadcasts with another agent's in the
        same step; NaN without broadcasts) and ``independent`` (that share under independent timing at
        the same rates)
    """
    broadcasts = np.asarray(broadcasts, dtype=bool)
    rates = broadcasts.mean(axis=0)
    counts = broadcasts.sum(axis=0)
    others = broadcasts.sum(axis=1, keepdims=True) - broadcasts  # per step and agent: how many others sent
    total = counts.sum()
    together = float((broadcasts & (others > 0)).sum() / total) if total else float("nan")
    n = broadcasts.shape[1]
    alone = np.array([np.prod([1 - rates[j] for j in range(n) if j != i]) for i in range(n)])
    independent = float(((1 - alone) * counts).sum() / total) if total else float("nan")
    return {"rates": rates.tolist(), "together": together, "independent": independent}


def run_options(policy: MlpHybridPolicy, env: gym.Env, seeds: list[int]) -> np.ndarray:
    """Every step's options of a policy as it is deployed, over one episode per seed.

    :param policy: the trained policy
    :param env: a joint event-triggered env
    :param seeds: one episode per seed; PyTorch's generator is seeded with the first (sampled options repeat)
    :return: (steps, N), the episodes one after another
    """
    th.manual_seed(seeds[0])
    rows = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            action, _ = policy.predict(obs, deterministic=True)
            rows.append(np.asarray(action["broadcast"]))
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
    return np.array(rows)


def main() -> None:
    """Run every policy and print the table (and write it as JSON with ``--out``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policies", type=Path, nargs="+", help="saved MAPPOC models (.zip) or policies (.pt)")
    parser.add_argument("--env", help="env id (default: from the study trial or rl-zoo3 run a policy is in)")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help="env settings to add or replace (JSON)")
    parser.add_argument("--episodes", type=int, default=20, help="episodes, seeds from 10000 on")
    parser.add_argument("--out", type=Path, help="write the rows as JSON")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    try:
        saved = [load_saved(path, args.env) for path in args.policies]
    except InputError as error:
        parser.error(str(error))
    th.set_num_threads(1)
    seeds = [EVAL_SEED + k for k in range(args.episodes)]
    rows = []
    print(f"{args.episodes} episodes (seeds {seeds[0]} to {seeds[-1]}), options as deployed, mean controls")
    print()
    print("| policy | broadcast rate per agent | together | independent |")
    print("|---|---|---:|---:|")
    for path, one in zip(args.policies, saved, strict=True):
        env_kwargs = {**one.env_kwargs, **args.env_kwargs}
        with gym.make(one.env_id, **env_kwargs) as env:
            row = {"policy": str(path), "env_kwargs": env_kwargs, **synchrony(run_options(one.policy, env, seeds))}
        rows.append(row)
        rates = ", ".join(f"{rate:.3f}" for rate in row["rates"])
        print(f"| {path.name} | {rates} | {row['together']:.3f} | {row['independent']:.3f} |", flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
