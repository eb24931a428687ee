"""Command-line input of sb3-detc: checks before rl-zoo3 runs, and :func:`run_cli`, which reports bad input.

The command lines :mod:`sb3_detc.train`, :mod:`sb3_detc.enjoy` and
:mod:`sb3_detc.record_video` check their input here (:func:`check_train_arguments`,
:func:`check_model_arguments`), then hand over to rl-zoo3; hyperparameter files are checked
with :func:`check_hyperparams_file`. :func:`run_cli` runs a command line after
:func:`~sb3_detc.zoo.register`: it reports bad input (:class:`InputError`) as one line and
lets any later error end the command with its traceback.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import inspect
import io
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, redirect_stdout
from pathlib import Path
from typing import Any

import gymnasium as gym
import rl_zoo3.exp_manager
import rl_zoo3.utils
import yaml
from huggingface_sb3 import EnvironmentName
from rl_zoo3.utils import ALGOS, get_class_by_name, get_latest_run_id, get_model_path
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.checks import (
    check_hyperparameters,
    check_observation_normalization,
    check_price_rule,
    check_rate_target,
)
from sb3_detc.mappoc.critics import CRITICS
from sb3_detc.mappoc.mappoc import PAPER_ITERATION
from sb3_detc.validation import is_integer
from sb3_detc.zoo import ALGORITHMS, HYPERPARAMS_DIR, register

__all__ = [
    "ZOO_KEYS",
    "InputError",
    "algorithm_arguments",
    "algorithm_class",
    "check_algorithm",
    "check_env",
    "check_hyperparams_file",
    "check_model_arguments",
    "check_train_arguments",
    "import_gym_packages",
    "python_value",
    "render_modes",
    "run_cli",
]

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


class InputError(Exception):
    """Bad command-line input: reported as one line on stderr with a non-zero exit code."""


# ----------------------------------------------------------------------------- input checks
def algorithm_class(algo: str) -> type[BaseAlgorithm]:
    """The class of an algorithm name: sb3-detc's (registered or not) or rl-zoo3's.

    :param algo: the algorithm name
    :return: its class
    :raises InputError: for a name that neither knows
    """
    check_algorithm(algo)
    return ALGORITHMS.get(algo) or ALGOS[algo]


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


def python_value(value: Any, key: str, where: str) -> Any:
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


def algorithm_arguments(entry: dict[str, Any], where: str) -> dict[str, Any]:
    """What an entry gives the algorithm's constructor, as rl-zoo3 passes it: every key rl-zoo3 does not consume.

    :param entry: the entry (e.g. from :func:`check_hyperparams_file`)
    :param where: file and entry, for messages
    :return: the entry without :data:`ZOO_KEYS` and ``policy``, ``policy_kwargs`` evaluated (:func:`python_value`)
    :raises InputError: if ``policy_kwargs`` is a string that is not a Python expression
    """
    arguments = {key: value for key, value in entry.items() if key not in ZOO_KEYS | {"policy"}}
    if "policy_kwargs" in arguments:
        arguments["policy_kwargs"] = python_value(arguments["policy_kwargs"], "policy_kwargs", where) or {}
    return arguments


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
    if not is_integer(n_envs, 1):
        raise InputError(f"{where}: n_envs must be a positive integer, got {n_envs!r}")
    for key in ("learning_rate", "clip_range", "clip_range_vf", "delta_std"):  # rl-zoo3's schedules
        if key in entry and not _is_schedule(entry[key]):
            needs = "a number or a linear schedule 'lin_<initial value>'"
            raise InputError(f"{where}: {key} must be {needs}, got {entry[key]!r}")
    policy_class = _policy_class(entry["policy"], algo, where)
    policy_kwargs = python_value(entry.get("policy_kwargs"), "policy_kwargs", where)
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
    normalize = python_value(entry.get("normalize", False), "normalize", where)
    algorithm = algorithm_class(algo)
    if issubclass(algorithm, MAPPOC):
        defaults = {name: p.default for name, p in inspect.signature(algorithm.__init__).parameters.items()}
        try:
            values = {**defaults, **entry}
            if values["n_steps"] is None:  # MAPPOC's default: the paper's iteration divided over the envs
                values["n_steps"] = PAPER_ITERATION
            for key in ("learning_rate", "clip_range"):  # a schedule 'lin_<initial value>': check its start
                if isinstance(values[key], str):
                    values[key] = float(values[key].split("_")[1])
            check_hyperparameters(**values)
            check_rate_target(values["target_savings"], values["fixed_trigger"], values["broadcast_price_rule"])
            parameter = inspect.signature(policy_class).parameters.get("critic")  # None: a policy without one
            critic = (policy_kwargs or {}).get("critic", None if parameter is None else parameter.default)
            if critic in CRITICS:  # an unknown critic is the policy's to refuse
                check_price_rule(values["broadcast_price_rule"], values["target_savings"], CRITICS[critic])
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
