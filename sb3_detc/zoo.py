"""rl-baselines3-zoo integration: algorithm names, hyperparameter files, run logs and input checks.

:func:`register` adds sb3-detc's algorithms to rl-zoo3 (``rl_zoo3.utils.ALGOS``) together with
Optuna samplers for ``--optimize``; the command lines (:func:`run_cli`) and :class:`ExperimentManager`
call it, importing this module does not:

* ``mappoc``: :class:`~sb3_detc.MAPPOC`, hyperparameters in ``hyperparams/mappoc.yml``;
* ``ppo_random_skip``: the paper's random-skip baseline, also :class:`~sb3_detc.MAPPOC`
  but trained with :class:`~sb3_detc.callbacks.RandomSkipCallback`
  (``hyperparams/ppo_random_skip.yml``); its runs are logged under its own name.

The command lines :mod:`sb3_detc.train`, :mod:`sb3_detc.enjoy` and
:mod:`sb3_detc.record_video` check their input here (:func:`check_train_arguments`,
:func:`check_model_arguments`), then hand over to rl-zoo3; :func:`run_cli` reports bad
input (:class:`InputError`) as one line and lets any later error end the command with its
traceback. Every run also writes the SB3 logger's values to ``progress.csv`` in its log
folder (:class:`ExperimentManager`), which :mod:`sb3_detc.plot` reads.
"""

from __future__ import annotations

import argparse
import difflib
import functools
import importlib
import inspect
import io
import os
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, redirect_stdout
from pathlib import Path
from typing import Any

import gymnasium as gym
import optuna
import rl_zoo3.exp_manager
import rl_zoo3.utils
import yaml
from huggingface_sb3 import EnvironmentName
from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from rl_zoo3.utils import ALGOS, get_class_by_name, get_latest_run_id, get_model_path
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import CSVOutputFormat
from stable_baselines3.common.vec_env import SubprocVecEnv, VecEnv

from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.checks import check_hyperparameters, check_observation_normalization
from sb3_detc.mappoc.critics import CRITICS

__all__ = [
    "ALGORITHMS",
    "HYPERPARAMS_DIR",
    "CSVLogCallback",
    "ExperimentManager",
    "InputError",
    "algorithm_class",
    "check_hyperparams_file",
    "check_model_arguments",
    "check_train_arguments",
    "convert_mappoc_params",
    "import_gym_packages",
    "register",
    "run_cli",
    "uses_rollout_workers",
    "sample_mappoc_params",
]

#: rl-zoo3 algorithm names of sb3-detc and their classes.
ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"mappoc": MAPPOC, "ppo_random_skip": MAPPOC}

#: Folder of the hyperparameter files shipped with the package, one per algorithm name.
HYPERPARAMS_DIR = Path(__file__).parent / "hyperparams"

#: Import path of the rollout-worker env wrapper (an entry naming it as ``env_wrapper`` runs in worker processes).
ROLLOUT_WORKER = "sb3_detc.mappoc.workers.RolloutWorker"

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
        "clip_range_broadcast": trial.suggest_categorical("clip_range_broadcast", [0.1, 0.2, 0.3]),
        "broadcast_ent_coef": trial.suggest_float("broadcast_ent_coef", 1e-4, 1.0, log=True),
        "max_grad_norm": trial.suggest_categorical("max_grad_norm", [0.5, 1.0, 5.0]),
        "reward_scale": trial.suggest_float("reward_scale", 1e-3, 1.0, log=True),
        "team_reward": trial.suggest_categorical("team_reward", [False, True]),
        "normalize_broadcast_advantage": trial.suggest_categorical("normalize_broadcast_advantage", [False, True]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCHS)),
        # the random-skip baseline replaces mu's options: no critic that needs the probabilities they were drawn with
        "critic": trial.suggest_categorical(
            "critic", [name for name, critic in CRITICS.items() if not critic.needs_draw_probabilities]
        ),
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
    """Add sb3-detc's algorithms and their Optuna samplers to rl-zoo3 (idempotent)."""
    ALGOS.update(ALGORITHMS)
    for name in ALGORITHMS:
        HYPERPARAMS_SAMPLER[name] = sample_mappoc_params
        HYPERPARAMS_CONVERTER[name] = convert_mappoc_params


def algorithm_class(algo: str) -> type[BaseAlgorithm]:
    """The class of an algorithm name: sb3-detc's (registered or not) or rl-zoo3's.

    :param algo: the algorithm name
    :return: its class
    :raises InputError: for a name that neither knows
    """
    check_algorithm(algo)
    return ALGORITHMS.get(algo) or ALGOS[algo]


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


def uses_rollout_workers(entry: dict[str, Any]) -> bool:
    """Whether a hyperparameter entry names :data:`ROLLOUT_WORKER` among its ``env_wrapper``.

    :param entry: the entry (``env_wrapper``: one name, a ``{name: arguments}`` mapping or a list of those)
    :return: True if its envs are rollout workers
    """
    wrappers = entry.get("env_wrapper") or []
    wrappers = wrappers if isinstance(wrappers, list) else [wrappers]
    return ROLLOUT_WORKER in [w if isinstance(w, str) else next(iter(w)) for w in wrappers]


class ExperimentManager(rl_zoo3.exp_manager.ExperimentManager):
    """rl-zoo3's experiment manager that writes ``progress.csv`` and continues step counts.

    Every run's log folder gets the logger's ``progress.csv``. rl-zoo3 restarts the step count
    of a model loaded to continue training (``-i``) at zero, which would restart the
    curriculum, the schedules and the checkpoint numbering; here ``-n`` steps are added to
    where the saved model stopped. Registers sb3-detc's algorithms (:func:`register`).

    :param args: rl-zoo3's arguments, then its experiment manager's (see ``rl_zoo3.exp_manager``)
    :param kwargs: as rl-zoo3's experiment manager takes them
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        register()
        super().__init__(*args, **kwargs)
        #: the vector env class of the evaluation envs (``--vec-env``), once training envs got another
        self.eval_vec_env_class: type[VecEnv] | None = None

    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> Any:
        """rl-zoo3's preprocessing; an entry with rollout-worker envs (:data:`ROLLOUT_WORKER`) gets worker processes.

        Rollout workers pay off only in their own processes (``SubprocVecEnv``), so an entry
        that names them as ``env_wrapper`` trains in them whatever ``--vec-env`` says; its
        evaluation envs, which step one at a time with the learner's policy, stay as
        ``--vec-env`` says (default: in the learner's process, without a message per step).

        :param hyperparams: the entry, as read from the file and the command line
        :return: what rl-zoo3's preprocessing returns
        """
        if uses_rollout_workers(hyperparams):
            self.eval_vec_env_class = self.vec_env_class
            self.vec_env_class = SubprocVecEnv
        return super()._preprocess_hyperparams(hyperparams)

    def create_envs(self, n_envs: int, eval_env: bool = False, no_log: bool = False) -> VecEnv:
        """rl-zoo3's envs; evaluation envs of the class in :attr:`eval_vec_env_class` where it is set.

        :param n_envs: number of envs
        :param eval_env: whether the envs are for evaluation
        :param no_log: whether to write no monitor files
        :return: the vector env
        """
        training = self.vec_env_class
        if eval_env and self.eval_vec_env_class is not None:
            self.vec_env_class = self.eval_vec_env_class
        try:
            return super().create_envs(n_envs, eval_env, no_log)
        finally:
            self.vec_env_class = training

    def create_callbacks(self) -> None:
        """rl-zoo3's callbacks (progress bar, checkpoints, evaluation) and a :class:`CSVLogCallback`."""
        super().create_callbacks()
        self.callbacks.append(CSVLogCallback(self.save_path))

    def learn(self, model: BaseAlgorithm) -> None:
        """Train ``model`` as rl-zoo3 does, continuing its step count if it was loaded to continue.

        Training envs of rollout workers and evaluation envs of ``--vec-env`` differ in class by
        design: SB3's evaluation callback's warning about it is left out.

        :param model: the model to train
        """
        with warnings.catch_warnings():
            if self.eval_vec_env_class is not None:
                warnings.filterwarnings("ignore", "Training and eval env are not of the same type", UserWarning)
            self._learn(model)

    def _learn(self, model: BaseAlgorithm) -> None:
        """rl-zoo3's ``learn``; a model loaded to continue (``-i``) learns with ``reset_num_timesteps=False``.

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
    """A hint at the closest of ``choices`` to a misspelt ``word``, for messages.

    :param word: the unknown name
    :param choices: the known names
    :return: ``" (did you mean '<choice>'?)"`` to append to the message, or ``""`` if no choice is close
    """
    match = difflib.get_close_matches(word, list(choices), n=1)
    return f" (did you mean {match[0]!r}?)" if match else ""


def check_algorithm(algo: str) -> None:
    """Raise :class:`InputError` unless ``algo`` is one of sb3-detc's or rl-zoo3's algorithm names.

    :param algo: the algorithm name
    """
    known = [*ALGORITHMS, *(name for name in ALGOS if name not in ALGORITHMS)]
    if algo not in known:
        raise InputError(f"unknown algorithm {algo!r}{_closest(algo, known)}; known: {', '.join(known)}")


def check_env(env_id: str) -> None:
    """Raise :class:`InputError` unless ``env_id`` is a registered Gymnasium id.

    :param env_id: the environment id
    """
    if env_id not in gym.registry:
        ours = [name for name in gym.registry if name.startswith("sb3_detc/")]
        raise InputError(
            f"unknown environment {env_id!r}{_closest(env_id, list(gym.registry))}; sb3-detc's: {', '.join(ours)} "
            "(ids of other packages: name the package that registers them with --gym-packages)"
        )


def import_gym_packages(modules: Sequence[str]) -> None:
    """Import the modules named with ``--gym-packages`` (as rl-zoo3 does), so that the ids they register are known.

    :param modules: module names, e.g. ``["myteam"]``
    :raises InputError: if one of them cannot be imported
    """
    for module in modules:
        try:
            importlib.import_module(module)
        except ImportError as error:
            raise InputError(f"--gym-packages: cannot import {module!r} ({error})") from None


def _evaluated(option: str, items: Sequence[str]) -> dict[str, Any]:
    """``key:value`` arguments (``-params``, ``--env-kwargs``) evaluated as rl-zoo3's ``StoreDict`` does.

    :param option: the option, for messages
    :param items: its ``key:value`` arguments
    :return: key -> evaluated value
    :raises InputError: if a value is not a Python expression
    """
    values = {}
    for item in items:
        key, _, text = item.partition(":")
        try:
            values[key] = eval(text, dict(vars(rl_zoo3.utils)))
        except Exception as error:  # any error of evaluating the user's expression
            raise InputError(f"{option} {item!r}: expected key:value with a Python value ({_what(error)})") from None
    return values


def _what(error: BaseException) -> str:
    """An exception as one line, for messages: ``<type>: <message>``.

    :param error: the exception
    """
    return f"{type(error).__name__}: {' '.join(str(error).split())}"


def _check_classes(entry: Any, where: str, kind: str, build: bool) -> None:
    """Check the classes of a ``callback``, ``env_wrapper`` or ``vec_env_wrapper`` entry (one or a list).

    :param entry: a name (``module.Class``), a ``{name: arguments}`` mapping or a list of those
    :param where: file and entry, for messages
    :param kind: what the classes are, for messages
    :param build: build every class with its arguments (callbacks need nothing else)
    """
    names = entry if isinstance(entry, list) else [entry]
    for item in names:
        if isinstance(item, dict):
            if len(item) != 1:
                raise InputError(f"{where}: a {kind} with arguments is one 'name: {{arguments}}' item, got {item}")
            ((name, kwargs),) = item.items()
        else:
            name, kwargs = item, {}
        if not isinstance(name, str) or "." not in name:
            raise InputError(f"{where}: a {kind} is named by its import path (module.Class), got {name!r}")
        try:
            cls = get_class_by_name(name)
        except (ImportError, AttributeError) as error:
            raise InputError(f"{where}: unknown {kind} {name!r} ({error})") from None
        if not isinstance(kwargs, dict):
            raise InputError(f"{where}: the arguments of {kind} {name!r} must be a mapping, got {kwargs!r}")
        if build:
            try:
                cls(**kwargs)
            except (TypeError, ValueError) as error:
                raise InputError(f"{where}: {kind} {name!r}: {error}") from None


def _read_hyperparams(conf: str | os.PathLike) -> dict[Any, Any]:
    """The content of an rl-zoo3 ``-conf``: a YAML file, a Python file or an importable module defining ``hyperparams``.

    :param conf: the file or module name
    :return: environment id -> hyperparameters
    :raises InputError: if there is no such file or module, or it is not a mapping
    """
    name, path = str(conf), Path(conf)
    if name.endswith((".yml", ".yaml")):
        if not path.is_file():
            raise InputError(f"hyperparameter file {name!r} not found")
        try:
            content = yaml.safe_load(path.read_text())
        except yaml.YAMLError as error:
            mark = getattr(error, "problem_mark", None)
            at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
            problem = getattr(error, "problem", None) or type(error).__name__
            raise InputError(f"{path}: not valid YAML{at}: {problem}") from None
    elif name.endswith(".py"):
        if not path.is_file():
            raise InputError(f"hyperparameter file {name!r} not found")
        namespace: dict[str, Any] = {}
        exec(path.read_text(), namespace)  # as rl-zoo3 reads a Python file
        content = namespace.get("hyperparams")
    else:
        try:
            content = getattr(importlib.import_module(name), "hyperparams", None)
        except ImportError as error:
            raise InputError(f"-conf {name!r} is no .yml or .py file and no module to import ({error})") from None
    if not isinstance(content, dict):
        raise InputError(f"{name}: expected a mapping of environment ids to hyperparameters")
    return content


def _policy_class(policy: Any, algo: str, where: str) -> type:
    """The policy class an entry names: an alias of the algorithm, an import path or a class (Python files).

    :param policy: the entry's ``policy``
    :param algo: the rl-zoo3 algorithm name, whose ``policy_aliases`` give the aliases
    :param where: file and entry, for messages
    :return: the policy class
    :raises InputError: if ``policy`` is not a name, or names no known alias or importable class
    """
    if isinstance(policy, type):
        return policy
    if not isinstance(policy, str):
        raise InputError(f"{where}: policy must be a name, got {policy!r}")
    if "." in policy:  # rl-zoo3 imports custom policies
        try:
            return get_class_by_name(policy)
        except (ImportError, AttributeError) as error:
            raise InputError(f"{where}: unknown policy {policy!r} ({error})") from None
    aliases = getattr(algorithm_class(algo), "policy_aliases", {})
    if policy not in aliases:
        known = ", ".join(aliases)
        raise InputError(f"{where}: unknown policy {policy!r}{_closest(policy, list(aliases))}; known: {known}")
    return aliases[policy]


def _python_value(value: Any, key: str, where: str) -> Any:
    """A value rl-zoo3 evaluates as Python if it is a string (``policy_kwargs``, ``normalize``).

    :param value: the entry's value
    :param key: its key, for messages
    :param where: file and entry, for messages
    :return: the evaluated value, or ``value`` itself if it is not a string
    :raises InputError: if the string is not a Python expression
    """
    if not isinstance(value, str):
        return value
    try:
        return eval(value, dict(vars(rl_zoo3.exp_manager)))
    except Exception as error:  # any error of evaluating the user's expression
        raise InputError(f"{where}: {key} {value!r} is not a Python expression ({_what(error)})") from None


def _check_values(entry: dict[str, Any], algo: str, where: str) -> None:
    """Check the values of an entry that rl-zoo3 or the algorithm would refuse only while building the run.

    :param entry: the entry (the file's, with the command line's ``-params``)
    :param algo: the rl-zoo3 algorithm name
    :param where: file and entry, for messages
    """
    steps = entry["n_timesteps"]
    if isinstance(steps, bool) or not isinstance(steps, int | float) or steps < 0:
        hint = " (YAML reads 1e6 as text: write 1000000 or !!float 1e6)" if isinstance(steps, str) else ""
        raise InputError(f"{where}: n_timesteps must be a number >= 0, got {steps!r}{hint}")
    n_envs = entry.get("n_envs", 1)
    if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
        raise InputError(f"{where}: n_envs must be a positive integer, got {n_envs!r}")
    for key in ("learning_rate", "clip_range", "clip_range_vf", "delta_std"):  # rl-zoo3's schedules
        if key in entry and not _is_schedule(entry[key]):
            needs = "a number or a linear schedule 'lin_<initial value>'"
            raise InputError(f"{where}: {key} must be {needs}, got {entry[key]!r}")
    policy_class = _policy_class(entry["policy"], algo, where)
    policy_kwargs = _python_value(entry.get("policy_kwargs"), "policy_kwargs", where)
    if policy_kwargs is not None:
        if not isinstance(policy_kwargs, dict):
            raise InputError(f"{where}: policy_kwargs must be a mapping, got {policy_kwargs!r}")
        parameters = inspect.signature(policy_class.__init__).parameters
        if all(p.kind != p.VAR_KEYWORD for p in parameters.values()):
            allowed = set(parameters) - {"self", "observation_space", "action_space", "lr_schedule"}
            for key in policy_kwargs:
                if key not in allowed:
                    raise InputError(
                        f"{where}: unknown policy_kwargs key {key!r}{_closest(str(key), sorted(allowed))} "
                        f"of {policy_class.__name__}"
                    )
    for key in ("env_wrapper", "vec_env_wrapper"):
        if entry.get(key) is not None:
            _check_classes(entry[key], where, key.replace("_", " "), build=False)
    if "callback" in entry:
        _check_classes(entry["callback"], where, "callback", build=True)
    normalize = _python_value(entry.get("normalize", False), "normalize", where)
    algorithm = algorithm_class(algo)
    if issubclass(algorithm, MAPPOC):
        defaults = {name: p.default for name, p in inspect.signature(algorithm.__init__).parameters.items()}
        try:
            values = {**defaults, **entry}
            for key in ("learning_rate", "clip_range"):  # a schedule 'lin_<initial value>': check its start
                if isinstance(values[key], str):
                    values[key] = float(values[key].split("_")[1])
            check_hyperparameters(**values)
            if normalize:  # rl-zoo3 wraps the envs in VecNormalize(**normalize) or VecNormalize()
                kwargs = normalize if isinstance(normalize, dict) else {}
                check_observation_normalization(kwargs.get("norm_obs", True), kwargs.get("norm_obs_keys"))
        except ValueError as error:
            raise InputError(f"{where}: {error}") from None


def _is_schedule(value: Any) -> bool:
    """Whether rl-zoo3 turns ``value`` into a schedule: a number or ``"<name>_<initial value>"``.

    :param value: an entry's ``learning_rate``, ``clip_range``, ``clip_range_vf`` or ``delta_std``
    """
    if isinstance(value, int | float):
        return True
    if not isinstance(value, str) or value.count("_") != 1:
        return False
    try:
        float(value.split("_")[1])
    except ValueError:
        return False
    return True


def check_hyperparams_file(
    path: str | os.PathLike, algo: str, env_id: str, overrides: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Check the entry of ``env_id`` in an rl-zoo3 hyperparameter file (``-conf``) for algorithm ``algo``.

    Checks that the file exists and is YAML (or a Python file or module defining
    ``hyperparams``, as rl-zoo3 reads them), that it has an entry for ``env_id`` (or
    ``default``), that every key is an argument of the algorithm or one rl-zoo3 consumes,
    that ``n_timesteps`` and ``policy`` are there, and the values that would otherwise
    fail only while the run is built: ``n_timesteps``, ``n_envs``, schedules, the policy
    name and its ``policy_kwargs`` keys, the wrapper and callback classes (every callback is
    built with its arguments) and, for sb3-detc's algorithms, the value ranges of MAPPOC
    and ``normalize`` (no ``VecNormalize`` of the network's observations).

    :param path: the hyperparameter file (``.yml``, ``.py``) or module name
    :param algo: the rl-zoo3 algorithm name
    :param env_id: the environment id
    :param overrides: values that replace the entry's (the command line's ``-params``)
    :return: the entry, with the overrides
    :raises InputError: on the first problem found, with the file and key in the message
    """
    content = _read_hyperparams(path)
    entry = content.get(env_id, content.get("default"))
    if entry is None:
        raise InputError(f"{path}: no entry for {env_id!r} (entries: {', '.join(map(str, content))})")
    where = f"{path} [{env_id}]"
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected a mapping of hyperparameters, got {entry!r}")
    entry = {**entry, **(overrides or {})}
    arguments = set(inspect.signature(algorithm_class(algo).__init__).parameters) - COMMAND_LINE_KEYS
    allowed = arguments | ZOO_KEYS
    for key in entry:
        if key not in allowed:
            raise InputError(f"{where}: unknown hyperparameter {key!r}{_closest(str(key), sorted(allowed))}")
    for key in ("n_timesteps", "policy"):
        if key not in entry:
            raise InputError(f"{where}: missing hyperparameter {key!r}")
    _check_values(entry, algo, where)
    return entry


def _known_arguments(argv: Sequence[str], *arguments: tuple[tuple[str, ...], Any]) -> argparse.Namespace:
    """The arguments among ``argv`` that the checks need; the rest is left to rl-zoo3's parser.

    :param argv: the command line
    :param arguments: ``(flags, default)`` of every argument; a list default takes one or more
        values, a bool default makes a switch
    :return: the parsed arguments
    :raises InputError: if one of them is malformed (e.g. has no value)
    """
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    for flags, default in arguments:
        if isinstance(default, bool):
            parser.add_argument(*flags, default=default, action="store_true")
        else:
            parser.add_argument(*flags, default=default, nargs="+" if isinstance(default, list) else None)
    try:
        known, _ = parser.parse_known_args(argv)
    except argparse.ArgumentError as error:
        raise InputError(str(error)) from None
    return known


def _integer(text: str | None) -> int | None:
    """A command-line value as an integer, for ``--exp-id`` and ``--load-checkpoint``.

    :param text: the value as given (None: the option is absent)
    :return: the integer, or None if ``text`` is None or no integer
    """
    try:
        return None if text is None else int(text)
    except ValueError:
        return None


def check_train_arguments(argv: Sequence[str]) -> list[str]:
    """Check the input of a training command line and complete it with sb3-detc's defaults.

    Defaults: ``--algo mappoc``, ``--env sb3_detc/LinearETC-v0`` and, for sb3-detc's
    algorithms, ``-conf`` the package's ``hyperparams/<algo>.yml`` and ``--n-eval-envs`` as
    many as ``--eval-episodes`` (rl-zoo3's default 5), so that the periodic evaluation runs its
    episodes side by side, with one batched policy call per step (rl-zoo3's default, one env,
    takes about twice as long on Multiwalker). The modules of ``--gym-packages`` are imported
    first, so that the ids they register are known.

    :param argv: rl-zoo3 training arguments (``rl_zoo3.train``'s command line)
    :return: the arguments to hand over to rl-zoo3
    :raises InputError: on a module of ``--gym-packages`` that cannot be imported, an
        unknown algorithm or environment, a bad hyperparameter file or ``-params`` value
        (:func:`check_hyperparams_file`), a malformed ``--env-kwargs`` or a missing model to
        continue from
    """
    known = _known_arguments(
        argv,
        (("--algo",), "mappoc"),
        (("--env",), "sb3_detc/LinearETC-v0"),
        (("-conf", "--conf-file"), None),
        (("-i", "--trained-agent"), ""),
        (("--gym-packages",), []),
        (("-params", "--hyperparams"), []),
        (("--env-kwargs",), []),
        (("--eval-env-kwargs",), []),
        (("--eval-episodes",), "5"),
        (("--n-eval-envs",), None),
    )
    import_gym_packages(known.gym_packages)
    check_algorithm(known.algo)
    check_env(known.env)
    overrides = _evaluated("-params", known.hyperparams)
    _evaluated("--env-kwargs", known.env_kwargs)
    _evaluated("--eval-env-kwargs", known.eval_env_kwargs)
    defaults = ["--algo", known.algo, "--env", known.env]
    conf = known.conf_file
    if conf is None and known.algo in ALGORITHMS:
        conf = str(HYPERPARAMS_DIR / f"{known.algo}.yml")
        defaults += ["-conf", conf]
    if known.n_eval_envs is None and known.algo in ALGORITHMS:
        defaults += ["--n-eval-envs", known.eval_episodes]
    if conf is not None:
        check_hyperparams_file(conf, known.algo, known.env, overrides)
    if known.trained_agent and not (known.trained_agent.endswith(".zip") and os.path.isfile(known.trained_agent)):
        raise InputError(f"no saved model {known.trained_agent!r} to continue from (-i takes a .zip file)")
    return [*defaults, *argv]


def check_model_arguments(argv: Sequence[str]) -> tuple[list[str], argparse.Namespace]:
    """Check the input of a command line that loads a trained model (enjoy, record_video).

    Defaults: ``--algo mappoc``, ``--env sb3_detc/LinearETC-v0``, ``-f logs`` (the training
    log folder; rl-zoo3's default would download models from the Hugging Face hub). The
    modules of ``--gym-packages`` are imported here and the option is left out of the
    returned arguments (rl-zoo3's ``record_video`` has no such option; the command lines
    run rl-zoo3 in this process, where the ids are registered now).

    :param argv: rl-zoo3 ``enjoy``/``record_video`` arguments
    :return: the arguments to hand over to rl-zoo3 and the checked ``algo``, ``env``, ``folder``
    :raises InputError: on a module of ``--gym-packages`` that cannot be imported, an
        unknown algorithm or environment, a malformed ``--env-kwargs``, or if the folder has
        no model to load (the latest run, or the one of ``--exp-id``, ``--load-best``,
        ``--load-checkpoint``, ``--load-last-checkpoint``)
    """
    known = _known_arguments(
        argv,
        (("--algo",), "mappoc"),
        (("--env",), "sb3_detc/LinearETC-v0"),
        (("-f", "--folder"), "logs"),
        (("--exp-id",), "0"),
        (("--load-best",), False),
        (("--load-checkpoint",), None),
        (("--load-last-checkpoint",), False),
        (("--gym-packages",), []),
        (("--env-kwargs",), []),
    )
    import_gym_packages(known.gym_packages)
    check_algorithm(known.algo)
    check_env(known.env)
    _evaluated("--env-kwargs", known.env_kwargs)
    env_name = EnvironmentName(known.env)
    exp_id, checkpoint = _integer(known.exp_id), _integer(known.load_checkpoint)
    if exp_id == 0 and get_latest_run_id(os.path.join(known.folder, known.algo), env_name) == 0:
        raise InputError(
            f"no trained {known.algo} model for {known.env} in {known.folder!r}: "
            f"train one with python -m sb3_detc.train --algo {known.algo} --env {known.env}"
        )
    if exp_id is not None and (known.load_checkpoint is None or checkpoint is not None):  # else rl-zoo3's parser fails
        try:
            with redirect_stdout(io.StringIO()):  # it prints which run it picks
                get_model_path(
                    exp_id, known.folder, known.algo, env_name, known.load_best, checkpoint, known.load_last_checkpoint
                )
        except (AssertionError, ValueError) as error:  # rl-zoo3's way to say that a folder or file is missing
            raise InputError(" ".join(str(error).split())) from None
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--gym-packages", nargs="+", default=[])
    _, rest = parser.parse_known_args(argv)
    return ["--algo", known.algo, "--env", known.env, "-f", known.folder, *rest], known


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
@contextmanager
def _argv(argv: Sequence[str]) -> Iterator[None]:
    """Make ``argv`` the arguments of ``sys.argv`` (after the program name) within the block, then restore it.

    :param argv: the arguments, without the program name
    """
    saved = sys.argv
    sys.argv = [saved[0] if saved else "sb3_detc", *argv]
    try:
        yield
    finally:
        sys.argv = saved


def run_cli(prog: str, main: Callable[[], None], argv: Sequence[str] | None = None) -> None:
    """Run a command line with ``argv`` as ``sys.argv`` after :func:`register`; bad input ends it with one line.

    Bad input is what the checks before the run find (:class:`InputError`: an unknown
    algorithm or environment, a malformed hyperparameter file, a missing model, a bad
    argument). It is reported as ``<prog>: error: <what is wrong>`` on stderr with exit
    code 2, like argparse's errors (which end the command as usual). Any other exception,
    e.g. one raised while training, is not caught: it ends the command with its traceback.

    :param prog: name of the command in error messages (e.g. ``python -m sb3_detc.train``)
    :param main: the command; it reads ``sys.argv`` and may raise :class:`InputError`
    :param argv: the arguments (default: ``sys.argv[1:]``)
    :raises SystemExit: with code 2 after printing the message of an :class:`InputError` on stderr
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    register()
    try:
        with _argv(argv):
            main()
    except InputError as error:
        text = " ".join(str(error).split()) or type(error).__name__
        print(f"{prog}: error: {text}", file=sys.stderr)
        raise SystemExit(2) from None
