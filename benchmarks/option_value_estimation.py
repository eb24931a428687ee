"""How well does MAPPOC's option-value critic tell the two options apart on the linear system?

The policy over options learns from the critic (greedy advantage ``Q(o) - max Q``, Sec. 3)
or from sampled returns. This benchmark isolates that estimation problem from everything
else: every agent's control is fixed to the model-based controller (its row of the LQR gain
on its view of held broadcasts, :class:`sb3_detc.triggers.FixedControl`), the options
are uniformly random and not trained (``train_broadcast_policy=False``), and MAPPOC trains only
its critic. Because the options are drawn independently of the state, the mean difference of
the discounted returns that follow a broadcast and a silence in the same class of states is
an unbiased estimate of ``Q(s, broadcast) - Q(s, silent)`` averaged over that class. It is
compared with the critic's own estimate on the same samples, for the states where a
broadcast matters most (the 20 % of agent-steps with the largest change of the trigger
features since the agent's last broadcast, as send-on-delta would rank them) and the rest.

All values are in the learner's reward units (team-mean reward times ``reward_scale``),
collected over all rollouts of a run; returns-to-go are the learner's rewards without the
bootstrap MAPPOC adds at truncations, cut at the end of each episode and of each rollout, and
only steps with at least ``horizon`` steps of rollout ahead are used. The observed difference
is the mean over rollouts of each rollout's difference, with the standard error over rollouts
(the agents share the team reward and returns-to-go overlap, so agent-steps are not
independent; rollouts follow each other in the same episodes, so even this interval is
slightly too narrow).

Rows are written to ``--out`` after every seed; seeds already there are not rerun.

    python benchmarks/option_value_estimation.py --seeds 1 2 --out option_value_estimation.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_detc import MAPPOC
from sb3_detc.study.sweep import OutError, check_at_least_one, run_rows
from sb3_detc.triggers import FixedControl, SendOnDelta

#: MAPPOC settings of ``benchmarks/linear_learning.py`` (lr 3e-4 to let the critic settle quickly).
HYPERPARAMS = {
    "learning_rate": 3e-4,
    "max_grad_norm": 0.5,
    "n_steps": 512,
    "batch_size": 256,
    "n_epochs": 10,
    "reward_scale": 0.01,
    "team_reward": True,
    "broadcast_ent_coef": 0.0,
    "train_broadcast_policy": False,
    "policy_kwargs": {"net_arch": [64, 64], "learn_log_std": True},
}


class OptionValueProbe(BaseCallback):
    """Collect, after every rollout, observed returns and the critic's option values per state class.

    :param quantile: states above this quantile of the trigger change count as "large change"
    :param horizon: steps of rollout needed after a sample for its return-to-go to be used
    """

    def __init__(self, quantile: float, horizon: int) -> None:
        super().__init__()
        self.quantile = quantile
        self.horizon = horizon
        self.samples: dict[str, dict[str, list[np.ndarray]]] = {
            name: {"broadcast": [], "silent": [], "critic": []} for name in ("large change", "rest")
        }

        self._rewards: list[np.ndarray] = []

    def _on_step(self) -> bool:
        # the learner's rewards of this step (n_envs, N), before a truncation's bootstrap is added to
        # them: MAPPOC hands them to the callbacks as SB3's on-policy algorithms do, as ``rewards``
        self._rewards.append(np.array(self.locals["rewards"]))
        return True

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        change = SendOnDelta(0.0).distance(buffer.observations)
        rewards, self._rewards = np.stack(self._rewards), []
        steps = buffer.buffer_size
        returns = np.zeros_like(rewards)
        running = np.zeros_like(rewards[0])
        for t in reversed(range(steps)):
            alive = 1.0 - (buffer.episode_starts[t + 1] if t + 1 < steps else np.ones(buffer.n_envs))
            running = rewards[t] + self.model.gamma * running * alive[:, None]
            returns[t] = running
        keep = slice(0, steps - self.horizon)
        change, returns, broadcast = change[keep], returns[keep], buffer.broadcast[keep]
        q_diff = buffer.option_values[keep][..., 1] - buffer.option_values[keep][..., 0]
        large = change > np.quantile(change, self.quantile)
        for name, mask in (("large change", large), ("rest", ~large)):
            self.samples[name]["broadcast"].append(returns[mask & (broadcast == 1)])
            self.samples[name]["silent"].append(returns[mask & (broadcast == 0)])
            self.samples[name]["critic"].append(q_diff[mask])


def build(seed: int, settings: dict[str, Any]) -> MAPPOC:
    """The untrained model of one seed, on its training envs.

    :param seed: seed of the envs and the model
    :param settings: MAPPOC's settings (:data:`HYPERPARAMS` with the command's changes)
    :return: the model
    :raises ValueError: for settings MAPPOC refuses (TypeError for unknown ones)
    """
    env_kwargs = {"broadcast_cost": 0.03}
    env = make_vec_env("sb3_detc/LinearETC-v0", n_envs=2, seed=seed, env_kwargs=env_kwargs, wrapper_class=FixedControl)
    return MAPPOC("MlpHybridPolicy", env, seed=seed, **settings)


def run(job: dict[str, Any]) -> list[dict[str, float | int | str]]:
    """Train the critic with one seed; returns one row per state class.

    :param job: ``seed``, ``timesteps`` (of training), ``quantile`` and ``horizon`` (see
        :class:`OptionValueProbe`), and ``settings`` (MAPPOC's, :func:`build`)
    :return: per state class (``large change``, ``rest``): samples, the observed difference of returns
        with its standard error over rollouts, the critic's mean estimate and the standard deviation
        of the returns
    """
    seed = job["seed"]
    th.set_num_threads(1)
    model = build(seed, job["settings"])
    probe = OptionValueProbe(job["quantile"], job["horizon"])
    model.learn(job["timesteps"], callback=probe)
    rows = []
    for name, parts in probe.samples.items():
        broadcast, silent, critic = (np.concatenate(parts[key]) for key in ("broadcast", "silent", "critic"))
        per_rollout = np.array(
            [b.mean() - s.mean() for b, s in zip(parts["broadcast"], parts["silent"], strict=True) if len(b) and len(s)]
        )
        rows.append(
            {
                "seed": seed,
                "states": name,
                "samples": len(critic),
                "rollouts": len(per_rollout),
                "observed": float(per_rollout.mean()),
                "observed_se": float(per_rollout.std(ddof=1) / np.sqrt(len(per_rollout))),
                "critic": float(critic.mean()),
                "return_std": float(np.concatenate([broadcast, silent]).std()),
            }
        )
    return rows


def main() -> None:
    """Train one critic per seed in parallel and print the observed and estimated option values."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--timesteps", type=int, default=60_000)
    parser.add_argument("--quantile", type=float, default=0.8)
    parser.add_argument("--horizon", type=int, default=60)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--set", type=json.loads, default={}, help="MAPPOC settings to change (JSON)")
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("option_value_estimation.json"),
        help="rows (JSON); seeds already in it with the same settings are not rerun",
    )
    args = parser.parse_args()
    check_at_least_one(parser, args, "timesteps", "horizon", "workers")
    if not 0 < args.quantile < 1:
        parser.error("--quantile must lie between 0 and 1")
    if not isinstance(args.set, dict):
        parser.error("--set takes a JSON object")
    settings = {**HYPERPARAMS, **args.set}
    try:
        model = build(args.seeds[0], settings)
    except (TypeError, ValueError) as error:
        parser.error(f"settings refused: {error}")
    if args.horizon >= model.n_steps:
        parser.error(f"--horizon must be below the rollout's {model.n_steps} steps")
    if args.timesteps < 2 * model.n_steps * model.n_envs:
        parser.error(f"--timesteps must give at least 2 rollouts ({2 * model.n_steps * model.n_envs} steps)")
    jobs = [
        {
            "seed": seed,
            "timesteps": args.timesteps,
            "quantile": args.quantile,
            "horizon": args.horizon,
            "settings": settings,
        }
        for seed in args.seeds
    ]
    try:
        rows = run_rows(run, jobs, args.out, args.workers)
    except OutError as error:
        parser.error(str(error))
    print("Q(s, broadcast) - Q(s, silent) in the learner's reward units x 1e-4")
    print("(observed: randomised comparison of the returns that followed; critic: MAPPOC's estimate)")
    print()
    print("| seed | states | samples | rollouts | observed +- s.e. | critic's estimate | return std |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for row in rows:
        print(
            f"| {row['seed']} | {row['states']} | {row['samples']} | {row['rollouts']} | "
            f"{1e4 * row['observed']:+.1f} +- "
            f"{1e4 * row['observed_se']:.1f} | {1e4 * row['critic']:+.1f} | {1e4 * row['return_std']:.0f} |"
        )


if __name__ == "__main__":
    main()
