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
collected over all rollouts of a run; returns-to-go are cut at the end of each rollout and
only steps with at least ``horizon`` steps of rollout ahead are used.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_detc import MAPPOC
from sb3_detc.triggers import FixedControl

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

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        change = np.linalg.norm(buffer.observations["trigger"] - buffer.observations["trigger_held"], axis=-1)
        steps = buffer.buffer_size
        returns = np.zeros_like(buffer.rewards)
        running = np.zeros_like(buffer.rewards[0])
        for t in reversed(range(steps)):
            alive = 1.0 - (buffer.episode_starts[t + 1] if t + 1 < steps else np.ones(buffer.n_envs))
            running = buffer.rewards[t] + self.model.gamma * running * alive[:, None]
            returns[t] = running
        keep = slice(0, steps - self.horizon)
        change, returns, broadcast = change[keep], returns[keep], buffer.broadcast[keep]
        q_diff = buffer.option_values[keep][..., 1] - buffer.option_values[keep][..., 0]
        large = change > np.quantile(change, self.quantile)
        for name, mask in (("large change", large), ("rest", ~large)):
            self.samples[name]["broadcast"].append(returns[mask & (broadcast == 1)])
            self.samples[name]["silent"].append(returns[mask & (broadcast == 0)])
            self.samples[name]["critic"].append(q_diff[mask])


def run(job: tuple[int, int, float, int, dict[str, Any]]) -> list[dict[str, float | int | str]]:
    """Train the critic with one seed; returns one row per state class.

    :param job: seed, training timesteps, quantile and horizon (see :class:`OptionValueProbe`), and
        MAPPOC settings that override :data:`HYPERPARAMS`
    :return: per state class (``large change``, ``rest``): samples, the observed difference of returns
        with its standard error, the critic's mean estimate and the standard deviation of the returns
    """
    seed, timesteps, quantile, horizon, overrides = job
    th.set_num_threads(1)
    env_kwargs = {"broadcast_cost": 0.03}
    env = make_vec_env("sb3_detc/LinearETC-v0", n_envs=2, seed=seed, env_kwargs=env_kwargs, wrapper_class=FixedControl)
    model = MAPPOC("MlpHybridPolicy", env, seed=seed, **{**HYPERPARAMS, **overrides})
    probe = OptionValueProbe(quantile, horizon)
    model.learn(timesteps, callback=probe)
    rows = []
    for name, parts in probe.samples.items():
        broadcast, silent, critic = (np.concatenate(parts[key]) for key in ("broadcast", "silent", "critic"))
        observed = broadcast.mean() - silent.mean()
        stderr = np.sqrt(broadcast.var() / len(broadcast) + silent.var() / len(silent))
        rows.append(
            {
                "seed": seed,
                "states": name,
                "samples": len(critic),
                "observed": float(observed),
                "observed_se": float(stderr),
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
    args = parser.parse_args()
    overrides = args.set
    jobs = [(seed, args.timesteps, args.quantile, args.horizon, overrides) for seed in args.seeds]
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        results = pool.map(run, jobs)
    print("Q(s, broadcast) - Q(s, silent) in the learner's reward units x 1e-4")
    print("(observed: randomised comparison of the returns that followed; critic: MAPPOC's estimate)")
    print()
    print("| seed | states | samples | observed +- s.e. | critic's estimate | return std |")
    print("|---|---|---:|---:|---:|---:|")
    for row in (row for rows in results for row in rows):
        print(
            f"| {row['seed']} | {row['states']} | {row['samples']} | {1e4 * row['observed']:+.1f} +- "
            f"{1e4 * row['observed_se']:.1f} | {1e4 * row['critic']:+.1f} | {1e4 * row['return_std']:.0f} |"
        )


if __name__ == "__main__":
    main()
