"""Evaluate a saved model or policy with the package's protocol: ``python -m sb3_detc.evaluate PATH``.

``PATH`` is a saved MAPPOC model (``.zip``: a run's final model or a checkpoint) or a saved
policy (``policy.pt``, as every study trial keeps it). The command runs the same seeded
episodes in every mode of the protocol (:func:`~sb3_detc.evaluation.evaluate_policy_modes`:
learned, the most likely options, random skips at the learned rate, periodic, never; with
``--fixed-families``, or the families of the study a policy comes from, each family at exactly
the learned rate (two of its triggers mixed) and, for a policy that learned its options (not one with a fixed trigger or
``--skip-prob``), ``mu`` thresholded at it), prints a line as each mode finishes and then
the modes' table: return, control return (without the communication cost), savings, and
package travel and fall rate where the env reports them.

The env and its settings come from, in this order:

* ``--env ID`` (with ``--env-kwargs key=value ...``);
* for a policy in a study's trial folder (``<study>/trials/<label>/seed<seed>/policy.pt``), the
  study (``<study>/study.yml``): its env, the trial's hyperparameter entry (``env_kwargs``, the
  fixed trigger a baseline trained with) and its evaluation episodes, seed and fixed
  families, so that the command evaluates the policy as the study did (``evaluation.json``);
* for a model in an rl-zoo3 run folder (``python -m sb3_detc.train``), the run's saved
  ``args.yml`` and ``config.yml``.

``--env-kwargs`` adds to or replaces the settings found. A path that is not a saved model or
policy is refused with one line (exit code 2). Examples::

    python -m sb3_detc.evaluate benchmarks/studies/multiwalker_paper/trials/mappoc_paper/seed0/policy.pt
    python -m sb3_detc.evaluate logs/mappoc/sb3_detc-LinearETC-v0_1/sb3_detc-LinearETC-v0.zip --episodes 20
    python -m sb3_detc.evaluate model.zip --env sb3_detc/MultiwalkerETC-v0 --env-kwargs broadcast_cost=0.25 --out e.json
    python -m sb3_detc.evaluate model.zip --env sb3_detc/MultiwalkerETC-v0 --episodes 1 --video episode.mp4
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import json
import re
import shutil
import sys
import tempfile
import time
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
import yaml
from gymnasium.wrappers import RecordVideo
from rl_zoo3.utils import get_saved_hyperparams
from stable_baselines3.common.save_util import json_to_data

from sb3_detc.cli import InputError, check_env, run_cli
from sb3_detc.evaluation import EVAL_SEED, Episodes, evaluate_episodes, evaluate_policy_modes
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.mappoc import FixedTrigger
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.study.spec import entry_fixed_trigger, load_folder_study
from sb3_detc.triggers import TRIGGER_FAMILIES, RandomTrigger

__all__ = ["EPISODES", "Saved", "load_saved", "main", "modes_table", "read_policy", "record_episode"]

#: Evaluation episodes per mode unless a study or ``--episodes`` says otherwise.
EPISODES = 50

#: What the command takes.
WHAT = "a saved MAPPOC model (.zip) or policy (policy.pt)"


@dataclass
class Saved:
    """A saved policy with what its evaluation needs.

    :param policy: the policy
    :param env_id: the env it acts in
    :param env_kwargs: the env's settings (communication cost included)
    :param trigger: the fixed trigger it trained with (None: its policy over options)
    :param episodes: evaluation episodes per mode (a study's, else :data:`EPISODES`)
    :param seed: seed of the first evaluation episode (a study's, else :data:`~sb3_detc.evaluation.EVAL_SEED`)
    :param source: where the env and its settings were found, for the reader
    :param fixed_families: the fixed trigger families compared at the learned rate (a study's, else none)
    """

    policy: MlpHybridPolicy
    env_id: str
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    trigger: FixedTrigger | None = None
    episodes: int = EPISODES
    seed: int = EVAL_SEED
    source: str = "--env"
    fixed_families: tuple[str, ...] = ()


def read_policy(path: Path) -> MlpHybridPolicy:
    """The policy of a saved MAPPOC model or of a saved policy, on the CPU.

    :param path: a model saved with ``model.save`` (``.zip``) or a policy saved with ``policy.save``
    :return: the policy
    :raises InputError: if ``path`` is neither (no file, not a saved model or policy, a model of another algorithm)
    """
    if not path.is_file():
        raise InputError(f"{path}: no such file; give {WHAT}")
    if not zipfile.is_zipfile(path):
        raise InputError(f"{path} is not {WHAT}")
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
        data = archive.read("data").decode() if "data" in names else None
    if data is not None and "policy.pth" in names:  # Stable-Baselines3's model file
        policy_class = json_to_data(data).get("policy_class")
        if not (isinstance(policy_class, type) and issubclass(policy_class, MlpHybridPolicy)):
            raise InputError(f"{path} is a model of another algorithm, not {WHAT}")
        return MAPPOC.load(path, device="cpu").policy
    if any(name.endswith("/data.pkl") for name in names):  # PyTorch's file, as policy.save writes it
        saved = th.load(path, map_location="cpu", weights_only=False)
        if isinstance(saved, dict) and {"data", "state_dict"} <= set(saved):
            return MlpHybridPolicy.load(str(path), device="cpu")
    raise InputError(f"{path} is not {WHAT}")


def _study_settings(path: Path, policy: MlpHybridPolicy) -> Saved | None:
    """What the study says about the policy of its trial folder ``<study>/trials/<label>/seed<seed>/``.

    :param path: the saved policy
    :param policy: the policy
    :return: the policy with the study's env, the trial's entry and evaluation; None outside a trial folder
    :raises InputError: if the study does not have the trial's algorithm (or as
        :func:`~sb3_detc.study.spec.load_folder_study`)
    """
    trial, algorithm = path.parent, path.parent.parent
    study = algorithm.parent.parent
    if algorithm.parent.name != "trials" or not re.fullmatch(r"seed\d+", trial.name):
        return None
    if not (study / "study.yml").is_file():
        return None
    spec = load_folder_study(study)
    found = [a for a in spec.algorithms if a.label == algorithm.name]
    if not found:
        raise InputError(f"{study / 'study.yml'} has no algorithm {algorithm.name!r} (the trial of {path})")
    entry = found[0].entry
    return Saved(
        policy,
        spec.env,
        dict(entry.get("env_kwargs") or {}),
        entry_fixed_trigger(entry),
        spec.episodes,
        spec.eval_seed,
        f"study {study}, trial {algorithm.name}/{trial.name}",
        spec.fixed_families,
    )


def _run_settings(path: Path, policy: MlpHybridPolicy) -> Saved | None:
    """What the rl-zoo3 run folder of a saved model says: its ``<env name>/args.yml`` and ``config.yml``.

    :param path: the saved model, in its run folder
    :param policy: its policy
    :return: the policy with the run's env, settings and fixed trigger; None without one run's saved arguments
    """
    found = sorted(path.parent.glob("*/args.yml"))
    if len(found) != 1:
        return None
    with open(found[0]) as file:
        args = yaml.load(file, Loader=yaml.UnsafeLoader)  # noqa: S506  (rl-zoo3 writes it with Python tags)
    config, _ = get_saved_hyperparams(str(found[0].parent))
    config = dict(config)
    return Saved(
        policy,
        args["env"],
        dict(config.get("env_kwargs") or {}),
        entry_fixed_trigger(config),
        source=f"run {path.parent}",
    )


def load_saved(path: str | Path, env_id: str | None = None) -> Saved:
    """A saved model's or policy's policy with the env and settings it was trained in (see the module).

    :param path: a saved MAPPOC model (``.zip``) or policy (``policy.pt``)
    :param env_id: the env (None: from the study's trial folder or the rl-zoo3 run folder that ``path`` is in)
    :return: the policy and what its evaluation needs
    :raises InputError: if ``path`` is not a saved model or policy (:func:`read_policy`), or
        ``env_id`` is None and no study or run folder tells the env
    """
    path = Path(path)
    policy = read_policy(path)
    if env_id is not None:
        check_env(env_id)
        return Saved(policy, env_id)
    saved = _study_settings(path, policy) or _run_settings(path, policy)
    if saved is None:
        raise InputError(
            f"cannot tell the env of {path}: it is in neither a study's trial folder nor an rl-zoo3 run folder; "
            "give --env ID (and --env-kwargs key=value ...)"
        )
    return saved


def record_episode(
    saved: Saved, out: Path, seed: int, sample_options: bool | None = None, trigger: FixedTrigger | None = None
) -> Path:
    """Record one episode of the policy's own options (the protocol's ``learned`` mode) as a video.

    Gymnasium's :class:`~gymnasium.wrappers.RecordVideo` writes the env's ``rgb_array`` frames
    (Multiwalker's mark every walker's option of the step: a green disc above a walker that
    broadcast, a grey ring above a silent one).

    :param saved: the policy and its env
    :param out: the video file (MP4)
    :param seed: the episode's seed
    :param sample_options: options sampled from ``mu`` (True) or its most likely ones (False)
        (None: as the policy's ``sample_options`` says)
    :param trigger: options to use instead of ``mu``'s (None: ``saved.trigger``)
    :return: ``out``
    """
    trigger = saved.trigger if trigger is None else trigger
    if trigger is not None and hasattr(trigger, "fork"):
        trigger = trigger.fork(seed)
    env = gym.make(saved.env_id, render_mode="rgb_array", **saved.env_kwargs)
    with tempfile.TemporaryDirectory() as folder:
        recorder = RecordVideo(env, str(Path(folder) / "video"), episode_trigger=lambda _: True, name_prefix="episode")
        try:
            evaluate_episodes(saved.policy, recorder, [seed], sample_options=sample_options, fixed_trigger=trigger)
        finally:
            recorder.close()
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(next(Path(folder).glob("video/*.mp4")), out)
    return out


def modes_table(result: dict[str, Any]) -> str:
    """Markdown table of a protocol's modes: means over the episodes.

    :param result: what :func:`~sb3_detc.evaluation.evaluate_policy_modes` returns
    :return: one row per mode (return, control return, savings, and package travel and fall
        rate where the env reports them), then the paired learned-minus-random difference and,
        where known, the dependence of the learned options on the state, the compared fixed
        families' triggers and the learned (and thresholded) minus the best family
    """
    modes = result["modes"]
    package = all(x is not None for x in modes["learned"]["package_travel"])
    header = "| mode | return | control return | savings |" + (" package travel | fall rate |" if package else "")
    lines = [header, "|---" * (header.count("|") - 1) + "|"]
    for mode, episodes in modes.items():
        row = (
            f"| {mode} | {np.mean(episodes['return']):.2f} | {np.mean(episodes['control_return']):.2f} "
            f"| {episodes['savings']:.3f} |"
        )
        if package:
            row += f" {np.mean(episodes['package_travel']):.2f} | {np.mean(episodes['failed']):.2f} |"
        lines.append(row)
    metrics = result["metrics"]
    lines += [
        "",
        "learned minus random skips at the learned rate, control return of the same episodes: "
        f"{metrics['learned_minus_random_control_return']:.2f}",
    ]
    if "option_state_information" in metrics:
        lines.append(
            f"dependence of the learned options on the state: {metrics['option_state_information']:.3g} bits "
            "(mutual information of options and state; 0: it ignores the state)"
        )
    for family, trigger in result.get("fixed", {}).items():
        lines.append(f"fixed family {family}: {trigger}")
    if "thresholded" in result:
        lines.append(f"mu thresholded at the learned rate: {result['thresholded']}")
    for mode in ("learned", "thresholded"):
        name = f"{mode}_minus_best_fixed_control_return"
        if name in metrics:
            lines.append(
                f"{mode} minus the best fixed family ({result['best_fixed']}), same episodes: {metrics[name]:.2f}"
            )
    return "\n".join(lines)


def _setting(text: str) -> Any:
    """An env setting from the command line: a Python literal (``2``, ``1e-3``, ``True``), else the text.

    :param text: the value of one ``key=value`` of ``--env-kwargs``
    :return: the literal's value, or ``text`` itself if it is no Python literal
    """
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def _arguments(argv: Sequence[str]) -> argparse.Namespace:
    """The command's arguments, checked.

    :param argv: the arguments
    :return: the parsed arguments, ``env_kwargs`` as a dict
    :raises InputError: on bad values
    """
    parser = argparse.ArgumentParser(prog="python -m sb3_detc.evaluate", description=__doc__.splitlines()[0])
    parser.add_argument("path", type=Path, help=WHAT)
    parser.add_argument(
        "--episodes", type=int, default=None, help=f"episodes per mode (default: the study's, or {EPISODES})"
    )
    parser.add_argument(
        "--seed", type=int, default=None, help=f"seed of the first episode (default: the study's, or {EVAL_SEED})"
    )
    parser.add_argument("--env", default=None, help="the env id (default: from the study or run folder of PATH)")
    parser.add_argument(
        "--env-kwargs", nargs="*", default=[], help="key=value settings of the env (Python literals, else text)"
    )
    parser.add_argument(
        "--sample-options",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the learned mode samples its options from mu, or takes the most likely (default: the policy's setting)",
    )
    parser.add_argument(
        "--skip-prob",
        type=float,
        default=None,
        help="the policy trained with random skips at this rate (a baseline): its learned mode is such a trigger",
    )
    parser.add_argument(
        "--fixed-families",
        nargs="*",
        choices=TRIGGER_FAMILIES,
        default=None,
        metavar="FAMILY",
        help="fixed trigger families to compare at exactly the learned rate, and mu thresholded at it "
        f"({', '.join(TRIGGER_FAMILIES)}; default: the study's; the option alone: none)",
    )
    parser.add_argument("--video", type=Path, default=None, help="record one episode of the learned mode (MP4)")
    parser.add_argument("--out", type=Path, default=None, help="write the evaluation as JSON")
    args = parser.parse_args(argv)
    bad = [item for item in args.env_kwargs if "=" not in item]
    if bad:
        raise InputError(f"--env-kwargs takes key=value, got {' '.join(bad)}")
    args.env_kwargs = {key: _setting(value) for key, value in (item.split("=", 1) for item in args.env_kwargs)}
    if args.episodes is not None and args.episodes < 1:
        raise InputError(f"--episodes must be >= 1, got {args.episodes}")
    if args.seed is not None and args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    if args.skip_prob is not None and not 0.0 <= args.skip_prob <= 1.0:
        raise InputError(f"--skip-prob must be in [0, 1], got {args.skip_prob}")
    if args.video is not None and importlib.util.find_spec("moviepy") is None:
        raise InputError("--video needs moviepy: pip install moviepy")
    return args


def _evaluate() -> None:
    """The evaluate command: load what ``sys.argv`` names, run the protocol with a line per mode, print the table.

    :raises InputError: on bad input (see :func:`_arguments` and :func:`load_saved`), or
        ``--video`` for an env that does not render
    """
    args = _arguments(sys.argv[1:])
    saved = load_saved(args.path, args.env)
    saved.env_kwargs.update(args.env_kwargs)
    if args.skip_prob is not None:
        saved.trigger = RandomTrigger(args.skip_prob)
    episodes = saved.episodes if args.episodes is None else args.episodes
    seed = saved.seed if args.seed is None else args.seed
    env = gym.make(saved.env_id, **saved.env_kwargs)
    try:
        if args.video is not None and "rgb_array" not in env.metadata.get("render_modes", []):
            raise InputError(f"{saved.env_id} does not render: --video needs an env with render_mode='rgb_array'")
        settings = ", ".join(f"{key}={value!r}" for key, value in saved.env_kwargs.items())
        print(f"{args.path}: {saved.env_id}({settings}) from the {saved.source}")
        print(f"{episodes} episode{'s' * (episodes != 1)} per mode from seed {seed}", flush=True)
        began = time.monotonic()

        def done(mode: str, result: Episodes) -> None:
            print(
                f"  {mode}: control return {np.mean(result.control_returns):.2f}, savings {result.savings:.3f} "
                f"({time.monotonic() - began:.0f} s)",
                flush=True,
            )

        families = saved.fixed_families if args.fixed_families is None else args.fixed_families
        result = evaluate_policy_modes(
            saved.policy,
            env,
            episodes,
            seed,
            saved.trigger,
            sample_options=args.sample_options,
            on_mode=done,
            fixed_families=families,
        )
    finally:
        env.close()
    learned = {"sampled": "options sampled from mu", "mode": "the most likely options of mu"}
    print(f"\nlearned: {learned.get(result['options'], 'the fixed trigger it trained with')}\n")
    print(modes_table(result))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
        print(f"\nEvaluation: {args.out}")
    if args.video is not None:
        video = record_episode(saved, args.video, seed, args.sample_options)
        print(f"Video of the learned mode's first episode: {video}")


def main(argv: Sequence[str] | None = None) -> None:
    """Run the evaluate command line.

    :param argv: the arguments (default: ``sys.argv[1:]``)
    """
    run_cli("python -m sb3_detc.evaluate", _evaluate, argv)


if __name__ == "__main__":
    main()
