"""How much communication matters on the linear system: LQR on held broadcasts.

Every agent applies its row of the centralised LQR gain to its own view of the team (own
current state, the others' held broadcasts after this step's broadcasts), for random
skipping and for send-on-delta triggers (broadcast when the own state moved more than
``delta`` since the last broadcast), on several system configurations. Costs are the
team's steady-state quadratic cost per step (after a burn-in), relative to the LQR bound
with periodic communication (:func:`sb3_detc.envs.linear.lqr_cost_per_step`). This is
what motivated the default system: with Gaussian noise alone, communication hardly
matters; with rare velocity kicks, *when* to communicate matters.

    python benchmarks/value_of_information.py
"""

from __future__ import annotations

import argparse

import numpy as np

from sb3_detc.envs.linear import LinearSystem, LQRController, lqr_cost_per_step
from sb3_detc.network import hold, initial_network

CONFIGS = {
    "Gaussian noise, weak coupling (earlier defaults)": dict(
        dt=0.1, q_reg=1.0, q_form=1.0, noise_vel=0.05, jump_prob=0.0
    ),
    "Gaussian noise, strong coupling": dict(noise_vel=0.05, jump_prob=0.0),
    "strong coupling + velocity kicks (defaults)": dict(),
}


def steady_cost(system: LinearSystem, trigger, steps: int, burn_in: int, seed: int) -> tuple[float, float]:
    """Mean team cost per step after ``burn_in`` and the broadcast rate, one long episode.

    :param system: the linear system (its ``max_cycles`` at least ``steps``)
    :param trigger: ``(message, held, rng) -> broadcast``: the current messages and the held ones (N, 2) and
        the generator, to every agent's option (N,) (1: broadcast)
    :param steps: steps of the episode
    :param burn_in: first steps left out of the cost and the rate
    :param seed: seed of the episode and of the generator passed to ``trigger``
    :return: the mean team cost per step and the broadcast rate (broadcasts / agent-steps) after the burn-in
    """
    controller = LQRController(system)
    n = system.n_agents
    rng = np.random.default_rng(seed)
    obs, _ = system.reset_arrays(seed)
    held, _ = initial_network(obs.message)
    costs, broadcasts = [], 0
    for k in range(steps):
        broadcast = trigger(obs.message, held, rng)
        held = hold(held, obs.message, broadcast)
        obs, rewards, *_ = system.step_arrays(controller.on_views(held, obs.message))
        if k >= burn_in:
            costs.append(-rewards.sum())
            broadcasts += broadcast.sum()
    return float(np.mean(costs)), broadcasts / ((steps - burn_in) * n)


def main() -> None:
    """Print, for every system configuration, the broadcast rate and relative cost of every trigger."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    burn_in = 200
    if args.steps <= burn_in:
        parser.error(f"--steps must be more than the {burn_in} steps of burn-in, got {args.steps}")
    for name, kwargs in CONFIGS.items():
        system = LinearSystem(max_cycles=args.steps, **kwargs)
        bound = lqr_cost_per_step(system)
        print(f"\n{name}: {kwargs or 'LinearSystem()'}; bound {bound:.4f} per step")
        print("| trigger | broadcast rate | cost / bound |")
        print("|---|---|---|")
        schemes = [("periodic", lambda m, h, r: np.ones(len(m), dtype=np.int64))]
        schemes += [
            (f"random skip {p}", lambda m, h, r, p=p: (r.random(len(m)) >= p).astype(np.int64)) for p in (0.5, 0.8, 0.9)
        ]
        schemes += [
            (f"send-on-delta {d}", lambda m, h, r, d=d: (np.linalg.norm(m - h, axis=1) > d).astype(np.int64))
            for d in (0.05, 0.1, 0.2)
        ]
        for label, trigger in schemes:
            cost, rate = steady_cost(system, trigger, args.steps, burn_in, args.seed)
            print(f"| {label} | {rate:.3f} | {cost / bound:.3f} |")


if __name__ == "__main__":
    main()
