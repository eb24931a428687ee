"""Run a study's trials on Ray Tune: locally (Ray started here) or on a Ray cluster.

The study folder is the state: :func:`run_study` skips every trial whose folder says
``done``, resumes every other one from its checkpoint (:mod:`sb3_detc.study.trial`) and
hands the rest to Ray Tune, one Tune trial per (algorithm, seed), each asking for the cores
its entry needs. Ray's own bookkeeping goes to ``<study dir>/.ray`` and is never read back.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import logging
import math
import multiprocessing
import os
import signal
import socket
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch as th
import yaml

from sb3_detc.files import replace_atomically
from sb3_detc.study.spec import CONF_FOLDER, StudyError, StudySpec, Trial, conf_copy, load_folder_study, same_study
from sb3_detc.study.trial import (
    LEARNER_THREADS,
    evaluate_trial,
    exclusive,
    read_status,
    run_trial,
    trial_folder,
)
from sb3_detc.validation import is_integer

__all__ = ["StudyProgress", "evaluate_study", "prepare_folder", "run_study", "trials_to_run"]

#: Seconds between two progress lines while nothing else happens.
PROGRESS_EVERY = 60.0

#: Seconds of recent progress from which the rate of a trial is estimated.
RATE_WINDOW = 600.0

#: A file in the study folder that asks the study to stop: running trials save a checkpoint at
#: the start of their next rollout and end, pending trials do not start. ``run`` writes it on
#: the first Ctrl-C (SIGINT) and removes it when it starts and ends.
STOP_FILE = ".stop"

#: The file a running study holds locked (:func:`run_study`).
LOCK_FILE = ".lock"

#: The lines of a study folder's ``.gitignore`` (:func:`prepare_folder`).
IGNORED = (
    ".ray/",
    STOP_FILE,
    LOCK_FILE,
    "*.tmp",
    "*.tmp.*",
    "checkpoint.zip",
    "checkpoint.json",
    "segments/",
    "best_policy.pt",
)


def prepare_folder(spec: StudySpec, directory: str | os.PathLike) -> Path:
    """Create the study folder, or check that an existing one belongs to this study.

    The folder keeps a copy of the study file (``study.yml``), of every hyperparameter file
    that it names (``conf/<label><suffix>``, see :func:`~sb3_detc.study.spec.load_folder_study`)
    and a ``.gitignore`` for Ray's files, scratch files and what a trial keeps only while it
    trains (its checkpoint, its segments and a selection's kept policy, :mod:`sb3_detc.study.trial`): a committed study
    holds its trials' results, and an unfinished trial resumes from its checkpoint on the
    machine that trains it.

    :param spec: the study
    :param directory: the study folder
    :return: the folder
    :raises StudyError: if the folder holds another study's trials, or a hyperparameter file
        changed since the folder's trials began
    """
    folder = Path(directory)
    copy = folder / "study.yml"
    if copy.is_file():
        if not same_study(yaml.safe_load(copy.read_text()), yaml.safe_load(spec.text)):
            raise StudyError(
                f"{folder} holds trials of another study file (its study.yml differs from {spec.path}); "
                "use a new --dir or the study file it was made with"
            )
    elif folder.exists() and any(folder.iterdir()):
        raise StudyError(f"{folder} is not empty and has no study.yml: not a study folder")
    folder.mkdir(parents=True, exist_ok=True)
    for algorithm in spec.algorithms:
        if not (algorithm.named_conf and algorithm.conf.is_file()):
            continue
        content = algorithm.conf.read_bytes()
        kept = conf_copy(folder / CONF_FOLDER, algorithm.label, algorithm.conf)
        if kept.is_file() and kept.read_bytes() != content:
            raise StudyError(
                f"{algorithm.conf} changed since the trials of {folder} began (their copy: {kept}); "
                "use a new --dir or the hyperparameters they were made with"
            )
        kept.parent.mkdir(exist_ok=True)
        replace_atomically(kept, lambda scratch, content=content: scratch.write_bytes(content))
    if not copy.is_file():
        replace_atomically(copy, lambda scratch: scratch.write_text(spec.text))
    (folder / ".gitignore").write_text("\n".join(IGNORED) + "\n")
    return folder


def _format_duration(seconds: float) -> str:
    """A duration in whole minutes, as ``42 min`` or ``3 h 05 min``.

    :param seconds: the duration in seconds (NaN or infinite: not known)
    :return: the text, ``unknown`` for a duration that is not finite
    """
    if not math.isfinite(seconds):
        return "unknown"
    minutes = int(round(seconds / 60))
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"


def _make_progress_callback(tune: Any) -> type:
    """The Ray Tune callback class that reports trial starts, results and ends to a :class:`StudyProgress`.

    Made on demand so that Ray is imported only when a study runs.

    :param tune: the ``ray.tune`` module
    :return: the class, to be called with the :class:`StudyProgress`
    """

    class StudyProgressCallback(tune.Callback):
        """Ray Tune callback that feeds a :class:`StudyProgress`.

        :param progress: the study's progress, told of every trial's start, results and end
        """

        def __init__(self, progress: StudyProgress) -> None:
            self.progress = progress

        def on_trial_start(self, iteration: int, trials: list, trial: Any, **info: Any) -> None:
            self.progress.started(trial.config["trial"])

        def on_trial_result(self, iteration: int, trials: list, trial: Any, result: dict, **info: Any) -> None:
            self.progress.result(trial.config["trial"], int(result.get("timesteps", 0)))

        def on_trial_complete(self, iteration: int, trials: list, trial: Any, **info: Any) -> None:
            self.progress.finished(trial.config["trial"], failed=False, stopped=bool(trial.last_result.get("stopped")))

        def on_trial_error(self, iteration: int, trials: list, trial: Any, **info: Any) -> None:
            self.progress.finished(trial.config["trial"], failed=True)

    return StudyProgressCallback


def _make_stopper(tune: Any) -> type:
    """The Ray Tune stopper class that ends the study once :data:`STOP_FILE` exists and no trial runs.

    Made on demand so that Ray is imported only when a study runs.

    :param tune: the ``ray.tune`` module
    :return: the class, to be called with the stop file and the :class:`StudyProgress`
    """

    class StudyStopper(tune.Stopper):
        """Ends the study once it was asked to stop and no trial runs any more: pending trials do not start.

        :param stop_file: the file whose existence asks the study to stop
        :param progress: the study's progress (which trials run)
        """

        def __init__(self, stop_file: Path, progress: StudyProgress) -> None:
            self.stop_file = stop_file
            self.progress = progress

        def __call__(self, trial_id: str, result: dict) -> bool:
            return False  # trials stop themselves, at the start of a rollout

        def stop_all(self) -> bool:
            return self.stop_file.exists() and not self.progress.running

    return StudyStopper


class StudyProgress:
    """Counts of finished, running, pending and failed trials and an estimate of the time left.

    The estimate divides the steps still to train by the rate at which the running trials
    advance together (steps per second over the last :data:`RATE_WINDOW` seconds of each).

    :param budgets: trial name -> training budget of every trial still to run
    :param done: number of trials already finished before this run
    :param stream: where the progress lines go
    """

    def __init__(self, budgets: dict[str, int], done: int = 0, stream: Any = None) -> None:
        self.budgets = budgets
        self.done = done
        self.failed = 0
        self.stream = stream or sys.stdout
        self.steps: dict[str, int] = {}
        self.history: dict[str, deque[tuple[float, int]]] = {}
        self.running: set[str] = set()
        self.finished_names: set[str] = set()
        self.stopped_names: set[str] = set()
        self._last_line = 0.0

    @property
    def pending(self) -> int:
        """Trials neither running nor finished."""
        return len(self.budgets) - len(self.running) - len(self.finished_names)

    def rate(self) -> float:
        """Steps per second of all running trials together (NaN before two reports).

        :return: the sum of every running trial's steps per second over its last :data:`RATE_WINDOW` seconds
            of reports, or NaN if none advanced yet
        """
        total = 0.0
        for name in self.running:
            samples = self.history.get(name)
            if samples and len(samples) > 1 and samples[-1][0] > samples[0][0]:
                total += (samples[-1][1] - samples[0][1]) / (samples[-1][0] - samples[0][0])
        return total if total > 0 else math.nan

    def seconds_left(self) -> float:
        """Estimated seconds until every trial has trained (evaluation not counted).

        :return: the steps still to train divided by :meth:`rate`: 0.0 when none are left, NaN while the
            rate is not known
        """
        left = sum(
            max(0, budget - self.steps.get(name, 0))
            for name, budget in self.budgets.items()
            if name not in self.finished_names or name in self.stopped_names
        )
        return left / self.rate() if left > 0 else 0.0

    def line(self) -> str:
        """The progress line.

        :return: the line: trials done, running (each with its share of the budget trained), pending,
            failed and stopped, and the time left
        """
        running = ", ".join(
            # A budget below one iteration trains the whole iteration: 100 %, not more.
            f"{name} {100 * min(1.0, self.steps.get(name, 0) / self.budgets[name]):.0f} %"
            for name in sorted(self.running)
        )
        return (
            f"[study] {self.done} done, {len(self.running)} running"
            + (f" ({running})" if running else "")
            + f", {self.pending} pending, {self.failed} failed"
            + (f", {len(self.stopped_names)} stopped" if self.stopped_names else "")
            + f"; time left: {_format_duration(self.seconds_left())}"
        )

    def show(self, force: bool = False) -> None:
        """Print the progress line (at most every :data:`PROGRESS_EVERY` seconds unless forced).

        :param force: print it even if the last line is more recent than :data:`PROGRESS_EVERY` seconds
        """
        now = time.monotonic()
        if force or now - self._last_line >= PROGRESS_EVERY:
            print(self.line(), file=self.stream, flush=True)
            self._last_line = now

    def started(self, name: str) -> None:
        """A trial started (or resumed).

        :param name: the trial's name (:attr:`Trial.name <sb3_detc.study.spec.Trial.name>`), a key of ``budgets``
        """
        self.running.add(name)
        self.show(force=True)

    def result(self, name: str, steps: int) -> None:
        """A trial reported its step count.

        :param name: the trial's name, a key of ``budgets``
        :param steps: environment steps the trial has trained so far (its model's step count)
        """
        self.steps[name] = steps
        now = time.monotonic()
        samples = self.history.setdefault(name, deque())
        samples.append((now, steps))
        while len(samples) > 2 and now - samples[1][0] >= RATE_WINDOW:
            samples.popleft()
        self.show()

    def finished(self, name: str, failed: bool, stopped: bool = False) -> None:
        """A trial ended: trained and evaluated, failed, or stopped on request before its budget.

        :param name: the trial's name
        :param failed: it raised an error
        :param stopped: it ended on a stop request (unfinished; its remaining steps still count)
        """
        self.running.discard(name)
        self.finished_names.add(name)
        if failed:
            self.failed += 1
        elif stopped:
            self.stopped_names.add(name)
        else:
            self.done += 1
            self.steps[name] = self.budgets[name]
        self.show(force=True)


def _check_address(address: str, timeout: float = 10.0) -> None:
    """Fail fast where a ``host:port`` cluster address does not answer (Ray itself retries for minutes).

    :param address: the address given with ``--address`` (``auto`` and ``ray://`` addresses are left to Ray)
    :param timeout: seconds to wait for a connection
    :raises StudyError: if nothing answers at the address
    """
    if address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise StudyError(f"--address must be auto or host:port of a Ray cluster's head, got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as error:
        raise StudyError(f"the Ray cluster at {address} does not answer ({error})") from None


def _trainable(config: dict[str, Any]) -> None:
    """One Ray Tune trial: run (or resume) a study trial and report its progress.

    The study is read from the folder's copies of the study file and of its hyperparameter files:
    what a trial trains does not change when those files change or vanish while the study runs,
    and on a cluster the nodes need the study folder only.

    :param config: ``directory`` (the study folder) and ``trial`` (the trial's name,
        :attr:`Trial.name <sb3_detc.study.spec.Trial.name>`)
    :raises KeyboardInterrupt: if the trial is interrupted other than by a stop request (and whatever
        :func:`~sb3_detc.study.trial.run_trial` raises when the trial fails)
    """
    from ray import tune

    spec = load_folder_study(config["directory"])
    trial = next(t for t in spec.trials() if t.name == config["trial"])
    budget = spec.budget(trial.algorithm)
    stop_file = Path(config["directory"]) / STOP_FILE

    def report(steps: int) -> None:
        if stop_file.exists():  # at the start of a rollout: the checkpoint then loses nothing
            raise KeyboardInterrupt("the study was asked to stop")
        tune.report({"timesteps": steps, "budget": budget})

    if not stop_file.exists():
        try:
            status = run_trial(spec, trial, config["directory"], on_progress=report)
            tune.report({"timesteps": status.get("timesteps", budget), "budget": budget, "done": 1})
            return
        except KeyboardInterrupt:
            if not stop_file.exists():
                raise
    # Stopped on request (checkpoint saved, status "interrupted"), or not started: a clean end for Ray.
    steps = read_status(trial_folder(config["directory"], trial)).get("timesteps", 0)
    tune.report({"timesteps": steps, "budget": budget, "stopped": 1})


@contextlib.contextmanager
def _stop_on_first_interrupt(stop_file: Path, stream: Any) -> Any:
    """Within the context, the first Ctrl-C (SIGINT) writes ``stop_file``; the next one interrupts at once.

    Ray Tune's own handler is switched off: it ends running trials about ten seconds after the
    signal, which cuts off a checkpoint that is being written. Outside the main thread it does nothing.

    :param stop_file: the file whose existence asks the study to stop (:data:`STOP_FILE` in the study folder)
    :param stream: where the message that the study is stopping goes
    """
    if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
        yield
        return
    previous = signal.getsignal(signal.SIGINT)

    def stop(signum: int, frame: Any) -> None:
        stop_file.touch()
        signal.signal(signal.SIGINT, previous)
        print(
            "[study] stopping: training trials save a checkpoint at the start of their next rollout, evaluating "
            "ones finish, pending ones do not start (Ctrl-C again stops at once, losing what each trial trained "
            "since its last checkpoint)",
            file=stream,
            flush=True,
        )

    switch = "TUNE_DISABLE_SIGINT_HANDLER"
    before = os.environ.get(switch)
    os.environ[switch] = "1"
    signal.signal(signal.SIGINT, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if before is None:
            os.environ.pop(switch, None)
        else:
            os.environ[switch] = before


class _NoMetricsWarning(logging.Filter):
    """Drops Ray Tune's warning that it cannot fetch the metrics of trials without results."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Whether to keep a record.

        :param record: a log record of Ray Tune's experiment analysis
        :return: False for the warning about trials without metrics, True for every other record
        """
        return not record.getMessage().startswith("Failed to fetch metrics")


@contextlib.contextmanager
def _without_results_warning() -> Any:
    """Within the context, Ray Tune does not warn of trials that have no results when the run ends.

    The study reads its results from the trial folders, not from Ray's; the trials a stop request
    leaves pending never report, and Ray's warning would list every one of them. Its other
    messages pass.
    """
    logger = logging.getLogger("ray.tune.analysis.experiment_analysis")
    quiet = _NoMetricsWarning()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


def run_study(
    spec: StudySpec,
    directory: str | os.PathLike,
    address: str | None = None,
    stream: Any = None,
    cpus: int | None = None,
    labels: list[str] | None = None,
) -> dict[str, str]:
    """Run every unfinished trial of a study on Ray Tune (or of some of its algorithms).

    :param spec: the study
    :param directory: the study folder (made if needed; on a cluster, a path every node sees)
    :param address: address of a running Ray cluster (``auto`` for the one this machine
        belongs to); None: start Ray on this machine with all its cores
    :param stream: where progress lines go (default: stdout)
    :param cpus: cores that Ray hands out to trials on this machine (default: all of them); fewer
        leave cores to other work, more run more trials at once (two Multiwalker trials on two
        cores were no faster together than one). Not with ``address`` (the cluster knows its cores).
    :param labels: the algorithms whose trials to run (None: all), e.g. to finish the seeds of one arm
        of a long study before the others'
    :return: trial name -> final status of every trial run (of the study, or of ``labels``):
        ``done``, ``failed``, or ``interrupted``, ``running`` or ``pending`` when the study was stopped
    :raises StudyError: if the folder belongs to another study or another run uses it, the cluster
        does not answer, ``cpus`` is not a positive integer or comes with ``address``, or a label is
        not the study's
    """
    if cpus is not None and not is_integer(cpus, 1):
        raise StudyError(f"cpus must be a positive integer, got {cpus!r}")
    if cpus is not None and address is not None:
        raise StudyError("give cpus or address, not both: a cluster's cores are its own")
    labels = _checked_labels(spec, f"the study {spec.path}", labels)
    folder = prepare_folder(spec, directory).resolve()
    with _only_run_in(folder):
        return _run_locked(spec, folder, address, stream, cpus, labels)


def _checked_labels(spec: StudySpec, subject: str, labels: list[str] | None) -> list[str] | None:
    """Labels that each name an algorithm of the study, each once.

    :param spec: the study
    :param subject: what holds the study, for the message (its file, or its folder)
    :param labels: the labels, or None (all algorithms)
    :return: the labels without repeats, in their order, or None
    :raises StudyError: for a string instead of a list, no labels, or labels that name no algorithm of the
        study (the message lists its algorithms)
    """
    if labels is None:
        return None
    known = [algorithm.label for algorithm in spec.algorithms]
    if isinstance(labels, str) or not labels:
        raise StudyError(
            f"give a list of one or more algorithm labels of {subject}, got {labels!r}; its algorithms: {known}"
        )
    unknown = [label for label in labels if label not in known]
    if unknown:
        raise StudyError(f"{subject} has no algorithm {', '.join(map(repr, unknown))}; its algorithms: {known}")
    return list(dict.fromkeys(labels))


def evaluate_study(
    directory: str | os.PathLike, labels: list[str] | None = None, stream: Any = None, cpus: int = 1
) -> dict[str, dict[str, Any] | None]:
    """Evaluate every finished trial of a study folder again with the current protocol.

    For a protocol that gained a mode or a metric since the trials finished: each finished
    trial's ``evaluation.json`` is rewritten (:func:`~sb3_detc.study.trial.evaluate_trial`,
    the study's episodes, seed and fixed families, one core per trial), as soon as its
    evaluation is complete; unfinished trials are left to ``run``. A trial whose evaluation
    raises is reported with its traceback (on stderr) and keeps its file; the others go on.
    The folder is locked as ``run`` locks it.

    :param directory: the study folder
    :param labels: the algorithms whose trials to evaluate (None: all)
    :param stream: where a line per trial goes (default: stdout)
    :param cpus: trials evaluated at once, each in a process of its own (1: one after another, in this process)
    :return: trial name -> its new evaluation, or None where it failed
    :raises StudyError: if the folder is not a study folder, another run uses it, a label is not the study's,
        or ``cpus`` is not a positive integer
    """
    if not is_integer(cpus, 1):
        raise StudyError(f"cpus must be a positive integer, got {cpus!r}")
    stream = sys.stdout if stream is None else stream
    folder = Path(directory)
    spec = load_folder_study(folder)
    labels = _checked_labels(spec, str(folder), labels)
    trials = [t for t in spec.trials() if labels is None or t.algorithm.label in labels]
    finished = [t for t in trials if read_status(trial_folder(folder, t)).get("status") == "done"]
    print(f"[study] evaluating {len(finished)} finished of {len(trials)} trials in {folder}", file=stream, flush=True)
    evaluations: dict[str, dict[str, Any] | None] = {}

    def done(trial: Trial, outcome: Callable[[], tuple[dict[str, Any], float]]) -> None:
        try:
            result, seconds = outcome()
        except Exception:  # noqa: BLE001  (reported with its traceback; the other trials go on)
            print(f"[study] {trial.name}: evaluation failed", file=stream, flush=True)
            traceback.print_exc()
            evaluations[trial.name] = None
            return
        metrics = result["metrics"]
        print(
            f"[study] {trial.name}: control return {metrics['control_return']:.2f}, "
            f"savings {metrics['savings']:.3f} ({_format_duration(seconds)}; "
            f"{len(evaluations) + 1} of {len(finished)})",
            file=stream,
            flush=True,
        )
        evaluations[trial.name] = result

    with _only_run_in(folder.resolve()):
        if cpus == 1:
            for trial in finished:
                done(trial, functools.partial(_evaluate_on_one_core, spec, trial, folder))
        else:
            context = multiprocessing.get_context("spawn")  # a fresh interpreter: no threads or state inherited
            with concurrent.futures.ProcessPoolExecutor(cpus, mp_context=context) as pool:
                futures = {pool.submit(_evaluate_on_one_core, spec, trial, folder): trial for trial in finished}
                for future in concurrent.futures.as_completed(futures):
                    done(futures[future], future.result)
    return {trial.name: evaluations[trial.name] for trial in finished}


def _evaluate_on_one_core(spec: StudySpec, trial: Trial, folder: Path) -> tuple[dict[str, Any], float]:
    """:func:`~sb3_detc.study.trial.evaluate_trial` with PyTorch on one thread, as a trial trains.

    :param spec: the study
    :param trial: the trial
    :param folder: the study folder
    :return: the evaluation and the seconds it took
    """
    threads = th.get_num_threads()
    th.set_num_threads(LEARNER_THREADS)
    began = time.monotonic()
    try:
        return evaluate_trial(spec, trial, folder), time.monotonic() - began
    finally:
        th.set_num_threads(threads)


def trials_to_run(spec: StudySpec, folder: Path, trials: list[Trial]) -> list[Trial]:
    """The trials of ``trials`` that are not done, in the order a run starts them.

    Longest first (stable): short trials fill the cores at the end instead of a long one running
    alone. Of equal budgets, the trials a stop interrupted (or a killed run left running) first, so
    that what was started finishes first.

    :param spec: the study
    :param folder: the study folder (its trials' ``status.json``)
    :param trials: the trials to consider, in the study's order
    :return: the trials to run, in order
    """
    status = {t.name: read_status(trial_folder(folder, t))["status"] for t in trials}
    todo = [t for t in trials if status[t.name] != "done"]
    return sorted(todo, key=lambda t: (-spec.budget(t.algorithm), status[t.name] not in ("interrupted", "running")))


def _only_run_in(folder: Path) -> contextlib.AbstractContextManager[Any]:
    """Hold the study folder's lock (``.lock``) while a run uses it: a second ``run`` (or ``evaluate``) is refused.

    Two runs on one folder would train the same trials twice and delete each other's segments and
    stop file (:func:`~sb3_detc.study.trial.exclusive`).

    :param folder: the study folder
    :return: the context that holds the lock
    :raises StudyError: if another process holds it
    """
    try:
        return exclusive(folder / LOCK_FILE)
    except BlockingIOError:
        message = f"another run or evaluation of a study uses {folder}; wait for it or stop it (Ctrl-C)"
        raise StudyError(message) from None


def _run_locked(
    spec: StudySpec, folder: Path, address: str | None, stream: Any, cpus: int | None, labels: list[str] | None
) -> dict[str, str]:
    """:func:`run_study` in its prepared and locked folder.

    :param spec: the study
    :param folder: the study folder (prepared, locked)
    :param address: as :func:`run_study`
    :param stream: as :func:`run_study`
    :param cpus: as :func:`run_study` (checked)
    :param labels: as :func:`run_study` (checked)
    :return: as :func:`run_study`
    :raises StudyError: if the cluster does not answer
    """
    (folder / STOP_FILE).unlink(missing_ok=True)  # left by a run that was killed while stopping
    trials = [t for t in spec.trials() if labels is None or t.algorithm.label in labels]
    todo = trials_to_run(spec, folder, trials)
    stream = stream or sys.stdout
    if not todo:
        of = f" of {', '.join(labels)}" if labels is not None else ""
        print(
            f"[study] all {len(trials)} trials{of} are done; see python -m sb3_detc.study report {folder}", file=stream
        )
        return {t.name: "done" for t in trials}
    if address is not None:
        _check_address(address)
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # with verbose=0: no tables of Ray's own
    import ray
    from ray import tune

    # Trials run torch on one thread (LEARNER_THREADS); should a trial's code start more, its idle
    # OpenMP threads sleep instead of spinning next to the trial's other processes.
    runtime_env = {"env_vars": {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}}
    if address is None:  # a local Ray that fails to start is a fault of its own: its traceback is kept
        ray.init(
            address="local",  # a Ray of its own, even where another one runs
            num_cpus=int(cpus) if cpus else os.cpu_count(),
            include_dashboard=False,
            log_to_driver=False,
            logging_level=logging.WARNING,
            runtime_env=runtime_env,
        )
    else:
        try:
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING, runtime_env=runtime_env)
        except (ConnectionError, RuntimeError, ValueError) as error:
            raise StudyError(f"cannot reach the Ray cluster at {address!r}: {' '.join(str(error).split())}") from None
    try:
        cores = int(ray.cluster_resources().get("CPU", 1))
        cpus = {t.name: min(t.algorithm.cpus, cores) for t in todo}
        progress = StudyProgress({t.name: spec.budget(t.algorithm) for t in todo}, len(trials) - len(todo), stream)
        print(
            f"[study] {len(trials)} trials: {len(trials) - len(todo)} done, {len(todo)} to run on {cores} cores "
            f"(results in {folder})",
            file=stream,
            flush=True,
        )
        trainable = tune.with_resources(_trainable, lambda config: {"cpu": cpus[config["trial"]]})
        tuner = tune.Tuner(
            trainable,
            param_space={
                "directory": str(folder),
                "trial": tune.grid_search([t.name for t in todo]),
            },
            tune_config=tune.TuneConfig(trial_dirname_creator=lambda trial: trial.config["trial"].replace("/", "_")),
            run_config=tune.RunConfig(
                name="study",
                storage_path=str(folder / ".ray"),
                verbose=0,
                stop=_make_stopper(tune)(folder / STOP_FILE, progress),
                callbacks=[_make_progress_callback(tune)(progress)],
                failure_config=tune.FailureConfig(max_failures=0, fail_fast=False),
            ),
        )
        with _stop_on_first_interrupt(folder / STOP_FILE, stream), _without_results_warning():
            tuner.fit()
    finally:
        ray.shutdown()
        (folder / STOP_FILE).unlink(missing_ok=True)
    statuses = {t.name: read_status(trial_folder(folder, t))["status"] for t in trials}
    failed = [name for name, status in statuses.items() if status == "failed"]
    progress.show(force=True)
    unfinished = sum(status not in ("done", "failed") for status in statuses.values())
    if unfinished:
        print(
            f"[study] {unfinished} trial(s) unfinished: run the same command again to continue them "
            "(from their checkpoints where they have one)",
            file=stream,
        )
    for name in failed:
        print(
            f"[study] {name} failed: see {trial_folder(folder, next(t for t in trials if t.name == name))}/error.txt",
            file=stream,
        )
    return statuses
