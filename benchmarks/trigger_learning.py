"""Learning only *when* to communicate: MAPPOC's trigger for a fixed model-based controller.

On ``sb3_detc/LinearETC-v0`` every agent's control is fixed to its row of the LQR gain applied
to its view of held broadcasts (:class:`sb3_detc.triggers.FixedControl`), the setting in
which send-on-delta is the classic event trigger. MAPPOC then learns only its policies over
options (its control policy has no effect). After training, the learned trigger (options
sampled from ``mu``) runs the same seeded evaluation episodes as random skipping at the same
broadcast rate and as send-on-delta; send-on-delta's cost at the learned savings is
interpolated on its delta sweep. Costs are per episode and team, relative to the optimal
centralised finite-horizon LQR cost with periodic communication (1.0). A learned trigger
that works lies below random skipping at equal savings, ideally near send-on-delta.

Variants (``--variants``):

* ``paper``: greedy broadcast advantage ``Q(o) - max Q``, rewards scaled by 0.01, gamma 0.99,
  undecided initial policy over options (broadcast probability 0.5), broadcast entropy 0.1
  until iteration 50, down to 0.001 at 150 (``linear_learning.py``'s settings, its entropy
  schedule 50 iterations earlier);
* ``sparse``: greedy advantage, normalised rewards, gamma 0.95, initial broadcast
  probability 0.1, constant broadcast entropy coefficient 0.01;
* ``sparse-return``: as ``sparse`` with the sampled broadcast advantage (lambda-return minus
  the state value) and broadcast entropy coefficient 0.003;
* ``afterstate``: as ``sparse`` with the afterstate critic (``critic="afterstate"``);
* ``afterstate-paper``: as ``paper`` with the afterstate critic;
* ``afterstate-normalised``: as ``afterstate`` with normalised broadcast advantages
  (``normalize_broadcast_advantage=True``) and broadcast entropy coefficient 0.03;
* ``centred-normalised``: the same with the centred critic (``critic="centred"``).

Rows are written to ``--out`` after every job; jobs already there are not rerun.

    python benchmarks/trigger_learning.py --variants afterstate-normalised --seeds 0 1 --out trigger_learning.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_detc import MAPPOC
from sb3_detc.callbacks import BroadcastEntropySchedule
from sb3_detc.envs.linear import LinearSystem, lqr_episode_cost
from sb3_detc.evaluation import evaluate_communication
from sb3_detc.study.sweep import OutError, check_at_least_one, run_rows
from sb3_detc.triggers import FixedControl, RandomTrigger, TriggerPoint, lqr_on_held_states, sweep_send_on_delta

BASE = {
    "n_steps": 512,
    "batch_size": 256,
    "n_epochs": 10,
    "max_grad_norm": 0.5,
    "team_reward": True,
}
SPARSE = {
    **BASE,
    "learning_rate": 3e-4,
    "normalize_reward": True,
    "reward_scale": 1.0,
    "gamma": 0.95,
    "policy_kwargs": {"net_arch": [64, 64], "broadcast_prob_init": 0.1},
}
#: variant -> (MAPPOC settings, broadcast entropy schedule or None)
VARIANTS: dict[str, tuple[dict[str, Any], dict[str, float] | None]] = {
    "paper": (
        {**BASE, "learning_rate": 1e-4, "reward_scale": 0.01, "policy_kwargs": {"net_arch": [64, 64]}},
        {"initial": 0.1, "final": 0.001, "start": 50, "end": 150},
    ),
    "sparse": ({**SPARSE, "broadcast_ent_coef": 0.01}, None),
    "sparse-return": ({**SPARSE, "broadcast_ent_coef": 0.003, "broadcast_advantage": "return"}, None),
}
VARIANTS["afterstate"] = (
    {**VARIANTS["sparse"][0], "policy_kwargs": {**SPARSE["policy_kwargs"], "critic": "afterstate"}},
    None,
)
VARIANTS["afterstate-paper"] = (
    {**VARIANTS["paper"][0], "policy_kwargs": {"net_arch": [64, 64], "critic": "afterstate"}},
    VARIANTS["paper"][1],
)
VARIANTS["afterstate-normalised"] = (
    {
        **SPARSE,
        "broadcast_ent_coef": 0.03,
        "normalize_broadcast_advantage": True,
        "policy_kwargs": {**SPARSE["policy_kwargs"], "critic": "afterstate"},
    },
    None,
)
VARIANTS["centred-normalised"] = (
    {
        **VARIANTS["afterstate-normalised"][0],
        "policy_kwargs": {**SPARSE["policy_kwargs"], "critic": "centred"},
    },
    None,
)
DELTAS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0)
EVAL_SEED = 10_000


def cost_at_savings(curve: list[TriggerPoint], savings: float, bound: float) -> float | None:
    """Send-on-delta's cost at given savings, interpolated linearly on its sweep.

    :param curve: the sweep's points (:func:`~sb3_detc.triggers.sweep_send_on_delta`)
    :param savings: the savings to read the cost at
    :param bound: the cost the result is relative to
    :return: the relative cost, or None if ``savings`` lies outside the savings the sweep reached
    """
    order = np.argsort([point.savings for point in curve])
    reached = [curve[i].savings for i in order]
    if not reached[0] <= savings <= reached[-1]:
        return None
    return float(np.interp(savings, reached, [curve[i].cost / bound for i in order]))


def run(job: dict[str, Any]) -> dict[str, Any]:
    """Train one trigger and evaluate it against random skipping and send-on-delta; one table row.

    :param job: ``variant`` (a key of :data:`VARIANTS`) and ``settings`` (its value), ``seed``,
        ``broadcast_cost``, ``timesteps`` (of training), ``eval_episodes`` and ``save_dir`` (the folder to
        save the model to; None: not kept)
    :return: the settings, training seconds, savings and the costs (relative to the LQR bound) of the
        learned trigger, random skipping at the same rate and send-on-delta at the same savings (None
        where the learned savings lie outside its sweep's)
    """
    variant, seed, broadcast_cost = job["variant"], job["seed"], job["broadcast_cost"]
    timesteps, episodes, save_dir = job["timesteps"], job["eval_episodes"], job["save_dir"]
    th.set_num_threads(1)
    settings, schedule = job["settings"]
    env_kwargs = {"broadcast_cost": broadcast_cost}
    env = make_vec_env("sb3_detc/LinearETC-v0", n_envs=2, seed=seed, env_kwargs=env_kwargs, wrapper_class=FixedControl)
    model = MAPPOC("MlpHybridPolicy", env, seed=seed, **settings)
    start = time.perf_counter()
    model.learn(timesteps, callback=BroadcastEntropySchedule(**schedule) if schedule else None)
    seconds = time.perf_counter() - start
    if save_dir is not None:
        model.save(Path(save_dir) / f"{variant}_xi{broadcast_cost:g}_seed{seed}.zip")

    eval_env = FixedControl(gym.make("sb3_detc/LinearETC-v0", **env_kwargs))
    bound = lqr_episode_cost(LinearSystem())

    def cost(**kwargs: Any) -> tuple[float, float]:
        report = evaluate_communication(model, eval_env, episodes, deterministic=True, seed=EVAL_SEED, **kwargs)
        return -report.mean_control_return * eval_env.unwrapped.n_agents / bound, report.savings

    learned, savings = cost(sample_options=True)
    random, _ = cost(fixed_trigger=RandomTrigger(savings, seed=seed))
    curve = sweep_send_on_delta(eval_env.env, lqr_on_held_states(eval_env), DELTAS, n_episodes=episodes, seed=EVAL_SEED)
    send_on_delta = cost_at_savings(curve, savings, bound)
    return {
        "variant": variant,
        "seed": seed,
        "broadcast_cost": broadcast_cost,
        "timesteps": timesteps,
        "train_seconds": round(seconds, 1),
        "savings": round(savings, 3),
        "cost_learned": round(learned, 3),
        "cost_random_same_rate": round(random, 3),
        "cost_send_on_delta_same_savings": None if send_on_delta is None else round(send_on_delta, 3),
    }


def main() -> None:
    """Train and evaluate every variant, broadcast cost and seed in parallel, write the rows and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--broadcast-costs", type=float, nargs="+", default=[0.03])
    parser.add_argument("--timesteps", type=int, default=150_000)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2, help="parallel training processes")
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(__file__).parent / "results" / "trigger_learning.json",
        help="rows (JSON); jobs already in it are not rerun, rows of other jobs are kept",
    )
    parser.add_argument("--save-dir", type=Path, default=None, help="folder for the trained models (default: not kept)")
    args = parser.parse_args()
    check_at_least_one(parser, args, "timesteps", "eval_episodes", "workers")
    for xi in args.broadcast_costs:
        try:
            gym.make("sb3_detc/LinearETC-v0", broadcast_cost=xi).close()
        except ValueError as error:
            parser.error(str(error))
    if args.save_dir is not None:
        args.save_dir.mkdir(parents=True, exist_ok=True)
    jobs = [
        {
            "variant": v,
            "seed": seed,
            "broadcast_cost": xi,
            "timesteps": args.timesteps,
            "eval_episodes": args.eval_episodes,
            "save_dir": None if args.save_dir is None else str(args.save_dir),
            "settings": VARIANTS[v],  # a job of changed settings is a new job
        }
        for v in args.variants
        for xi in args.broadcast_costs
        for seed in args.seeds
    ]
    try:
        rows = run_rows(run, jobs, args.out, args.workers)
    except OutError as error:
        parser.error(str(error))
    print(f"{args.timesteps} steps per run, {args.eval_episodes} evaluation episodes")
    print()
    print(
        "| variant | broadcast cost | seed | savings | cost learned | cost random, same rate "
        "| cost send-on-delta, same savings |"
    )
    print("|---|---|---|---:|---:|---:|---:|")
    for row in rows:
        send_on_delta = row["cost_send_on_delta_same_savings"]
        print(
            f"| {row['variant']} | {row['broadcast_cost']} | {row['seed']} | {row['savings']:.3f} | "
            f"{row['cost_learned']:.3f} | {row['cost_random_same_rate']:.3f} | "
            f"{'outside the sweep' if send_on_delta is None else f'{send_on_delta:.3f}'} |"
        )


if __name__ == "__main__":
    main()
