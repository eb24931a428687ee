"""Study files: which algorithms (hyperparameter entries), which seeds, what budget, how to evaluate.

A study file is YAML::

    env: sb3_detc/MultiwalkerETC-v0      # registered environment id
    seeds: [0, 1, 2, 3, 4]               # default seeds of every algorithm
    n_timesteps: 6144000                 # optional: training budget (default: each entry's own)
    checkpoint_interval: 204800          # optional: environment steps between checkpoints (default: 100000)
    evaluation:                          # optional
      episodes: 50                       # seeded episodes per mode (the same for every trial)
      seed: 10000                        # seed of the first episode (episode k: seed + k)
      fixed_families: [periodic, send_on_delta_max_age]  # optional: fixed triggers at the learned rate
    algorithms:                          # label -> trial settings
      mappoc_paper:
        algo: mappoc                     # rl-zoo3 algorithm name
      control_first:
        algo: mappoc
        seeds: [0, 1, 2]                 # optional: this algorithm's own seeds
        cpus: 2                          # optional: cores per trial (default: see below)
        conf: my_hyperparams.yml         # optional: another hyperparameter file (relative to the study file)
        hyperparams:                     # optional: overrides of the entry, as rl-zoo3's --hyperparams
          broadcast_ent_coef: 0.03
        selection:                       # optional: keep the policy best on validation episodes, not the last
          every: 102400                  # environment steps between two validations
          episodes: 20                   # optional: validation episodes (default 20)
          seed: 20000                    # optional: the first one's seed (default: after the evaluation's)
          tolerance: 0.01                # optional: how far below the rate target a kept policy may save

The entry of ``env`` is taken from the package's hyperparameter file of the algorithm
(``sb3_detc/hyperparams/<algo>.yml``) unless ``conf`` names another one. A trial uses as
many cores as its entry's rollout workers (``n_envs`` with
:class:`~sb3_detc.mappoc.workers.RolloutWorker` envs), otherwise one; its learner uses one torch
thread (:data:`~sb3_detc.study.trial.LEARNER_THREADS`): the workers wait while the learner
updates, and it waits while they collect. With ``selection`` a trial's final policy is the one
that did best on the validation episodes at the entry's rate target
(:class:`~sb3_detc.callbacks.SelectBestCallback`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from rl_zoo3.utils import get_callback_list

from sb3_detc.callbacks import FixedTriggerCallback
from sb3_detc.cli import InputError, check_algorithm, check_env, check_hyperparams_file
from sb3_detc.renamed import renamed_keys
from sb3_detc.triggers import TRIGGER_FAMILIES
from sb3_detc.validation import is_integer
from sb3_detc.zoo import ALGORITHMS, HYPERPARAMS_DIR, uses_rollout_workers

__all__ = [
    "CONF_FOLDER",
    "AlgorithmSpec",
    "Selection",
    "StudyError",
    "StudySpec",
    "Trial",
    "conf_copy",
    "entry_fixed_trigger",
    "load_folder_study",
    "load_study",
    "same_study",
]

#: Keys of a study file and of one algorithm's settings.
STUDY_KEYS = frozenset({"env", "seeds", "n_timesteps", "checkpoint_interval", "evaluation", "algorithms"})
ALGORITHM_KEYS = frozenset({"algo", "seeds", "cpus", "conf", "hyperparams", "selection"})
SELECTION_KEYS = frozenset({"every", "episodes", "seed", "tolerance"})

#: A study folder's copies of the hyperparameter files its study file names (``conf``), one per algorithm,
#: ``<label><suffix>``: the folder is read without the files the study was started from.
CONF_FOLDER = "conf"
#: What a study's ``conf`` may be: a YAML or Python hyperparameter file.
CONF_SUFFIXES = (".yml", ".yaml", ".py")
EVALUATION_KEYS = frozenset({"episodes", "seed", "fixed_families"})


class StudyError(InputError):
    """A malformed study file or study folder: reported as one line with exit code 2."""


@dataclass(frozen=True)
class Selection:
    """How a trial keeps the policy best on validation episodes (:class:`~sb3_detc.callbacks.SelectBestCallback`).

    :param every: environment steps between two validations
    :param episodes: validation episodes
    :param seed: the first validation episode's seed (episode k: seed + k); None: right after the
        study's evaluation episodes
    :param tolerance: how far below the rate target the savings of a kept policy may lie
    """

    every: int
    episodes: int = 20
    seed: int | None = None
    tolerance: float = 0.01


@dataclass(frozen=True)
class AlgorithmSpec:
    """One algorithm of a study: a hyperparameter entry, its overrides and its seeds.

    :param label: the name of the algorithm in the study (folder names, report rows)
    :param algo: rl-zoo3 algorithm name
    :param conf: the hyperparameter file
    :param hyperparams: overrides of the entry
    :param seeds: the seeds
    :param cpus: cores per trial
    :param entry: the entry of the study's env in ``conf``, with the overrides applied
    :param named_conf: whether the study file names ``conf`` (else it is sb3-detc's file of ``algo``)
    :param selection: how the trials keep the policy best on validation episodes (None: the last one)
    """

    label: str
    algo: str
    conf: Path
    hyperparams: dict[str, Any]
    seeds: tuple[int, ...]
    cpus: int
    entry: dict[str, Any]
    named_conf: bool = False
    selection: Selection | None = None


@dataclass(frozen=True)
class Trial:
    """One (algorithm, seed) run of a study.

    :param algorithm: the algorithm's settings
    :param seed: the seed
    """

    algorithm: AlgorithmSpec
    seed: int

    @property
    def name(self) -> str:
        """The trial's name, also its folder below ``trials/``: ``<label>/seed<seed>``."""
        return f"{self.algorithm.label}/seed{self.seed}"


@dataclass(frozen=True)
class StudySpec:
    """A parsed study file (see the module for the format).

    :param path: the study file
    :param text: its content (a study folder remembers it)
    :param env: environment id
    :param n_timesteps: training budget, or None for every entry's own ``n_timesteps``
    :param checkpoint_interval: environment steps between checkpoints
    :param episodes: evaluation episodes per mode
    :param eval_seed: seed of the first evaluation episode
    :param algorithms: the algorithms, in the file's order
    :param fixed_families: the fixed trigger families the evaluation compares at every trial's learned
        rate (names from :data:`~sb3_detc.triggers.TRIGGER_FAMILIES`;
        :func:`~sb3_detc.evaluation.evaluate_policy_modes`)
    """

    path: Path
    text: str
    env: str
    n_timesteps: int | None
    checkpoint_interval: int
    episodes: int
    eval_seed: int
    algorithms: tuple[AlgorithmSpec, ...] = field(default_factory=tuple)
    fixed_families: tuple[str, ...] = ()

    def trials(self) -> list[Trial]:
        """Every (algorithm, seed) trial: each algorithm's first seed (in the file's order), then the second ones, ...

        Run in this order, a study has comparable results of every algorithm early.

        :return: the trials, in this order
        """
        trials = [
            (k, a, Trial(algorithm, seed))
            for a, algorithm in enumerate(self.algorithms)
            for k, seed in enumerate(algorithm.seeds)
        ]
        return [trial for _, _, trial in sorted(trials, key=lambda item: item[:2])]

    def validation_seeds(self, episodes: int, seed: int | None = None) -> list[int]:
        """The seeds of validation episodes (a ``selection``'s), one per episode.

        :param episodes: how many
        :param seed: the first one's (None: right after the evaluation's episodes)
        :return: ``seed``, ``seed + 1``, ...
        """
        first = self.eval_seed + self.episodes if seed is None else seed
        return list(range(first, first + episodes))

    def budget(self, algorithm: AlgorithmSpec) -> int:
        """Training steps of one trial of ``algorithm``.

        :param algorithm: one of :attr:`algorithms`
        :return: the study's ``n_timesteps`` if it has one, else the ``n_timesteps`` of the algorithm's entry
        """
        return int(self.n_timesteps if self.n_timesteps is not None else algorithm.entry["n_timesteps"])


def entry_fixed_trigger(entry: dict[str, Any]) -> Any:
    """The trigger of a fixed-trigger callback in a hyperparameter entry (the random-skip baseline), else None.

    :param entry: a hyperparameter entry (its ``callback`` is read)
    :return: the trigger the entry trains with instead of the policy over options, or None
    """
    if "callback" not in entry:
        return None
    callbacks = get_callback_list({"callback": entry["callback"]})
    triggers = [c.trigger for c in callbacks if isinstance(c, FixedTriggerCallback)]
    return triggers[0] if triggers else None


def _fail(path: Path, message: str) -> StudyError:
    """The error of a malformed study file, for the caller to raise.

    :param path: the study file
    :param message: what is wrong
    :return: the error, its message prefixed with the file
    """
    return StudyError(f"{path}: {message}")


def _int(path: Path, where: str, value: Any, minimum: int) -> int:
    """A checked integer setting of a study file.

    :param path: the study file
    :param where: the setting, for the message (e.g. ``'n_timesteps'``)
    :param value: the parsed value (a float with an integer value, e.g. ``100000.0``, counts as an integer)
    :param minimum: the smallest allowed value
    :return: the value as an ``int``
    :raises StudyError: if it is no integer (or a bool) or below ``minimum``
    """
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not is_integer(value, minimum):
        raise _fail(path, f"{where} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _seeds(path: Path, where: str, value: Any) -> tuple[int, ...]:
    """A checked list of seeds of a study file.

    :param path: the study file
    :param where: the setting, for the message (e.g. ``'seeds'``)
    :param value: the parsed value
    :return: the seeds, in the file's order
    :raises StudyError: if it is no non-empty list of integers >= 0, or lists a seed twice
    """
    if not isinstance(value, list) or not value:
        raise _fail(path, f"{where} must be a non-empty list of integers, got {value!r}")
    seeds = tuple(_int(path, where, seed, 0) for seed in value)
    if len(set(seeds)) != len(seeds):
        raise _fail(path, f"{where} lists a seed twice: {list(seeds)}")
    return seeds


def _unknown(path: Path, where: str, keys: Any, allowed: frozenset[str]) -> None:
    """Check that a mapping of a study file has only known keys.

    :param path: the study file
    :param where: the mapping, for the message (e.g. ``the study``)
    :param keys: the mapping's keys
    :param allowed: the known keys
    :raises StudyError: naming the first unknown key (in sorted order) and the allowed ones
    """
    extra = sorted(set(map(str, keys)) - allowed)
    if extra:
        raise _fail(path, f"unknown key {extra[0]!r} in {where} (allowed: {', '.join(sorted(allowed))})")


def _algorithm(
    path: Path,
    env: str,
    label: Any,
    settings: Any,
    seeds: tuple[int, ...] | None,
    conf_folder: Path | None = None,
) -> AlgorithmSpec:
    """One checked algorithm of a study file, with its entry of the hyperparameter file.

    :param path: the study file (a relative ``conf`` is relative to its folder)
    :param env: the study's environment id
    :param label: the algorithm's key under ``algorithms``
    :param settings: its parsed settings (``algo``, and optionally ``conf``, ``hyperparams``, ``seeds``, ``cpus``)
    :param seeds: the study's top-level seeds, used where the algorithm has none (None: not given)
    :param conf_folder: where the copy of a ``conf`` file is (a study folder's :data:`CONF_FOLDER`;
        None, or no copy there: at the path the study file gives)
    :return: the algorithm; ``cpus`` defaults to the entry's ``n_envs`` where it uses rollout workers, else 1
    :raises StudyError: on the first problem of the algorithm's settings or of its entry
    """
    if not isinstance(label, str) or not label or "/" in label or label.startswith("."):
        raise _fail(
            path, f"an algorithm label must be a non-empty name without '/', not starting with '.', got {label!r}"
        )
    if not isinstance(settings, dict):
        raise _fail(path, f"algorithm {label!r} needs a mapping with at least 'algo', got {settings!r}")
    _unknown(path, f"algorithm {label!r}", settings, ALGORITHM_KEYS)
    algo = settings.get("algo")
    if not isinstance(algo, str):
        raise _fail(path, f"algorithm {label!r}: missing 'algo' (an rl-zoo3 algorithm name)")
    try:
        check_algorithm(algo)
    except InputError as error:
        raise _fail(path, f"algorithm {label!r}: {error}") from None
    if "conf" in settings:
        conf = Path(os.path.expanduser(str(settings["conf"])))
        if conf.suffix not in CONF_SUFFIXES:
            raise _fail(path, f"algorithm {label!r}: 'conf' must name a .yml, .yaml or .py file, got {conf}")
        kept = None if conf_folder is None else conf_copy(conf_folder, label, conf)
        if kept is not None and kept.is_file():
            conf = kept
        elif not conf.is_absolute():  # also a folder made before it kept copies
            conf = path.parent / conf
    elif algo in ALGORITHMS:
        conf = HYPERPARAMS_DIR / f"{algo}.yml"
    else:
        raise _fail(path, f"algorithm {label!r}: {algo!r} is not one of sb3-detc's algorithms, name its 'conf' file")
    hyperparams = settings.get("hyperparams") or {}
    if not isinstance(hyperparams, dict):
        raise _fail(path, f"algorithm {label!r}: 'hyperparams' must be a mapping, got {hyperparams!r}")
    own = settings.get("seeds")
    trial_seeds = _seeds(path, f"the seeds of {label!r}", own) if own is not None else seeds
    if trial_seeds is None:
        raise _fail(path, f"algorithm {label!r} has no seeds (give 'seeds' at the top or in the algorithm)")
    hyperparams = renamed_keys(hyperparams)  # also a study file of an earlier version
    entry = _checked_entry(path, env, label, algo, conf, hyperparams)
    if entry.get("normalize") not in (None, False, "False"):
        raise _fail(
            path,
            f"algorithm {label!r}: a study does not carry VecNormalize statistics ('normalize') into its checkpoints "
            "and evaluations; normalise the rewards with normalize_reward: true (MAPPOC) or train with "
            "python -m sb3_detc.train",
        )
    cpus = settings.get("cpus")
    if cpus is None:
        cpus = int(entry.get("n_envs", 1)) if uses_rollout_workers(entry) else 1
    cpus = _int(path, f"'cpus' of {label!r}", cpus, 1)
    selection = _selection(path, label, settings["selection"]) if "selection" in settings else None
    if selection is not None and entry_fixed_trigger(entry) is not None:
        raise _fail(
            path,
            f"algorithm {label!r} trains under a fixed trigger ({entry_fixed_trigger(entry)!r}): its policy over "
            "options never decides, there is nothing to select ('selection')",
        )
    return AlgorithmSpec(label, algo, conf, dict(hyperparams), trial_seeds, cpus, entry, "conf" in settings, selection)


def _selection(path: Path, label: str, settings: Any) -> Selection:
    """The checked ``selection`` of an algorithm.

    :param path: the study file
    :param label: the algorithm's label
    :param settings: the parsed mapping
    :return: the selection
    :raises StudyError: if it is no mapping with ``every``, has unknown keys or a value out of range
    """
    where = f"'selection' of {label!r}"
    if not isinstance(settings, dict) or "every" not in settings:
        raise _fail(path, f"{where} must be a mapping with at least 'every', got {settings!r}")
    _unknown(path, where, settings, SELECTION_KEYS)
    every = _int(path, f"'selection: every' of {label!r}", settings["every"], 1)
    episodes = _int(path, f"'selection: episodes' of {label!r}", settings.get("episodes", 20), 1)
    seed = settings.get("seed")
    seed = None if seed is None else _int(path, f"'selection: seed' of {label!r}", seed, 0)
    tolerance = settings.get("tolerance", 0.01)
    if isinstance(tolerance, bool) or not isinstance(tolerance, int | float) or not 0 <= tolerance < 1:
        raise _fail(path, f"'selection: tolerance' of {label!r} must be a number in [0, 1), got {tolerance!r}")
    return Selection(every, episodes, seed, float(tolerance))


def _checked_entry(
    path: Path, env: str, label: str, algo: str, conf: Path, hyperparams: dict[str, Any]
) -> dict[str, Any]:
    """The entry with the overrides, checked as a whole (as rl-zoo3's ``-params`` would be).

    :param path: the study file, for the message
    :param env: environment id, the entry's key in ``conf`` (else its ``default`` entry)
    :param label: the algorithm's label, for the message
    :param algo: rl-zoo3 algorithm name
    :param conf: the hyperparameter file
    :param hyperparams: overrides of the entry
    :return: the entry with the overrides applied
    :raises StudyError: if the file, the entry or the overrides are not valid
    """
    try:
        return check_hyperparams_file(conf, algo, env, hyperparams)
    except InputError as error:
        raise _fail(path, f"algorithm {label!r}: {error}") from None


def same_study(first: Any, second: Any) -> bool:
    """Whether two study files' contents (parsed YAML) describe the same study, also across renamed hyperparameters.

    :param first: a parsed study file
    :param second: another
    :return: True if they are equal once the hyperparameter overrides of every algorithm carry the current names
    """

    def renamed(content: Any) -> Any:
        if not isinstance(content, dict) or not isinstance(content.get("algorithms"), dict):
            return content
        algorithms = {
            label: {**settings, "hyperparams": renamed_keys(settings["hyperparams"])}
            if isinstance(settings, dict) and isinstance(settings.get("hyperparams"), dict)
            else settings
            for label, settings in content["algorithms"].items()
        }
        return {**content, "algorithms": algorithms}

    return renamed(first) == renamed(second)


def conf_copy(conf_folder: Path, label: str, conf: Path) -> Path:
    """Where a study folder keeps its copy of the hyperparameter file an algorithm names.

    :param conf_folder: the folder's :data:`CONF_FOLDER`
    :param label: the algorithm's label
    :param conf: the file the study file names
    :return: ``<conf_folder>/<label><suffix of conf>``
    """
    return conf_folder / f"{label}{conf.suffix}"


def load_folder_study(directory: str | os.PathLike) -> StudySpec:
    """The study of a study folder, from its copies of the study file and of the hyperparameter files it names.

    :param directory: the study folder
    :return: the study
    :raises StudyError: if the folder has no ``study.yml``, or as :func:`load_study`
    """
    directory = Path(directory)
    if not (directory / "study.yml").is_file():
        raise StudyError(f"{directory} is not a study folder (no study.yml)")
    return load_study(directory / "study.yml", directory / CONF_FOLDER)


def load_study(path: str | os.PathLike, conf_folder: str | os.PathLike | None = None) -> StudySpec:
    """Read and check a study file.

    :param path: the YAML file
    :param conf_folder: where the hyperparameter files that algorithms name (``conf``) are, as
        ``<label><suffix>`` (a study folder's copies, see :func:`load_folder_study`); None, or
        no copy there: at the paths the study file gives
    :return: the study
    :raises StudyError: on the first problem, with the file and the key in the message
    """
    path = Path(path)
    conf_folder = None if conf_folder is None else Path(conf_folder)
    if not path.is_file():
        raise StudyError(f"study file {str(path)!r} not found")
    text = path.read_text()
    try:
        content = yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise _fail(path, f"not valid YAML{at}: {getattr(error, 'problem', None) or type(error).__name__}") from None
    if not isinstance(content, dict):
        raise _fail(path, "a study file is a mapping with at least 'env' and 'algorithms'")
    _unknown(path, "the study", content, STUDY_KEYS)
    env = content.get("env")
    if not isinstance(env, str):
        raise _fail(path, "missing 'env' (a registered environment id)")
    try:
        check_env(env)
    except InputError as error:
        raise _fail(path, str(error)) from None
    seeds = _seeds(path, "'seeds'", content["seeds"]) if "seeds" in content else None
    n_timesteps = content.get("n_timesteps")
    if n_timesteps is not None:
        n_timesteps = _int(path, "'n_timesteps'", n_timesteps, 1)
    interval = _int(path, "'checkpoint_interval'", content.get("checkpoint_interval", 100_000), 1)
    evaluation = content.get("evaluation") or {}
    if not isinstance(evaluation, dict):
        raise _fail(path, f"'evaluation' must be a mapping, got {evaluation!r}")
    _unknown(path, "'evaluation'", evaluation, EVALUATION_KEYS)
    episodes = _int(path, "'evaluation: episodes'", evaluation.get("episodes", 50), 1)
    eval_seed = _int(path, "'evaluation: seed'", evaluation.get("seed", 10_000), 0)
    families = evaluation.get("fixed_families", [])
    if not isinstance(families, list) or any(family not in TRIGGER_FAMILIES for family in families):
        raise _fail(
            path, f"'evaluation: fixed_families' must be a list of {', '.join(TRIGGER_FAMILIES)}; got {families!r}"
        )
    algorithms = content.get("algorithms")
    if not isinstance(algorithms, dict) or not algorithms:
        raise _fail(path, "'algorithms' must be a non-empty mapping of labels to settings")
    specs = tuple(_algorithm(path, env, label, settings, seeds, conf_folder) for label, settings in algorithms.items())
    study = StudySpec(path, text, env, n_timesteps, interval, episodes, eval_seed, specs, tuple(families))
    evaluated = set(range(eval_seed, eval_seed + episodes))
    for algorithm in specs:
        if study.budget(algorithm) < 1:
            raise _fail(path, f"algorithm {algorithm.label!r} trains 0 steps: its 'n_timesteps' must be >= 1")
        selection = algorithm.selection
        if selection is not None and evaluated & set(study.validation_seeds(selection.episodes, selection.seed)):
            raise _fail(
                path,
                f"the validation episodes of {algorithm.label!r} ('selection: seed') overlap the evaluation's "
                f"(seeds {eval_seed} to {eval_seed + episodes - 1}): the kept policy would be judged on episodes it "
                "was chosen on",
            )
    return study
