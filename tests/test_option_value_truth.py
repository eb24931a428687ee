"""``benchmarks/option_value_truth.py``: each critic beside the value of a broadcast without its price."""

from __future__ import annotations

import json
from pathlib import Path

SCRIPT = "option_value_truth.py"


def test_the_price_is_added_back_to_a_critic_that_learns_it(tmp_path: Path, run_benchmark_here) -> None:
    record = {
        "settings": {"broadcast_prob": "0.5", "gamma": "0.95", "horizon": "60", "broadcast_cost": "0.03"},
        "samples": [[0.01 * k, 0.0, 0.0] for k in range(20)],  # changes, ages, values of zero
        "estimates": {"option_heads": [-0.01] * 20, "afterstate": [0.002] * 20},
    }
    (tmp_path / "run.json").write_text(json.dumps(record))
    printed = run_benchmark_here(SCRIPT, "--tabulate", "--out", str(tmp_path / "run.json"), check=True).stdout
    assert "price of a broadcast in team-mean reward: 0.0100" in printed  # 0.03 shared by 3 agents
    rows = [line for line in printed.splitlines() if line.startswith("| 0.")]
    assert len(rows) == 7 and sum(int(row.split("|")[2]) for row in rows) == 20  # a sample on an edge counts once
    assert all("| +0.0000 (0.0000) | +0.0020 (0.0000) |" in row for row in rows)


def test_tabulate_reads_a_run_of_an_earlier_version(tmp_path: Path, run_benchmark_here) -> None:
    record = {
        "settings": {"broadcast_prob": "0.5", "gamma": "0.95", "horizon": "60", "comm_cost": "0.03"},
        "samples": [[0.01 * k, 0.0, 0.01] for k in range(20)],
        "estimates": {"option_heads": [0.0] * 20},
    }
    (tmp_path / "run.json").write_text(json.dumps(record))
    printed = run_benchmark_here(SCRIPT, "--tabulate", "--out", str(tmp_path / "run.json"), check=True).stdout
    assert "price of a broadcast in team-mean reward: 0.0100 (added back to the estimates of option_heads)" in printed
    done = run_benchmark_here(SCRIPT, "--tabulate", "--out", str(tmp_path / "none.json"))
    assert done.returncode == 2 and "--tabulate needs the JSON of an earlier run" in done.stderr


def test_a_run_with_other_settings_in_out_is_refused_untouched(tmp_path: Path, run_benchmark_here) -> None:
    record = {
        "settings": {"broadcast_prob": "0.5", "gamma": "0.95", "horizon": "60", "steps": "9000", "every": "3"},
        "samples": [],
        "estimates": {},
    }
    record["settings"].update(comm_cost="0.03", seed="0", timesteps="100000")  # an earlier version's name
    out = tmp_path / "run.json"
    out.write_text(json.dumps(record))
    done = run_benchmark_here(SCRIPT, "--steps", "30", "--gamma", "0.9", "--out", str(out))
    assert done.returncode == 2 and "holds a run with other settings (gamma, steps)" in done.stderr
    assert json.loads(out.read_text()) == record


def test_a_critic_already_in_out_is_not_trained_again(tmp_path: Path, run_benchmark) -> None:
    out = tmp_path / "run.json"
    arguments = ["--steps", "30", "--timesteps", "1024", "--out", str(out)]
    run_benchmark(SCRIPT, *arguments, check=True)  # the samples only
    record = json.loads(out.read_text())
    record["estimates"] = {"afterstate": [0.5] * len(record["samples"])}  # as if trained
    out.write_text(json.dumps(record))
    printed = run_benchmark(SCRIPT, *arguments, "--critics", "afterstate", check=True).stdout
    assert "trained" not in printed and "| +0.5000 (0.0000) |" in printed
    assert json.loads(out.read_text())["estimates"]["afterstate"] == [0.5] * len(record["samples"])
