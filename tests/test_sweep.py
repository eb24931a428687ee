"""``sb3_detc.study.sweep``: sweeps keep every finished job's rows and rerun only what is missing."""

from __future__ import annotations

import json
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
