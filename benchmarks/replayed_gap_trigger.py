"""A trigger learned from replayed option gaps against predictive triggering (linear system, LQR on predictions).

MAPPOC's policy over options follows its critic's estimate of what a broadcast is worth, and on
the linear system that estimate ranks the decisions unlike their true value
(``critic_gap_ranking.py``, ``option_value_truth.py``). This script asks what a trigger learned
from *accurate* values of a broadcast reaches: one step of rollout policy iteration.

1. Start from predictive triggering (:class:`~sb3_detc.triggers.PredictiveTrigger`), tuned to the
   target savings on training episodes, with LQR on the receivers' predictions.
2. In ``--train-episodes`` training episodes under the current trigger, at
   ``--decisions`` random (step, agent) pairs per episode, copy the env twice: in one copy the agent
   broadcasts, in the other it stays silent; everything else (the noise, the others' options, the
   later options of the current trigger) is the same in both. The difference of the team's
   control returns over the next ``--horizon`` steps is a low-variance sample of the value of that
   broadcast.
3. Fit, per agent, the value of a broadcast as a quadratic form of what the receivers' prediction
   of the agent would miss if it stayed silent (:meth:`~sb3_detc.triggers.PredictiveTrigger.deviation`),
   by least squares: ``g_i(d) = d' M_i d``.
4. The new trigger broadcasts where ``g_i(d) > lambda``, ``lambda`` tuned to the target savings on
   training episodes. ``--iterations`` repeats 2 to 4 from it.

The learned trigger then runs on the evaluation's seeded episodes, and predictive triggering tuned
to its savings on the same episodes; per seed (an independent set of training episodes and
replays) the paired difference of control return per agent and episode, and over the seeds its
mean with a 95 % bootstrap interval (rliable, as the studies' reports).

    python benchmarks/replayed_gap_trigger.py --seeds 0 1 2 3 4 --out benchmarks/results/replayed_gap_trigger.json
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.files import replace_atomically
from sb3_detc.study.report import interval_estimates
from sb3_detc.triggers import (
    Control,
    PredictiveTrigger,
    Trigger,
    evaluate_trigger,
    lqr_on_predicted_states,
    tune_trigger_on_env,
)


def quadratic_features(deviation: np.ndarray) -> np.ndarray:
    """The monomials of a quadratic form of a 2-D deviation: ``(d0^2, d0 d1, d1^2)``.

    :param deviation: deviations (..., 2)
    :return: features (..., 3)
    """
    d0, d1 = deviation[..., 0], deviation[..., 1]
    return np.stack([d0 * d0, d0 * d1, d1 * d1], axis=-1)


class GapTrigger:
    """Broadcast where the fitted value of a broadcast exceeds ``threshold``.

    :param predictive: the predictive trigger whose deviation the fit reads
    :param coef: per agent the coefficients of :func:`quadratic_features`, (N, 3)
    :param threshold: the price a broadcast must be worth
    """

    def __init__(self, predictive: PredictiveTrigger, coef: np.ndarray, threshold: float) -> None:
        self.predictive, self.coef, self.threshold = predictive, coef, threshold

    def __repr__(self) -> str:
        return f"GapTrigger(threshold={self.threshold:g})"

    def value(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The fitted value of every agent's broadcast now, (B, N).

        :param obs: a batch of joint observations
        :return: values (B, N)
        """
        return np.einsum("bnk,nk->bn", quadratic_features(self.predictive.deviation(obs)), self.coef)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options (B, N): 1 where :meth:`value` exceeds the threshold.

        :param obs: a batch of joint observations
        :return: options (B, N), int64
        """
        return (self.value(obs) > self.threshold).astype(np.int64)


def batched(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One joint observation with a batch axis of size 1.

    :param obs: a joint observation
    :return: the same arrays, (1, N, ...)
    """
    return {key: np.asarray(value)[None] for key, value in obs.items()}


def branch_return(
    env: gym.Env, obs: dict[str, Any], agent: int, option: int, trigger: Trigger, control: Control, horizon: int
) -> float:
    """Team control return of ``horizon`` steps of a copy of ``env`` in which ``agent`` takes ``option`` now.

    :param env: the env at the decision (copied, not stepped)
    :param obs: its current joint observation
    :param agent: the deciding agent
    :param option: its option now (1 broadcast, 0 silent)
    :param trigger: everyone's options otherwise
    :param control: the control law
    :param horizon: steps to follow (fewer at the episode's end)
    :return: the sum of the agents' control rewards
    """
    branch = copy.deepcopy(env)  # copies the generator: the same noise in every copy
    total = 0.0
    for step in range(horizon):
        options = np.asarray(trigger(batched(obs)))[0].astype(np.int64)
        if step == 0:
            options[agent] = option
        obs, _, terminated, truncated, info = branch.step({"broadcast": options, "control": control(obs, options)})
        total += float(np.sum(info["control_rewards"]))
        if terminated or truncated:
            break
    return total


def replayed_gaps(
    env: gym.Env,
    trigger: Trigger,
    control: Control,
    predictive: PredictiveTrigger,
    episodes: list[int],
    decisions: int,
    horizon: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Values of a broadcast, replayed at random decisions of episodes under ``trigger``.

    :param env: the joint env
    :param trigger: the trigger the episodes and the replays follow
    :param control: the control law
    :param predictive: the predictive trigger whose deviation is recorded
    :param episodes: seeds of the episodes
    :param decisions: replayed decisions per episode
    :param horizon: steps of a replay
    :param rng: draws the decisions
    :return: agents (S,), deviations (S, 2), values of a broadcast (S,)
    """
    agents, deviations, gaps = [], [], []
    for seed in episodes:
        obs, _ = env.reset(seed=seed)
        length = env.unwrapped.network.system.max_cycles
        chosen = set(rng.choice(length, min(decisions, length), replace=False).tolist())
        done, step = False, 0
        while not done:
            if step in chosen:
                agent = int(rng.integers(len(obs["age"])))
                gap = branch_return(env, obs, agent, 1, trigger, control, horizon)
                gap -= branch_return(env, obs, agent, 0, trigger, control, horizon)
                agents.append(agent)
                deviations.append(predictive.deviation(batched(obs))[0, agent])
                gaps.append(gap)
            options = np.asarray(trigger(batched(obs)))[0].astype(np.int64)
            obs, _, terminated, truncated, _ = env.step({"broadcast": options, "control": control(obs, options)})
            done, step = terminated or truncated, step + 1
    return np.array(agents), np.array(deviations), np.array(gaps)


def fit_gaps(agents: np.ndarray, deviations: np.ndarray, gaps: np.ndarray, n_agents: int) -> tuple[np.ndarray, list]:
    """Per agent, least-squares coefficients of the value of a broadcast on :func:`quadratic_features`.

    :param agents: the deciding agents (S,)
    :param deviations: their deviations (S, 2)
    :param gaps: the replayed values (S,)
    :param n_agents: number of agents
    :return: coefficients (N, 3) and every agent's R^2 on its samples
    """
    coef, r2 = np.zeros((n_agents, 3)), []
    for agent in range(n_agents):
        mine = agents == agent
        x, y = quadratic_features(deviations[mine]), gaps[mine]
        coef[agent] = np.linalg.lstsq(x, y, rcond=None)[0]
        r2.append(float(1.0 - np.var(y - x @ coef[agent]) / np.var(y)))
    return coef, r2


def episode_returns(env: gym.Env, trigger: Trigger, control: Control, seeds: list[int]) -> tuple[np.ndarray, float]:
    """Control return per agent of every episode, and the savings over them.

    :param env: the joint env
    :param trigger: the trigger
    :param control: the control law
    :param seeds: the episodes' seeds
    :return: returns (episodes,) and savings
    """
    points = [evaluate_trigger(env, trigger, control, 1, seed) for seed in seeds]
    n_agents = env.unwrapped.network.system.n_agents
    return -np.array([p.cost for p in points]) / n_agents, float(np.mean([p.savings for p in points]))


def run_seed(env: gym.Env, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """One seed: learn the trigger from its own training episodes, compare it on the evaluation's.

    :param env: the joint env
    :param seed: the seed of the training episodes and of the replayed decisions
    :param args: the command line
    :return: the seed's record
    """
    control = lqr_on_predicted_states(env)
    train = [100_000 * (seed + 1) + k for k in range(args.train_episodes)]
    tune = {"target_savings": args.target, "control": control, "tolerance": args.tolerance}
    trigger, _ = tune_trigger_on_env(env, "predictive", initial=0.2, n_episodes=50, seed=train[0], **tune)
    predictive = trigger
    rng = np.random.default_rng(seed)
    record: dict[str, Any] = {"seed": seed, "iterations": []}
    started = time.time()
    for iteration in range(args.iterations):
        agents, deviations, gaps = replayed_gaps(
            env, trigger, control, predictive, train, args.decisions, args.horizon, rng
        )
        coef, r2 = fit_gaps(agents, deviations, gaps, len(predictive.predictor.closed_loop))
        trigger, point = tune_trigger_on_env(
            env,
            lambda threshold, coef=coef: GapTrigger(predictive, coef, threshold),
            initial=float(np.median(gaps[gaps > 0])),
            n_episodes=50,
            seed=train[0],
            **tune,
        )
        record["iterations"].append(
            {"samples": len(gaps), "coef": coef.tolist(), "r2": r2, "threshold": trigger.threshold}
        )
        print(
            f"seed {seed} iteration {iteration}: {len(gaps)} replays, R^2 {np.round(r2, 2).tolist()}, "
            f"threshold {trigger.threshold:.4g} ({time.time() - started:.0f} s)",
            flush=True,
        )
    evaluation = list(range(args.seed, args.seed + args.episodes))
    learned, savings = episode_returns(env, trigger, control, evaluation)
    matched, _ = tune_trigger_on_env(
        env,
        "predictive",
        initial=predictive.delta,
        n_episodes=args.episodes,
        seed=args.seed,
        target_savings=savings,
        control=control,
        tolerance=args.tolerance,
    )
    baseline, baseline_savings = episode_returns(env, matched, control, evaluation)
    record.update(
        learned=float(learned.mean()),
        savings=savings,
        predictive=float(baseline.mean()),
        predictive_savings=baseline_savings,
        predictive_delta=matched.delta,
        learned_minus_predictive=float((learned - baseline).mean()),
    )
    print(
        f"seed {seed}: learned {record['learned']:.3f} at {savings:.4f}, predictive {record['predictive']:.3f} at "
        f"{baseline_savings:.4f}, difference {record['learned_minus_predictive']:+.3f}",
        flush=True,
    )
    return record


def main() -> None:
    """Run every seed, write the JSON, print the summary."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="seeds (default 0 to 4)")
    parser.add_argument("--target", type=float, default=0.9, help="target savings (default 0.9)")
    parser.add_argument("--train-episodes", type=int, default=200, help="training episodes per seed (default 200)")
    parser.add_argument("--decisions", type=int, default=50, help="replayed decisions per episode (default 50)")
    parser.add_argument("--horizon", type=int, default=60, help="steps of a replay (default 60)")
    parser.add_argument("--iterations", type=int, default=1, help="policy iterations (default 1)")
    parser.add_argument("--episodes", type=int, default=50, help="evaluation episodes (default 50)")
    parser.add_argument("--seed", type=int, default=10000, help="the first evaluation episode's seed (default 10000)")
    parser.add_argument(
        "--tolerance", type=float, default=0.002, help="savings tolerance of the tuning (default 0.002)"
    )
    parser.add_argument("--out", type=Path, help="JSON file of the records (written after every seed)")
    args = parser.parse_args()
    if not 0.0 < args.target < 1.0:
        parser.error(f"--target must lie in (0, 1), got {args.target}")
    for name in ("train_episodes", "decisions", "horizon", "iterations", "episodes"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    records = []
    with gym.make("sb3_detc/LinearETC-v0") as env:
        for seed in args.seeds:
            records.append(run_seed(env, seed, args))
            if args.out is not None:
                payload = json.dumps({"args": vars(args) | {"out": str(args.out)}, "seeds": records}, indent=1)
                replace_atomically(args.out, lambda path, payload=payload: path.write_text(payload + "\n"))
    differences = np.array([[r["learned_minus_predictive"]] for r in records])
    if len(records) > 1:
        means, intervals = interval_estimates({"x": differences})
        low, high = intervals["x"][:, 0]
        print(
            f"learned minus predictive over {len(records)} seeds: {means['x'][0]:+.3f} [{low:+.3f}, {high:+.3f}] "
            f"(control return per agent and episode, {args.episodes} paired episodes per seed)"
        )


if __name__ == "__main__":
    main()
