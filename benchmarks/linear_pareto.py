"""Cost versus communication savings on the linear system: send-on-delta, random skipping, MAPPOC.

On the default ``sb3_detc/LinearETC-v0``, every point is the mean team control cost per
episode (communication cost excluded) relative to the optimal centralised finite-horizon
LQR cost with periodic communication (:func:`sb3_detc.envs.linear.lqr_episode_cost`, the
physical bound 1.0), against the communication savings ``1 - broadcasts / agent-steps``:

(a) send-on-delta triggers with the LQR controller on held states over a sweep of delta,
(b) random skipping with the same controller over skip probabilities,
(c) optionally trained MAPPOC models (``--models a.zip b.zip``), learned options sampled and
    the mean control, evaluated with :func:`sb3_detc.evaluation.evaluate_communication`.

(a) and (b) use the same seeded episodes (episode i has seed ``seed + i``); the models'
episodes start from ``seed`` and continue its generator. Writes a PNG and prints a
markdown table.

    python benchmarks/linear_pareto.py --models logs/pareto_models/*.zip --fixed-control --out pareto.png
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium
import matplotlib
import numpy as np
import torch

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.envs.linear import lqr_episode_cost
from sb3_detc.triggers import (
    FixedControl,
    RandomTrigger,
    TriggerPoint,
    evaluate_trigger,
    lqr_on_held_states,
    sweep_send_on_delta,
)

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the backend)

ENV_ID = "sb3_detc/LinearETC-v0"
DELTAS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0)
SKIP_PROBS = (0.0, 0.25, 0.5, 0.75, 0.9, 0.95)
DEFAULT_OUT = Path(__file__).parent / "results" / "linear_pareto.png"


def model_point(path: str, env: gymnasium.Env, n_episodes: int, seed: int) -> TriggerPoint:
    """A trained MAPPOC model as one point: learned options sampled, mean control.

    :param path: the saved model (.zip); its file name labels the point
    :param env: the joint env to evaluate on (optionally wrapped in :class:`~sb3_detc.triggers.FixedControl`)
    :param n_episodes: evaluation episodes
    :param seed: seed of the first episode (the following ones continue its generator)
    :return: the model's savings and mean team control cost per episode, with its standard error
    """
    from sb3_detc import MAPPOC
    from sb3_detc.evaluation import evaluate_communication

    model = MAPPOC.load(path, device="cpu")
    report = evaluate_communication(
        model, env, n_eval_episodes=n_episodes, deterministic=True, sample_options=True, seed=seed
    )
    n_agents = env.unwrapped.n_agents
    # The report's returns are team means per agent: the team cost is N times minus them.
    sem = report.std_control_return * np.sqrt(n_episodes / max(n_episodes - 1, 1)) / np.sqrt(n_episodes)
    return TriggerPoint(
        label=f"MAPPOC {Path(path).name}",
        savings=report.savings,
        cost=-n_agents * report.mean_control_return,
        cost_sem=n_agents * sem,
        episodes=n_episodes,
    )


def plot(curves: dict[str, list[TriggerPoint]], models: list[TriggerPoint], bound: float, out: Path) -> None:
    """Cost relative to the bound against savings, one line per baseline, one marker per model.

    :param curves: baseline name -> its points, in sweep order
    :param models: one point per trained model (:func:`model_point`)
    :param bound: the optimal centralised LQR cost per episode (team) that the costs are divided by
    :param out: the PNG to write (its folder is made if needed)
    """
    fig, ax = plt.subplots(figsize=(7, 4.5))
    styles = {"send-on-delta, LQR on held states": "o-", "random skip, LQR on held states": "s--"}
    for name, points in curves.items():
        ax.errorbar(
            [p.savings for p in points],
            [p.cost / bound for p in points],
            yerr=[p.cost_sem / bound for p in points],
            fmt=styles.get(name, "o-"),
            capsize=3,
            label=name,
        )
    for point in models:
        ax.errorbar(point.savings, point.cost / bound, yerr=point.cost_sem / bound, fmt="*", ms=12, label=point.label)
    ax.axhline(1.0, color="k", lw=1, ls=":", label="bound: centralised LQR, periodic communication")
    ax.set_xlabel("communication savings (1 - broadcasts / agent-steps)")
    ax.set_ylabel("team control cost per episode / LQR bound")
    ax.set_xlim(-0.02, 1.02)
    ax.set_ylim(bottom=0.0)
    ax.set_title("Linear formation (sb3_detc/LinearETC-v0): cost versus savings")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main() -> None:
    """Sweep the baselines, evaluate the models, write the plot and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=500, help="episodes per point")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    parser.add_argument("--models", nargs="*", default=[], help="trained MAPPOC models (.zip) to add as points")
    parser.add_argument(
        "--fixed-control",
        action="store_true",
        help="the models' triggers drive LQR on held states, as the curves (models trained with FixedControl)",
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="where to write the PNG")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    torch.set_num_threads(1)
    start = time.perf_counter()

    env = gymnasium.make(ENV_ID)
    bound = lqr_episode_cost(env.unwrapped.network.system)
    control = lqr_on_held_states(env)
    curves = {
        "send-on-delta, LQR on held states": sweep_send_on_delta(env, control, DELTAS, args.episodes, args.seed),
        "random skip, LQR on held states": [
            evaluate_trigger(
                env, RandomTrigger(p, seed=args.seed), control, args.episodes, args.seed, label=f"random skip {p:g}"
            )
            for p in SKIP_PROBS
        ],
    }
    model_env = FixedControl(env) if args.fixed_control else env
    models = [model_point(path, model_env, args.episodes, args.seed) for path in args.models]
    plot(curves, models, bound, args.out)

    print(f"env: {ENV_ID} (defaults); {args.episodes} episodes per point, seeds {args.seed}..")
    print(f"bound (optimal centralised finite-horizon LQR, periodic communication): {bound:.3f} per episode (team)")
    print()
    print("| trigger | savings | cost / bound | +- s.e. |")
    print("|---|---:|---:|---:|")
    for point in [p for points in curves.values() for p in points] + models:
        print(f"| {point.label} | {point.savings:.3f} | {point.cost / bound:.3f} | {point.cost_sem / bound:.3f} |")
    print()
    print(f"plot: {args.out}; {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
