"""``benchmarks/study_variant.py``: a base study and its variant side by side."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_folders_that_are_not_studies_are_a_usage_error(tmp_path: Path) -> None:
    command = [sys.executable, str(ROOT / "benchmarks" / "study_variant.py"), str(tmp_path), str(tmp_path / "other")]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 2 and "not a study folder" in done.stderr and "Traceback" not in done.stderr
