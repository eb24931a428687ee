"""``benchmarks/study_variant.py``: a base study and its variant side by side."""

from __future__ import annotations

from pathlib import Path


def test_folders_that_are_not_studies_are_a_usage_error(tmp_path: Path, run_benchmark) -> None:
    done = run_benchmark("study_variant.py", str(tmp_path), str(tmp_path / "other"))
    assert done.returncode == 2 and "not a study folder" in done.stderr and "Traceback" not in done.stderr
