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

With ``--from-zoo`` the settings and callbacks are those of the ``sb3_detc/LinearETC-v0``
entry of ``sb3_detc/hyperparams/mappoc.yml`` (what ``python -m sb3_detc.train`` trains);
without it, the script's own settings below (the one-stage run of benchmarks/appendix.md, section
"Linear system: control and communication learned jointly").

Rows are written to ``--out`` after every job; jobs already there are not rerun.

    python benchmarks/linear_learning.py --critics afterstate --seeds 0 1 --timesteps 600000 --out rows.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch as th
from rl_zoo3.utils import get_callback_list
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_detc import MAPPOC
from sb3_detc.callbacks import BroadcastEntropySchedule, ControlFirstCallback
from sb3_detc.cli import ZOO_KEYS, algorithm_arguments, check_hyperparams_file
from sb3_detc.envs.linear import LinearSystem, lqr_episode_cost
from sb3_detc.evaluation import evaluate_communication
from sb3_detc.mappoc.critics import CRITICS
from sb3_detc.study.sweep import OutError, check_at_least_one, run_rows
from sb3_detc.triggers import RandomTrigger
from sb3_detc.zoo import HYPERPARAMS_DIR

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
#: Broadcast entropy: 0.1 while the control policy learns (iterations 0-100 of 1024 steps), then down to 0.001 at 200.
ENTROPY_SCHEDULE = {"initial": 0.1, "final": 0.001, "start": 100, "end": 200}
EVAL_SEED = 10_000
ENV_ID = "sb3_detc/LinearETC-v0"
#: The keys of a zoo entry, besides MAPPOC's arguments, that the script reproduces (others are refused).
REPRODUCED = frozenset({"n_timesteps", "policy", "n_envs", "env_kwargs", "callback"})


def zoo_recipe() -> dict[str, Any]:
    """The linear entry of the package's ``mappoc.yml``: MAPPOC settings, envs, steps, callbacks.

    :return: ``settings`` (MAPPOC arguments, ``policy_kwargs`` as a dict), ``n_envs``,
        ``env_kwargs``, ``n_timesteps`` and ``callback`` (the entry's callback list)
    :raises ValueError: if the entry uses rl-zoo3 settings the script does not reproduce (e.g. ``normalize``)
        or another policy than ``MlpHybridPolicy``
    """
    path = HYPERPARAMS_DIR / "mappoc.yml"
    entry = dict(check_hyperparams_file(path, "mappoc", ENV_ID))
    unknown = sorted((ZOO_KEYS - REPRODUCED) & entry.keys())
    if unknown:
        raise ValueError(f"the {ENV_ID} entry of {path} uses {unknown}, which this script does not reproduce")
    if entry["policy"] != "MlpHybridPolicy":
        raise ValueError(
            f"the {ENV_ID} entry of {path} names the policy {entry['policy']!r}; the script trains MlpHybridPolicy"
        )
    return {
        "settings": algorithm_arguments(entry, f"{path} [{ENV_ID}]"),
        "n_envs": entry.get("n_envs", 1),
        "env_kwargs": entry.get("env_kwargs", {}),
        "n_timesteps": int(entry["n_timesteps"]),
        "callback": entry.get("callback", []),
    }


def build(job: dict[str, Any]) -> tuple[MAPPOC, dict[str, Any], list[BaseCallback]]:
    """The model, env settings and callbacks of one job, untrained.

    :param job: ``broadcast_cost``, ``seed``, ``changes`` (settings to change) and either ``recipe``
        (:func:`zoo_recipe`) or ``hyperparams`` (:data:`HYPERPARAMS`), ``broadcast_advantage``, ``critic``
        and ``control_first`` (None for the broadcast entropy schedule ``entropy_schedule``, or the
        arguments of :class:`~sb3_detc.callbacks.ControlFirstCallback` for two stages)
    :return: the model (on its training envs), the env keyword arguments and the callbacks
    :raises ValueError: for settings MAPPOC or the callbacks refuse (TypeError for unknown ones)
    """
    broadcast_cost, seed, changes, recipe = job["broadcast_cost"], job["seed"], job["changes"], job.get("recipe")
    if recipe is not None:
        base, n_envs = recipe["settings"], recipe["n_envs"]
        env_kwargs = {**recipe["env_kwargs"], "broadcast_cost": broadcast_cost}
        callbacks: list[BaseCallback] = get_callback_list({"callback": recipe["callback"]})
    else:
        base = {**job["hyperparams"], "broadcast_advantage": job["broadcast_advantage"]}
        base["policy_kwargs"] = {**job["hyperparams"]["policy_kwargs"], "critic": job["critic"]}
        n_envs, env_kwargs = 2, {"broadcast_cost": broadcast_cost}
        control_first = job["control_first"]
        schedule = BroadcastEntropySchedule(**job["entropy_schedule"])
        callbacks = [schedule if control_first is None else ControlFirstCallback(**control_first)]
    env = make_vec_env(ENV_ID, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs)
    policy_kwargs = {**base.get("policy_kwargs", {}), **changes.get("policy_kwargs", {})}
    settings = {**base, **changes, "policy_kwargs": policy_kwargs}
    return MAPPOC("MlpHybridPolicy", env, seed=seed, **settings), env_kwargs, callbacks


def run(job: dict[str, Any]) -> dict[str, Any]:
    """Train one model and evaluate it at equal communication; returns one table row.

    :param job: the model's settings (:func:`build`), ``timesteps`` and ``eval_episodes``
    :return: the settings, training seconds, savings and the costs (relative to the LQR bound) of the
        learned trigger, random options at the same rate and periodic communication
    """
    th.set_num_threads(1)
    model, env_kwargs, callbacks = build(job)
    seed = job["seed"]
    start = time.perf_counter()
    model.learn(job["timesteps"], callback=callbacks)
    train_seconds = time.perf_counter() - start
    eval_env = gym.make(ENV_ID, **env_kwargs)
    bound = lqr_episode_cost(LinearSystem()) / eval_env.unwrapped.n_agents  # per agent, like the returns

    def evaluate(**kwargs) -> tuple[float, float]:
        report = evaluate_communication(
            model, eval_env, job["eval_episodes"], deterministic=True, seed=EVAL_SEED, **kwargs
        )
        return -report.mean_control_return / bound, report.savings

    cost_learned, savings = evaluate(sample_options=True)
    cost_random, _ = evaluate(fixed_trigger=RandomTrigger(savings, seed=seed))
    cost_periodic, _ = evaluate(fixed_trigger=RandomTrigger(0.0))
    return {
        "broadcast_cost": job["broadcast_cost"],
        "seed": seed,
        "recipe": "zoo entry" if job.get("recipe") is not None else "script",
        "broadcast_advantage": model.broadcast_advantage,
        "critic": model.policy.critic,
        "changes": job["changes"],
        "control_first": job.get("control_first"),
        "timesteps": job["timesteps"],
        "train_seconds": round(train_seconds, 1),
        "savings": round(savings, 3),
        "cost_learned": round(cost_learned, 3),
        "cost_random_same_rate": round(cost_random, 3),
        "cost_periodic": round(cost_periodic, 3),
    }


def main() -> None:
    """Train and evaluate every broadcast cost, variant and seed in parallel, write the rows and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--broadcast-costs", type=float, nargs="+", default=[0.03])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--from-zoo", action="store_true", help="settings and callbacks of the mappoc.yml entry")
    parser.add_argument("--broadcast-advantages", nargs="+", help="(not with --from-zoo; default: greedy)")
    parser.add_argument(
        "--critics", nargs="+", choices=list(CRITICS), help="(not with --from-zoo; default: option_heads)"
    )
    parser.add_argument("--set", type=json.loads, default={}, help="MAPPOC settings to change (JSON)")
    parser.add_argument(
        "--control-first",
        type=json.loads,
        default=None,
        help="two stages instead of the entropy schedule (not with --from-zoo): ControlFirstCallback "
        'arguments (JSON), e.g. \'{"switch": 293, "trigger_learning_rate": 1e-3}\'',
    )
    parser.add_argument("--timesteps", type=int, help="training steps (default: 300000, or the entry's)")
    parser.add_argument("--eval-episodes", type=int, default=60)
    parser.add_argument("--workers", type=int, default=2, help="parallel training processes")
    parser.add_argument(
        "--out", type=Path, default=Path("linear_learning.json"), help="rows (JSON); jobs already in it are not rerun"
    )
    args = parser.parse_args()
    check_at_least_one(parser, args, "eval_episodes", "workers", "timesteps")
    if not isinstance(args.set, dict) or not isinstance(args.control_first, dict | None):
        parser.error("--set and --control-first take a JSON object")
    common = {"eval_episodes": args.eval_episodes, "changes": args.set}
    if args.from_zoo:
        if args.broadcast_advantages or args.critics or args.control_first is not None:
            parser.error("--from-zoo takes the broadcast advantage, critic and stages from the entry (use --set)")
        try:
            recipe = zoo_recipe()
        except ValueError as error:
            parser.error(str(error))
        common.update(recipe=recipe, timesteps=args.timesteps or recipe["n_timesteps"])
        variants = [{}]
    else:
        common.update(timesteps=args.timesteps or 300_000, control_first=args.control_first, hyperparams=HYPERPARAMS)
        if args.control_first is None:
            common["entropy_schedule"] = ENTROPY_SCHEDULE
        variants = [
            {"broadcast_advantage": adv, "critic": critic}
            for adv in args.broadcast_advantages or ["greedy"]
            for critic in args.critics or ["option_heads"]
        ]
    jobs = [
        {**common, **variant, "broadcast_cost": xi, "seed": seed}
        for xi in args.broadcast_costs
        for variant in variants
        for seed in args.seeds
    ]
    for variant in variants:  # refuse bad settings before anything trains
        for xi in args.broadcast_costs:
            try:
                build({**common, **variant, "broadcast_cost": xi, "seed": args.seeds[0]})
            except (TypeError, ValueError) as error:
                parser.error(f"settings {variant or ''} at broadcast cost {xi} refused: {error}")
    try:
        rows = run_rows(run, jobs, args.out, args.workers)
    except OutError as error:
        parser.error(str(error))
    bound = lqr_episode_cost(LinearSystem())
    print(f"episode cost bound (optimal centralised LQR, periodic communication): {bound:.3f} per team")
    print(f"settings: {'the zoo entry of ' + ENV_ID if args.from_zoo else 'the script'}; changed: {args.set}")
    if args.control_first is not None:
        print(f"two stages: ControlFirstCallback({args.control_first})")
    print()
    print(
        "| broadcast cost | broadcast advantage | critic | seed | savings | cost learned | cost random, same rate "
        "| cost periodic |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['broadcast_cost']} | {row['broadcast_advantage']} | {row['critic']} | {row['seed']} | "
            f"{row['savings']:.2f} | "
            f"{row['cost_learned']:.2f} | {row['cost_random_same_rate']:.2f} | {row['cost_periodic']:.2f} |"
        )


if __name__ == "__main__":
    main()
