"""``benchmarks/trigger_for_controller_front.py``: the front of triggers learned for frozen controllers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

SCRIPT = "trigger_for_controller_front.py"


def seed_row(seed: int, learned: float, periodic: float, settings: dict | None = None) -> dict:
    """A row as ``multiwalker_trigger_for_controller.py`` writes it, with one compared family."""
    metrics = {
        "savings": 0.9,
        "control_return": learned,
        "fixed_periodic_savings": 0.9,
        "fixed_periodic_control_return": periodic,
        "best_fixed_control_return": periodic,
        "learned_minus_best_fixed_control_return": learned - periodic,
    }
    return {"seed": seed, "env_kwargs": settings or {"broadcast_cost": 0.25}, "metrics": metrics, "saved": None}


def test_every_file_is_a_point_with_its_interval_beside_the_families(tmp_path: Path, run_benchmark_here) -> None:
    learned, periodic = [10.0, 20.0, 30.0], [40.0, 41.0, 45.0]
    first = tmp_path / "a.json"
    first.write_text(json.dumps([seed_row(s, x, y) for s, (x, y) in enumerate(zip(learned, periodic, strict=True))]))
    second = tmp_path / "b.json"
    second.write_text(json.dumps([seed_row(0, 50.0, 30.0)]))
    out = tmp_path / "front.png"
    done = run_benchmark_here(SCRIPT, str(first), str(second), "--labels", "slow", "fast", "--out", str(out))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "| algorithm | learned | periodic | learned minus best fixed |"
    slow = next(line for line in lines if line.startswith("| slow (3 seeds) |"))
    # the mean over seeds with an interval around it, at the mean savings
    assert f"{np.mean(learned):.2f} [" in slow and " at 0.900 |" in slow
    assert f"{np.mean(learned) - np.mean(periodic):.2f} [" in slow
    assert (
        "| fast (1 seeds) | 50.00 [50.00, 50.00] at 0.900 | 30.00 [30.00, 30.00] at 0.900 | 20.00 [20.00, 20.00] |"
        in lines
    )
    assert out.stat().st_size > 0


def test_rows_without_families_or_of_other_settings_are_refused(tmp_path: Path, run_benchmark_here) -> None:
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps([{"seed": 0, "env_kwargs": {}, "metrics": {"savings": 0.9, "control_return": 1.0}}]))
    done = run_benchmark_here(SCRIPT, str(bare), "--out", str(tmp_path / "f.png"))
    assert done.returncode == 2 and "the rows of bare compared no fixed family" in done.stderr
    mixed = tmp_path / "mixed.json"
    mixed.write_text(json.dumps([seed_row(0, 1.0, 2.0), seed_row(1, 1.0, 2.0, {"broadcast_cost": 1.0})]))
    done = run_benchmark_here(SCRIPT, str(mixed), "--out", str(tmp_path / "f.png"))
    assert done.returncode == 2 and "evaluated with different environment settings" in done.stderr
    done = run_benchmark_here(SCRIPT, str(mixed), "--labels", "a", "b", "--out", str(tmp_path / "f.png"))
    assert done.returncode == 2 and "--labels names 2 files, 1 given" in done.stderr
