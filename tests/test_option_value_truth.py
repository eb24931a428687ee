"""``benchmarks/option_value_truth.py``: each critic beside the value of a broadcast without its price."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "option_value_truth.py"

_spec = importlib.util.spec_from_file_location("option_value_truth", SCRIPT)
option_value_truth = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(option_value_truth)


def test_the_price_is_added_back_to_a_critic_that_learns_it(capsys: pytest.CaptureFixture) -> None:
    data = np.array([[0.01 * k, 0.0, 0.0] for k in range(20)])  # changes, ages, values of zero
    estimates = {"option_heads": np.full(20, -0.01), "afterstate": np.full(20, 0.002)}
    settings = {"broadcast_prob": "0.5", "gamma": "0.95", "horizon": "60"}
    option_value_truth.print_table(data, estimates, 0.01, settings)
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 0.")]
    assert len(rows) == 7 and sum(int(row.split("|")[2]) for row in rows) == 20  # a sample on an edge counts once
    assert all("| +0.0000 (0.0000) | +0.0020 (0.0000) |" in row for row in rows)


def test_tabulate_reads_a_run_of_an_earlier_version(tmp_path: Path) -> None:
    record = {
        "settings": {"broadcast_prob": "0.5", "gamma": "0.95", "horizon": "60", "comm_cost": "0.03"},
        "samples": [[0.01 * k, 0.0, 0.01] for k in range(20)],
        "estimates": {"option_heads": [0.0] * 20},
    }
    (tmp_path / "run.json").write_text(json.dumps(record))
    command = [sys.executable, str(SCRIPT), "--tabulate", "--out", str(tmp_path / "run.json")]
    printed = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    assert "price of a broadcast in team-mean reward: 0.0100 (added back to the estimates of option_heads)" in printed
    done = subprocess.run([*command[:-1], str(tmp_path / "none.json")], capture_output=True, text=True)
    assert done.returncode == 2 and "--tabulate needs the JSON of an earlier run" in done.stderr


def test_a_run_with_other_settings_in_out_is_refused_untouched(tmp_path: Path) -> None:
    record = {
        "settings": {"broadcast_prob": "0.5", "gamma": "0.95", "horizon": "60", "steps": "9000", "every": "3"},
        "samples": [],
        "estimates": {},
    }
    record["settings"].update(comm_cost="0.03", seed="0", timesteps="100000")  # an earlier version's name
    out = tmp_path / "run.json"
    out.write_text(json.dumps(record))
    command = [sys.executable, str(SCRIPT), "--steps", "30", "--gamma", "0.9", "--out", str(out)]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 2 and "holds a run with other settings (gamma, steps)" in done.stderr
    assert json.loads(out.read_text()) == record


def test_a_critic_already_in_out_is_not_trained_again(tmp_path: Path) -> None:
    out = tmp_path / "run.json"
    command = [sys.executable, str(SCRIPT), "--steps", "30", "--timesteps", "1024", "--out", str(out)]
    subprocess.run(command, check=True, capture_output=True, text=True)  # the samples only
    record = json.loads(out.read_text())
    record["estimates"] = {"afterstate": [0.5] * len(record["samples"])}  # as if trained
    out.write_text(json.dumps(record))
    printed = subprocess.run([*command, "--critics", "afterstate"], check=True, capture_output=True, text=True).stdout
    assert "trained" not in printed and "| +0.5000 (0.0000) |" in printed
    assert json.loads(out.read_text())["estimates"]["afterstate"] == [0.5] * len(record["samples"])
