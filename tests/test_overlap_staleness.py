"""``benchmarks/overlap_staleness.py``: how far overlapping rollouts sample from each update's start."""

from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path

import pytest

from sb3_detc.study.spec import StudyError

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "benchmarks" / "studies" / "multiwalker_paper"

_spec = importlib.util.spec_from_file_location("overlap_staleness", ROOT / "benchmarks" / "overlap_staleness.py")
overlap_staleness = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(overlap_staleness)


def logged(folder: Path, label: str, seed: int, rows: list[dict[str, float]], finished: bool) -> None:
    """A trial's one segment with the given logger rows (and an evaluation if finished)."""
    trial = folder / "trials" / label / f"seed{seed}"
    (trial / "segments" / "0").mkdir(parents=True)
    columns = sorted({name for row in rows for name in row})
    text = ",".join(columns) + "\n" + "".join(",".join(str(row.get(c, "")) for c in columns) + "\n" for row in rows)
    (trial / "segments" / "0" / "progress.csv").write_text(text)
    if finished:
        (trial / "evaluation.json").write_text("{}")


def test_the_table_gives_median_and_90th_percentile_per_trial(tmp_path: Path) -> None:
    folder = tmp_path / "study"
    folder.mkdir()
    shutil.copy(STUDY / "study.yml", folder / "study.yml")
    overlap = [
        {
            "time/total_timesteps": 2048 * k,
            "train/kl_pi": 0.01 * k,
            "train/kl_mu": 1e-11,
            "rollout/sampler_kl_pi": 0.1 * k,
        }
        for k in range(1, 12)
    ]
    overlap[-1].pop("rollout/sampler_kl_pi")  # an iteration that logged no sampler KL is left out of its column
    logged(folder, "mappoc_paper_overlap", 3, overlap, finished=False)
    logged(folder, "mappoc_paper", 0, [{"time/total_timesteps": 2048, "train/kl_pi": 0.5}], finished=True)
    logged(folder, "random_skip_paper", 1, [{"time/total_timesteps": 2048, "rollout/ep_rew_mean": 1.0}], True)

    table = overlap_staleness.staleness_table(folder)
    header, *rows = [line.strip("| ").split(" | ") for line in table.splitlines() if line.startswith("| ")]
    assert header[3:] == list(overlap_staleness.COLUMNS)
    assert rows == [
        ["mappoc_paper", "0", "1", "-", "0.5 [0.5]", "-", "-"],
        # sampler: 0.1..1.0, median 0.55, 90th percentile 0.91; update: 0.01..0.11; kl_mu float noise -> 0
        ["mappoc_paper_overlap", "3", "11 (running)", "0.55 [0.91]", "0.06 [0.1]", "-", "0 [0]"],
    ]


def test_a_folder_without_a_study_or_logs_is_a_usage_error(tmp_path: Path) -> None:
    with pytest.raises(StudyError, match="no study.yml"):
        overlap_staleness.staleness_table(tmp_path)
    shutil.copy(STUDY / "study.yml", tmp_path / "study.yml")
    with pytest.raises(StudyError, match="no trial has logged"):
        overlap_staleness.staleness_table(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        overlap_staleness.main([str(tmp_path)])
    assert exit_.value.code == 2
