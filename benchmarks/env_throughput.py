"""Environment throughput: steps per second of our Multiwalker views against the stock PettingZoo one.

What is measured (all three with 3 walkers, each env's default settings):

1. ``joint``: the joint Gymnasium env ``gymnasium.make("sb3_detc/MultiwalkerETC-v0")``, as
   returned by ``gymnasium.make`` (NOT ``.unwrapped``: its default wrappers, order
   enforcing and the passive env checker, stay on, just as the stock env keeps its own
   PettingZoo wrappers); action ``{"broadcast": (3,), "control": (3, 4)}``;
2. ``pettingzoo (ours)``: ``sb3_detc.envs.multiwalker_etc_v0.parallel_env()``, per-agent dict
   actions ``{agent: {"broadcast": 0 or 1, "control": (4,)}}``;
3. ``pettingzoo stock``: ``pettingzoo.sisl.multiwalker_v9.parallel_env()``, per-agent actions
   ``{agent: (4,)}``.

How: uniformly random actions (broadcast in {0, 1}, control uniform in the control box; shapes
and bounds read from each env's action space). Actions are drawn with NumPy in blocks of
:data:`BLOCK` steps and packed into each env's action format *outside* the timed section,
so action sampling costs nothing in any of the three measurements. The timed section is
``step`` plus ``reset`` whenever an episode ends: random walkers fall after well under 100
steps, so a reset (a new Box2D world, terrain and walkers) happens often and is part of the
throughput. Each measurement starts with a seeded reset (``--seed`` plus the repeat index)
and runs until at least ``--seconds`` of timed env work have been done (it stops at a block
boundary). The three envs are measured interleaved (A, B, C, A, B, C, ...) so that drift in
machine load hits all of them alike; the table reports the median over ``--repeats``.

Everything is printed to stdout (a markdown table and the machine); nothing is written to
disk. The benchmark itself never imports PyTorch (``import sb3_detc`` may load it; the
output says whether it is loaded).

Run: ``.venv/bin/python benchmarks/env_throughput.py [--seconds 10] [--repeats 3] [--seed 0]``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import Box2D
import gymnasium
import numpy as np
import pettingzoo
from gymnasium import spaces
from pettingzoo.sisl import multiwalker_v9

import sb3_detc  # noqa: F401  (registers the gymnasium ids)
from sb3_detc.envs import multiwalker_etc_v0

#: Steps of pre-sampled actions per block.
BLOCK = 512


@dataclass
class Measurement:
    """One timed run of one env.

    :param steps: steps taken in the run
    :param seconds: timed seconds of env work (steps and resets)
    :param episodes: episodes that ended inside the run
    :param episode_steps: steps of those episodes
    """

    steps: int
    seconds: float
    episodes: int
    episode_steps: int

    @property
    def rate(self) -> float:
        """Steps per second of timed env work."""
        return self.steps / self.seconds


@dataclass
class Bench:
    """An env under test: how to reset it, step it and build its actions from sampled arrays.

    :param name: the env's name in the output
    :param env: the env itself
    :param n_agents: number of agents N
    :param control_low: lower bounds of one agent's control (m,)
    :param control_high: upper bounds of one agent's control (m,)
    :param runs: the measurements so far, in order
    """

    name: str
    env: Any
    n_agents: int
    control_low: np.ndarray
    control_high: np.ndarray
    runs: list[Measurement] = field(default_factory=list)

    def reset(self, seed: int | None) -> None:
        """Reset the env.

        :param seed: seed of the reset (None: continue the env's own generator)
        """
        self.env.reset(seed=seed)

    def step(self, action: Any) -> bool:
        """Step once; return True if the episode ended.

        :param action: one action of this env, as built by :meth:`pack`
        :return: whether the episode ended with this step
        """
        raise NotImplementedError

    def pack(self, broadcast: np.ndarray, control: np.ndarray) -> list[Any]:
        """Turn arrays of shape (T, N) and (T, N, m) into T actions of this env.

        :param broadcast: broadcast decisions, 0 or 1, (T, N) (T steps, N agents)
        :param control: controls (T, N, m), float32 (m: one agent's control size)
        :return: the T actions, in order
        """
        raise NotImplementedError

    def sample(self, rng: np.random.Generator, n_steps: int) -> list[Any]:
        """Draw uniformly random actions: broadcast in {0, 1}, control uniform in the control box.

        :param rng: the generator of the actions
        :param n_steps: number of steps to draw actions for
        :return: the ``n_steps`` actions of this env (:meth:`pack`)
        """
        broadcast = rng.integers(0, 2, size=(n_steps, self.n_agents))
        shape = (n_steps, self.n_agents, *self.control_low.shape)
        control = rng.uniform(self.control_low, self.control_high, size=shape).astype(np.float32)
        return self.pack(broadcast, control)


class JointBench(Bench):
    """The joint Gymnasium env; the episode has ended when it is terminated or truncated."""

    def step(self, action: dict[str, np.ndarray]) -> bool:
        """Step once; see :meth:`Bench.step`.

        :param action: ``{"broadcast": (N,), "control": (N, m)}``
        :return: whether the episode terminated or was truncated
        """
        _, _, terminated, truncated, _ = self.env.step(action)
        return terminated or truncated

    def pack(self, broadcast: np.ndarray, control: np.ndarray) -> list[Any]:
        """One joint dict action per step; see :meth:`Bench.pack`.

        :param broadcast: broadcast decisions, 0 or 1, (T, N)
        :param control: controls (T, N, m)
        :return: T actions ``{"broadcast": (N,), "control": (N, m)}``
        """
        return [{"broadcast": c, "control": u} for c, u in zip(broadcast, control, strict=True)]


class ParallelBench(Bench):
    """A PettingZoo parallel env; the episode has ended when no agent is left.

    :param args: the :class:`Bench` fields, in order (``name``, ``env``, ``n_agents``, ``control_low``,
        ``control_high``)
    :param with_broadcast: the env takes per-agent ``{"broadcast": 0 or 1, "control": (m,)}`` actions
        (ours); False: per-agent control arrays (m,) (the stock env)
    :param kwargs: further :class:`Bench` fields, by name
    """

    def __init__(self, *args: Any, with_broadcast: bool, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.with_broadcast = with_broadcast
        self.agents = list(self.env.possible_agents)

    def step(self, action: dict[str, Any]) -> bool:
        """Step once; see :meth:`Bench.step`.

        :param action: agent -> that agent's action
        :return: whether no agent is left
        """
        self.env.step(action)
        return not self.env.agents

    def pack(self, broadcast: np.ndarray, control: np.ndarray) -> list[Any]:
        """One per-agent dict action per step; see :meth:`Bench.pack`.

        :param broadcast: broadcast decisions, 0 or 1, (T, N) (ignored without ``with_broadcast``)
        :param control: controls (T, N, m)
        :return: T actions agent -> ``{"broadcast": 0 or 1, "control": (m,)}``, or agent -> control (m,)
            without ``with_broadcast``
        """
        if self.with_broadcast:
            return [
                {a: {"broadcast": int(c[i]), "control": u[i]} for i, a in enumerate(self.agents)}
                for c, u in zip(broadcast, control, strict=True)
            ]
        return [{a: u[i] for i, a in enumerate(self.agents)} for u in control]


def make_benches() -> list[Bench]:
    """The three envs, in measurement order.

    :return: the joint Gymnasium env, our PettingZoo view and the stock PettingZoo env, each as a :class:`Bench`
    """
    joint = gymnasium.make("sb3_detc/MultiwalkerETC-v0")
    joint_control = joint.action_space["control"]
    ours = multiwalker_etc_v0.parallel_env()
    ours_control = ours.action_space(ours.possible_agents[0])["control"]
    stock = multiwalker_v9.parallel_env()
    stock_control = stock.action_space(stock.possible_agents[0])
    for box in (joint_control, ours_control, stock_control):
        assert isinstance(box, spaces.Box)
    return [
        JointBench(
            "joint gymnasium (ours)",
            joint,
            joint_control.shape[0],
            joint_control.low[0],
            joint_control.high[0],
        ),
        ParallelBench(
            "pettingzoo view (ours)",
            ours,
            len(ours.possible_agents),
            ours_control.low,
            ours_control.high,
            with_broadcast=True,
        ),
        ParallelBench(
            "pettingzoo stock multiwalker_v9",
            stock,
            len(stock.possible_agents),
            stock_control.low,
            stock_control.high,
            with_broadcast=False,
        ),
    ]


def measure(bench: Bench, seconds: float, seed: int, rng: np.random.Generator) -> Measurement:
    """Run random actions for at least ``seconds`` of timed env work (steps and resets).

    :param bench: the env under test
    :param seconds: timed seconds to reach; the run stops at the first :data:`BLOCK` boundary after them
    :param seed: seed of the first reset (the resets after episode ends are not seeded)
    :param rng: the generator of the actions
    :return: the measurement
    """
    timed = 0.0
    steps = episodes = episode_steps = length = 0
    start = time.perf_counter()
    bench.reset(seed)
    timed += time.perf_counter() - start
    while timed < seconds:
        actions = bench.sample(rng, BLOCK)  # not timed
        start = time.perf_counter()
        for action in actions:
            length += 1
            if bench.step(action):
                bench.reset(None)
                episodes += 1
                episode_steps += length
                length = 0
        timed += time.perf_counter() - start
        steps += len(actions)
    return Measurement(steps=steps, seconds=timed, episodes=episodes, episode_steps=episode_steps)


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (else :func:`platform.processor`, else ``unknown CPU``).

    :return: the model name
    """
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def machine_line() -> str:
    """The machine in one line: CPU, logical CPUs, OS, Python and the versions of the env libraries.

    :return: the line (no newline)
    """
    versions = (
        f"numpy {np.__version__}, gymnasium {gymnasium.__version__}, pettingzoo {pettingzoo.__version__}, "
        f"Box2D {getattr(Box2D, '__version__', '?')}"
    )
    return (
        f"{cpu_model()}, {os.cpu_count()} logical CPUs, {platform.system()} {platform.release()}, "
        f"Python {platform.python_version()}, {versions}"
    )


def table(benches: Sequence[Bench]) -> str:
    """The Markdown table of the results: median and per-repeat steps/s, ratio to the stock env, episodes.

    :param benches: the measured envs, each with its runs; the last is the stock env (the ``vs stock`` reference)
    :return: the table
    """
    stock_rate = statistics.median(m.rate for m in benches[-1].runs)
    lines = [
        "| env | steps/s (median) | steps/s per repeat | vs stock | episodes | mean episode length |",
        "|---|---:|---|---:|---:|---:|",
    ]
    for bench in benches:
        rate = statistics.median(m.rate for m in bench.runs)
        per_repeat = ", ".join(f"{m.rate:.0f}" for m in bench.runs)
        episodes = sum(m.episodes for m in bench.runs)
        mean_length = sum(m.episode_steps for m in bench.runs) / max(episodes, 1)
        lines.append(
            f"| {bench.name} | {rate:.0f} | {per_repeat} | {rate / stock_rate:.2f}x | {episodes} | {mean_length:.1f} |"
        )
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Parse and check the command line (exits with a usage error on invalid values).

    :param argv: the arguments (None: ``sys.argv[1:]``)
    :return: ``seconds``, ``repeats`` and ``seed``
    """
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="timed seconds per measurement (default 10)")
    parser.add_argument("--repeats", type=int, default=3, help="measurements per env (default 3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the actions and the first resets (default 0)")
    args = parser.parse_args(argv)
    if args.seconds <= 0 or args.repeats < 1:
        parser.error("--seconds must be > 0 and --repeats >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    """Measure every env ``--repeats`` times, interleaved, and print the table and the machine.

    :param argv: the arguments (None: ``sys.argv[1:]``)
    """
    args = parse_args(argv)
    benches = make_benches()
    rngs = [np.random.default_rng([args.seed, i]) for i in range(len(benches))]
    for bench, rng in zip(benches, rngs, strict=True):  # warm-up, not reported
        measure(bench, 0.2, args.seed, rng)
    load_before = os.getloadavg()
    for repeat in range(args.repeats):
        for bench, rng in zip(benches, rngs, strict=True):
            bench.runs.append(measure(bench, args.seconds, args.seed + repeat, rng))
            load = os.getloadavg()[0]
            print(
                f"repeat {repeat + 1}/{args.repeats} {bench.name}: {bench.runs[-1].rate:.0f} steps/s (load {load:.2f})",
                flush=True,
            )
    load_after = os.getloadavg()

    print()
    print(f"date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}")
    print(f"command: {' '.join([os.path.basename(sys.executable), *sys.argv])}")
    print(f"machine: {machine_line()}")
    torch_loaded = "yes, by an import, unused" if "torch" in sys.modules else "no"
    print(f"load average (1 min) before/after: {load_before[0]:.2f}/{load_after[0]:.2f}; torch loaded: {torch_loaded}")
    print(
        f"settings: {args.repeats} interleaved repeats x {args.seconds:g} s per env, seed {args.seed}, "
        "uniformly random actions, resets included in the time"
    )
    print()
    print(table(benches))
    print()
    print(
        "Random walkers fall early, so episodes are short and every episode end costs a reset "
        "(new Box2D world); 'episodes' and 'mean episode length' count the episodes that ended "
        "during the timed runs (all repeats)."
    )


if __name__ == "__main__":
    main()
