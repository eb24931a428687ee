"""MAPPOC on the coupled linear agents: cost against the LQR bound and communication savings.

For every communication cost ``xi`` and seed, MAPPOC trains on ``sb3_detc/LinearETC-v0``
and is then evaluated on the same seeded episodes in three ways, all with its learned
control policy (deterministic: mean control):

* **learned**: options from the learned policy over options (sampled, as in training);
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
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_detc import MAPPOC
from sb3_detc.envs.linear import LinearSystem, lqr_episode_cost
from sb3_detc.evaluation import evaluate_communication
from sb3_detc.triggers import RandomTrigger

#: MAPPOC settings for the linear env (the paper's are for Multiwalker).
HYPERPARAMS = {
    "learning_rate": 3e-4,
    "n_steps": 512,
    "batch_size": 256,
    "n_epochs": 10,
    "reward_scale": 1.0,
    "normalize_reward": True,
    "option_ent_coef": 0.01,
    "policy_kwargs": {"net_arch": [64, 64], "learn_log_std": True},
}


def run(comm_cost: float, seed: int, timesteps: int, eval_episodes: int) -> dict[str, float]:
    """Train one model and evaluate it; returns the table row."""
    env = make_vec_env("sb3_detc/LinearETC-v0", n_envs=2, seed=seed, env_kwargs={"comm_cost": comm_cost})
    model = MAPPOC("MlpHybridPolicy", env, seed=seed, **HYPERPARAMS)
    start = time.perf_counter()
    model.learn(timesteps)
    train_seconds = time.perf_counter() - start
    eval_env = gym.make("sb3_detc/LinearETC-v0", comm_cost=comm_cost)
    bound = lqr_episode_cost(LinearSystem()) / eval_env.unwrapped.n_agents  # per agent, like the returns

    def cost(report) -> float:
        return -report.mean_control_return / bound

    learned = evaluate_communication(model, eval_env, eval_episodes, deterministic=False, seed=10_000)
    # the control policy's mean for the comparisons at equal communication
    learned_det = evaluate_communication(
        model, eval_env, eval_episodes, deterministic=True, seed=10_000,
        option_override=None,
    )
    random = evaluate_communication(
        model, eval_env, eval_episodes, deterministic=True, seed=10_000,
        option_override=RandomTrigger(1 - learned.broadcast_rate, seed=seed),
    )
    periodic = evaluate_communication(
        model, eval_env, eval_episodes, deterministic=True, seed=10_000, option_override=RandomTrigger(0.0)
    )
    return {
        "comm_cost": comm_cost,
        "seed": seed,
        "train_seconds": train_seconds,
        "savings": learned.savings,
        "cost_learned": cost(learned),
        "savings_mode": learned_det.savings,
        "cost_mode": cost(learned_det),
        "cost_random_same_rate": cost(random),
        "cost_periodic": cost(periodic),
    }
