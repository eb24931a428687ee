"""What the event-triggered network does, shown on the linear benchmark with hand-made schemes.

Run ``python -m sb3_detc.demo``. N coupled linear agents (:class:`~sb3_detc.envs.linear.LinearSystem`,
default parameters) run behind :class:`~sb3_detc.envs.wrappers.EventTriggeredNetwork` through its
joint view :func:`sb3_detc.envs.linear_etc_v0.joint_env`. Every agent applies the centralised
LQR gain to *its own view* of the team: its own current state and the others' held
broadcasts after this step's broadcasts (same-step delivery), built with
:func:`sb3_detc.network.hold`. Each communication scheme (periodic, random skips, every
4th step) runs the same seeded episodes, so initial states and process noise are equal
across schemes and only the communication differs. The printed table shows how much
communication a scheme saves and what it costs in control performance, against the
steady-state LQR bound :func:`~sb3_detc.envs.linear.lqr_cost_per_step`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from sb3_detc.envs import linear_etc_v0
from sb3_detc.envs.linear import LQRController, lqr_cost_per_step
from sb3_detc.envs.wrappers import JointEnv
from sb3_detc.network import hold

#: Steps per episode.
EPISODE_STEPS = 200

#: Steps at the start of every episode left out of the ratio to the steady-state LQR bound
#: (the transient from the random initial state).
TRANSIENT_STEPS = 50

#: A communication scheme: ``(step k, generator, N) -> options (N,)`` in {0, 1} (1 = broadcast).
Scheme = Callable[[int, np.random.Generator, int], np.ndarray]


def periodic(period: int) -> Scheme:
    """Every agent broadcasts at the steps ``k = 0, period, 2 period, ...`` and is silent otherwise.

    :param period: steps between two broadcasts (1 = every step)
    :return: the scheme
    """

    def scheme(k: int, rng: np.random.Generator, n_agents: int) -> np.ndarray:
        return np.full(n_agents, int(k % period == 0), dtype=np.int64)

    return scheme


def random_skip(p_skip: float) -> Scheme:
    """Every agent independently skips its broadcast with probability ``p_skip`` at every step.

    :param p_skip: probability of staying silent
    :return: the scheme
    """

    def scheme(k: int, rng: np.random.Generator, n_agents: int) -> np.ndarray:
        return (rng.random(n_agents) >= p_skip).astype(np.int64)

    return scheme


#: The demonstrated schemes, in print order.
SCHEMES: dict[str, Scheme] = {
    "periodic": periodic(1),
    "random skip p=0.5": random_skip(0.5),
    "random skip p=0.8": random_skip(0.8),
    "every 4th step": periodic(4),
}


@dataclass
class SchemeResult:
    """Statistics of one scheme over all episodes.

    :param name: scheme name
    :param broadcasts: broadcasts per agent and episode, shape (episodes, N)
    :param costs: team quadratic cost of every step, shape (episodes, EPISODE_STEPS)
    """

    name: str
    broadcasts: np.ndarray
    costs: np.ndarray

    @property
    def broadcasts_per_agent(self) -> float:
        """Mean broadcasts per agent and episode."""
        return float(self.broadcasts.mean())

    @property
    def savings(self) -> float:
        """Communication savings ``Gamma = 1 - broadcasts / agent-steps``."""
        return 1.0 - self.broadcasts_per_agent / self.costs.shape[1]

    @property
    def cost_all(self) -> float:
        """Mean team cost per step over all steps."""
        return float(self.costs.mean())

    @property
    def cost_steady(self) -> float:
        """Mean team cost per step after the first :data:`TRANSIENT_STEPS` steps of every episode."""
        return float(self.costs[:, TRANSIENT_STEPS:].mean())


def networked_control(controller: LQRController, obs: dict[str, np.ndarray], comm: np.ndarray) -> np.ndarray:
    """Controls when every agent applies the centralised gain to its own view of the team.

    Agent i's view is the held broadcasts after this step's broadcasts (same-step delivery,
    :func:`~sb3_detc.network.hold` of the joint observation's ``held`` and ``message``) with
    its own row replaced by its own current state ``local[i]``; its control is row i of
    ``-K x^(i)``.

    :param controller: the centralised LQR controller
    :param obs: joint observation of the network (before this step's decisions)
    :param comm: this step's options, shape (N,)
    :return: controls, shape (N, 1)
    """
    held = hold(obs["held"], obs["message"], comm)  # (N, 2): what every receiver holds now
    return controller.on_views(held, obs["local"])


def run_scheme(
    env: JointEnv,
    controller: LQRController,
    name: str,
    scheme: Scheme,
    episodes: int,
    seed: int,
    rng: np.random.Generator,
) -> SchemeResult:
    """Run the seeded episodes ``seed, seed + 1, ...`` of one scheme.

    :param env: joint linear env with ``max_cycles = EPISODE_STEPS``
    :param controller: the centralised LQR controller
    :param name: scheme name
    :param scheme: the communication scheme
    :param episodes: number of episodes
    :param seed: seed of the first episode (the env's generator: initial states and noise)
    :param rng: generator of the scheme's random decisions
    :return: the scheme's statistics
    """
    n = env.n_agents
    broadcasts = np.zeros((episodes, n), dtype=np.int64)
    costs = np.zeros((episodes, EPISODE_STEPS))
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        for k in range(EPISODE_STEPS):
            comm = scheme(k, rng, n)
            control = networked_control(controller, obs, comm)
            obs, _, terminated, truncated, info = env.step({"comm": comm, "control": control})
            costs[episode, k] = -info["control_rewards"].sum()
            if terminated or truncated:
                if k != EPISODE_STEPS - 1:
                    raise RuntimeError(f"episode ended after {k + 1} steps, expected {EPISODE_STEPS}.")
                break
        broadcasts[episode] = info["broadcasts"]
    return SchemeResult(name=name, broadcasts=broadcasts, costs=costs)


def format_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A plain-text table: first column left-aligned, the others right-aligned.

    :param header: column titles
    :param rows: cells of every row
    :return: the table, one line per row
    """
    widths = [max(len(str(cell)) for cell in column) for column in zip(header, *rows, strict=True)]

    def line(cells: Sequence[str]) -> str:
        first, *rest = cells
        return "  ".join([first.ljust(widths[0]), *(c.rjust(w) for c, w in zip(rest, widths[1:], strict=True))])

    return "\n".join([line(header), "  ".join("-" * w for w in widths), *(line(row) for row in rows)])


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command line of the demo.

    :param argv: arguments (None: ``sys.argv[1:]``)
    :return: the parsed arguments
    """
    parser = argparse.ArgumentParser(
        prog="python -m sb3_detc.demo", description="Event-triggered communication schemes on the linear benchmark."
    )
    parser.add_argument("--episodes", type=int, default=30, help="seeded episodes per scheme (default 30)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode (default 0)")
    parser.add_argument("--n-agents", type=int, default=3, help="number of agents N >= 2 (default 3)")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error("--episodes must be >= 1")
    if args.n_agents < 2:
        parser.error("--n-agents must be >= 2")
    return args


def main(argv: Sequence[str] | None = None) -> list[SchemeResult]:
    """Run every scheme and print what the network did.

    :param argv: command-line arguments (None: ``sys.argv[1:]``)
    :return: the statistics of every scheme, in print order
    """
    args = parse_args(argv)
    env = linear_etc_v0.joint_env(n_agents=args.n_agents, max_cycles=EPISODE_STEPS)
    system = env.network.system
    controller = LQRController(system)
    bound = lqr_cost_per_step(system)
    results = [
        run_scheme(env, controller, name, scheme, args.episodes, args.seed, np.random.default_rng([args.seed, i]))
        for i, (name, scheme) in enumerate(SCHEMES.items())
    ]

    last_seed = args.seed + args.episodes - 1
    print(
        f"Event-triggered network on the linear benchmark: N = {args.n_agents} agents, "
        f"{args.episodes} episode(s) x {EPISODE_STEPS} steps per scheme (seeds {args.seed}..{last_seed}; "
        "same initial states and noise for every scheme)."
    )
    print(
        "Network: each step every agent broadcasts its state or stays silent; receivers hold the last "
        "broadcast (zero-order hold) and its age counts the silent steps; every broadcast costs "
        f"comm_cost = {env.network.comm_cost:g} reward (not included in the costs below)."
    )
    print(
        "Control: each agent applies the centralised LQR gain to its own view (own current state, the others' "
        "held broadcasts after this step's broadcasts)."
    )
    print(
        "Cost: team quadratic cost per step (-sum of the agents' control rewards). The ratio compares the cost "
        f"after the first {TRANSIENT_STEPS} steps of every episode (the transient from the random initial state "
        f"is left out) with the steady-state LQR bound trace(PW) = {bound:.4f}."
    )
    print()
    header = [
        "scheme",
        "broadcasts/agent/episode",
        "savings Gamma",
        "cost/step (all)",
        f"cost/step (k>={TRANSIENT_STEPS})",
        "ratio to LQR bound",
    ]
    rows = [
        [
            r.name,
            f"{r.broadcasts_per_agent:.1f}",
            f"{r.savings:.2f}",
            f"{r.cost_all:.4f}",
            f"{r.cost_steady:.4f}",
            f"{r.cost_steady / bound:.2f}",
        ]
        for r in results
    ]
    print(format_table(header, rows))
    print()
    print(f"Broadcasts per agent in episode 1 (seed {args.seed}), out of {EPISODE_STEPS} steps:")
    agents = env.network.possible_agents
    print(format_table(["scheme", *agents], [[r.name, *(str(b) for b in r.broadcasts[0])] for r in results]))
    return results


if __name__ == "__main__":
    main()
