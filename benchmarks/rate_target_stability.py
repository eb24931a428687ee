"""How steadily a rate target holds the broadcast rate: one training run of the LinearETC-LQR-v0 entry with a target.

MAPPOC's ``target_savings`` adapts a price per broadcast by dual ascent after every rollout. Where a
broadcast is worth little, the policy over options answers a small change of the price with a large
change of its rate, and the two can chase each other. This script trains the package's
``sb3_detc/LinearETC-LQR-v0`` entry of ``hyperparams/mappoc.yml`` (its settings, envs and steps, one
torch thread; the policy over options reads its own age) with a target and the given step size of
the price, with or without the normalised option advantages of the entry, and prints every fifth
rollout's broadcast rate, the mean and standard deviation of the last 30 rollouts' rates, the final
price, and the savings and control return of the final policy on 50 seeded episodes (seeds 10000 to
10049, options sampled from the policy over options).

    python benchmarks/rate_target_stability.py --target 0.8 --price-lr 0.02
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc import MAPPOC
from sb3_detc.cli import algorithm_arguments, check_hyperparams_file
from sb3_detc.evaluation import EVAL_SEED, evaluate_episodes
from sb3_detc.mappoc.workers import RolloutWorker
from sb3_detc.zoo import HYPERPARAMS_DIR

ENV_ID = "sb3_detc/LinearETC-LQR-v0"


class Rates(BaseCallback):
    """Every rollout's broadcast rate."""

    def __init__(self) -> None:
        super().__init__()
        self.rates: list[float] = []

    def _on_rollout_end(self) -> None:
        self.rates.append(float(self.model.rollout_buffer.broadcast.mean()))

    def _on_step(self) -> bool:
        return True


def main() -> None:
    """Train once with a rate target and print how the rate moved."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", type=float, default=0.8, help="target_savings, in (0, 1)")
    parser.add_argument("--price-lr", type=float, default=0.02, help="broadcast_price_lr (> 0)")
    parser.add_argument(
        "--raw-advantages", action="store_true", help="normalize_broadcast_advantage=False (the entry: True)"
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(1)
    path = HYPERPARAMS_DIR / "mappoc.yml"
    entry = check_hyperparams_file(path, "mappoc", ENV_ID)
    arguments = algorithm_arguments(entry, f"{path} [{ENV_ID}]")
    # mu reads its own age, as in the study files with rate targets
    arguments["policy_kwargs"] = {**arguments["policy_kwargs"], "option_age_scale": 0.1}
    env = make_vec_env(
        ENV_ID, n_envs=entry["n_envs"], seed=args.seed, wrapper_class=RolloutWorker, env_kwargs=entry["env_kwargs"]
    )
    try:
        model = MAPPOC(
            entry["policy"],
            env,
            **{**arguments, "normalize_broadcast_advantage": not args.raw_advantages},
            target_savings=args.target,
            broadcast_price_lr=args.price_lr,
            seed=args.seed,
        )
    except ValueError as error:
        parser.error(str(error))
    rates = Rates()
    start = time.perf_counter()
    model.learn(int(entry["n_timesteps"]), callback=rates)
    seconds = time.perf_counter() - start
    last = np.array(rates.rates[-30:])
    print(
        f"target {args.target} price lr {args.price_lr} normalised advantages {not args.raw_advantages}: "
        f"{seconds:.0f} s; last 30 rollouts' rate {last.mean():.3f} (sd {last.std():.3f}); "
        f"price {model.broadcast_price:.3f}"
    )
    print("rate every 5th rollout:", np.round(rates.rates[::5], 2).tolist())
    with gym.make(ENV_ID, **entry["env_kwargs"]) as evaluation_env:
        episodes = evaluate_episodes(model.policy, evaluation_env, list(range(EVAL_SEED, EVAL_SEED + 50)))
    print(
        f"final policy on 50 episodes: savings {episodes.savings:.3f}, "
        f"control return {np.mean(episodes.control_returns):.3f}"
    )


if __name__ == "__main__":
    main()
