"""rl-baselines3-zoo integration: algorithm names, hyperparameter files, run logs and input checks.

Importing this module (:func:`register`) adds sb3-detc's algorithms to rl-zoo3 (``rl_zoo3.utils.ALGOS``) together
with Optuna samplers for ``--optimize``:

* ``mappoc``: :class:`~sb3_detc.MAPPOC`, hyperparameters in ``hyperparams/mappoc.yml``;
* ``ppo_random_skip``: the paper's random-skip baseline, also :class:`~sb3_detc.MAPPOC`
  but trained with :class:`~sb3_detc.callbacks.RandomSkipCallback`
  (``hyperparams/ppo_random_skip.yml``); its runs are logged under its own name.

The command lines :mod:`sb3_detc.train`, :mod:`sb3_detc.enjoy` and
:mod:`sb3_detc.record_video` check their input here (:func:`check_train_arguments`,
:func:`check_model_arguments`), then hand over to rl-zoo3. Every run also writes the SB3
logger's values to ``progress.csv`` in its log folder (:class:`ExperimentManager`), which
:mod:`sb3_detc.plot` reads.
"""

from __future__ import annotations

import argparse
import difflib
import functools
import inspect
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import gymnasium as gym
import optuna
import rl_zoo3.exp_manager
import yaml
from huggingface_sb3 import EnvironmentName
from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from rl_zoo3.utils import ALGOS, get_class_by_name, get_latest_run_id
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import CSVOutputFormat

from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.policies import CRITICS

__all__ = [
    "ALGORITHMS",
    "HYPERPARAMS_DIR",
    "CSVLogCallback",
    "ExperimentManager",
    "InputError",
    "check_hyperparams_file",
    "check_model_arguments",
    "check_train_arguments",
    "convert_mappoc_params",
    "register",
    "run_cli",
    "sample_mappoc_params",
]

#: rl-zoo3 algorithm names of sb3-detc and their classes.
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"mappoc": MAPPOC, "ppo_random_skip": MAPPOC}

#: Folder of the hyperparameter files shipped with the package, one per algorithm name.
HYPERPARAMS_DIR = Path(__file__).parent / "hyperparams"

#: Keys of a hyperparameter entry that rl-zoo3 itself consumes (not passed to the algorithm).
ZOO_KEYS = frozenset(
    {
        "n_timesteps",
        "n_envs",
        "normalize",
        "env_wrapper",
        "vec_env_wrapper",
        "frame_stack",
        "callback",
        "monitor_kwargs",
        "env_kwargs",
        "noise_type",
        "noise_std",
    }
)

#: Arguments of the algorithm that rl-zoo3 sets from its command line, never from the file.
COMMAND_LINE_KEYS = frozenset({"self", "env", "tensorboard_log", "seed", "verbose", "device", "_init_setup_model"})

#: Network sizes the Optuna sampler chooses from (the paper's is ``paper``).
NET_ARCHS = {"small": [64, 64], "medium": [128, 128], "paper": [96, 96, 96]}


class InputError(Exception):
    """Bad command-line input: reported as one line on stderr with a non-zero exit code."""


# ----------------------------------------------------------------------------- registration
def sample_mappoc_params(
    trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict[str, Any]
) -> dict[str, Any]:
    """Optuna sampler of MAPPOC hyperparameters (rl-zoo3's sampler signature).

    :param trial: the Optuna trial
    :param n_actions: size of a Box action space (unused: the joint action space is a Dict)
    :param n_envs: number of training environments (the minibatch is at most one rollout)
    :param additional_args: rl-zoo3's extra arguments (unused)
    :return: keyword arguments of :class:`~sb3_detc.MAPPOC`
    """
    params = {
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True),
        "n_steps": trial.suggest_categorical("n_steps", [128, 256, 512, 1024, 2048]),
        "batch_size": trial.suggest_categorical("batch_size", [32, 64, 128, 256]),
        "n_epochs": trial.suggest_categorical("n_epochs", [5, 10, 20]),
        "gamma": trial.suggest_categorical("gamma", [0.95, 0.98, 0.99, 0.995]),
        "gae_lambda": trial.suggest_categorical("gae_lambda", [0.9, 0.95, 0.98]),
        "clip_range": trial.suggest_categorical("clip_range", [0.1, 0.2, 0.3]),
        "clip_range_option": trial.suggest_categorical("clip_range_option", [0.1, 0.2, 0.3]),
        "option_ent_coef": trial.suggest_float("option_ent_coef", 1e-4, 1.0, log=True),
        "max_grad_norm": trial.suggest_categorical("max_grad_norm", [0.5, 1.0, 5.0]),
        "reward_scale": trial.suggest_float("reward_scale", 1e-3, 1.0, log=True),
        "team_reward": trial.suggest_categorical("team_reward", [False, True]),
        "normalize_option_advantage": trial.suggest_categorical("normalize_option_advantage", [False, True]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCHS)),
        # the centred critic needs mu's own options, which the random-skip baseline replaces
        "critic": trial.suggest_categorical("critic", [c for c in CRITICS if c != "centred"]),
    }
    params["batch_size"] = min(params["batch_size"], params["n_steps"] * n_envs)
    return convert_mappoc_params(params)


def convert_mappoc_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """Turn sampled MAPPOC parameters into keyword arguments (rl-zoo3's converter signature).

    :param sampled_params: the parameters of a trial, as :func:`sample_mappoc_params` names them
    :return: keyword arguments of :class:`~sb3_detc.MAPPOC` (``net_arch`` and ``critic`` go into ``policy_kwargs``)
    """
    params = dict(sampled_params)
    policy_kwargs = {"net_arch": NET_ARCHS[params.pop("net_arch")], "learn_log_std": True}
    if "critic" in params:
        policy_kwargs["critic"] = params.pop("critic")
    return {**params, "policy_kwargs": policy_kwargs}


def register() -> None:
    """Add sb3-detc's algorithms and their Optuna samplers to rl-zoo3 (idempotent; done on import)."""
    ALGOS.update(ALGORITHMS)
    for name in ALGORITHMS:
        HYPERPARAMS_SAMPLER[name] = sample_mappoc_params
        HYPERPARAMS_CONVERTER[name] = convert_mappoc_params


register()


# ----------------------------------------------------------------------------- run logs
class CSVLogCallback(BaseCallback):
    """Write everything the SB3 logger dumps to ``<folder>/progress.csv`` while training.

    rl-zoo3 logs to stdout and TensorBoard only; :mod:`sb3_detc.plot` reads this file.

    :param folder: the run's log folder
    :param verbose: verbosity level
    """

    def __init__(self, folder: str | os.PathLike, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.path = Path(folder) / "progress.csv"
        self._output: CSVOutputFormat | None = None

    def _on_training_start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._output = CSVOutputFormat(str(self.path))
        self.logger.output_formats.append(self._output)

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        if self._output is not None:
            self.logger.output_formats.remove(self._output)
            self._output.close()
            self._output = None


class ExperimentManager(rl_zoo3.exp_manager.ExperimentManager):
    """rl-zoo3's experiment manager that writes ``progress.csv`` and continues step counts.

    Every run's log folder gets the logger's ``progress.csv``. rl-zoo3 restarts the step count
    of a model loaded to continue training (``-i``) at zero, which would restart the
    curriculum, the schedules and the checkpoint numbering; here ``-n`` steps are added to
    where the saved model stopped.
    """

    def create_callbacks(self) -> None:
        """rl-zoo3's callbacks (progress bar, checkpoints, evaluation) and a :class:`CSVLogCallback`."""
        super().create_callbacks()
        self.callbacks.append(CSVLogCallback(self.save_path))

    def learn(self, model: BaseAlgorithm) -> None:
        """Train ``model`` as rl-zoo3 does, continuing its step count if it was loaded to continue.

        :param model: the model to train
        """
        if not self.continue_training:
            super().learn(model)
            return
        # On the class, not the instance: checkpoints pickle the instance's attributes.
        cls = type(model)
        own = cls.__dict__.get("learn")
        cls.learn = functools.partialmethod(cls.learn, reset_num_timesteps=False)  # type: ignore[method-assign]
        try:
            super().learn(model)
        finally:
            if own is None:
                del cls.learn
            else:
                cls.learn = own  # type: ignore[method-assign]


# ----------------------------------------------------------------------------- input checks
def _closest(word: str, choices: Sequence[str]) -> str:
    match = difflib.get_close_matches(word, list(choices), n=1)
    return f" (did you mean {match[0]!r}?)" if match else ""


def check_algorithm(algo: str) -> None:
    """Raise :class:`InputError` unless ``algo`` is an rl-zoo3 algorithm name (after :func:`register`).

    :param algo: the algorithm name
    """
    if algo not in ALGOS:
        raise InputError(f"unknown algorithm {algo!r}{_closest(algo, list(ALGOS))}; known: {', '.join(ALGOS)}")


def check_env(env_id: str) -> None:
    """Raise :class:`InputError` unless ``env_id`` is a registered Gymnasium id.

    :param env_id: the environment id
    """
    if env_id not in gym.registry:
        ours = [name for name in gym.registry if name.startswith("sb3_detc/")]
        raise InputError(
            f"unknown environment {env_id!r}{_closest(env_id, list(gym.registry))}; sb3-detc's: {', '.join(ours)}"
        )


def _check_callbacks(entry: Any, where: str) -> None:
    names = entry if isinstance(entry, list) else [entry]
    for item in names:
        if isinstance(item, dict):
            if len(item) != 1:
                raise InputError(f"{where}: a callback with arguments is one 'name: {{arguments}}' item, got {item}")
            ((name, kwargs),) = item.items()
        else:
            name, kwargs = item, {}
        if not isinstance(name, str) or "." not in name:
            raise InputError(f"{where}: a callback is named by its import path (module.Class), got {name!r}")
        try:
            callback_class = get_class_by_name(name)
        except (ImportError, AttributeError) as error:
            raise InputError(f"{where}: unknown callback {name!r} ({error})") from None
        if not isinstance(kwargs, dict):
            raise InputError(f"{where}: the arguments of callback {name!r} must be a mapping, got {kwargs!r}")
        try:
            callback_class(**kwargs)
        except (TypeError, ValueError) as error:
            raise InputError(f"{where}: callback {name!r}: {error}") from None


def check_hyperparams_file(path: str | os.PathLike, algo: str, env_id: str) -> dict[str, Any]:
    """Check the entry of ``env_id`` in an rl-zoo3 YAML hyperparameter file for algorithm ``algo``.

    Checks that the file exists and is YAML, that it has an entry for ``env_id`` (or
    ``default``), that every key is an argument of the algorithm or one rl-zoo3 consumes,
    that ``n_timesteps`` and ``policy`` are there, and that every callback can be imported
    and built with its arguments.

    :param path: the YAML file
    :param algo: the rl-zoo3 algorithm name
    :param env_id: the environment id
    :return: the entry
    :raises InputError: on the first problem found, with the file and key in the message
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"hyperparameter file {str(path)!r} not found")
    try:
        content = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(error, "problem", None) or type(error).__name__
        raise InputError(f"{path}: not valid YAML{at}: {problem}") from None
    if not isinstance(content, dict):
        raise InputError(f"{path}: expected a mapping of environment ids to hyperparameters")
    entry = content.get(env_id, content.get("default"))
    if entry is None:
        raise InputError(f"{path}: no entry for {env_id!r} (entries: {', '.join(map(str, content))})")
    where = f"{path} [{env_id}]"
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected a mapping of hyperparameters, got {entry!r}")
    arguments = set(inspect.signature(ALGOS[algo].__init__).parameters) - COMMAND_LINE_KEYS
    allowed = arguments | ZOO_KEYS
    for key in entry:
        if key not in allowed:
            raise InputError(f"{where}: unknown hyperparameter {key!r}{_closest(str(key), sorted(allowed))}")
    for key in ("n_timesteps", "policy"):
        if key not in entry:
            raise InputError(f"{where}: missing hyperparameter {key!r}")
    if "callback" in entry:
        _check_callbacks(entry["callback"], where)
    return entry


def _known_arguments(argv: Sequence[str], *arguments: tuple[tuple[str, ...], Any]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(add_help=False)
    for flags, default in arguments:
        parser.add_argument(*flags, default=default)
    known, _ = parser.parse_known_args(argv)
    return known


def check_train_arguments(argv: Sequence[str]) -> list[str]:
    """Check the input of a training command line and complete it with sb3-detc's defaults.

    Defaults: ``--algo mappoc``, ``--env sb3_detc/LinearETC-v0`` and, for sb3-detc's
    algorithms, ``-conf`` the package's ``hyperparams/<algo>.yml``.

    :param argv: rl-zoo3 training arguments (``rl_zoo3.train``'s command line)
    :return: the arguments to hand over to rl-zoo3
    :raises InputError: on an unknown algorithm or environment, a bad hyperparameter file or
        a missing model to continue from
    """
    known = _known_arguments(
        argv,
        (("--algo",), "mappoc"),
        (("--env",), "sb3_detc/LinearETC-v0"),
        (("-conf", "--conf-file"), None),
        (("-i", "--trained-agent"), ""),
    )
    check_algorithm(known.algo)
    check_env(known.env)
    defaults = ["--algo", known.algo, "--env", known.env]
    conf = known.conf_file
    if conf is None and known.algo in ALGORITHMS:
        conf = str(HYPERPARAMS_DIR / f"{known.algo}.yml")
        defaults += ["-conf", conf]
    if conf is not None and conf.endswith((".yml", ".yaml")):
        check_hyperparams_file(conf, known.algo, known.env)
    if known.trained_agent and not (known.trained_agent.endswith(".zip") and os.path.isfile(known.trained_agent)):
        raise InputError(f"no saved model {known.trained_agent!r} to continue from (-i takes a .zip file)")
    return [*defaults, *argv]


def check_model_arguments(argv: Sequence[str]) -> tuple[list[str], argparse.Namespace]:
    """Check the input of a command line that loads a trained model (enjoy, record_video).

    Defaults: ``--algo mappoc``, ``--env sb3_detc/LinearETC-v0``, ``-f logs`` (the training
    log folder; rl-zoo3's default would download models from the Hugging Face hub).

    :param argv: rl-zoo3 ``enjoy``/``record_video`` arguments
    :return: the arguments to hand over to rl-zoo3 and the checked ``algo``, ``env``, ``folder``
    :raises InputError: on an unknown algorithm or environment, or (without ``--exp-id``) if
        the folder has no run of the algorithm on the environment
    """
    known = _known_arguments(
        argv, (("--algo",), "mappoc"), (("--env",), "sb3_detc/LinearETC-v0"), (("-f", "--folder"), "logs")
    )
    check_algorithm(known.algo)
    check_env(known.env)
    env_name = EnvironmentName(known.env)
    if get_latest_run_id(os.path.join(known.folder, known.algo), env_name) == 0 and "--exp-id" not in argv:
        raise InputError(
            f"no trained {known.algo} model for {known.env} in {known.folder!r}: "
            f"train one with python -m sb3_detc.train --algo {known.algo} --env {known.env}"
        )
    return ["--algo", known.algo, "--env", known.env, "-f", known.folder, *argv], known


def render_modes(env_id: str) -> list[str]:
    """Render modes of a registered environment (builds it once).

    :param env_id: the environment id
    :return: its ``metadata["render_modes"]``
    """
    env = gym.make(env_id)
    try:
        return list(env.metadata.get("render_modes", []))
    finally:
        env.close()


# ----------------------------------------------------------------------------- command lines
#: Errors that bad input raises inside rl-zoo3 (reported as one line, like :class:`InputError`).
INPUT_ERRORS = (InputError, ValueError, TypeError, KeyError, FileNotFoundError, ImportError, AssertionError)


@contextmanager
def _argv(argv: Sequence[str]) -> Iterator[None]:
    saved = sys.argv
    sys.argv = [saved[0] if saved else "sb3_detc", *argv]
    try:
        yield
    finally:
        sys.argv = saved


def run_cli(prog: str, main: Callable[[], None], argv: Sequence[str] | None = None) -> None:
    """Run an rl-zoo3 command line with ``argv`` as ``sys.argv``; bad input ends it with one line.

    :param prog: name of the command in error messages (e.g. ``python -m sb3_detc.train``)
    :param main: the command; it reads ``sys.argv`` and may raise :class:`InputError`
    :param argv: the arguments (default: ``sys.argv[1:]``)
    :raises SystemExit: with code 2 after printing ``<prog>: error: <what is wrong>`` on stderr
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        with _argv(argv):
            main()
    except INPUT_ERRORS as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        text = " ".join(str(message).split()) or type(error).__name__
        if not isinstance(error, (InputError, ValueError, AssertionError)):
            text = f"{type(error).__name__}: {text}"
        print(f"{prog}: error: {text}", file=sys.stderr)
        raise SystemExit(2) from None
