"""Does a trained policy over options time its messages? Its broadcast probability and option gap against the own age.

A policy over options that reads the age of its own last broadcast (``option_age_scale``) can
learn a schedule: rarely broadcast right after a broadcast, more and more often as the own
information ages. This script runs a saved policy or model (read as ``python -m sb3_detc.evaluate``
reads it: the env and its settings from the study trial or rl-zoo3 run it is in, or ``--env``) on
seeded episodes with options drawn at random with probability ``--broadcast-prob`` (so that every
age occurs, whatever the policy would choose) and the policy's mean controls, and prints, per band
of the own age: the number of agent-steps, the policy's mean probability of broadcasting (and its
standard deviation over the states of the band), and the critic's mean gap between both options'
values ``Q(1) - Q(0)`` as the policy computes them without a broadcast price (a critic that learns
the cost from the rewards, the paper's ``option_heads``, includes it), with the correlation of the
gap with the age.

    python benchmarks/option_age_profile.py \\
        benchmarks/results/multiwalker_trigger_rate_age_ent/mappoc_paper_seed0_ac3ef814fe.pt \\
        --env sb3_detc/MultiwalkerETC-v0 --env-kwargs '{"broadcast_cost": 0.25}' --episodes 10
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

#: Lower edges of the age bands (steps since the own last broadcast); the last band is open.
BANDS = (0, 4, 8, 16, 32)


def profile(policy: MlpHybridPolicy, env: gym.Env, seeds: list[int], broadcast_prob: float) -> dict[str, np.ndarray]:
    """Run episodes with random options and record, per agent-step, the own age, ``p_i`` and ``Q(1) - Q(0)``.

    :param policy: the trained policy
    :param env: a joint event-triggered env (observations with ``age``)
    :param seeds: one episode per seed
    :param broadcast_prob: probability of a broadcast in the random options (every agent, every step)
    :return: ``age``, ``probability`` and ``gap``, one entry per agent-step
    """
    rng = np.random.default_rng(seeds[0] if seeds else 0)
    policy.set_training_mode(False)
    ages, probabilities, gaps = [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            tensors = {key: th.as_tensor(np.asarray(value)[None]).float() for key, value in obs.items()}
            n = tensors["age"].shape[1]
            broadcast = th.as_tensor((rng.random((1, n)) < broadcast_prob).astype(np.int64))
            with th.no_grad():
                action = policy(tensors, deterministic=True, broadcast=broadcast)
                probability = policy.broadcast_probabilities(tensors)
            ages.append(np.asarray(obs["age"])[:, 0])
            probabilities.append(probability[0].numpy())
            gaps.append((action.option_values[0, :, 1] - action.option_values[0, :, 0]).numpy())
            control = th.clamp(action.control, policy.control_low, policy.control_high)[0].numpy()
            obs, _, terminated, truncated, _ = env.step({"broadcast": broadcast[0].numpy(), "control": control})
            done = terminated or truncated
    return {"age": np.concatenate(ages), "probability": np.concatenate(probabilities), "gap": np.concatenate(gaps)}


def bands(samples: dict[str, np.ndarray]) -> list[dict[str, float | int | None]]:
    """Summaries per age band (:data:`BANDS`): samples, mean and sd of ``p_i``, mean of the gap.

    :param samples: the result of :func:`profile`
    :return: one dict per band that has samples (``low``, ``high`` (None: open), ``n``, ``probability``,
        ``probability_sd``, ``gap``)
    """
    rows = []
    for low, high in zip(BANDS, (*BANDS[1:], None), strict=True):
        inside = (samples["age"] >= low) & (True if high is None else samples["age"] < high)
        if inside.any():
            p = samples["probability"][inside]
            rows.append(
                {
                    "low": low,
                    "high": high,
                    "n": int(inside.sum()),
                    "probability": float(p.mean()),
                    "probability_sd": float(p.std()),
                    "gap": float(samples["gap"][inside].mean()),
                }
            )
    return rows


def main() -> None:
    """Profile a saved policy and print the table (and write it as JSON with ``--out``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policy", type=Path, help="a saved MAPPOC model (.zip) or policy (policy.pt)")
    parser.add_argument("--env", help="env id (default: from the study trial or rl-zoo3 run the policy is in)")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help="env settings to add or replace (JSON)")
    parser.add_argument("--episodes", type=int, default=10, help="episodes, seeds from 10000 on")
    parser.add_argument("--broadcast-prob", type=float, default=0.0625, help="probability of a random broadcast")
    parser.add_argument("--out", type=Path, help="write the bands as JSON")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    if not 0 <= args.broadcast_prob <= 1:
        parser.error("--broadcast-prob must be in [0, 1]")
    try:
        saved = load_saved(args.policy, args.env)
    except InputError as error:
        parser.error(str(error))
    th.set_num_threads(1)
    env_kwargs = {**saved.env_kwargs, **args.env_kwargs}
    with gym.make(saved.env_id, **env_kwargs) as env:
        samples = profile(saved.policy, env, [EVAL_SEED + k for k in range(args.episodes)], args.broadcast_prob)
    rows = bands(samples)
    where = f"{args.policy} on {saved.env_id} {env_kwargs}"
    print(f"{where}: {args.episodes} episodes, options random at {args.broadcast_prob}")
    print()
    print("| own age | agent-steps | p(broadcast), mean (sd) | Q(1) - Q(0), mean |")
    print("|---|---:|---|---:|")
    for row in rows:
        age = f"{row['low']} and more" if row["high"] is None else f"{row['low']} to {row['high'] - 1}"
        print(f"| {age} | {row['n']} | {row['probability']:.3f} ({row['probability_sd']:.3f}) | {row['gap']:+.3f} |")
    correlation = np.corrcoef(samples["gap"], samples["age"])[0, 1] if samples["age"].std() > 0 else float("nan")
    print()
    print(f"Correlation of the option gap with the own age: {correlation:.2f}")
    if args.out is not None:
        args.out.write_text(json.dumps({"bands": rows, "gap_age_correlation": float(correlation)}, indent=1))


if __name__ == "__main__":
    main()
