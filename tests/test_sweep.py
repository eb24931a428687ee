"""``sb3_detc.study.sweep``: sweeps keep every finished job's rows and rerun only what is missing."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from sb3_detc.study.sweep import JOB, OutError, job_key, run_rows
from sb3_detc.study.trial import exclusive


def square(job: dict[str, Any]) -> dict[str, Any] | list[dict[str, Any]]:
    """A job of the tests: a mark per call, sleeps ``sleep`` s, waits for job ``after`` to start, fails on a
    negative number, two rows for ``split``."""
    marks = Path(job["marks"])
    (marks / f"{job['x']}.{len(list(marks.iterdir()))}").touch()
    time.sleep(job.get("sleep", 0))
    for _ in range(600):  # "after": wait (up to 60 s) until that job has started
        if "after" not in job or any(mark.name.startswith(f"{job['after']}.") for mark in marks.iterdir()):
            break
        time.sleep(0.1)
    if job["x"] < 0:
        raise ArithmeticError(f"no square of {job['x']} here")
    row = {"x": job["x"], "square": job["x"] ** 2}
    return [row, {**row, "half": True}] if job.get("split") else row


def test_jobs_in_the_file_are_not_rerun_and_other_rows_are_kept(tmp_path: Path) -> None:
    out, marks = tmp_path / "rows.json", tmp_path / "marks"
    marks.mkdir()
    out.write_text(json.dumps([{"x": 9, "square": 81}]))  # a row of an earlier version, without its job
    jobs = [{"x": x, "marks": str(marks)} for x in (1, 2)]
    assert [row["square"] for row in run_rows(square, [*jobs, jobs[0]], out, workers=2)] == [1, 4]  # 1 runs once
    more = [*jobs, {"x": 3, "marks": str(marks), "split": True}]
    rows = run_rows(square, more, out, workers=2)
    assert [row["square"] for row in rows] == [1, 4, 9, 9] and rows[-1]["half"]
    assert sorted(mark.name.split(".")[0] for mark in marks.iterdir()) == ["1", "2", "3"]  # every job ran once
    kept = json.loads(out.read_text())
    assert kept[0] == {"x": 9, "square": 81} and len(kept) == 5
    assert [row[JOB] for row in kept[1:]].count(job_key(more[2])) == 2


def test_a_failing_job_stops_the_sweep_with_its_error_and_keeps_what_finished(tmp_path: Path) -> None:
    out, marks = tmp_path / "rows.json", tmp_path / "marks"
    marks.mkdir()
    jobs = [{"x": x, "marks": str(marks), "sleep": 0 if x < 2 else 3} for x in (1, -1, 2, 3, 4, 5)]
    with pytest.raises(ArithmeticError, match="no square of -1"):
        run_rows(square, jobs, out, workers=1)  # one worker: the jobs run in order
    # the worker may take job 2 before the failure is seen (it then runs and keeps its row); jobs
    # queued to it after that do not start
    assert [row["x"] for row in json.loads(out.read_text())] in ([1], [1, 2])
    assert not any(mark.name.split(".")[0] in ("3", "4", "5") for mark in marks.iterdir())


def test_jobs_running_beside_a_failing_one_keep_their_rows(tmp_path: Path) -> None:
    out, marks = tmp_path / "rows.json", tmp_path / "marks"
    marks.mkdir()
    jobs = [{"x": -1, "after": 2, "marks": str(marks)}, {"x": 2, "sleep": 3, "marks": str(marks)}]
    with pytest.raises(ArithmeticError, match="no square of -1"):
        run_rows(square, jobs, out, workers=2)  # -1 fails once 2 has started, while 2 sleeps
    assert [row["x"] for row in json.loads(out.read_text())] == [2]


@pytest.mark.parametrize("content", ["{not json", '{"rows": []}', "[1, 2]"])
def test_a_file_of_something_else_is_refused_untouched(tmp_path: Path, content: str) -> None:
    out = tmp_path / "rows.json"
    out.write_text(content)
    with pytest.raises(OutError, match="give another --out"):
        run_rows(square, [{"x": 1, "marks": str(tmp_path)}], out, workers=1)
    assert out.read_text() == content


def test_a_second_sweep_on_the_same_file_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "rows.json"
    with exclusive(tmp_path / "rows.json.lock"), pytest.raises(OutError, match="another sweep is writing to"):
        run_rows(square, [{"x": 1, "marks": str(tmp_path)}], out, workers=1)
    assert not out.exists()


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, ended but not yet reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def wait_for(condition: Any, seconds: float) -> bool:
    """Poll ``condition()`` every 0.1 s for up to ``seconds``; whether it came true."""
    for _ in range(int(seconds * 10)):
        if condition():
            return True
        time.sleep(0.1)
    return condition()


#: A job module for sweeps in a subprocess: the job writes its process id, waits, and marks its cleanup.
WAITING_JOB = """
import os
import time
from pathlib import Path

def wait(job):
    Path(job["pid"]).write_text(str(os.getpid()))
    try:
        time.sleep(120)
    finally:
        Path(job["closed"]).touch()  # what a job opened is closed
    return {}
"""


def start_waiting_sweep(tmp_path: Path) -> tuple[subprocess.Popen, int]:
    """A sweep of one waiting job in a subprocess, and its worker's process id once the job runs."""
    (tmp_path / "sweep_jobs.py").write_text(WAITING_JOB)
    job = {"pid": str(tmp_path / "pid"), "closed": str(tmp_path / "closed")}
    out = str(tmp_path / "rows.json")
    script = (
        f"import sys; sys.path.insert(0, {str(tmp_path)!r}); from pathlib import Path; from sweep_jobs import wait; "
        f"from sb3_detc.study.sweep import run_rows; run_rows(wait, [{job!r}], Path({out!r}), 1)"
    )
    sweep = subprocess.Popen([sys.executable, "-c", script], stderr=subprocess.PIPE, text=True)
    if not wait_for(lambda: (tmp_path / "pid").is_file() and (tmp_path / "pid").read_text(), 60):
        sweep.kill()
        raise AssertionError("the job did not start")
    return sweep, int((tmp_path / "pid").read_text())


PROC = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table in /proc")


@PROC
def test_a_killed_sweep_interrupts_its_workers_job_which_cleans_up_and_ends(tmp_path: Path) -> None:
    sweep, worker = start_waiting_sweep(tmp_path)
    sweep.send_signal(signal.SIGTERM)  # the sweep's process alone, as `kill` does
    sweep.communicate(timeout=10)
    try:
        assert wait_for(lambda: (tmp_path / "closed").is_file(), 20)
        assert wait_for(lambda: not alive(worker), 20)
    finally:
        if alive(worker):
            os.kill(worker, signal.SIGKILL)


@PROC
def test_a_terminated_worker_cleans_up_and_the_sweep_reports_its_broken_pool(tmp_path: Path) -> None:
    sweep, worker = start_waiting_sweep(tmp_path)
    os.kill(worker, signal.SIGTERM)  # as the pool terminates its workers, or a user the worker
    try:
        _, stderr = sweep.communicate(timeout=30)
    finally:
        sweep.kill()
    assert sweep.returncode != 0 and "BrokenProcessPool" in stderr
    assert (tmp_path / "closed").is_file() and wait_for(lambda: not alive(worker), 20)
