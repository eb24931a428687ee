"""Evaluate a saved MAPPOC model with the study's protocol (``sb3_detc.study``), for a run made outside a study.

The same seeded episodes in four communication modes (learned, random at the learned rate, periodic,
never), as every study trial is evaluated, so that a run of the command line can be set beside a
study's trials:

    python benchmarks/evaluate_saved_model.py <model.zip> --env sb3_detc/MultiwalkerETC-v0 \\
        --env-kwargs broadcast_cost=0.25 --episodes 50 --seed 10000 --out result.json

A model of the random-skip baseline (``ppo_random_skip``) trained with a random trigger instead of
its policy over options: ``--skip-prob 0.55`` evaluates its own options as the study does, with
that trigger.
"""

from __future__ import annotations

import argparse
import ast
import json
from pathlib import Path

import gymnasium as gym
import torch as th

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc import MAPPOC
from sb3_detc.study.trial import evaluate_policy_modes
from sb3_detc.triggers import RandomTrigger


def setting(text: str) -> object:
    """An env setting from the command line: a Python literal (``2``, ``1e-3``, ``True``), else the text.

    :param text: the value of one ``key=value`` of ``--env-kwargs``
    :return: the literal's value, or ``text`` itself if it is no Python literal
    """
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def main() -> None:
    """Evaluate the model in the four communication modes, write the JSON and print its metrics."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path, help="a saved MAPPOC model (.zip)")
    parser.add_argument("--env", required=True, help="the joint env id")
    parser.add_argument(
        "--env-kwargs", nargs="*", default=[], help="key=value of the env (Python literals; other values as text)"
    )
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=10000, help="seed of the first episode")
    parser.add_argument("--out", type=Path, required=True, help="JSON file of the evaluation")
    parser.add_argument(
        "--skip-prob",
        type=float,
        default=None,
        help="the model trained with random skips at this rate (the baseline): its own options are such a trigger",
    )
    args = parser.parse_args()
    if any("=" not in item for item in args.env_kwargs):
        parser.error(f"--env-kwargs takes key=value, got {args.env_kwargs}")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if not args.model.is_file():
        parser.error(f"no saved model {args.model}")
    try:
        own_trigger = None if args.skip_prob is None else RandomTrigger(args.skip_prob)
    except ValueError as error:
        parser.error(f"--skip-prob: {error}")
    env_kwargs = {key: setting(value) for key, value in (item.split("=", 1) for item in args.env_kwargs)}
    th.set_num_threads(1)
    policy = MAPPOC.load(args.model, device="cpu").policy
    env = gym.make(args.env, **env_kwargs)
    try:
        result = evaluate_policy_modes(policy, env, args.episodes, args.seed, own_trigger)
    finally:
        env.close()
    args.out.write_text(json.dumps(result, indent=1))
    for key, value in result["metrics"].items():
        print(f"{key}: {value:.4g}")


if __name__ == "__main__":
    main()
