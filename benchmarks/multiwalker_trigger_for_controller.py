"""A trigger learned for a controller that needs messages: MAPPOC's policies over options on a study's controllers.

On Multiwalker the controllers of the paper's random-skip baseline need their messages beyond
about 75 % savings, and there *when* matters: a message every 8th step keeps the walkers going,
random messages at the same rate do not (``benchmarks/README.md``, value of information). Can
MAPPOC's policy over options learn such timing? For every finished seed of a study algorithm
(default: ``random_skip_paper`` of ``multiwalker_paper``) the trial's final policy is loaded into
MAPPOC built from the trial's own entry (rl-zoo3's experiment manager, as the study trains it;
a policy built with other settings than the entry now gives is refused); its control policy is
frozen. The critic first learns alone for ``--warm-up`` steps (it learned for random options,
and the baseline trained without the communication cost), then the critic and the policies over
options (``set_trained_policies(control_policy=False, broadcast_policy=True)``), at the
communication cost ``--broadcast-cost`` (default: the entry's). ``--normalize-reward``
normalises the learner's rewards with fresh statistics (as stage 2 of
:class:`~sb3_detc.callbacks.ControlFirstCallback` with ``trigger_normalize_reward``); by default
the entry's setting stays. The entry's callbacks (random skips, the action noise schedule, whose
noise has ended by the end of training) are left out.

The trained policy then runs the study's evaluation protocol on the study's seeded episodes
(:func:`~sb3_detc.evaluation.evaluate_policy_modes`: the learned options, sampled from ``mu`` or
its most likely ones as the policy's ``sample_options`` says (the entry's setting), the most
likely options, random options at the learned rate, every step, never) and a message every
``k`` steps at the ``k`` whose savings ``1 - 1/k`` lie closest to the learned savings. The control
policy is the trial's, unchanged, so the value of information sweep of the same study
(``multiwalker_value_of_information.py``) shows the same controller under fixed triggers.

With ``--fixed-families`` the evaluation also compares fixed trigger families tuned to the learned
rate on the same episodes (:func:`~sb3_detc.evaluation.evaluate_policy_modes`), the learned options
sampled from ``mu``, and ``mu`` made deterministic at the learned rate (the protocol's ``thresholded``,
a column of the families' table); a rate target comes with ``--set '{"target_savings": 0.875}'``. With
``--option-age-scale`` the policy over options starts afresh and reads the age of its own last
broadcast (every periodic schedule in phase then lies within what it can represent); the trial's
controls and critic are kept. With ``--start-period K`` as well, the warm-up's options come from a
message every ``K``-th step, all agents in phase (the critic learns that schedule's values), and
``mu`` then imitates the schedule (:func:`~sb3_detc.callbacks.imitate_trigger`) and learns from
there: a trigger that starts as the strongest fixed family at ``1 - 1/K`` savings and can lose to
it only by learning badly. ``--start-dither SKIP EXTRA`` adds random deviations to that schedule
(:class:`~sb3_detc.triggers.DitheredTrigger`: each scheduled message skipped with ``SKIP``, each
silence broken with ``EXTRA``), in the warm-up and in what ``mu`` imitates, so that the critic
has seen both options at every age before ``mu`` follows it.

With ``--select-every N`` the policy runs ``--select-episodes`` validation episodes (the seeds right
after the evaluation's) every ``N`` steps of ``mu``'s training and at its end, options sampled, and
the one with the highest control return at the target savings (within 0.01 below it, or above) is
kept instead of the last (:class:`~sb3_detc.callbacks.SelectBestCallback`, as rl-zoo3 keeps
``best_model.zip``); the row lists every validation.

One job per seed, one after another (each trains with the entry's two rollout-worker
processes); every finished seed's row is written to ``--out`` at once and a seed already there
is not trained again (:mod:`sb3_detc.study.sweep`; a job is its settings and the digest of the trial's
policy). ``--save-dir`` keeps the trained policies (policy only; each row names its file).

    python benchmarks/multiwalker_trigger_for_controller.py benchmarks/studies/multiwalker_paper \\
        --broadcast-cost 1.0 --out benchmarks/results/multiwalker_trigger_for_controller.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_detc.callbacks import SelectBestCallback, imitate_trigger
from sb3_detc.cli import python_value
from sb3_detc.evaluation import evaluate_episodes
from sb3_detc.files import replace_atomically
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.study.report import interval_text, metric_estimates
from sb3_detc.study.spec import StudyError, Trial, load_folder_study
from sb3_detc.study.sweep import OutError, check_at_least_one, job_key, run_rows
from sb3_detc.study.trial import (
    evaluate_policy_modes,
    read_status,
    trial_folder,
    trial_manager,
)
from sb3_detc.triggers import TRIGGER_FAMILIES, DitheredTrigger, PeriodicTrigger

#: Training steps of the policies over options (500 of the paper's iterations of 2048 steps).
TIMESTEPS = 1_024_000
#: Steps at the start in which only the critic learns (50 iterations).
WARM_UP = 102_400
#: Rollouts between two lines of progress.
PROGRESS_EVERY = 25


class Progress(BaseCallback):
    """Print the steps, the savings of the last rollout, the recent return and the time every ``every`` rollouts.

    The return is the mean over the last (up to 100) training episodes of the agents' mean return,
    the communication cost included (SB3's ``ep_info_buffer``, as ``rollout/ep_rew_mean``); it is
    left out while no episode has ended.

    :param label: what is trained, at the start of every line
    :param every: rollouts between two lines
    """

    def __init__(self, label: str, every: int = PROGRESS_EVERY) -> None:
        super().__init__()
        self.label = label
        self.every = every
        self.rollouts = 0
        self.began = time.monotonic()

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self.rollouts += 1
        if self.rollouts % self.every == 0:
            rate = float(np.mean(self.model.rollout_buffer.broadcast))
            episodes = [info["r"] for info in self.model.ep_info_buffer or ()]
            recent = f"return of the last {len(episodes)} episodes {np.mean(episodes):.1f}, " if episodes else ""
            print(
                f"{self.label}: {self.num_timesteps} steps, savings in the last rollout {1 - rate:.3f}, {recent}"
                f"{time.monotonic() - self.began:.0f} s",
                flush=True,
            )


def finished_policy(folder: Path, trial: Trial) -> Path | None:
    """The final policy of a finished trial.

    :param folder: the study folder
    :param trial: the trial
    :return: its ``policy.pt``, or None if the trial is not done
    """
    trial_dir = trial_folder(folder, trial)
    done = read_status(trial_dir)["status"] == "done" and (trial_dir / "policy.pt").is_file()
    return trial_dir / "policy.pt" if done else None


def env_settings(entry: dict[str, Any], job: dict[str, Any]) -> dict[str, Any]:
    """The env's keyword arguments of training and evaluation: the entry's, the job's changes, its cost.

    :param entry: the trial's hyperparameter entry
    :param job: ``changes`` (its ``env_kwargs``, if any) and ``broadcast_cost`` (None: the entry's)
    :return: the keyword arguments
    """
    env_kwargs = {**(entry.get("env_kwargs") or {}), **job["changes"].get("env_kwargs", {})}
    if job["broadcast_cost"] is not None:
        env_kwargs["broadcast_cost"] = job["broadcast_cost"]
    return env_kwargs


def load_all_but_mu(policy: MlpHybridPolicy, saved: MlpHybridPolicy) -> None:
    """Load a saved policy's controls and critic into ``policy`` and leave its ``mu`` as initialised.

    For a ``mu`` with other inputs than the saved one's (e.g. the own age): the networks that
    share a batched chain with it are copied over their common part (the rest is zero padding).

    :param policy: the policy to load into (its ``mu`` stays as it is)
    :param saved: the trained policy whose ``pi`` and ``q`` (and every other parameter of the same shape) to take
    """
    fresh = [value.clone() for value in policy.net_parameters("mu")]
    own = policy.state_dict()
    policy.load_state_dict({**own, **{k: v for k, v in saved.state_dict().items() if v.shape == own[k].shape}})
    with th.no_grad():
        for net in ("q", "pi"):
            for new, old in zip(policy.net_parameters(net), saved.net_parameters(net), strict=True):
                common = tuple(slice(0, min(a, b)) for a, b in zip(new.shape, old.shape, strict=True))
                new[common] = old[common]
        for new, value in zip(policy.net_parameters("mu"), fresh, strict=True):
            new.copy_(value)


def build(job: dict[str, Any], log_folder: Path) -> tuple[Any, dict[str, Any]]:
    """MAPPOC of the trial's entry on its training envs, with the trial's final policy loaded and ``pi`` frozen.

    The model is built as the study trains its trials (rl-zoo3's experiment manager, the entry with
    the study's overrides), with the job's changes, the env settings of :func:`env_settings` and
    none of the entry's callbacks (the baseline's random skips and action noise schedule, whose
    noise has ended by the end of training).

    :param job: ``folder`` (the study folder), ``algorithm`` (its label), ``seed``, ``broadcast_cost``
        (None: the entry's), ``timesteps``, ``changes`` (entry settings to change) and ``normalize_reward``
        (normalise the learner's rewards with fresh statistics); optionally ``option_age_scale``: ``mu``
        starts afresh and reads the age of its own last broadcast with this factor (the trial's ``mu``
        is dropped; its controls and critic are kept, :func:`load_all_but_mu`; ``broadcast_prob_init``
        in the changed ``policy_kwargs`` sets where it starts)
    :param log_folder: where rl-zoo3's experiment manager may write
    :return: the model, options from ``mu``, only the critic learning; and the env's keyword arguments
    :raises StudyError: if the trial has not finished, or its policy was built with other settings
    """
    folder = Path(job["folder"])
    spec = load_folder_study(folder)
    (trial,) = [t for t in spec.trials() if t.algorithm.label == job["algorithm"] and t.seed == job["seed"]]
    path = finished_policy(folder, trial)
    if path is None:
        raise StudyError(f"{trial.name} of {folder} has not finished")
    algorithm = trial.algorithm
    env_kwargs = env_settings(algorithm.entry, job)
    changes = {key: value for key, value in job["changes"].items() if key != "env_kwargs"}
    hyperparams = {**algorithm.hyperparams, **changes, "env_kwargs": env_kwargs, "callback": []}
    # sample_options says how the trigger is evaluated, not how the networks are built
    free = {"observation_space", "action_space", "lr_schedule", "sample_options"}
    fresh_mu = job.get("option_age_scale") is not None
    if fresh_mu:
        policy_kwargs = hyperparams.get("policy_kwargs", algorithm.entry.get("policy_kwargs"))
        policy_kwargs = python_value(policy_kwargs, "policy_kwargs", f"{folder} {trial.name}") or {}
        hyperparams["policy_kwargs"] = {**policy_kwargs, "option_age_scale": job["option_age_scale"]}
        # mu's inputs, start and window
        free |= {"option_age_scale", "option_others_age_scale", "broadcast_prob_init", "broadcast_interval"}
    model, _ = trial_manager(spec, trial, log_folder, job["timesteps"], hyperparams).setup_experiment()
    saved = MlpHybridPolicy.load(str(path), device="cpu")
    entry = model.policy.constructor_parameters()
    differ = sorted(
        key for key, value in saved.constructor_parameters().items() if key not in free and entry.get(key) != value
    )
    if differ:
        model.env.close()
        raise StudyError(f"{path} was built with other policy settings than the entry gives now: {differ}")
    if fresh_mu:
        load_all_but_mu(model.policy, saved)
    else:
        model.policy.load_state_dict(saved.state_dict())
    model.set_fixed_trigger(None)
    model.set_trained_policies(control_policy=False, broadcast_policy=False)
    if job["normalize_reward"]:
        model.set_reward_normalization(True, fresh_statistics=True)
    return model, env_kwargs


def nearest_period(savings: float) -> int | None:
    """The period ``k`` of a message every ``k`` steps whose savings ``1 - 1/k`` lie closest to ``savings``.

    :param savings: the savings to match, in [0, 1]
    :return: the period (>= 1), or None for savings of 1 (never)
    """
    if savings >= 1:
        return None
    exact = 1 / (1 - savings)
    return min({max(1, math.floor(exact)), math.ceil(exact)}, key=lambda k: abs(1 - 1 / k - savings))


def start_trigger(job: dict[str, Any]) -> PeriodicTrigger | DitheredTrigger | None:
    """The trigger of the warm-up, which ``mu`` then imitates: the job's schedule, with its deviations if any.

    :param job: optionally ``start_period`` and ``start_dither`` (skip and extra probabilities)
    :return: the trigger, or None without ``start_period`` (the warm-up takes ``mu``'s options)
    """
    if not job.get("start_period"):
        return None
    schedule = PeriodicTrigger(job["start_period"])
    dither = job.get("start_dither")
    return schedule if dither is None else DitheredTrigger(schedule, *dither, seed=job["seed"])


def run(job: dict[str, Any], progress_every: int = PROGRESS_EVERY) -> dict[str, Any]:
    """Train the policies over options for one seed's controller and evaluate them; one table row.

    The critic learns alone first (``warm_up`` steps, options from the untrained ``mu``: it learned
    for random options, and the baseline trained without the communication cost), then the critic
    and ``mu`` together for the rest of ``timesteps``. With ``start_period`` the warm-up's options
    come from that schedule (all agents in phase; with ``start_dither``, with random deviations)
    and ``mu`` imitates it before it learns.

    :param job: as :func:`build` takes it, ``warm_up`` (steps, part of ``timesteps``), optionally
        ``start_period`` (a period: the warm-up under that schedule, ``mu`` started as it) and
        ``start_dither`` (the schedule's skip and extra probabilities, :func:`start_trigger`),
        ``fixed_families`` (optional: the families the evaluation compares, with the learned options
        sampled), ``select_every`` and ``select_episodes`` (optional: keep the policy best on that
        many validation episodes, evaluated every that many steps,
        :class:`~sb3_detc.callbacks.SelectBestCallback`), ``policy`` (the trial's policy's digest: a
        retrained trial is a new job) and ``save_dir`` (where to keep the trained policy; None: not kept)
    :param progress_every: rollouts between two lines of progress (:class:`Progress`)
    :return: the seed, the training seconds, the study protocol's metrics of the learned trigger
        (:func:`~sb3_detc.evaluation.evaluate_policy_modes`), the control return, package travel (None
        where the env reports none), fall rate and savings of a message every ``k`` steps at the nearest
        savings (None if the trigger never broadcasts), the file of the saved policy, with
        ``start_period`` the share of decisions the imitation matched and with ``select_every`` the
        validations and the kept one (:meth:`~sb3_detc.callbacks.SelectBestCallback.restore`)
    """
    th.set_num_threads(1)
    spec = load_folder_study(Path(job["folder"]))
    label = f"{job['algorithm']} seed {job['seed']}"
    with tempfile.TemporaryDirectory() as log_folder:
        model, env_kwargs = build(job, Path(log_folder))
        schedule = start_trigger(job)
        began = time.monotonic()
        select, selection = None, None
        try:
            model.set_fixed_trigger(schedule)
            model.learn(job["warm_up"], callback=Progress(f"{label}, critic alone", progress_every))
            if schedule is not None:
                imitation = imitate_trigger(model, schedule, job["start_period"])
                print(f"{label}: mu imitated {schedule!r}, {imitation:.3f} of the decisions matched", flush=True)
                model.set_fixed_trigger(None)
            model.set_trained_policies(control_policy=False, broadcast_policy=True)
            rest = job["timesteps"] - job["warm_up"]
            callbacks: list[BaseCallback] = [Progress(label, progress_every)]
            if job.get("select_every"):
                seeds = spec.validation_seeds(job["select_episodes"])  # right after the evaluation's episodes
                validation = gym.make(spec.env, **env_kwargs)
                select = SelectBestCallback(validation, seeds, job["select_every"], sample_options=True)
                callbacks.append(select)
            model.learn(rest, callback=callbacks, reset_num_timesteps=False)
            if select is not None:
                selection = select.restore()
        finally:
            model.env.close()
            if select is not None:
                select.eval_env.close()
        seconds = time.monotonic() - began
    policy, saved = model.policy, None
    if job["save_dir"] is not None:
        digest = hashlib.sha256(job_key(job).encode()).hexdigest()[:10]
        path = Path(job["save_dir"]) / f"{job['algorithm']}_seed{job['seed']}_{digest}.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        replace_atomically(path, lambda scratch: policy.save(str(scratch)), path.stem + ".tmp.pt")
        saved = path.name
    env = gym.make(spec.env, **env_kwargs)
    try:
        families = job.get("fixed_families", [])
        # with families compared, the learned row samples mu's options as they were trained (the mode has its own row)
        evaluation = evaluate_policy_modes(
            policy,
            env,
            spec.episodes,
            spec.eval_seed,
            sample_options=True if families else None,
            fixed_families=families,
        )
        period, periodic = nearest_period(evaluation["metrics"]["savings"]), None
        if period is not None:
            seeds = [spec.eval_seed + k for k in range(spec.episodes)]
            episodes = evaluate_episodes(policy, env, seeds, deterministic=True, fixed_trigger=PeriodicTrigger(period))
            travel = episodes.package_travel
            periodic = {
                "period": period,
                "control_return": float(np.mean(episodes.control_returns)),
                "package_travel": None if np.isnan(travel).any() else float(np.mean(travel)),
                "fall_rate": float(np.mean(episodes.failed)),
                "savings": episodes.savings,
            }
    finally:
        env.close()
    return {
        "algorithm": job["algorithm"],
        "seed": job["seed"],
        "env_kwargs": env_kwargs,
        "timesteps": job["timesteps"],
        "train_seconds": round(seconds, 1),
        "metrics": evaluation["metrics"],
        "periodic_nearest": periodic,
        "saved": saved,
        **({"imitation_accuracy": imitation} if schedule is not None else {}),
        **({"selection": selection} if selection is not None else {}),
    }


def print_table(rows: list[dict[str, Any]]) -> None:
    """Print one line per seed and the means over seeds with 95 % bootstrap intervals.

    The means include every fixed family that all rows compared, and the learned minus the best of them.

    :param rows: the rows of :func:`run`
    """
    print(
        "| seed | savings | control return learned | random, same rate | learned minus random | every k-th step "
        "| package travel learned | fall rate learned |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        m, periodic = row["metrics"], row["periodic_nearest"]
        every = "" if periodic is None else f"{periodic['control_return']:.1f} (k = {periodic['period']})"
        cells = [
            f"{m['savings']:.3f}",
            f"{m['control_return']:.1f}",
            f"{m['random_same_rate_control_return']:.1f}",
            f"{m['learned_minus_random_control_return']:+.1f}",
            every,
            f"{m.get('package_travel', float('nan')):.2f}",
            f"{m.get('fall_rate', float('nan')):.2f}",
        ]
        print(f"| {row['seed']} | " + " | ".join(cells) + " |")
    if len(rows) < 2:
        return
    names = {
        "savings": "savings",
        "control return learned": "control_return",
        "control return random, same rate": "random_same_rate_control_return",
        "learned minus random": "learned_minus_random_control_return",
    }
    families = [f for f in TRIGGER_FAMILIES if all(f"fixed_{f}_control_return" in row["metrics"] for row in rows)]
    for family in families:
        names[f"control return {family.replace('_', ' ')}"] = f"fixed_{family}_control_return"
    if families:
        names["learned minus best family"] = "learned_minus_best_fixed_control_return"
    if all("thresholded_minus_best_fixed_control_return" in row["metrics"] for row in rows):
        names["control return thresholded at the learned rate"] = "thresholded_control_return"
        names["thresholded minus best family"] = "thresholded_minus_best_fixed_control_return"
    mean, ci = metric_estimates([row["metrics"] for row in rows])
    print()
    print(f"Over {len(rows)} seeds, mean [95 % bootstrap interval]:")
    for name, key in names.items():
        print(f"- {name}: {interval_text(mean[key], *ci[key], 3 if name == 'savings' else 1)}")


def print_families(rows: list[dict[str, Any]]) -> None:
    """Print, per seed, the savings and control return of the learned trigger, of ``mu`` thresholded at its rate
    and of every compared fixed family, and the learned (and thresholded) minus the best family.

    :param rows: the rows of :func:`run` (rows without compared families print nothing)
    """
    families = [f for f in TRIGGER_FAMILIES if any(f"fixed_{f}_control_return" in row["metrics"] for row in rows)]
    if not families:
        return
    modes = ["thresholded"] if any("thresholded_control_return" in row["metrics"] for row in rows) else []
    compared = [f"fixed_{family}" for family in families]
    differences = ["learned", *modes]
    print()
    print(
        "| seed | learned | "
        + " | ".join(name.removeprefix("fixed_").replace("_", " ") for name in modes + compared)
        + "".join(f" | {mode} minus best family" for mode in differences)
        + " |"
    )
    print("|---|" + "---|" * (1 + len(modes + compared) + len(differences)))
    for row in rows:
        m = row["metrics"]
        cells = [f"{m['savings']:.3f}, {m['control_return']:.1f}"]
        for name in modes + compared:
            savings, value = m.get(f"{name}_savings"), m.get(f"{name}_control_return")
            cells.append("" if value is None else f"{savings:.3f}, {value:.1f}")
        for mode in differences:
            value = m.get(f"{mode}_minus_best_fixed_control_return")
            cells.append("" if value is None else f"{value:+.1f}")
        print(f"| {row['seed']} | " + " | ".join(cells) + " |")


def main() -> None:
    """Train and evaluate every seed one after another, write the rows and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="a study folder with finished trials")
    parser.add_argument("--algorithm", default="random_skip_paper", help="the study algorithm whose controllers to use")
    parser.add_argument("--seeds", type=int, nargs="+", help="(default: every finished seed of the algorithm)")
    parser.add_argument("--broadcast-cost", type=float, help="communication cost per broadcast (default: the entry's)")
    parser.add_argument("--timesteps", type=int, default=TIMESTEPS, help="training steps per seed, warm-up included")
    parser.add_argument("--warm-up", type=int, default=WARM_UP, help="first steps in which only the critic learns")
    parser.add_argument("--set", type=json.loads, default={}, help="entry settings to change (JSON), e.g. MAPPOC's")
    parser.add_argument(
        "--normalize-reward", action="store_true", help="normalise the learner's rewards, with fresh statistics"
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("multiwalker_trigger_for_controller.json"),
        help="rows (JSON); seeds already in it with the same settings are not trained again",
    )
    parser.add_argument("--save-dir", type=Path, help="folder for the trained policies (default: not kept)")
    parser.add_argument(
        "--progress-every", type=int, default=PROGRESS_EVERY, help="rollouts between two lines of progress"
    )
    parser.add_argument(
        "--option-age-scale",
        type=float,
        help="start mu afresh, reading the age of its own last broadcast times this factor (default: the trial's mu)",
    )
    parser.add_argument(
        "--start-period",
        type=int,
        help="the warm-up's options from a message every K-th step (in phase); mu then imitates it "
        "(needs --option-age-scale)",
    )
    parser.add_argument(
        "--start-dither",
        type=float,
        nargs=2,
        metavar=("SKIP", "EXTRA"),
        help="with --start-period: each scheduled message skipped with SKIP, each silence broken with EXTRA",
    )
    parser.add_argument(
        "--select-every",
        type=int,
        help="evaluate the policy on validation episodes every N steps of mu's training and at its end, and keep "
        "the best one at the target savings (default: keep the last)",
    )
    parser.add_argument(
        "--select-episodes", type=int, default=20, help="validation episodes of --select-every (after the evaluation's)"
    )
    parser.add_argument(
        "--fixed-families",
        nargs="+",
        choices=TRIGGER_FAMILIES,
        default=[],
        help="fixed trigger families the evaluation compares at the learned rate (the learned options sampled)",
    )
    args = parser.parse_args()
    check_at_least_one(parser, args, "timesteps", "progress_every", "select_every", "select_episodes")
    if not 0 <= args.warm_up < args.timesteps:
        parser.error("--warm-up must be >= 0 and below --timesteps")
    if args.broadcast_cost is not None and not args.broadcast_cost >= 0:
        parser.error("--broadcast-cost must be >= 0")
    if args.option_age_scale is not None and not (math.isfinite(args.option_age_scale) and args.option_age_scale > 0):
        parser.error("--option-age-scale must be a finite number > 0")
    if args.start_period is not None and not (args.start_period >= 1 and args.option_age_scale and args.warm_up > 0):
        parser.error("--start-period takes a period >= 1, with --option-age-scale and a --warm-up > 0")
    if args.start_dither is not None and not (args.start_period and all(0 <= p <= 1 for p in args.start_dither)):
        parser.error("--start-dither takes two probabilities in [0, 1], with --start-period")
    if not isinstance(args.set, dict) or not isinstance(args.set.get("env_kwargs", {}), dict) or "callback" in args.set:
        parser.error("--set takes a JSON object of entry settings (env_kwargs an object; no callback)")
    try:
        spec = load_folder_study(args.folder)
    except StudyError as error:
        parser.error(str(error))
    trials = {t.seed: t for t in spec.trials() if t.algorithm.label == args.algorithm}
    policies = {seed: finished_policy(args.folder, t) for seed, t in trials.items()}
    finished = {seed for seed, path in policies.items() if path is not None}
    if not finished:
        labels = ", ".join(sorted(a.label for a in spec.algorithms))
        parser.error(f"{args.folder} has no finished trial of {args.algorithm!r} (algorithms: {labels})")
    seeds = sorted(set(args.seeds or finished))
    if set(seeds) - finished:
        parser.error(f"seeds {sorted(set(seeds) - finished)} of {args.algorithm} have not finished")
    job = {
        "folder": str(args.folder),  # as given: the same key on every machine
        "algorithm": args.algorithm,
        "broadcast_cost": args.broadcast_cost,
        "timesteps": args.timesteps,
        "warm_up": args.warm_up,
        "changes": args.set,
        "normalize_reward": args.normalize_reward,
        "save_dir": None if args.save_dir is None else str(args.save_dir),
    }
    if args.fixed_families:  # only then part of the key: rows of earlier runs keep theirs
        job["fixed_families"] = args.fixed_families
    if args.option_age_scale is not None:
        job["option_age_scale"] = args.option_age_scale
    if args.start_period is not None:
        job["start_period"] = args.start_period
    if args.start_dither is not None:
        job["start_dither"] = args.start_dither
    if args.select_every is not None:
        job["select_every"], job["select_episodes"] = args.select_every, args.select_episodes
    jobs = [
        {**job, "seed": seed, "policy": hashlib.sha256(policies[seed].read_bytes()).hexdigest()[:16]} for seed in seeds
    ]
    try:
        rows = run_rows(partial(run, progress_every=args.progress_every), jobs, args.out, workers=1)
    except OutError as error:
        parser.error(str(error))
    print(
        f"{args.algorithm} of {args.folder}: policies over options trained for {args.timesteps} steps "
        f"({args.warm_up} of them the critic alone) on the frozen controllers, env {rows[0]['env_kwargs']}; "
        f"{spec.episodes} evaluation episodes from seed {spec.eval_seed}"
    )
    print()
    print_table(rows)
    print_families(rows)


if __name__ == "__main__":
    main()
