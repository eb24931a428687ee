"""``benchmarks/paper_claims.py``: the paper's claims against a study's finished seeds, with fixed verdict rules."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "benchmarks" / "studies" / "multiwalker_paper"
LABELS = ("mappoc_paper", "random_skip_paper", "control_first")


class ClaimsRefused(Exception):
    """The script refused the study folder (its message)."""


@pytest.fixture
def claims(run_benchmark_here):
    """The claims table the script prints for a study folder, or its usage error."""

    def table(folder: Path, mappoc: str, baseline: str, recipe: str | None) -> str:
        arguments = [str(folder), "--mappoc", mappoc, "--baseline", baseline, "--recipe", recipe or ""]
        done = run_benchmark_here("paper_claims.py", *arguments)
        if done.returncode == 2 and done.stderr.startswith("error: "):
            raise ClaimsRefused(done.stderr)
        assert done.returncode == 0, done.stderr
        return done.stdout

    return table


def study_copy(tmp_path: Path, entropies: dict[int, float], labels: tuple[str, ...] = LABELS) -> Path:
    """Seeds 0 and 1 of the study's MAPPOC, baseline and recipe (their evaluations), with given final entropies."""
    folder = tmp_path / "multiwalker_paper"
    folder.mkdir()
    shutil.copy(STUDY / "study.yml", folder / "study.yml")
    for label in labels:
        for seed in (0, 1):
            source, target = STUDY / "trials" / label / f"seed{seed}", folder / "trials" / label / f"seed{seed}"
            target.mkdir(parents=True)
            for name in ("status.json", "evaluation.json"):
                shutil.copy(source / name, target / name)
            entropy = entropies[seed] if label == "mappoc_paper" else 0.5
            (target / "progress.csv").write_text(f"time/iterations,train/entropy_mu\n1,0.693\n2,{entropy}\n3,\n")
    return folder


def metrics(folder: Path, label: str, seed: int) -> dict:
    return json.loads((folder / "trials" / label / f"seed{seed}" / "evaluation.json").read_text())["metrics"]


def set_metrics(folder: Path, label: str, seed: int, **values: float) -> None:
    path = folder / "trials" / label / f"seed{seed}" / "evaluation.json"
    evaluation = json.loads(path.read_text())
    evaluation["metrics"].update(values)
    path.write_text(json.dumps(evaluation))


def rows(table: str) -> dict[str, tuple[str, str]]:
    """Claim -> (our result, verdict) of the Markdown table."""
    cells = [line.strip("|").split(" | ") for line in table.splitlines() if line.startswith("| ") and "---" not in line]
    return {claim.strip(): (result, verdict.strip()) for claim, result, verdict in cells[1:]}


def test_the_claims_of_two_seeds_follow_their_evaluations(tmp_path: Path, claims) -> None:
    folder = study_copy(tmp_path, {0: 0.692, 1: 0.3})
    table = rows(claims(folder, "mappoc_paper", "random_skip_paper", "control_first"))
    paper = [metrics(folder, "mappoc_paper", seed) for seed in (0, 1)]
    differences = [m["learned_minus_random_control_return"] for m in paper]
    result, verdict = table["learned timing beats random timing at the same rate"]
    # With two seeds the bootstrap interval runs from the smaller to the larger value.
    assert f"{np.mean(differences):.1f} [{min(differences):.1f}, {max(differences):.1f}]" in result
    assert min(differences) < 0 < max(differences) and verdict == "no evidence: the interval contains zero"
    result, verdict = table["... with about 55 % savings, learned"]
    assert "at the end 0.692, 0.300" in result and verdict.endswith("learned in 1 of 2 seeds")
    # The committed evaluations of seeds 0 and 1: both carry the package (20.5 m and 28.1 m against the
    # periodic trigger's 19.4 m and 26.3 m), neither succeeds.
    assert [round(m["package_travel"], 1) for m in paper] == [20.5, 28.1]
    assert [round(m["periodic_package_travel"], 1) for m in paper] == [19.4, 26.3]
    assert [m["success"] for m in paper] == [0.0, 0.0]
    assert table["MAPPOC learns to carry the package"][1].endswith("2 of 2 seeds carry")
    assert table["about half of the runs succeed"][1] == "no: 0 %"
    assert "(beyond the paper) control_first saves more" in table


@pytest.mark.parametrize(
    ("changes", "claim", "verdict"),
    [
        ({"learned_minus_random_control_return": [5.0, 8.0]}, "learned timing beats", "yes: the interval lies above"),
        ({"learned_minus_random_control_return": [-5.0, -8.0]}, "learned timing beats", "no: the interval lies below"),
        ({"success": [1.0, 0.0]}, "about half of the runs succeed", "yes: 50 %"),
        ({"package_travel": [1.0, 1.0]}, "MAPPOC learns to carry the package", "no: 0 of 2 seeds carry"),
        ({"savings": [0.9, 0.95]}, "... with about 55 % savings, learned", "savings no, learned in 0 of 2 seeds"),
    ],
)
def test_verdicts_follow_their_rules(tmp_path: Path, changes: dict, claim: str, verdict: str, claims) -> None:
    folder = study_copy(tmp_path, {0: 0.692, 1: 0.692}, LABELS[:2])
    for metric, values in changes.items():
        for seed, value in enumerate(values):
            set_metrics(folder, "mappoc_paper", seed, **{metric: value})
    table = rows(claims(folder, "mappoc_paper", "random_skip_paper", None))
    (found,) = [v for c, (_, v) in table.items() if c.startswith(claim)]
    assert found.startswith(verdict)


def test_a_study_without_the_named_algorithms_or_package_travel_is_refused(tmp_path: Path, claims) -> None:
    folder = study_copy(tmp_path, {0: 0.692, 1: 0.692}, LABELS[:2])
    with pytest.raises(ClaimsRefused, match="no finished seed of 'mappoc_paper_overlap'"):
        claims(folder, "mappoc_paper_overlap", "random_skip_paper", None)
    for seed in (0, 1):
        path = folder / "trials" / "mappoc_paper" / f"seed{seed}" / "evaluation.json"
        evaluation = json.loads(path.read_text())
        del evaluation["metrics"]["package_travel"]
        path.write_text(json.dumps(evaluation))
    with pytest.raises(ClaimsRefused, match="no package travel"):
        claims(folder, "mappoc_paper", "random_skip_paper", None)


@pytest.mark.parametrize(
    ("label", "changes", "claim", "verdict"),
    [
        ("random_skip_paper", {"package_travel": [0.0, 0.0]}, "PPO with random skips", "yes: 0 of 2 baseline"),
        ("random_skip_paper", {"package_travel": [99.0, 99.0]}, "PPO with random skips", "no: 2 of 2 baseline"),
        ("control_first", {"savings": [0.5, 0.52]}, "(beyond the paper) control_first", "savings no"),
        ("control_first", {"savings": [0.95, 0.97]}, "(beyond the paper) control_first", "savings yes"),
    ],
)
def test_the_baseline_and_recipe_verdicts_follow_their_rules(
    tmp_path: Path, label: str, changes: dict, claim: str, verdict: str, claims
) -> None:
    folder = study_copy(tmp_path, {0: 0.692, 1: 0.692})
    for metric, values in changes.items():
        for seed, value in enumerate(values):
            set_metrics(folder, label, seed, **{metric: value})
    table = rows(claims(folder, "mappoc_paper", "random_skip_paper", "control_first"))
    (found,) = [v for c, (_, v) in table.items() if c.startswith(claim)]
    assert found.startswith(verdict)


def test_a_finished_trial_without_its_progress_is_refused(tmp_path: Path, claims) -> None:
    folder = study_copy(tmp_path, {0: 0.692, 1: 0.692}, LABELS[:2])
    (folder / "trials" / "mappoc_paper" / "seed1" / "progress.csv").unlink()
    with pytest.raises(ClaimsRefused, match="seed1: finished, but its progress.csv is missing"):
        claims(folder, "mappoc_paper", "random_skip_paper", None)


RATE_STUDY = ROOT / "benchmarks" / "studies" / "multiwalker_rate"


def rate_copy(tmp_path: Path, differences: list[float]) -> Path:
    """Seeds 0 and 1 of the rate study's joint_9375 and seed 0 of periodic_16, with given learned minus best fixed."""
    folder = tmp_path / "multiwalker_rate"
    folder.mkdir()
    shutil.copy(RATE_STUDY / "study.yml", folder / "study.yml")
    for label, seeds in (("joint_9375", (0, 1)), ("periodic_16", (0,))):
        for seed in seeds:
            source, target = RATE_STUDY / "trials" / label / f"seed{seed}", folder / "trials" / label / f"seed{seed}"
            target.mkdir(parents=True)
            for name in ("status.json", "evaluation.json"):
                shutil.copy(source / name, target / name)
    for seed, difference in enumerate(differences):
        set_metrics(folder, "joint_9375", seed, learned_minus_best_fixed_control_return=difference)
    return folder


@pytest.mark.parametrize(
    ("differences", "verdict"),
    [
        ([91.7, -4.0], "no evidence: the interval contains zero (2 seeds)"),
        ([3.0, 5.0], "yes: the interval lies above zero (2 seeds)"),
        ([-3.0, -5.0], "no: the interval lies below zero (2 seeds)"),
    ],
)
def test_the_rate_study_row_compares_the_learned_trigger_with_the_best_fixed_family(
    tmp_path: Path, differences: list[float], verdict: str, run_benchmark_here
) -> None:
    paper = study_copy(tmp_path, {0: 0.692, 1: 0.692}, LABELS[:2])
    rate = rate_copy(tmp_path, differences)
    arguments = [str(paper), "--recipe", "", "--rate-study", str(rate), "--rate-arm", "joint_9375"]
    done = run_benchmark_here("paper_claims.py", *arguments)
    assert done.returncode == 0, done.stderr
    claim = "(beyond the paper) a learned trigger beats the best fixed trigger at the same savings (joint_9375)"
    result, found = rows(done.stdout)[claim]
    assert found == verdict
    low, high = min(differences), max(differences)
    assert (
        f"with the same controller (50 paired episodes per seed) {np.mean(differences):.1f} [{low:.1f}, {high:.1f}]"
        in result
    )
    periodic = metrics(rate, "periodic_16", 0)["control_return"]
    assert f"periodic_16: control return {periodic:.1f}" in result and "P(joint_9375 > periodic_16)" in result


def test_a_rate_study_without_the_arm_or_its_fixed_families_is_refused(tmp_path: Path, run_benchmark_here) -> None:
    paper = study_copy(tmp_path, {0: 0.692, 1: 0.692}, LABELS[:2])
    rate = rate_copy(tmp_path, [1.0, 2.0])
    arguments = [str(paper), "--recipe", "", "--rate-study", str(rate), "--rate-arm"]
    done = run_benchmark_here("paper_claims.py", *arguments, "schedule_first_9375")
    assert done.returncode == 2 and "no finished seed of 'schedule_first_9375'" in done.stderr
    for seed in (0, 1):
        path = rate / "trials" / "joint_9375" / f"seed{seed}" / "evaluation.json"
        evaluation = json.loads(path.read_text())
        del evaluation["metrics"]["learned_minus_best_fixed_control_return"]
        path.write_text(json.dumps(evaluation))
    done = run_benchmark_here("paper_claims.py", *arguments, "joint_9375")
    assert done.returncode == 2 and "compared no fixed trigger family" in done.stderr


def test_a_row_per_results_file_of_triggers_learned_for_frozen_controllers(tmp_path: Path, run_benchmark_here) -> None:
    paper = study_copy(tmp_path, {0: 0.692, 1: 0.692}, LABELS[:2])
    source = json.loads((ROOT / "benchmarks" / "results" / "multiwalker_trigger_rate_9375.json").read_text())[:2]
    for row, difference in zip(source, (-3.0, -5.0), strict=True):
        row["metrics"]["learned_minus_best_fixed_control_return"] = difference
    path = tmp_path / "frozen_9375.json"
    path.write_text(json.dumps(source))
    done = run_benchmark_here("paper_claims.py", str(paper), "--recipe", "", "--frozen", str(path))
    assert done.returncode == 0, done.stderr
    claim = (
        "(beyond the paper) a trigger learned for the frozen controllers of mappoc_paper beats the best fixed "
        "trigger at the same savings (frozen_9375)"
    )
    result, verdict = rows(done.stdout)[claim]
    assert verdict == "no: the interval lies below zero (2 seeds)"
    assert result.startswith("target 0.9375: ") and "with the same controller -4.0 [-5.0, -3.0]" in result
    del source[1]["metrics"]["learned_minus_best_fixed_control_return"]
    path.write_text(json.dumps(source))
    done = run_benchmark_here("paper_claims.py", str(paper), "--recipe", "", "--frozen", str(path))
    assert done.returncode == 2 and "compared no fixed trigger family" in done.stderr
