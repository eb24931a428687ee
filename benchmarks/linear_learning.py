"""MAPPOC on the coupled linear agents: cost against the LQR bound and communication savings.

For every communication cost ``xi`` and seed, MAPPOC trains on ``sb3_detc/LinearETC-v0``
and is then evaluated on the same seeded episodes in three ways, all with its learned
control policy (deterministic: mean control):

* **learned**: options sampled from the learned policy over options, as in training (its
  mode is a poor summary of a stochastic trigger: an agent whose most likely option is
  "silent" in some state may never broadcast again);
* **random, same rate**: options drawn at random with the learned broadcast rate (the
  paper's baseline at equal communication);
* **periodic**: every agent broadcasts every step.

Costs are the team's quadratic cost per episode (communication cost excluded), relative
to the exact expected cost of the optimal centralised finite-horizon LQR controller under
periodic communication (:func:`sb3_detc.envs.linear.lqr_episode_cost`): 1.00 is the
physical lower bound. Savings are ``1 - broadcasts / agent-steps``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_detc import MAPPOC
from sb3_detc.callbacks import ControlFirstCallback, OptionEntropySchedule
from sb3_detc.envs.linear import LinearSystem, lqr_episode_cost
from sb3_detc.evaluation import evaluate_communication
from sb3_detc.mappoc.policies import CRITICS
from sb3_detc.triggers import RandomTrigger

#: MAPPOC settings for the linear env (the paper's are for Multiwalker).
HYPERPARAMS = {
    "learning_rate": 1e-4,
    "max_grad_norm": 0.5,
    "n_steps": 512,
    "batch_size": 256,
    "n_epochs": 10,
    "reward_scale": 0.01,
    "team_reward": True,
    "policy_kwargs": {"net_arch": [64, 64], "learn_log_std": True},
}
#: Option entropy: 0.1 while the control policy learns (iterations 0-100 of 1024 steps), then down to 0.001 at 200.
ENTROPY_SCHEDULE = {"initial": 0.1, "final": 0.001, "start": 100, "end": 200}
EVAL_SEED = 10_000


def run(job: tuple[float, int, str, str, int, int, dict[str, Any], dict[str, Any] | None]) -> dict[str, Any]:
    """Train one model and evaluate it at equal communication; returns one table row.

    The last entry of ``job``: None for the option entropy schedule, or the arguments of
    :class:`~sb3_detc.callbacks.ControlFirstCallback` for two stages.
    """
    comm_cost, seed, option_advantage, critic, timesteps, eval_episodes, changes, control_first = job
    th.set_num_threads(1)
    env = make_vec_env("sb3_detc/LinearETC-v0", n_envs=2, seed=seed, env_kwargs={"comm_cost": comm_cost})
    policy_kwargs = {**HYPERPARAMS["policy_kwargs"], "critic": critic, **changes.get("policy_kwargs", {})}
    settings = {**HYPERPARAMS, **changes, "policy_kwargs": policy_kwargs}
    model = MAPPOC("MlpHybridPolicy", env, seed=seed, option_advantage=option_advantage, **settings)
    start = time.perf_counter()
    if control_first is None:
        callback: BaseCallback = OptionEntropySchedule(**ENTROPY_SCHEDULE)
    else:
        callback = ControlFirstCallback(**control_first)
    model.learn(timesteps, callback=callback)
    train_seconds = time.perf_counter() - start
    eval_env = gym.make("sb3_detc/LinearETC-v0", comm_cost=comm_cost)
    bound = lqr_episode_cost(LinearSystem()) / eval_env.unwrapped.n_agents  # per agent, like the returns

    def evaluate(**kwargs) -> tuple[float, float]:
        report = evaluate_communication(model, eval_env, eval_episodes, deterministic=True, seed=EVAL_SEED, **kwargs)
        return -report.mean_control_return / bound, report.savings

    cost_learned, savings = evaluate(deterministic_options=False)
    cost_random, _ = evaluate(option_override=RandomTrigger(savings, seed=seed))
    cost_periodic, _ = evaluate(option_override=RandomTrigger(0.0))
    return {
        "comm_cost": comm_cost,
        "seed": seed,
        "option_advantage": option_advantage,
        "critic": critic,
        "changes": changes,
        "control_first": control_first,
        "timesteps": timesteps,
        "train_seconds": round(train_seconds, 1),
        "savings": round(savings, 3),
        "cost_learned": round(cost_learned, 3),
        "cost_random_same_rate": round(cost_random, 3),
        "cost_periodic": round(cost_periodic, 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--comm-costs", type=float, nargs="+", default=[0.03])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--option-advantages", nargs="+", default=["greedy"])
    parser.add_argument("--critics", nargs="+", default=["option_heads"], choices=list(CRITICS))
    parser.add_argument("--set", type=json.loads, default={}, help="MAPPOC settings to change (JSON)")
    parser.add_argument(
        "--control-first",
        type=json.loads,
        default=None,
        help="two stages instead of the entropy schedule: ControlFirstCallback arguments (JSON), e.g. "
        '\'{"switch": 293, "trigger_learning_rate": 1e-3}\'',
    )
    parser.add_argument("--timesteps", type=int, default=300_000)
    parser.add_argument("--eval-episodes", type=int, default=60)
    parser.add_argument("--workers", type=int, default=2, help="parallel training processes")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "linear_learning.json")
    args = parser.parse_args()
    jobs = [
        (xi, seed, adv, critic, args.timesteps, args.eval_episodes, args.set, args.control_first)
        for xi in args.comm_costs
        for adv in args.option_advantages
        for critic in args.critics
        for seed in args.seeds
    ]
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        rows = pool.map(run, jobs)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))
    bound = lqr_episode_cost(LinearSystem())
    print(f"episode cost bound (optimal centralised LQR, periodic communication): {bound:.3f} per team")
    print(f"settings changed: {args.set}")
    if args.control_first is not None:
        print(f"two stages: ControlFirstCallback({args.control_first})")
    print()
    print(
        "| comm cost | option advantage | critic | seed | savings | cost learned | cost random, same rate "
        "| cost periodic |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['comm_cost']} | {row['option_advantage']} | {row['critic']} | {row['seed']} | "
            f"{row['savings']:.2f} | "
            f"{row['cost_learned']:.2f} | {row['cost_random_same_rate']:.2f} | {row['cost_periodic']:.2f} |"
        )


if __name__ == "__main__":
    main()
