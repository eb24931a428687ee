"""Sweeps of independent training jobs that keep every finished row and go on where they stopped.

The benchmark scripts that train one model per job (``linear_learning.py``,
``trigger_learning.py``, ``option_value_estimation.py``, ``multiwalker_trigger_for_controller.py``)
run their jobs through :func:`run_rows`: jobs run in parallel processes, every finished job's rows
are written to the results file at once (atomically), and a job whose rows are already in the file
is not run again. An interruption (Ctrl-C, a killed job) loses only the jobs that were running; the
same command then runs only what is missing. A failing job stops the sweep with its traceback once
the jobs running beside it have finished and written their rows; jobs not yet started do not start.
A job
is identified by everything it is given (:func:`job_key`): the scripts put the settings they
train with into their jobs, so a changed setting is a new job.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from functools import partial
from pathlib import Path
from typing import Any

from sb3_detc.study.trial import exclusive, replace_atomically

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


def _keyed(run: Callable[[dict[str, Any]], dict[str, Any] | Rows], job: dict[str, Any]) -> tuple[str, Rows]:
    """Run one job in a worker; its key and its rows."""
    result = run(job)
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
    :return: the rows of the sweep's jobs, in the order of ``jobs``
    :raises OutError: if ``out`` holds something else (:func:`read_rows`) or another sweep writes to it
    :raises ValueError: if ``workers`` is below 1
    :raises concurrent.futures.process.BrokenProcessPool: if a job's process was killed
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
        pending = [job for job, key in zip(jobs, keys, strict=True) if key not in done]
        print(f"{len(jobs) - len(pending)} of {len(jobs)} jobs already in {out}; running {len(pending)}", flush=True)
        if pending:
            context = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(min(workers, len(pending)), mp_context=context) as pool:
                running = {pool.submit(_keyed, run, job) for job in pending}
                failure: BaseException | None = None
                try:
                    while running:
                        finished, running = wait(running, return_when=FIRST_COMPLETED)
                        for future in finished:
                            if future.cancelled():
                                continue
                            if future.exception() is not None:
                                error = future.exception()
                                failure = failure or error
                                running = _cancel_waiting(running)
                                print(
                                    f"a job failed ({type(error).__name__}: {error}); "
                                    f"the {len(running)} running beside it finish first",
                                    flush=True,
                                )
                                continue
                            key, new = future.result()
                            rows.extend({JOB: key, **row} for row in new)
                            replace_atomically(out, partial(_write, rows))
                            left = len(running)
                            print(f"a job finished, rows written to {out}; {left} to go", flush=True)
                finally:
                    _cancel_waiting(running)  # Ctrl-C: do not start what has not started
                if failure is not None:
                    raise failure  # with the job's traceback, after the jobs that were running kept their rows
    return [row for key in keys for row in rows if row.get(JOB) == key]


def _cancel_waiting(futures: set[Future[Any]]) -> set[Future[Any]]:
    """Cancel the jobs that have not started.

    :param futures: the jobs' futures
    :return: those of the jobs that were running already
    """
    return {future for future in futures if not future.cancel()}


def _write(rows: Rows, path: Path) -> None:
    """Write rows as indented JSON."""
    path.write_text(json.dumps(rows, indent=1))


def check_at_least_one(parser: argparse.ArgumentParser, args: argparse.Namespace, *names: str) -> None:
    """Refuse integer arguments below 1 with a usage error (arguments left at None are not checked).

    :param parser: the command's parser
    :param args: its parsed arguments
    :param names: attribute names of the arguments (``eval_episodes`` for ``--eval-episodes``)
    """
    for name in names:
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
