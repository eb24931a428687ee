"""The true value of a broadcast on the linear system, measured with common random numbers.

Every agent's control is fixed to LQR on its view of held broadcasts
(:class:`sb3_detc.triggers.FixedControl`) and options are drawn at random with a fixed
broadcast probability. At every ``--every``-th step of a long run one agent ``j`` is picked
and the env is copied twice: in one copy ``j`` broadcasts, in the other it stays silent,
everything else (the others' options, the process noise, the later random options) is the
same in both copies. The difference of the discounted team-mean control rewards over the
next ``--horizon`` steps is then a low-variance sample of ``Q_j(s, broadcast) - Q_j(s,
silent)`` without the communication cost, the quantity a learned trigger has to weigh
against the price of a broadcast. The table groups the samples by how far the agent's
trigger features moved since its last broadcast (what send-on-delta looks at).

With ``--critics``, MAPPOC then trains each kind of option-value critic on the same kind of
data (fixed control, random options with the same probability, policies over options not
trained) and its estimate of the same difference on the same states is set beside the
truth: how much of the value of a broadcast each critic resolves. A critic that learns the price
of a broadcast with the rewards (``option_heads``) gives the value minus the price; the table adds
the price back, so that every estimate is of the value without it. ``--tabulate`` prints the table
of an earlier run from its JSON without running anything.

    python benchmarks/option_value_truth.py --critics option_heads afterstate centred --timesteps 200000
    python benchmarks/option_value_truth.py --tabulate
"""

from __future__ import annotations

import argparse
import copy
import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc import MAPPOC
from sb3_detc.files import replace_atomically
from sb3_detc.mappoc.critics import CRITICS
from sb3_detc.renamed import renamed_keys
from sb3_detc.study.sweep import check_at_least_one
from sb3_detc.triggers import FixedControl, SendOnDelta

#: MAPPOC settings of the critics' training (those of ``trigger_learning.py``'s sparse variants).
HYPERPARAMS: dict[str, Any] = {
    "n_steps": 512,
    "batch_size": 256,
    "n_epochs": 10,
    "learning_rate": 3e-4,
    "max_grad_norm": 0.5,
    "team_reward": True,
    "normalize_reward": True,
    "reward_scale": 1.0,
    "gamma": 0.95,
    "broadcast_ent_coef": 0.0,
    "train_broadcast_policy": False,
}

#: The arguments that decide a run's samples and estimates (a run in ``--out`` with others is refused).
SETTINGS = ("broadcast_prob", "gamma", "horizon", "steps", "every", "broadcast_cost", "seed", "timesteps")


def branch_returns(
    env: gym.Env, broadcast: np.ndarray, agent: int, p: float, gamma: float, horizon: int, seed: int
) -> float:
    """Value of ``agent``'s broadcast now: the difference of two copies' discounted team-mean control returns.

    :param env: the fixed-control joint env, at the state of the decision
    :param broadcast: everyone's options of this step (N,); ``agent``'s is replaced
    :param agent: the deciding agent
    :param p: probability of broadcasting of the later random options
    :param gamma: discount factor
    :param horizon: steps to follow (fewer at the end of the episode)
    :param seed: seed of the later random options, the same in both copies
    :return: the discounted team-mean control return after a broadcast minus that after a silence
    """
    n = broadcast.shape[0]
    returns = []
    for option in (1, 0):
        branch = copy.deepcopy(env)  # copies the env's generator: the same noise in both branches
        options = broadcast.copy()
        options[agent] = option
        later = np.random.default_rng(seed)  # the same later options in both branches
        total, discount = 0.0, 1.0
        for _ in range(horizon):
            _, _, terminated, truncated, info = branch.step({"broadcast": options, "control": np.zeros((n, 1))})
            total += discount * float(np.mean(info["control_rewards"]))
            if terminated or truncated:
                break
            discount *= gamma
            options = (later.random(n) < p).astype(np.int64)
        returns.append(total)
    return returns[0] - returns[1]


def critic_estimates(
    job: tuple[str, float, float, int, int, list[tuple[dict, np.ndarray, int]]],
) -> tuple[str, np.ndarray]:
    """Train one critic on random options and return its ``Q_j(s, 1) - Q_j(s, 0)`` on the samples.

    :param job: critic kind, broadcast probability, communication cost, timesteps, seed and
        the samples (observation before the decision, options of the step, deciding agent)
    :return: the critic kind and its estimates in team-mean reward (samples,): without the communication
        cost for a critic that adds it to its option values itself (``needs_price``), with it for one that
        learns it
    """
    critic, p, broadcast_cost, timesteps, seed, samples = job
    th.set_num_threads(1)
    env_kwargs = {"broadcast_cost": broadcast_cost}
    env = make_vec_env("sb3_detc/LinearETC-v0", n_envs=2, seed=seed, env_kwargs=env_kwargs, wrapper_class=FixedControl)
    # mu itself draws the random options: untrained, it broadcasts with probability p in every
    # state (its output layer starts near zero), and the centred critic gets the exact probabilities
    policy_kwargs = {"net_arch": [64, 64], "critic": critic, "broadcast_prob_init": p}
    model = MAPPOC("MlpHybridPolicy", env, seed=seed, policy_kwargs=policy_kwargs, **HYPERPARAMS)
    model.learn(timesteps)
    obs = {key: th.as_tensor(np.stack([s[0][key] for s in samples])) for key in samples[0][0]}
    broadcast = th.as_tensor(np.stack([s[1] for s in samples]))
    agent = np.array([s[2] for s in samples])
    control = th.zeros(*broadcast.shape, model.n_control)
    with th.no_grad():
        q = model.policy.evaluate_actions(
            obs, broadcast, control, p_broadcast=th.full(broadcast.shape, p)
        ).option_values
    gap = (q[..., 1] - q[..., 0]).numpy()[np.arange(len(agent)), agent]
    # back from the learner's units (reward normalisation) to team-mean reward
    return critic, gap * np.sqrt(model.reward_transform.return_rms.var[agent] + 1e-8) / model.reward_scale


def main() -> None:
    """Measure the value of a broadcast along a long run, train the critics if asked, write the JSON and print."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--broadcast-prob", type=float, default=0.5, help="probability of broadcasting of the random options"
    )
    parser.add_argument("--gamma", type=float, default=0.95)
    parser.add_argument("--horizon", type=int, default=60, help="steps after the decision (at most to the episode end)")
    parser.add_argument("--steps", type=int, default=9000, help="steps of the long run")
    parser.add_argument("--every", type=int, default=3, help="measure at every k-th step")
    parser.add_argument("--broadcast-cost", type=float, default=0.03, help="only to state the price of a broadcast")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--critics", nargs="*", default=[], choices=list(CRITICS))
    parser.add_argument(
        "--timesteps", type=int, default=100_000, help="training steps of every critic (part of the run's settings)"
    )
    parser.add_argument("--workers", type=int, default=2, help="parallel training processes")
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(__file__).parent / "results" / "option_value_truth.json",
        help="the run (JSON), written after the samples and after every critic; critics already in it are not "
        "trained again, a run with other settings is refused",
    )
    parser.add_argument("--tabulate", action="store_true", help="print the table of the run in --out, run nothing")
    args = parser.parse_args()
    if args.tabulate:
        try:
            record = json.loads(args.out.read_text())
            settings = renamed_keys(record["settings"])  # also a run of an earlier version
            samples, estimates = record["samples"], {c: np.asarray(e) for c, e in record["estimates"].items()}
        except (OSError, ValueError, KeyError) as error:
            parser.error(f"--tabulate needs the JSON of an earlier run in --out ({error!r})")
        n = FixedControl(gym.make("sb3_detc/LinearETC-v0")).unwrapped.n_agents
        print_table(np.asarray(samples), estimates, float(settings["broadcast_cost"]) / n, settings)
        return
    check_at_least_one(parser, args, "horizon", "steps", "every", "timesteps", "workers")
    if not 0 < args.broadcast_prob < 1 or not 0 < args.gamma <= 1 or not args.broadcast_cost >= 0:
        parser.error("--broadcast-prob must lie strictly between 0 and 1, --gamma in (0, 1], --broadcast-cost >= 0")
    settings = {key: str(getattr(args, key)) for key in SETTINGS}
    estimates = earlier_estimates(args.out, settings, parser)
    env = FixedControl(gym.make("sb3_detc/LinearETC-v0"))
    n = env.unwrapped.n_agents
    samples, states = measure(env, args)
    data = np.asarray(samples)

    def write() -> None:
        record = {"settings": settings, "samples": samples, "estimates": {c: e.tolist() for c, e in estimates.items()}}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        replace_atomically(args.out, lambda path: path.write_text(json.dumps(record)))

    write()
    pending = [c for c in args.critics if c not in estimates]
    jobs = [(c, args.broadcast_prob, args.broadcast_cost, args.timesteps, args.seed, states) for c in pending]
    if jobs:
        context = multiprocessing.get_context("spawn")  # a killed worker raises BrokenProcessPool, never hangs
        with ProcessPoolExecutor(min(args.workers, len(jobs)), mp_context=context) as pool:
            for future in as_completed([pool.submit(critic_estimates, job) for job in jobs]):
                critic, estimate = future.result()
                estimates[critic] = estimate
                write()
                print(f"{critic} trained, written to {args.out}", flush=True)
    shown = {c: estimates[c] for c in args.critics}
    print_table(data, shown, args.broadcast_cost / n, settings)


def earlier_estimates(out: Path, settings: dict[str, str], parser: argparse.ArgumentParser) -> dict[str, np.ndarray]:
    """The critics' estimates of an earlier run with the same settings (none if ``out`` does not exist).

    :param out: the JSON of a run
    :param settings: this run's settings (:data:`SETTINGS`, as text)
    :param parser: the command's parser, to refuse a file of another run
    :return: critic -> its estimates on the samples
    """
    if not out.is_file():
        return {}
    try:
        record = json.loads(out.read_text())
        earlier = {key: value for key, value in renamed_keys(record["settings"]).items() if key in SETTINGS}
        estimates = {c: np.asarray(e) for c, e in record["estimates"].items()}
    except (UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as error:
        parser.error(f"{out} is not the JSON of a run ({error!r}); give another --out")
    if earlier != settings:
        differ = sorted(key for key in SETTINGS if earlier.get(key) != settings[key])
        parser.error(f"{out} holds a run with other settings ({', '.join(differ)}); give its settings or another --out")
    return estimates


def measure(env: gym.Env, args: argparse.Namespace) -> tuple[list[tuple[float, float, float]], list[tuple]]:
    """The value of a broadcast at every ``--every``-th step of a long run with random options.

    :param env: the fixed-control joint env
    :param args: the command's arguments (``broadcast_prob``, ``gamma``, ``horizon``, ``steps``, ``every``, ``seed``)
    :return: the samples (trigger change, age, value of a broadcast) and the states they were measured in
        (observation, options of the step, deciding agent)
    """
    rng = np.random.default_rng(args.seed)
    n = env.unwrapped.n_agents
    obs, _ = env.reset(seed=args.seed)
    samples, states = [], []
    for step in range(args.steps):
        broadcast = (rng.random(n) < args.broadcast_prob).astype(np.int64)
        if step % args.every == 0:
            agent = int(rng.integers(n))
            seed = int(rng.integers(1 << 30))
            value = branch_returns(env, broadcast, agent, args.broadcast_prob, args.gamma, args.horizon, seed)
            change = float(SendOnDelta(0.0).distance({key: obs[key][agent] for key in ("trigger", "trigger_held")}))
            samples.append((change, float(obs["age"][agent, 0]), value))
            states.append(({key: np.array(v) for key, v in obs.items()}, broadcast, agent))
        obs, _, terminated, truncated, _ = env.step({"broadcast": broadcast, "control": np.zeros((n, 1))})
        if terminated or truncated:
            obs, _ = env.reset()
    return samples, states


def print_table(data: np.ndarray, estimates: dict[str, np.ndarray], price: float, settings: dict[str, str]) -> None:
    """Print the samples and the critics' estimates, grouped by the change of the trigger features.

    :param data: (trigger change, age, value of a broadcast) per sample
    :param estimates: critic -> its estimates on the samples (:func:`critic_estimates`)
    :param price: a broadcast's cost in team-mean reward, added back to the estimates of a critic
        that learns it with the rewards
    :param settings: the run's settings (``broadcast_prob``, ``gamma``, ``horizon``)
    """
    estimates = {c: e if CRITICS[c].needs_price else e + price for c, e in estimates.items()}
    print(
        f"broadcast probability {settings['broadcast_prob']}, gamma {settings['gamma']}, horizon "
        f"{settings['horizon']}, {len(data)} samples; price of a broadcast in team-mean reward: {price:.4f} "
        f"(added back to the estimates of {', '.join(c for c in estimates if not CRITICS[c].needs_price) or 'none'})"
    )
    print()
    header = "| trigger change | samples | value of a broadcast +- s.e. | share above the price |"
    print(header + "".join(f" {critic}: estimate (spread) |" for critic in estimates))
    print("|---|---:|---:|---:|" + "---:|" * len(estimates))
    edges = np.quantile(data[:, 0], [0, 0.2, 0.4, 0.6, 0.8, 0.9, 0.95, 1.0])
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        # half-open bins, the last closed: a sample on an edge counts once
        rows = (data[:, 0] >= lo) & ((data[:, 0] < hi) if k < len(edges) - 2 else (data[:, 0] <= hi))
        value = data[rows, 2]
        sem = value.std(ddof=1) / np.sqrt(len(value))
        line = (
            f"| {lo:.3f} to {hi:.3f} | {len(value)} | {value.mean():+.4f} +- {sem:.4f} | {np.mean(value > price):.2f} |"
        )
        print(line + "".join(f" {e[rows].mean():+.4f} ({e[rows].std():.4f}) |" for e in estimates.values()))
    for critic, estimate in estimates.items():
        print(f"{critic}: correlation with the truth over all samples {np.corrcoef(estimate, data[:, 2])[0, 1]:+.3f}")


if __name__ == "__main__":
    main()
