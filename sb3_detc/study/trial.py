"""One trial of a study: train from a hyperparameter entry with checkpoints, resume, evaluate.

A trial's folder (``<study dir>/trials/<label>/seed<seed>/``) holds plain files:

* ``status.json``: ``status`` (``running``, ``done``, ``interrupted`` or ``failed``), ``timesteps``, ``budget``,
  ``seconds`` (training time over all attempts; of an attempt that ended without notice, up to
  its latest checkpoint) and ``attempts`` (where each attempt trained, :func:`machine_record`,
  with ``start_timesteps``, the step it started from);
* ``progress.csv.xz``: the logger's rows of all attempts, each cut where the next one resumed
  (:func:`merged_progress`), as CSV compressed with xz, its numbers kept to
  :data:`PROGRESS_DIGITS` significant digits (:func:`sb3_detc.plot.read_progress` reads it); rewritten at every
  checkpoint;
* while it trains (never committed, see :func:`~sb3_detc.study.runner.prepare_folder`):
  ``checkpoint.zip`` and ``checkpoint.json``, the latest checkpoint (the whole model, optimizer
  included) and its step count, written atomically every ``checkpoint_interval`` steps at the
  start of a rollout; ``segments/<first step>/``, rl-zoo3's files of every attempt
  (``config.yml``, monitor files, the logger's ``progress.csv``);
* when done: ``policy.pt`` (the final policy only, :meth:`MlpHybridPolicy.load`) and
  ``evaluation.json`` (:func:`evaluate_policy_modes`); the checkpoint and the segments are
  removed, so that a finished trial holds :data:`FINISHED_FILES` alone (and ``selection.json``, below);
* ``error.txt``: the traceback of the last failure (removed when the trial is done);
* for an algorithm with a ``selection`` (:data:`SELECTION_FILES`): ``selection.json``, every
  validation and the kept one (:class:`~sb3_detc.callbacks.SelectBestCallback`), which stays, and
  while it trains ``best_policy.pt``, the kept policy, which becomes ``policy.pt`` (ignored by git
  like the checkpoint: carry both to resume elsewhere).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import platform
import shutil
import subprocess
import time
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import pandas as pd
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.save_util import load_from_zip_file

import sb3_detc
from sb3_detc.callbacks import SelectBestCallback
from sb3_detc.evaluation import MODES, SUCCESS_NO_FALL, SUCCESS_TRAVEL, carries_package, evaluate_policy_modes
from sb3_detc.files import replace_atomically
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.plot import PROGRESS_CSV, PROGRESS_XZ
from sb3_detc.renamed import renamed_column
from sb3_detc.study.spec import StudySpec, Trial, entry_fixed_trigger
from sb3_detc.zoo import ExperimentManager

__all__ = [
    "FINISHED_FILES",
    "SELECTION_FILES",
    "MODES",
    "PROGRESS_DIGITS",
    "SUCCESS_NO_FALL",
    "SUCCESS_TRAVEL",
    "TrialCheckpoint",
    "carries_package",
    "code_commit",
    "evaluate_policy_modes",
    "evaluate_trial",
    "exclusive",
    "machine_record",
    "merged_progress",
    "progress_number",
    "read_status",
    "run_trial",
    "trial_folder",
]

#: Torch threads of a trial's learner, whatever its cores (those are its rollout workers'). The
#: small networks' update is no faster on two threads, and with OpenMP's passive waiting (which
#: ``run`` sets) up to three times slower (``benchmarks/results/study_trial_threads_multiwalker.md``).
LEARNER_THREADS = 1

#: The files of a finished trial's folder: nothing else is kept.
FINISHED_FILES = ("evaluation.json", "policy.pt", PROGRESS_XZ, "status.json")
#: The files of a trial's ``selection`` (:class:`~sb3_detc.callbacks.SelectBestCallback`): the record, which
#: stays when the trial is done, and the kept policy, which is then ``policy.pt``.
SELECTION_FILES = ("selection.json", "best_policy.pt")


def trial_folder(directory: str | os.PathLike, trial: Trial) -> Path:
    """The folder of ``trial`` in the study folder ``directory``.

    :param directory: the study folder
    :param trial: the trial
    :return: ``<directory>/trials/<label>/seed<seed>`` (not created here)
    """
    return Path(directory) / "trials" / trial.algorithm.label / f"seed{trial.seed}"


def exclusive(lock: Path) -> contextlib.AbstractContextManager[Any]:
    """Hold a lock file for as long as the returned context is open: a second holder is refused.

    The lock is the operating system's (``fcntl.flock``), released when the context closes or the
    process ends, however it ends; where ``fcntl`` is missing (Windows) or the file system has no
    locks, nothing is locked (the latter with a warning).

    :param lock: the lock file (created if missing, never deleted)
    :return: the context that holds the lock
    :raises BlockingIOError: if another process holds it
    """
    try:
        import fcntl
    except ImportError:
        return contextlib.nullcontext()
    handle = open(lock, "a")  # noqa: SIM115 (closed by the returned context)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise
    except OSError as error:  # e.g. a file system without locks: go on, as where fcntl is missing
        handle.close()
        warnings.warn(f"cannot lock {lock} ({error}); make sure no other process uses what it guards", stacklevel=3)
        return contextlib.nullcontext()
    return contextlib.closing(handle)  # closing the file releases the lock


def _write_json(path: Path, content: dict[str, Any], compact: bool = False) -> None:
    """Write a JSON file atomically (:func:`replace_atomically`).

    :param path: the file
    :param content: what it holds
    :param compact: without spaces and line breaks (e.g. an evaluation's per-episode lists), else indented
    """
    text = json.dumps(content, separators=(",", ":")) if compact else json.dumps(content, indent=1)
    replace_atomically(path, lambda scratch: scratch.write_text(text + "\n"))


def read_status(folder: Path) -> dict[str, Any]:
    """A trial's ``status.json`` (``{"status": "pending"}`` if it has none).

    :param folder: the trial folder
    :return: the parsed content of ``status.json``, or ``{"status": "pending"}``
    """
    path = folder / "status.json"
    return json.loads(path.read_text()) if path.is_file() else {"status": "pending"}


class TrialCheckpoint(BaseCallback):
    """Save the whole model to ``<folder>/checkpoint.zip`` every ``interval`` steps, at the start of a rollout.

    At the start of a rollout the model has learned from every step it counted, so a run
    resumed from the checkpoint repeats nothing and loses nothing but the steps after it.
    The file is replaced atomically; ``checkpoint.json`` repeats its step count for readers.
    At every rollout start ``on_progress`` gets the step count, after every save ``on_save``.
    :meth:`save` saves at any other moment (the trial does when it is interrupted).

    :param folder: the trial folder
    :param interval: environment steps between checkpoints
    :param on_progress: called with the model's step count at the start of every rollout
    :param on_save: called after every checkpoint
    :param verbose: verbosity level
    """

    def __init__(
        self,
        folder: Path,
        interval: int,
        on_progress: Callable[[int], None] | None = None,
        on_save: Callable[[int], None] | None = None,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        self.folder = Path(folder)
        self.interval = interval
        self.on_progress = on_progress
        self.on_save = on_save
        #: step count of the latest checkpoint (at the start of training: where it started)
        self.saved_at = 0

    def _on_training_start(self) -> None:
        self.saved_at = self.model.num_timesteps

    def save(self) -> None:
        """Save the model now (replacing the checkpoint atomically) and call ``on_save``."""
        steps = self.model.num_timesteps
        replace_atomically(self.folder / "checkpoint.zip", self.model.save, "checkpoint.tmp.zip")
        _write_json(self.folder / "checkpoint.json", {"timesteps": steps})
        self.saved_at = steps
        if self.on_save is not None:
            self.on_save(steps)

    def _on_rollout_start(self) -> None:
        steps = self.model.num_timesteps
        if steps - self.saved_at >= self.interval:
            self.save()
        if self.on_progress is not None:
            self.on_progress(steps)

    def _on_step(self) -> bool:
        return True


def merged_progress(folder: Path) -> pd.DataFrame:
    """The logger's rows of all attempts of a trial, each attempt's rows cut where the next one resumed.

    :param folder: the trial folder
    :return: the rows, by ``time/total_timesteps`` (empty if nothing was logged)
    """
    starts = sorted((int(path.name), path) for path in (folder / "segments").glob("*") if path.name.isdigit())
    parts = []
    for k, (_, path) in enumerate(starts):
        csv = path / PROGRESS_CSV
        if not csv.is_file() or csv.stat().st_size == 0:
            continue
        rows = pd.read_csv(csv).rename(columns=renamed_column)  # also logs of earlier versions
        if k + 1 < len(starts) and "time/total_timesteps" in rows:
            rows = rows[rows["time/total_timesteps"] <= starts[k + 1][0]]
        parts.append(rows)
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()


#: Significant digits a trial's ``progress.csv.xz`` keeps of its fractional numbers (whole numbers,
#: such as step counts, stay whole): the curves lose nothing one could see, and the file is half the
#: size of one with every digit.
PROGRESS_DIGITS = 6


def progress_number(value: float) -> str:
    """A logged number as ``progress.csv.xz`` keeps it: whole numbers exactly, others to :data:`PROGRESS_DIGITS`.

    :param value: a logged value
    :return: its text in the CSV
    """
    return str(int(value)) if value.is_integer() else f"{value:.{PROGRESS_DIGITS}g}"


def _write_progress(folder: Path) -> None:
    """Write the trial's ``progress.csv.xz`` (atomically), nothing if nothing was logged.

    The rows are :func:`merged_progress`'s, the numbers as :func:`progress_number` writes them.

    :param folder: the trial folder
    """
    rows = merged_progress(folder)
    if not rows.empty:
        write = functools.partial(rows.to_csv, index=False, float_format=progress_number, compression="xz")
        replace_atomically(folder / PROGRESS_XZ, write, "progress.tmp.csv.xz")
        (folder / PROGRESS_CSV).unlink(missing_ok=True)  # one log per trial: a plain one is outdated now


def code_commit(source: Path | None = None) -> str | None:
    """The git commit of the package's source, so that a trial's attempts name the code they ran.

    :param source: the folder whose code to name; None for the sb3_detc package itself
    :return: the commit's hash, with ``+modified`` when files under ``source`` differ from it (or
        are untracked); None when ``source`` is not in a git checkout (an installed wheel) or git
        is missing
    """
    source = Path(sb3_detc.__file__).parent if source is None else source
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=source, capture_output=True, text=True, check=True
        ).stdout.strip()
        changes = subprocess.run(
            ["git", "status", "--porcelain", "--", "."], cwd=source, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return commit + ("+modified" if changes else "")


def machine_record() -> dict[str, Any]:
    """Where and how this process trains: what an attempt's steps per second depend on.

    :return: host name, processor model, cores, torch's threads, ``OMP_WAIT_POLICY`` (None
        if unset), versions of Python, torch and sb3_detc, the code (:func:`code_commit`), and the
        time (UTC, ISO 8601)
    """
    processor = platform.processor()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        models = [
            line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines() if line.startswith("model name")
        ]
        processor = models[0] if models else processor
    return {
        "host": platform.node(),
        "processor": processor,
        "cores": os.cpu_count(),
        "torch_threads": th.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "python": platform.python_version(),
        "torch": th.__version__,
        "sb3_detc": sb3_detc.__version__,
        "commit": code_commit(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def trial_manager(
    spec: StudySpec,
    trial: Trial,
    log_folder: Path,
    timesteps: int,
    hyperparams: dict[str, Any] | None = None,
    trained_agent: str = "",
) -> ExperimentManager:
    """rl-zoo3's experiment manager that builds a trial's model as the study trains it.

    The trial's entry (with the study's overrides), its seed, on the CPU, without rl-zoo3's own
    evaluation, checkpoints and console log.

    :param spec: the study
    :param trial: the trial
    :param log_folder: where the manager writes its logs
    :param timesteps: the steps to train
    :param hyperparams: settings over the conf file's entry (None: the study's, ``trial.algorithm.hyperparams``)
    :param trained_agent: a saved model to continue from ("": a new model)
    :return: the manager; ``setup_experiment()`` builds the model
    """
    algorithm = trial.algorithm
    args = argparse.Namespace(
        algo=algorithm.algo, env=spec.env, seed=trial.seed, n_timesteps=timesteps, study=str(spec.path)
    )
    return ExperimentManager(
        args,
        algorithm.algo,
        spec.env,
        log_folder=str(log_folder),
        n_timesteps=timesteps,
        eval_freq=-1,
        save_freq=-1,
        log_interval=-1,
        hyperparams=dict(algorithm.hyperparams if hyperparams is None else hyperparams),
        trained_agent=trained_agent,
        seed=trial.seed,
        verbose=0,
        config=str(algorithm.conf),
        device="cpu",
    )


def _train(spec: StudySpec, trial: Trial, folder: Path, on_progress: Callable[[int], None] | None) -> None:
    """Train a trial to its budget (from its checkpoint if it has one) and save ``progress.csv.xz`` and ``policy.pt``.

    Every attempt logs to its own segment ``segments/<first step>/``; ``status.json`` keeps the step
    count, the training seconds and the attempts (as their segments, those from the checkpoint on are dropped).

    :param spec: the study
    :param trial: the trial
    :param folder: the trial folder
    :param on_progress: called with the step count at the start of every rollout (None: nothing is called)
    :raises RuntimeError: if the checkpoint is not below the budget
    :raises KeyboardInterrupt: if training stopped before the budget (status ``interrupted``, checkpoint saved)
    """
    algorithm = trial.algorithm
    budget = spec.budget(algorithm)
    checkpoint = folder / "checkpoint.zip"
    start = 0
    if checkpoint.is_file():  # the step count saved in the model itself (checkpoint.json is for readers)
        data, _, _ = load_from_zip_file(checkpoint, load_data=True, device="cpu", print_system_info=False)
        start = int(data["num_timesteps"])
    if start >= budget:
        raise RuntimeError(f"the checkpoint of {trial.name} is at {start} steps, not below the budget {budget}")
    manager = trial_manager(
        spec, trial, folder / "segments", budget - start, trained_agent=str(checkpoint) if start else ""
    )
    drop_stale_segments(folder, start)
    segment = folder / "segments" / str(start)
    manager.save_path = str(segment)
    manager.params_path = str(segment / "params")
    model, _ = manager.setup_experiment()
    status = read_status(folder)
    attempts = [a for a in status.get("attempts", []) if a["start_timesteps"] < start]
    attempts.append({"start_timesteps": start, **machine_record()})
    _write_json(folder / "status.json", {**status, "attempts": attempts})

    earlier = status.get("seconds", 0.0)  # training time of the attempts before
    began = time.monotonic()

    def saved(steps: int) -> None:  # a killed attempt keeps its time up to its latest checkpoint
        _write_progress(folder)
        status = read_status(folder)
        _write_json(
            folder / "status.json", {**status, "timesteps": steps, "seconds": earlier + time.monotonic() - began}
        )

    checkpoints = TrialCheckpoint(folder, spec.checkpoint_interval, on_progress, saved)
    manager.callbacks.append(checkpoints)
    select = selection_callback(spec, trial, folder, start)
    if select is not None:
        manager.callbacks.append(select)
    interrupted = False
    try:
        manager.learn(model)
    except (KeyboardInterrupt, SystemExit):  # what rl-zoo3's learn() does not catch itself
        interrupted = True
    finally:
        if select is not None:
            select.eval_env.close()
    if interrupted or model.num_timesteps < budget:  # rl-zoo3's learn() ends quietly on a KeyboardInterrupt
        # said first: Ray may end the process before the checkpoint is written
        _write_json(folder / "status.json", {**read_status(folder), "status": "interrupted"})
        if model.num_timesteps > checkpoints.saved_at:
            # nothing is lost (stopped during an update, the rest of that update is); the status then
            # counts the steps and the time up to this checkpoint (on_save), never more than it holds
            checkpoints.save()
        raise KeyboardInterrupt(f"training of {trial.name} stopped at {model.num_timesteps} of {budget} steps")
    seconds = earlier + time.monotonic() - began
    _write_json(folder / "status.json", {**read_status(folder), "timesteps": model.num_timesteps, "seconds": seconds})
    _write_progress(folder)  # first: a trial with its policy never trains again, and its segments go when it is done
    if select is not None:
        select.restore()  # the policy kept on the validation episodes (selection.json says which)
    replace_atomically(folder / "policy.pt", lambda scratch: model.policy.save(str(scratch)), "policy.tmp.pt")


def selection_callback(spec: StudySpec, trial: Trial, folder: Path, start: int) -> SelectBestCallback | None:
    """The callback that keeps a trial's policy best on its algorithm's validation episodes.

    Its record (``selection.json``) and the kept policy (``best_policy.pt``) are in the trial's
    folder, so that a trial resumed from its checkpoint goes on with them; a trial that starts
    afresh (``start`` 0) drops those of an attempt that left no checkpoint.

    :param spec: the study
    :param trial: the trial
    :param folder: the trial's folder
    :param start: the step the trial resumes from (0 without a checkpoint)
    :return: the callback (its validation env to be closed by the caller); None if the algorithm has no ``selection``
    """
    selection = trial.algorithm.selection
    if selection is None:
        return None
    if start == 0:
        for stale in SELECTION_FILES:
            (folder / stale).unlink(missing_ok=True)
    seeds = spec.validation_seeds(selection.episodes, selection.seed)
    return SelectBestCallback(trial_env(spec, trial), seeds, selection.every, selection.tolerance, save_path=folder)


def trial_env(spec: StudySpec, trial: Trial) -> gym.Env:
    """A (not vectorised) env of a trial's entry, with its settings, as its evaluation runs it.

    :param spec: the study
    :param trial: the trial
    :return: the env, for the caller to close
    """
    return gym.make(spec.env, **(trial.algorithm.entry.get("env_kwargs") or {}))


def drop_stale_segments(folder: Path, start: int) -> None:
    """Delete the logs of attempts that reached beyond the checkpoint a trial resumes from.

    An attempt's segment ``segments/<step>`` starts at the checkpoint it resumed from; a
    segment that starts at or after ``start`` belongs to an attempt whose later checkpoints
    are lost, and would otherwise be merged into the trial's curves.

    :param folder: the trial's folder
    :param start: the step the trial resumes from (0 without a checkpoint)
    """
    segments = folder / "segments"
    if segments.is_dir():
        for stale in segments.iterdir():
            if stale.name.isdigit() and int(stale.name) >= start:
                shutil.rmtree(stale)


def evaluate_trial(spec: StudySpec, trial: Trial, directory: str | os.PathLike) -> dict[str, Any]:
    """Run the evaluation protocol on a trial's final policy and write its ``evaluation.json``.

    The study's episodes, seed and fixed families, the trial's env settings and fixed trigger
    (:func:`evaluate_policy_modes`); ``timesteps`` is the trial's step count. The file is
    replaced at once when the evaluation is complete, so an interrupted evaluation leaves the
    previous one.

    :param spec: the study
    :param trial: the trial, whose folder holds ``policy.pt``
    :param directory: the study folder
    :return: the evaluation
    :raises FileNotFoundError: if the trial has no final policy
    """
    folder = trial_folder(directory, trial)
    policy = MlpHybridPolicy.load(str(folder / "policy.pt"), device="cpu")
    env = trial_env(spec, trial)
    try:
        evaluation = evaluate_policy_modes(
            policy,
            env,
            spec.episodes,
            spec.eval_seed,
            entry_fixed_trigger(trial.algorithm.entry),
            fixed_families=spec.fixed_families,
        )
    finally:
        env.close()
    evaluation["timesteps"] = read_status(folder).get("timesteps", spec.budget(trial.algorithm))
    _write_json(folder / "evaluation.json", evaluation, compact=True)
    return evaluation


def run_trial(
    spec: StudySpec,
    trial: Trial,
    directory: str | os.PathLike,
    on_progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Train (or resume) and evaluate one trial in its folder; a finished trial is left as it is.

    :param spec: the study
    :param trial: the trial
    :param directory: the study folder
    :param on_progress: called with the step count at the start of every rollout
    :return: the trial's status
    :raises Exception: whatever training or evaluation raised, after writing its traceback
        to ``error.txt`` and ``failed`` to ``status.json`` (``interrupted`` for a
        ``KeyboardInterrupt`` or ``SystemExit``, with no traceback)
    """
    folder = trial_folder(directory, trial)
    folder.mkdir(parents=True, exist_ok=True)
    status = read_status(folder)
    if status["status"] == "done":
        return status
    budget = spec.budget(trial.algorithm)
    _write_json(folder / "status.json", {**status, "status": "running", "budget": budget})
    threads = th.get_num_threads()
    th.set_num_threads(LEARNER_THREADS)
    try:
        if not (folder / "policy.pt").is_file():
            _train(spec, trial, folder, on_progress)
        evaluate_trial(spec, trial, directory)
        for leftover in ("checkpoint.zip", "checkpoint.json", "error.txt", "best_policy.pt"):
            (folder / leftover).unlink(missing_ok=True)
        shutil.rmtree(folder / "segments", ignore_errors=True)
        status = {**read_status(folder), "status": "done"}
        status.pop("error", None)
        _write_json(folder / "status.json", status)
        return status
    except (KeyboardInterrupt, SystemExit):  # stopped from outside (Ctrl-C, Ray): resumed by the next run
        _write_json(folder / "status.json", {**read_status(folder), "status": "interrupted"})
        raise
    except BaseException as error:
        (folder / "error.txt").write_text(traceback.format_exc())
        _write_json(
            folder / "status.json",
            {**read_status(folder), "status": "failed", "error": f"{type(error).__name__}: {error}"},
        )
        raise
    finally:
        th.set_num_threads(threads)
