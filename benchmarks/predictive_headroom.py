"""Predictive triggering against a threshold on its prediction error weighted by what it costs (linear system).

Predictive triggering (:class:`~sb3_detc.triggers.PredictiveTrigger`) broadcasts when the
receivers' prediction of an agent is off by more than ``delta`` in the Euclidean norm, and LQR
acts on the predictions. Every unit of that error does not cost the same: an agent's own control
acts on its own state, so its error costs only through the others' controls, ``du = G_i e`` with
``G_i`` agent i's columns of the LQR gain without its own row, and with the team's controls off by
``du`` the Q-function of LQR grows by ``du' (R + B'PB) du`` (``P`` the Riccati solution). This
script weights the error by that cost, summed over the next ``horizon`` steps as the agent's own
closed loop ``Phi_i`` carries it (an approximation: it leaves out the other agents' errors, the
others' drift and the next broadcast)::

    ||e||_W = sqrt(e' W_i e),   W_i = sum_{k < horizon} (Phi_i^k)' G_i' (R + B'PB) G_i Phi_i^k,

tunes both rules to each target savings on the same seeded episodes and prints, per agent and
episode (the units of the studies' tables), their control returns and the paired difference with
its 95 % interval over the episodes: what one better-informed threshold on this error gains over
predictive triggering (a lower bound on what a trigger could gain, not an upper one).

    python benchmarks/predictive_headroom.py --targets 0.8 0.9 0.95 --horizons 1 10
"""

from __future__ import annotations

import argparse
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
from scipy.stats import t as student

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.envs.linear import LinearSystem, lqr_gain
from sb3_detc.triggers import PredictiveTrigger, Trigger, evaluate_trigger, lqr_on_predicted_states, tune_trigger_on_env


def error_cost_weights(system: LinearSystem, horizon: int) -> np.ndarray:
    """Per agent, the matrix ``W_i`` whose quadratic form is the cost of a prediction error over ``horizon`` steps.

    :param system: the linear system
    :param horizon: steps of the prediction the cost is summed over (>= 1)
    :return: ``W``, (N, 2, 2), symmetric positive semidefinite
    """
    gain, riccati = lqr_gain(system)
    _, b, _, r, _ = system.joint_matrices()
    curvature = r + b.T @ riccati @ b
    closed_loop = PredictiveTrigger(system, 0.0).predictor.closed_loop
    weights = np.zeros((system.n_agents, 2, 2))
    for agent in range(system.n_agents):
        others = gain[:, 2 * agent : 2 * agent + 2].copy()
        others[agent] = 0.0  # the agent's own control acts on its current state, not on the prediction
        step_cost, power = others.T @ curvature @ others, np.eye(2)
        for _ in range(horizon):
            weights[agent] += power.T @ step_cost @ power
            power = closed_loop[agent] @ power
    return weights


class CostWeightedPredictive(PredictiveTrigger):
    """Predictive triggering on the error in the norm ``sqrt(e' W_i e)`` instead of the Euclidean one.

    :param system: the linear system
    :param delta: threshold (>= 0), in the units of the weighted norm
    :param weights: ``W`` (N, 2, 2), e.g. :func:`error_cost_weights`
    :raises ValueError: on a bad ``delta`` or ``weights`` of the wrong shape
    """

    def __init__(self, system: LinearSystem, delta: float, weights: np.ndarray) -> None:
        super().__init__(system, delta)
        self.weights = np.asarray(weights, dtype=np.float64)
        if self.weights.shape != (system.n_agents, 2, 2):
            raise ValueError(f"weights must have shape {(system.n_agents, 2, 2)}, got {self.weights.shape}.")

    def __repr__(self) -> str:
        return f"CostWeightedPredictive(delta={self.delta:g})"

    def error(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The weighted norm of the receivers' prediction error, (B, N).

        :param obs: a batch of joint observations, as :meth:`PredictiveTrigger.deviation` reads them
        :return: ``sqrt(e' W_i e)`` per agent, (B, N)
        """
        deviation = self.deviation(obs)
        squared = np.einsum("bni,nij,bnj->bn", deviation, self.weights, deviation)
        return np.sqrt(np.maximum(squared, 0.0))  # a singular W may give -1e-16


def episode_returns(env: gym.Env, trigger: Trigger, episodes: int, seed: int) -> tuple[np.ndarray, float]:
    """Per-episode control returns per agent with LQR on the predictions, and the savings over all episodes.

    :param env: the joint env
    :param trigger: the trigger
    :param episodes: number of episodes, seeded ``seed``, ``seed + 1``, ...
    :param seed: the first episode's seed
    :return: returns (episodes,) and savings
    """
    control = lqr_on_predicted_states(env)
    points = [evaluate_trigger(env, trigger, control, 1, seed + episode) for episode in range(episodes)]
    agents = env.unwrapped.network.system.n_agents
    return -np.array([p.cost for p in points]) / agents, float(np.mean([p.savings for p in points]))


def compare(env: gym.Env, target: float, horizons: list[int], episodes: int, seed: int) -> list[dict[str, Any]]:
    """Both rules tuned to ``target`` on the same episodes, one row per weighted rule.

    :param env: the joint env
    :param target: savings to tune to
    :param horizons: the weighted rules' horizons
    :param episodes: number of episodes
    :param seed: the first episode's seed
    :return: rows with the savings and returns of both rules and the paired difference
    """
    system = env.unwrapped.network.system
    control = lqr_on_predicted_states(env)  # for both: the tuner's default for a callable family acts on held states
    tune = {"target_savings": target, "control": control, "n_episodes": episodes, "seed": seed, "tolerance": 0.002}
    euclidean, _ = tune_trigger_on_env(env, "predictive", initial=0.2, **tune)
    base, base_savings = episode_returns(env, euclidean, episodes, seed)
    rows = []
    for horizon in horizons:
        weights = error_cost_weights(system, horizon)
        make = partial(CostWeightedPredictive, system, weights=weights)
        weighted, _ = tune_trigger_on_env(env, make, initial=0.2, **tune)
        returns, savings = episode_returns(env, weighted, episodes, seed)
        gain = returns - base
        half = student.ppf(0.975, episodes - 1) * gain.std(ddof=1) / np.sqrt(episodes)
        rows.append(
            {
                "target": target,
                "horizon": horizon,
                "euclidean": (base_savings, float(base.mean())),
                "weighted": (savings, float(returns.mean())),
                "gain": (float(gain.mean()), float(gain.mean() - half), float(gain.mean() + half)),
            }
        )
    return rows


def main() -> None:
    """Print the table of both rules at every target."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--targets", type=float, nargs="+", default=[0.9], help="savings targets (default 0.9)")
    parser.add_argument("--horizons", type=int, nargs="+", default=[1, 10], help="weights' horizons (default 1 10)")
    parser.add_argument("--episodes", type=int, default=50, help="seeded episodes (default 50)")
    parser.add_argument("--seed", type=int, default=10000, help="the first episode's seed (default 10000)")
    args = parser.parse_args()
    if args.episodes < 2:
        parser.error(f"--episodes must be at least 2 (an interval over episodes), got {args.episodes}")
    if any(not 0.0 < target < 1.0 for target in args.targets):
        parser.error(f"--targets must lie in (0, 1), got {args.targets}")
    if any(horizon < 1 for horizon in args.horizons):
        parser.error(f"--horizons must be at least 1, got {args.horizons}")
    print(f"control return per agent and episode, {args.episodes} episodes from seed {args.seed}; gain: weighted minus")
    print("Euclidean, paired over the episodes, mean [95 % interval]")
    print("| target | horizon | Euclidean: savings | return | weighted: savings | return | gain |")
    print("|---:|---:|---:|---:|---:|---:|---|")
    with gym.make("sb3_detc/LinearETC-v0") as env:
        for target in args.targets:
            for row in compare(env, target, args.horizons, args.episodes, args.seed):
                gain = "{:+.3f} [{:+.3f}, {:+.3f}]".format(*row["gain"])
                print(
                    f"| {target:g} | {row['horizon']} | {row['euclidean'][0]:.4f} | {row['euclidean'][1]:.3f} | "
                    f"{row['weighted'][0]:.4f} | {row['weighted'][1]:.3f} | {gain} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
