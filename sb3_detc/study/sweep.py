"""Sweeps of independent jobs that keep every finished row and go on where they stopped.

A sweep runs a function over a list of jobs (JSON-like dicts), one job per process, and keeps
the rows the jobs return in one JSON file. :func:`run_rows` writes every finished job's rows to
the file at once (atomically), and a job whose rows are already in the file is not run again:
an interruption (Ctrl-C, a killed process) loses only the jobs that were running, and the same
call then runs only what is missing. A failing job's traceback is printed at once; the jobs
running beside it finish and write their rows, no other job starts, and the sweep then raises
the job's error. A job is identified by everything it is given (:func:`job_key`): put the
settings a job trains with into the job, so that a changed setting is a new job.

The benchmark scripts that train one model per job (``benchmarks/linear_learning.py`` and
others) run their jobs this way::

    from pathlib import Path

    from sb3_detc.study.sweep import run_rows

    def run(job: dict) -> dict:  # a module-level function: it is pickled to the worker processes
        return {"seed": job["seed"], "square": job["seed"] ** 2}

    if __name__ == "__main__":
        rows = run_rows(run, [{"seed": seed} for seed in range(5)], Path("rows.json"), workers=2)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from functools import partial
from pathlib import Path
from typing import Any

from sb3_detc.files import replace_atomically
from sb3_detc.study.trial import exclusive

#: The key of a row that holds its job (as JSON).
JOB = "job"

Rows = list[dict[str, Any]]


class OutError(Exception):
    """The results file cannot take the sweep's rows: it holds something else, or another sweep writes to it.

    (A job's own errors pass as they are.)
    """


def job_key(job: dict[str, Any]) -> str:
    """The identity of a job: its JSON with sorted keys (values JSON cannot hold written as text).

    :param job: the job's arguments
    :return: the key written into every row of the job
    """
    return json.dumps(job, sort_keys=True, default=str)


def read_rows(out: Path) -> Rows:
    """The rows of an earlier sweep (none if ``out`` does not exist).

    :param out: the JSON file of rows
    :return: the rows, those of every job and command that wrote to the file
    :raises OutError: if the file is not a JSON list of objects
    """
    if not out.is_file():
        return []
    try:
        rows = json.loads(out.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise OutError(f"{out}: not the JSON rows of an earlier run ({error}); give another --out") from None
    if not isinstance(rows, list) or not all(isinstance(row, dict) for row in rows):
        raise OutError(f"{out}: not the JSON rows of an earlier run (not a list of objects); give another --out")
    return rows


#: In a worker process: the sweep's event that tells the jobs queued to it not to start.
_stop: Any = None
#: In a worker process: set while a job runs.
_running = threading.Event()
#: In a worker process: set once the worker was told to end (its sweep died, or a ``SIGTERM``).
_ending = threading.Event()
#: Seconds an ending worker gives its running job to clean up before the worker exits.
ORPHAN_GRACE = 30.0


def _start_worker(stop: Any) -> None:
    """Keep the sweep's stop event in a worker process and watch the sweep (the pool's initializer).

    A worker must not outlive its sweep: if the sweep's process dies (a ``kill``, which unlike
    Ctrl-C reaches it alone), the worker ends as on a ``SIGTERM`` (:func:`_interrupt`): its running
    job is interrupted as Ctrl-C would (a ``KeyboardInterrupt``, also when the worker was started
    with Ctrl-C ignored), so the job's ``finally`` blocks close what it opened (e.g. a model's
    rollout workers), and the worker exits once they have run, after at most :data:`ORPHAN_GRACE`
    seconds; an idle worker exits at once.

    :param stop: the event
    """
    global _stop
    _stop = stop
    signal.signal(signal.SIGTERM, _interrupt)
    parent = multiprocessing.parent_process()
    if parent is not None:
        threading.Thread(target=_leave_with, args=(parent.sentinel,), daemon=True).start()


def _interrupt(signum: int, frame: Any) -> None:
    """The worker's ``SIGTERM`` handler: end the worker, its running job interrupted as Ctrl-C would.

    Further ``SIGTERM`` signals are ignored (the pool may send more; they must not cut the job's
    cleanup short); the worker exits after the job's ``finally`` blocks (:func:`_keyed`) or after
    :data:`ORPHAN_GRACE` seconds, whichever comes first.

    :param signum: the signal
    :param frame: the interrupted frame
    :raises KeyboardInterrupt: if a job runs
    """
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _ending.set()
    if not _running.is_set():
        os._exit(1)
    threading.Thread(target=_exit_after, args=(ORPHAN_GRACE,), daemon=True).start()
    raise KeyboardInterrupt(f"signal {signum}: the sweep's worker was told to end")


def _exit_after(seconds: float) -> None:
    """Exit the worker process after ``seconds``, whatever it does then.

    :param seconds: the delay
    """
    time.sleep(seconds)
    os._exit(1)


def _leave_with(sentinel: int) -> None:
    """Wait until the sweep's process ends, then end this worker (:func:`_interrupt`).

    :param sentinel: the sweep process's sentinel (ready once it has ended)
    """
    multiprocessing.connection.wait([sentinel])
    os.kill(os.getpid(), signal.SIGTERM)


def _keyed(run: Callable[[dict[str, Any]], dict[str, Any] | Rows], job: dict[str, Any]) -> tuple[str, Rows | None]:
    """Run one job in a worker unless the sweep has stopped.

    :param run: the sweep's function from a job to its row or rows
    :param job: the job
    :return: the job's key and its rows (None: not run, the sweep stopped before it started)
    """
    if _stop is not None and _stop.is_set():
        return job_key(job), None
    try:
        _running.set()
        result = run(job)
    finally:
        if _ending.is_set():  # the job has cleaned up; the worker ends
            os._exit(1)
        _running.clear()
    return job_key(job), result if isinstance(result, list) else [result]


def run_rows(
    run: Callable[[dict[str, Any]], dict[str, Any] | Rows], jobs: list[dict[str, Any]], out: Path, workers: int
) -> Rows:
    """Run the jobs not yet in ``out`` in parallel, writing every job's rows as soon as it finishes.

    Rows of ``out`` that belong to no job of this sweep (other settings, or rows without their
    job, of an earlier version) are kept. While the sweep runs it holds the lock file
    ``<out>.lock``: a second sweep on the same file is refused.

    :param run: a module-level function (it is pickled to spawned processes) from a job to its row
        or list of rows (JSON objects)
    :param jobs: the jobs, JSON-like dicts; a job's key (:func:`job_key`) is written into its rows
    :param out: the JSON file of rows, read at the start and rewritten after every job
    :param workers: parallel processes (at least 1)
    :return: the rows of the sweep's jobs, in the order of ``jobs`` (a job listed twice: once)
    :raises OutError: if ``out`` holds something else (:func:`read_rows`) or another sweep writes to it
    :raises ValueError: if ``workers`` is below 1
    :raises concurrent.futures.process.BrokenProcessPool: if a job's process was killed or ended (a
        ``SIGTERM`` to a worker interrupts its job, lets it clean up and ends the worker)
    :raises Exception: the first error a job raised, once the jobs running beside it have finished
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        lock = exclusive(out.with_name(out.name + ".lock"))
    except BlockingIOError:
        raise OutError(f"another sweep is writing to {out}; wait for it or give another --out") from None
    with lock:
        rows = read_rows(out)
        keys = [job_key(job) for job in jobs]
        done = {row.get(JOB) for row in rows}
        unique = dict(zip(keys, jobs, strict=True))  # a job listed twice runs once
        pending = [job for key, job in unique.items() if key not in done]
        already = len(unique) - len(pending)
        print(f"{already} of {len(unique)} jobs already in {out}; running {len(pending)}", flush=True)
        if pending:
            context = multiprocessing.get_context("spawn")
            stop = context.Event()
            failure: BaseException | None = None
            with ProcessPoolExecutor(
                min(workers, len(pending)), mp_context=context, initializer=_start_worker, initargs=(stop,)
            ) as pool:
                running = {pool.submit(_keyed, run, job) for job in pending}
                try:
                    while running:
                        finished, running = wait(running, return_when=FIRST_COMPLETED)
                        for future in finished:
                            error = None if future.cancelled() else future.exception()
                            if error is not None and failure is None:
                                failure = error
                                stop.set()
                                traceback.print_exception(error)
                                print("a job failed; the jobs running beside it finish first", flush=True)
                            if future.cancelled() or error is not None:
                                continue
                            key, new = future.result()
                            if new is None:  # queued before the sweep stopped: not run
                                continue
                            rows.extend({JOB: key, **row} for row in new)
                            replace_atomically(out, partial(_write, rows))
                            left = len(running)
                            print(f"a job finished, rows written to {out}; {left} to go", flush=True)
                finally:
                    stop.set()  # a failure or Ctrl-C: what has not started does not start
                    for future in running:
                        future.cancel()
            if failure is not None:
                raise failure  # with the job's traceback, after the jobs that were running kept their rows
    return [row for key in unique for row in rows if row.get(JOB) == key]


def _write(rows: Rows, path: Path) -> None:
    """Write rows as indented JSON.

    :param rows: the rows
    :param path: the file
    """
    path.write_text(json.dumps(rows, indent=1))


def check_at_least_one(parser: argparse.ArgumentParser, args: argparse.Namespace, *names: str) -> None:
    """Refuse integer arguments below 1 (counts of jobs, workers, steps) with a usage error.

    Arguments left at None are not checked.

    :param parser: the command's parser
    :param args: its parsed arguments
    :param names: attribute names of the arguments (``eval_episodes`` for ``--eval-episodes``)
    """
    for name in names:
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
