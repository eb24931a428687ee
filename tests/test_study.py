"""Multi-seed studies: study files, the Ray Tune runner, resumption after a kill, the report."""

from __future__ import annotations

import contextlib
import json
import lzma
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml

import sb3_detc
from sb3_detc import plot
from sb3_detc.evaluation import evaluate_episodes
from sb3_detc.files import replace_atomically
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.plot import PROGRESS_XZ, progress_file, read_progress
from sb3_detc.study import report
from sb3_detc.study.__main__ import main as study_main
from sb3_detc.study.report import report_study, splice, summarise
from sb3_detc.study.runner import prepare_folder, run_study, trials_to_run
from sb3_detc.study.spec import Selection, StudyError, entry_fixed_trigger, load_folder_study, load_study
from sb3_detc.study.trial import (
    FINISHED_FILES,
    MODES,
    PROGRESS_DIGITS,
    SELECTION_FILES,
    code_commit,
    drop_stale_segments,
    read_status,
    trial_folder,
)

ROOT = Path(__file__).resolve().parents[1]

#: A tiny study: the LQR-controlled linear system (one core per trial), 2 algorithms x 2 seeds.
TINY = {
    "env": "sb3_detc/LinearETC-LQR-v0",
    "seeds": [0, 1],
    "n_timesteps": 2048,
    "checkpoint_interval": 1024,
    "evaluation": {"episodes": 3, "seed": 500},
    "algorithms": {"learned": {"algo": "mappoc"}, "random": {"algo": "ppo_random_skip"}},
}

#: The tiny study with a budget per algorithm: the random-skip baseline trains one iteration (1024 steps).
TINY_BUDGETS = {
    **{key: value for key, value in TINY.items() if key != "n_timesteps"},
    "algorithms": {
        "learned": {"algo": "mappoc", "hyperparams": {"n_timesteps": 2048}},
        "random": {"algo": "ppo_random_skip", "hyperparams": {"n_timesteps": 1}},
    },
}


def write_study(folder: Path, content: dict | str, name: str = "study.yml") -> Path:
    path = folder / name
    path.write_text(content if isinstance(content, str) else yaml.safe_dump(content, sort_keys=False))
    return path


def run_command(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sb3_detc.study", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )


@contextlib.contextmanager
def study_process(*args: str, output: int = subprocess.PIPE):
    """The study command running in a process group of its own, killed at the end of the context if still running."""
    process = subprocess.Popen(
        [sys.executable, "-m", "sb3_detc.study", *args],
        cwd=ROOT,
        stdout=output,
        stderr=output,
        text=True,
        start_new_session=True,
    )
    try:
        yield process
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


def wait_for(process: subprocess.Popen, ready, what: str, timeout: float = 300) -> float:
    """Poll ``ready()`` until it is true; fail if the process ends first or after ``timeout`` seconds.

    :return: the deadline (``time.monotonic()`` clock)
    """
    deadline = time.monotonic() + timeout
    while not ready():
        assert process.poll() is None, (f"the study ended before {what}", process.communicate())
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.2)
    return deadline


# ----------------------------------------------------------------------------- study files
@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"env": "sb3_detc/NoSuchEnv-v0"}, "unknown environment"),
        ({"algorithms": {"a": {"algo": "mapoc"}}}, "unknown algorithm 'mapoc'"),
        ({"algorithms": {"a": {"algo": "mappoc", "hyperparams": {"learning_rat": 1e-3}}}}, "learning_rat"),
        ({"algorithms": {"a": {"algo": "mappoc", "colour": 1}}}, "unknown key 'colour'"),
        ({"algorithms": {"a/b": {"algo": "mappoc"}}}, "label must be a non-empty name without '/'"),
        ({"algorithms": {".ray": {"algo": "mappoc"}}}, "not starting with '.', got '.ray'"),
        ({"seeds": [0, 0]}, "seed twice"),
        ({"seeds": "zero"}, "list of integers"),
        ({"n_timesteps": -5}, "'n_timesteps' must be an integer >= 1"),
        ({"evaluation": {"episodes": 0}}, "episodes"),
        ({"evaluation": {"episods": 3}}, "unknown key 'episods'"),
        ({"budget": 3}, "unknown key 'budget'"),
        ({"algorithms": {}}, "'algorithms' must be a non-empty mapping"),
        (
            {"algorithms": {"a": {"algo": "mappoc", "hyperparams": {"normalize": "dict(norm_obs_keys=['local'])"}}}},
            "does not carry VecNormalize statistics",
        ),
    ],
)
def test_bad_study_files_are_refused_with_the_key_in_the_message(tmp_path, change, message):
    path = write_study(tmp_path, {**TINY, **change})
    with pytest.raises(StudyError, match=message):
        load_study(path)


def test_an_algorithm_without_steps_is_refused(tmp_path):
    budgets = {key: value for key, value in TINY.items() if key != "n_timesteps"}
    path = write_study(
        tmp_path, {**budgets, "algorithms": {"a": {"algo": "mappoc", "hyperparams": {"n_timesteps": 0}}}}
    )
    with pytest.raises(StudyError, match="algorithm 'a' trains 0 steps"):
        load_study(path)


def test_malformed_yaml_and_missing_file(tmp_path):
    with pytest.raises(StudyError, match="not valid YAML at line 3"):
        load_study(write_study(tmp_path, "env: x\nseeds: [0, 1\n"))
    with pytest.raises(StudyError, match="not found"):
        load_study(tmp_path / "nothing.yml")


def test_a_study_file_names_entries_overrides_and_seeds(tmp_path):
    spec = load_study(
        write_study(
            tmp_path,
            {
                **TINY,
                "algorithms": {
                    "learned": {"algo": "mappoc", "seeds": [3], "hyperparams": {"learning_rate": 5e-4}},
                    "random": {"algo": "ppo_random_skip", "cpus": 2},
                },
            },
        )
    )
    learned, random = spec.algorithms
    assert learned.seeds == (3,) and random.seeds == (0, 1)
    assert learned.entry["learning_rate"] == 5e-4 and learned.entry["n_envs"] == 8  # the rest from the entry
    assert learned.cpus == 1  # no rollout workers
    assert random.cpus == 2  # the cores it asked for
    assert [t.name for t in spec.trials()] == ["learned/seed3", "random/seed0", "random/seed1"]
    assert spec.budget(learned) == 2048


def test_the_shipped_study_files_load():
    shipped = sorted((ROOT / "sb3_detc" / "studies").glob("*.yml"))
    assert {path.name for path in shipped} >= {"multiwalker_paper.yml", "linear.yml", "linear_lqr.yml"}
    for path in shipped:
        spec = load_study(path)
        assert all(len(a.seeds) >= 5 for a in spec.algorithms), path
    paper = load_study(ROOT / "sb3_detc" / "studies" / "multiwalker_paper.yml")
    assert paper.episodes >= 50
    assert {a.label: a.cpus for a in paper.algorithms} == {
        "mappoc_paper": 2,
        "random_skip_paper": 2,
        "control_first": 2,
        "mappoc_paper_overlap": 2,
    }
    assert all("overlap_rollouts" not in a.hyperparams for a in paper.algorithms)  # removed in 0.2.0
    assert all(paper.budget(a) == 6_144_000 for a in paper.algorithms)
    rate = load_study(ROOT / "sb3_detc" / "studies" / "linear_lqr_rate.yml")
    assert rate.fixed_families == ("periodic", "periodic_staggered", "send_on_delta_max_age", "predictive")
    assert {a.label: a.hyperparams["target_savings"] for a in rate.algorithms} == {
        "target_80": 0.8,
        "target_90": 0.9,
        "target_95": 0.95,
        "predicted_90": 0.9,
        "predicted_held_90": 0.9,
        "predicted_held_90_short": 0.9,
        "predicted_held_90_long": 0.9,
        "predicted_held_90_distance": 0.9,
        "predictive_first_90": 0.9,
        "predictive_first_90_gamma99": 0.9,
        "predictive_first_90_raw": 0.9,
        "predictive_imitated_90": 0.9,
        "predictive_first_90_noent": 0.9,
        "predictive_first_90_noent_return": 0.9,
        "predictive_first_90_quantile": 0.9,
        "predicted_held_90_quantile": 0.9,
        "predictive_first_90_lambda50": 0.9,
        "predictive_first_90_lambda0": 0.9,
        "predictive_first_90_lambda80": 0.9,
        "predicted_held_90_lambda50": 0.9,
        "predictive_first_90_lambda50_switch200": 0.9,
        "predictive_first_90_lambda50_clip05": 0.9,
        "predictive_first_90_lambda50_select": 0.9,
        "predictive_first_90_replayed": 0.9,
        "predictive_first_90_replayed_noent": 0.9,
        "predictive_first_90_replayed_value": 0.9,
        "predictive_first_90_replayed_noent_select": 0.9,
        "predictive_first_90_replayed_expected_noent": 0.9,
        "predictive_first_90_replayed_expected_noent_anneal": 0.9,
        "predictive_first_90_replayed_expected_noent_anneal_1m": 0.9,
        "predictive_first_90_replayed_expected_noent_anneal_gradient": 0.9,
        "predictive_first_90_replayed_expected_noent_anneal_gradient_1m": 0.9,
    }
    selected = {a.label: a.selection for a in rate.algorithms if a.selection is not None}
    assert set(selected) == {"predictive_first_90_lambda50_select", "predictive_first_90_replayed_noent_select"}
    assert all(s.every == 25600 and s.episodes == 50 for s in selected.values())
    assert rate.validation_seeds(50) == list(range(10050, 10100))  # after the evaluation's 50 episodes
    # the receivers' predictions shown, at five times the others' budget, at the same and at twenty times
    held = {a.label: a for a in rate.algorithms if a.label.startswith("predicted_held")}
    assert all(a.hyperparams["env_kwargs"]["predicted_held"] for a in held.values())
    assert rate.budget(held["predicted_held_90"]) == 5 * rate.budget(held["predicted_held_90_short"]) == 500_000
    assert rate.budget(held["predicted_held_90_long"]) == 2_000_000
    assert held["predicted_held_90_long"].hyperparams["broadcast_ent_coef"] == 0.01
    assert "option_distance_scale=5.0" in held["predicted_held_90_distance"].hyperparams["policy_kwargs"]
    assert rate.budget(held["predicted_held_90_distance"]) == 500_000
    # started as predictive triggering (send-on-delta on the shown predictions), then learned
    first = next(a for a in rate.algorithms if a.label == "predictive_first_90")
    assert first.hyperparams["env_kwargs"]["predicted_held"] and rate.budget(first) == 500_000
    assert first.hyperparams["callback"][0] == {"sb3_detc.callbacks.DeltaFirstCallback": {"switch": 50, "delta": 0.21}}
    variants = {a.label: a.hyperparams for a in rate.algorithms if a.label.startswith("predictive_first_90_")}
    assert variants["predictive_first_90_gamma99"] == {**first.hyperparams, "gamma": 0.99}
    assert variants["predictive_first_90_raw"] == {**first.hyperparams, "normalize_broadcast_advantage": False}
    no_bonus = {**first.hyperparams, "broadcast_ent_coef": 0.0}
    assert variants["predictive_first_90_noent"] == no_bonus
    assert variants["predictive_first_90_noent_return"] == {**no_bonus, "broadcast_advantage": "return"}
    quantile = {key: value for key, value in first.hyperparams.items() if key != "broadcast_price_lr"}
    assert variants["predictive_first_90_quantile"] == {**quantile, "broadcast_price_rule": "quantile"}
    assert variants["predictive_first_90_lambda50"] == {**first.hyperparams, "gae_lambda": 0.5}
    assert variants["predictive_first_90_lambda0"] == {**first.hyperparams, "gae_lambda": 0.0}
    assert variants["predictive_first_90_lambda80"] == {**first.hyperparams, "gae_lambda": 0.8}
    lambda50 = variants["predictive_first_90_lambda50"]
    assert variants["predictive_first_90_lambda50_clip05"] == {**lambda50, "clip_range_broadcast": 0.05}
    replayed = {"broadcast_advantage": "replayed", "replay_share": 0.125, "replay_horizon": 40}
    assert variants["predictive_first_90_replayed"] == {**lambda50, **replayed}
    no_replayed_bonus = {**lambda50, **replayed, "broadcast_ent_coef": 0.0}
    assert variants["predictive_first_90_replayed_noent"] == no_replayed_bonus
    assert variants["predictive_first_90_replayed_noent_select"] == no_replayed_bonus
    expected = {**no_replayed_bonus, "broadcast_advantage": "replayed_expected"}
    assert variants["predictive_first_90_replayed_expected_noent"] == expected
    annealed = {**expected, "learning_rate": "lin_1e-3"}
    assert variants["predictive_first_90_replayed_expected_noent_anneal"] == annealed
    twice = {**annealed, "n_timesteps": 1_000_000}
    assert variants["predictive_first_90_replayed_expected_noent_anneal_1m"] == twice
    chosen = {**annealed, "replay_choice": "gradient"}
    assert variants["predictive_first_90_replayed_expected_noent_anneal_gradient"] == chosen
    assert variants["predictive_first_90_replayed_expected_noent_anneal_gradient_1m"] == {
        **chosen,
        "n_timesteps": 1_000_000,
    }
    fitted = {"broadcast_advantage": "replayed_value", "replay_temperature": 0.1}
    assert variants["predictive_first_90_replayed_value"] == {**no_replayed_bonus, **fitted}
    later = {"sb3_detc.callbacks.DeltaFirstCallback": {"switch": 200, "delta": 0.21}}
    assert variants["predictive_first_90_lambda50_switch200"] == {
        **lambda50,
        "callback": [later, *first.hyperparams["callback"][1:]],
    }
    assert held["predicted_held_90_lambda50"].hyperparams == {
        **held["predicted_held_90_distance"].hyperparams,
        "gae_lambda": 0.5,
    }
    imitated = next(a for a in rate.algorithms if a.label == "predictive_imitated_90")
    assert imitated.hyperparams == {**first.hyperparams, "n_timesteps": 51_200}  # stops at the switch
    joint = load_study(ROOT / "sb3_detc" / "studies" / "multiwalker_rate.yml")
    assert joint.fixed_families == ("periodic", "periodic_staggered", "send_on_delta_max_age")
    assert joint.episodes >= 50
    learned, periodic, schedule_first = joint.algorithms
    assert learned.hyperparams["target_savings"] == 0.9375 and learned.cpus == 2
    assert joint.budget(learned) == 6_144_000 and len(learned.seeds) == 5  # the paper's budget
    # the schedule at the same savings, its controller trained for it with the same settings otherwise
    assert repr(entry_fixed_trigger(periodic.entry)) == "PeriodicTrigger(period=16, staggered=False)"
    assert "target_savings" not in periodic.hyperparams and joint.budget(periodic) == 6_144_000
    assert periodic.hyperparams["policy_kwargs"] == learned.hyperparams["policy_kwargs"]
    # the schedule for two thirds of the budget, then the learned trigger started as the schedule
    stages = schedule_first.hyperparams["callback"][0]["sb3_detc.callbacks.ScheduleFirstCallback"]
    assert stages == {"switch": 2000, "period": 16} and joint.budget(schedule_first) == 6_144_000
    assert schedule_first.hyperparams["policy_kwargs"] == learned.hyperparams["policy_kwargs"]
    assert schedule_first.hyperparams["target_savings"] == 0.9375
    window = load_study(ROOT / "sb3_detc" / "studies" / "multiwalker_window.yml")
    assert window.fixed_families == joint.fixed_families and window.episodes == joint.episodes
    (learned_in_window,) = window.algorithms
    assert window.budget(learned_in_window) == 6_144_000 and len(learned_in_window.seeds) == 5
    # joint_9375 with the window, starting at about one message in 16 steps inside it
    same = {"broadcast_prob_init=0.0625, option_age_scale=0.1)": "broadcast_prob_init=0.125, option_age_scale=0.1"}
    kwargs = learned.hyperparams["policy_kwargs"].replace(*next(iter(same.items())))
    assert learned_in_window.hyperparams == {
        **learned.hyperparams,
        "policy_kwargs": kwargs + ", broadcast_interval=(8, 24))",
    }
    assert learned_in_window.selection == Selection(every=307_200, episodes=20)  # the validation-best policy kept
    assert window.validation_seeds(20) == list(range(10050, 10070))


def test_command_line_bad_input_is_one_line_with_exit_code_2(tmp_path, capsys):
    path = write_study(tmp_path, {**TINY, "env": "sb3_detc/NoSuchEnv-v0"})
    result = run_command("run", str(path), "--dir", str(tmp_path / "out"))  # as a user runs it
    assert result.returncode == 2
    assert result.stderr.strip().startswith("python -m sb3_detc.study: error:")
    assert len(result.stderr.strip().splitlines()) == 1
    path = write_study(tmp_path, TINY)
    for arguments, message in (
        (["report", str(tmp_path / "nowhere")], "not a study folder"),
        (["run", str(path), "--dir", str(tmp_path / "out"), "--cpus", "0"], "cpus must be a positive integer"),
        (["run", str(path), "--dir", str(tmp_path / "out"), "--cpus", "2", "--address", "auto"], "not both"),
    ):
        with pytest.raises(SystemExit) as stop:
            study_main(arguments)
        error = capsys.readouterr().err
        assert stop.value.code == 2 and message in error, error
        assert len(error.strip().splitlines()) == 1


def test_a_folder_of_another_study_is_refused(tmp_path):
    folder = tmp_path / "out"
    folder.mkdir()
    write_study(folder, {**TINY, "seeds": [7]})
    with pytest.raises(SystemExit) as stop:
        study_main(["run", str(write_study(tmp_path, TINY)), "--dir", str(folder)])
    assert stop.value.code == 2


def test_a_study_folder_keeps_the_hyperparameter_files_it_names(tmp_path):
    """The folder is read with its copy of a ``conf`` file, without the study's own files; a changed file is refused."""
    source = tmp_path / "source"
    source.mkdir()
    conf = source / "mine.yml"
    conf.write_text((sb3_detc.zoo.HYPERPARAMS_DIR / "mappoc.yml").read_text())
    study = {**TINY, "algorithms": {"mine": {"algo": "mappoc", "conf": "mine.yml"}}}
    folder = prepare_folder(load_study(write_study(source, study)), tmp_path / "out")
    assert (folder / "conf" / "mine.yml").read_text() == conf.read_text()
    conf.write_text(conf.read_text() + "\n# changed\n")
    with pytest.raises(StudyError, match="mine.yml changed since the trials"):
        prepare_folder(load_study(source / "study.yml"), folder)
    conf.unlink()  # the folder alone: as committed, on another machine
    assert load_folder_study(folder).algorithms[0].conf == folder / "conf" / "mine.yml"
    with pytest.raises(StudyError, match="not a study folder"):
        load_folder_study(tmp_path)
    absolute = {**TINY, "algorithms": {"mine": {"algo": "mappoc", "conf": str(conf)}}}
    (folder / "conf" / "mine.yml").rename(conf)
    old = tmp_path / "old"  # a folder made before folders kept copies: the path the study file gives
    old.mkdir()
    write_study(old, absolute)
    assert load_folder_study(old).algorithms[0].conf == conf
    module = {**TINY, "algorithms": {"mine": {"algo": "mappoc", "conf": "my_package.hyperparams"}}}
    with pytest.raises(StudyError, match="'conf' must name a .yml, .yaml or .py file"):
        load_study(write_study(tmp_path, module))


def test_a_folder_another_run_uses_is_refused(tmp_path, capsys):
    fcntl = pytest.importorskip("fcntl")
    study = write_study(tmp_path, TINY)
    folder = prepare_folder(load_study(study), tmp_path / "out")
    with open(folder / ".lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as a running study holds it
        with pytest.raises(SystemExit) as stop:
            study_main(["run", str(study), "--dir", str(folder)])
    assert stop.value.code == 2 and "another run or evaluation of a study uses" in capsys.readouterr().err
    assert not any((folder / "trials").glob("*/*/status.json"))


def test_an_address_that_does_not_answer_is_reported(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        study_main(
            ["run", str(write_study(tmp_path, TINY)), "--dir", str(tmp_path / "out"), "--address", "127.0.0.1:1"]
        )
    assert stop.value.code == 2
    assert "does not answer" in capsys.readouterr().err


def test_a_local_ray_that_fails_to_start_keeps_its_error_and_frees_the_folder(tmp_path, monkeypatch):
    """Not a bad input: the error itself reaches the caller (the command line prints its traceback)."""
    ray = pytest.importorskip("ray")

    def fail(**kwargs):
        raise RuntimeError("no room for the object store")

    monkeypatch.setattr(ray, "init", fail)
    study, out = load_study(write_study(tmp_path, TINY)), tmp_path / "out"
    with pytest.raises(RuntimeError, match="no room for the object store"):
        run_study(study, out)
    with pytest.raises(RuntimeError, match="no room for the object store"):  # the lock was let go
        run_study(study, out)
    assert not (out / ".stop").exists() and not any((out / "trials").glob("*/*/status.json"))


# ----------------------------------------------------------------------------- running and reporting
@pytest.fixture(scope="module")
def finished_study(tmp_path_factory):
    """The tiny study with a budget per algorithm, run once through the command line."""
    folder = tmp_path_factory.mktemp("study")
    path = write_study(folder, TINY_BUDGETS, "tiny.yml")
    result = run_command("run", str(path), "--dir", str(folder / "out"))
    assert result.returncode == 0, result.stdout + result.stderr
    return path, folder / "out", result


def test_a_study_runs_every_trial_through_ray_and_evaluates_it(finished_study):
    path, out, result = finished_study
    assert "[study] 4 done, 0 running, 0 pending, 0 failed" in result.stdout
    # the longest trials first: both seeds of the 2048-step algorithm start before the baseline's
    first_pair = next(line for line in result.stdout.splitlines() if " 2 running (" in line)
    assert "learned/seed0" in first_pair and "learned/seed1" in first_pair, result.stdout
    spec = load_study(path)
    for trial in spec.trials():
        folder = trial_folder(out, trial)
        status = read_status(folder)
        budget = 2048 if trial.algorithm.label == "learned" else 1024  # one iteration of 1024 steps
        assert status["status"] == "done" and status["timesteps"] == budget
        # the final policy, its evaluation, its status and its compressed log; no checkpoint, no segments
        assert sorted(p.name for p in folder.iterdir()) == sorted(FINISHED_FILES)
        # where it trained; Ray's workers get OpenMP's passive waiting unless the caller chose a policy
        [machine] = status["attempts"]
        assert machine["start_timesteps"] == 0
        assert machine["omp_wait_policy"] == os.environ.get("OMP_WAIT_POLICY", "PASSIVE")
        assert machine["torch_threads"] == 1 and machine["cores"] == os.cpu_count()
        assert machine["commit"] == code_commit() and machine["sb3_detc"] == sb3_detc.__version__
        evaluation = json.loads((folder / "evaluation.json").read_text())
        learns = trial.algorithm.label == "learned"  # only a policy that learned its options has their mode
        modes = [mode for mode in MODES if mode != "thresholded" and (learns or mode != "mode")]  # no families
        assert set(evaluation["modes"]) == set(modes)
        for mode in modes:
            assert len(evaluation["modes"][mode]["control_return"]) == 3
        assert evaluation["modes"]["periodic"]["savings"] == 0.0
        assert evaluation["modes"]["never"]["savings"] == 1.0
        # the same seeded episodes: never broadcasting is the same for the same controller (LQR here)
        never = evaluation["modes"]["never"]["control_return"]
        assert (
            never
            == json.loads((trial_folder(out, spec.trials()[0]) / "evaluation.json").read_text())["modes"]["never"][
                "control_return"
            ]
        )


def test_evaluating_a_study_again_rewrites_the_evaluations_of_the_chosen_finished_trials(finished_study, tmp_path):
    _, out, _ = finished_study
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    learned = copy / "trials" / "learned" / "seed0" / "evaluation.json"
    random = copy / "trials" / "random" / "seed0" / "evaluation.json"
    learned.write_text('{"stale": true}\n')
    random_stamp = random.stat().st_mtime_ns
    result = run_command("evaluate", str(copy), "--algorithms", "learned")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "[study] evaluating 2 finished of 2 trials" in result.stdout
    assert "[study] learned/seed0: control return" in result.stdout
    # the protocol is seeded: the evaluation is the one the run wrote, step count included
    assert learned.read_text() == (out / "trials" / "learned" / "seed0" / "evaluation.json").read_text()
    assert random.stat().st_mtime_ns == random_stamp  # not chosen
    # a trial whose evaluation fails is reported with its traceback; the others go on, the exit code says so;
    # two at once, each in a process of its own, with the same evaluations
    (copy / "trials" / "learned" / "seed1" / "policy.pt").unlink()
    random.write_text('{"stale": true}\n')
    failed = run_command("evaluate", str(copy), "--cpus", "2")
    assert failed.returncode == 1
    assert "[study] learned/seed1: evaluation failed" in failed.stdout and "FileNotFoundError" in failed.stderr
    assert "[study] random/seed1: control return" in failed.stdout and " of 4)" in failed.stdout
    assert "[study] 1 evaluation(s) failed: learned/seed1" in failed.stdout
    assert random.read_text() == (out / "trials" / "random" / "seed0" / "evaluation.json").read_text()
    assert learned.read_text() == (out / "trials" / "learned" / "seed0" / "evaluation.json").read_text()
    refused = run_command("evaluate", str(copy), "--algorithms", "nope")
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == [
        f"python -m sb3_detc.study: error: {copy} has no algorithm 'nope'; its algorithms: ['learned', 'random']"
    ]
    refused = run_command("evaluate", str(copy), "--cpus", "0")
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == [
        "python -m sb3_detc.study: error: cpus must be a positive integer, got 0"
    ]


def test_a_run_can_be_limited_to_some_algorithms(tmp_path, capsys):
    study = {**TINY, "seeds": [0], "n_timesteps": 1024}
    path, out = write_study(tmp_path, study), tmp_path / "out"
    with pytest.raises(SystemExit) as refused:
        study_main(["run", str(path), "--dir", str(out), "--algorithms", "random", "nope"])
    assert refused.value.code == 2 and not out.exists()  # checked before the folder is made
    assert capsys.readouterr().err.strip().splitlines() == [
        f"python -m sb3_detc.study: error: the study {path} has no algorithm 'nope'; its algorithms: "
        "['learned', 'random']"
    ]
    result = run_command("run", str(path), "--dir", str(out), "--algorithms", "random", "random")
    assert result.returncode == 0, result.stdout + result.stderr  # every trial it was asked to run is done
    assert "1 trials: 0 done, 1 to run" in result.stdout  # a repeated label runs its trials once
    assert "other algorithms' trials: the same command without --algorithms" in result.stdout
    assert read_status(out / "trials" / "random" / "seed0")["status"] == "done"
    assert read_status(out / "trials" / "learned" / "seed0")["status"] == "pending"
    study_main(["run", str(path), "--dir", str(out), "--algorithms", "random"])  # nothing to run: no Ray
    assert "all 1 trials of random are done" in capsys.readouterr().out
    # the folder's own study decides, whatever the labels
    other = write_study(tmp_path, {**study, "seeds": [1]}, name="other.yml")
    with pytest.raises(SystemExit) as mixed:
        study_main(["run", str(other), "--dir", str(out), "--algorithms", "random"])
    assert mixed.value.code == 2 and "another study" in capsys.readouterr().err
    for labels in ("random", []):  # the API refuses a bare string and an empty list
        with pytest.raises(StudyError, match="give a list of one or more algorithm labels"):
            run_study(load_study(path), out, labels=labels)


def test_running_a_finished_study_again_trains_nothing(finished_study):
    path, out, _ = finished_study
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("evaluation.json")}
    result = run_command("run", str(path), "--dir", str(out))
    assert result.returncode == 0 and "all 4 trials are done" in result.stdout
    assert {p: p.stat().st_mtime_ns for p in out.rglob("evaluation.json")} == stamps


def test_the_report_equals_a_hand_computation_from_the_evaluation_files(finished_study):
    path, out, _ = finished_study
    text = report_study(out, plot=True)
    summary = json.loads((out / "summary.json").read_text())
    spec = load_study(path)
    for algorithm in spec.algorithms:
        evaluations = [
            json.loads((trial_folder(out, t) / "evaluation.json").read_text())
            for t in spec.trials()
            if t.algorithm.label == algorithm.label
        ]
        control = [np.mean(e["modes"]["learned"]["control_return"]) for e in evaluations]
        random = [np.mean(e["modes"]["random_same_rate"]["control_return"]) for e in evaluations]
        paired = [
            np.mean(
                np.subtract(e["modes"]["learned"]["control_return"], e["modes"]["random_same_rate"]["control_return"])
            )
            for e in evaluations
        ]
        entry = summary[algorithm.label]
        # the files keep every episode's returns at float32 precision; the metrics were computed before, at full
        close = {"rel": 1e-6, "abs": 1e-5}
        assert entry["mean"]["control_return"] == pytest.approx(np.mean(control), **close)
        assert entry["mean"]["random_same_rate_control_return"] == pytest.approx(np.mean(random), **close)
        assert entry["mean"]["learned_minus_random_control_return"] == pytest.approx(np.mean(paired), **close)
        assert entry["mean"]["savings"] == pytest.approx(
            np.mean(
                [
                    1 - sum(e["modes"]["learned"]["broadcasts"]) / (3 * sum(e["modes"]["learned"]["length"]))
                    for e in evaluations
                ]
            )
        )
        # With two seeds, a bootstrap resample of the mean takes each seed's value alone with
        # probability 1/4 each: the 95 % percentile interval runs from the smaller to the larger.
        assert entry["ci95"]["control_return"] == pytest.approx([min(control), max(control)], **close)
        assert entry["ci95"]["learned_minus_random_control_return"] == pytest.approx(
            [min(paired), max(paired)], **close
        )
        assert set(entry["seeds"]) == {"0", "1"}
        assert {"timesteps", "return", "savings", "periodic_control_return", "never_control_return"} <= set(
            entry["mean"]
        )
        assert f"## {algorithm.label} ({algorithm.algo}): 2 of 2 seeds finished" in text
    assert (out / "curves.png").stat().st_size > 0
    assert (out / "estimates.png").stat().st_size > 0 and f"Final policies: {out / 'estimates.png'}" in text
    assert "Not drawn (trained one iteration): random." in text  # a single point is no curve
    pairs = {(row["better"], row["than"]) for row in summary["comparisons"]}
    assert pairs == {("learned", "random"), ("random", "learned")}
    result = run_command("report", str(out), "--no-plot")
    assert result.returncode == 0 and "Probability of improvement" in result.stdout


#: The committed study folders.
COMMITTED = sorted((ROOT / "benchmarks" / "studies").glob("*/study.yml"))


#: What an unfinished trial carries to resume on another machine (its log so far may come too).
RESUME_FILES = {"checkpoint.zip", "checkpoint.json", "segments", "status.json"}


def test_a_committed_study_keeps_what_its_report_reads_and_nothing_else():
    """A finished trial keeps what the report reads; an unfinished one what resuming needs, not counted in the size."""
    trials = [trial for study in COMMITTED for trial in study.parent.glob("trials/*/*")]
    assert COMMITTED and trials
    unfinished = [trial for trial in trials if read_status(trial)["status"] != "done"]
    for trial in trials:
        names = {p.name for p in trial.iterdir()}
        if trial in unfinished:  # with a selection, also its record and kept policy
            assert RESUME_FILES <= names <= RESUME_FILES | {PROGRESS_XZ, *SELECTION_FILES}, trial
        else:  # with a selection, also its record
            assert sorted(names - {"selection.json"}) == sorted(FINISHED_FILES), trial
    studies = ROOT / "benchmarks" / "studies"  # not the runs' own hidden folders (Ray's session, locks)
    kept = [
        p
        for p in studies.rglob("*")
        if p.is_file() and not any(x.startswith(".") for x in p.relative_to(studies).parts)
    ]
    size = sum(p.stat().st_size for p in kept if not any(trial in p.parents for trial in unfinished))
    # Most of it is the trials' final policies (about 66 KiB on the linear system, 0.8 MiB on Multiwalker), kept
    # so that every trial can be evaluated again when the protocol changes; the bound catches what should not be kept.
    assert size < 80 * 2**20, f"benchmarks/studies holds {size / 2**20:.0f} MiB"


def test_the_report_of_a_committed_study_regenerates_from_its_kept_files(tmp_path):
    """Tables and figures from the trials' evaluations and compressed logs, as committed."""
    source = ROOT / "benchmarks" / "studies" / "linear_lqr"
    folder = tmp_path / "linear_lqr"
    for path in source.rglob("*"):  # the trials' files and the study file; not the report and its figures
        if path.is_file() and (path.name in FINISHED_FILES or path.name == "study.yml"):
            (folder / path.relative_to(source)).parent.mkdir(parents=True, exist_ok=True)
            (folder / path.relative_to(source)).write_bytes(path.read_bytes())
    text = report_study(folder, plot=True)
    # the same text, "Curves: ..." included: every algorithm's curves were drawn from its logs
    expected = (source / "report.md").read_text().replace(str(source.relative_to(ROOT)), str(folder))
    assert text + "\n" == expected and f"Curves: {folder / 'curves.png'}" in text


def test_a_compressed_log_reads_as_the_plain_one(tmp_path):
    text = "time/iterations,time/total_timesteps,comm/option_ent_coef,curriculum/phase\n1,1024,0.1,a\n2,2048,,b\n"
    plain, compressed = tmp_path / "plain", tmp_path / "compressed"
    plain.mkdir()
    compressed.mkdir()
    (plain / "progress.csv").write_text(text)
    (compressed / PROGRESS_XZ).write_bytes(lzma.compress(text.encode()))
    assert progress_file(compressed) == compressed / PROGRESS_XZ and progress_file(tmp_path) is None
    expected, columns = read_progress(plain), read_progress(compressed)
    assert columns.keys() == expected.keys() and "comm/broadcast_ent_coef" in columns  # renamed as well
    for key, values in expected.items():
        np.testing.assert_array_equal(columns[key], values)


VOI = "multiwalker_value_of_information.py"
#: A results page: the marks between which the value of information sweep puts its table, text around them.
VOI_PAGE = (
    "above\n<!-- multiwalker_value_of_information.py: start -->\n<!-- multiwalker_value_of_information.py: end -->\n"
    "below\n"
)


def test_the_value_of_information_sweep_refuses_a_results_file_it_cannot_read(tmp_path, run_benchmark_here):
    write_study(tmp_path, TINY)  # a study folder without trials
    for text in ("{half", "[1, 2]"):
        (tmp_path / "broken.json").write_text(text)
        done = run_benchmark_here(VOI, str(tmp_path), "--out", str(tmp_path / "broken.json"))
        assert done.returncode == 2 and "not the JSON of an earlier sweep" in done.stderr
        assert "Traceback" not in done.stderr and (tmp_path / "broken.json").read_text() == text


def test_the_value_of_information_sweep_runs_fixed_triggers_and_the_mode_of_learned_options(
    finished_study, tmp_path, run_benchmark, run_benchmark_here
):
    _, out, _ = finished_study
    results_file = tmp_path / "results" / "voi.json"  # a folder that does not exist yet
    command = [str(out), "--out", str(results_file), "--rates", "0.5", "--periods", "2"]
    command += ["--deltas", "0", "1e9"]  # send-on-delta at every change and never
    printed = run_benchmark(VOI, *command, check=True).stdout
    results = json.loads(results_file.read_text())
    spec = load_study(out / "study.yml")
    assert set(results) == {trial.name for trial in spec.trials()}
    seeds = [spec.eval_seed + k for k in range(spec.episodes)]
    for trial in spec.trials():
        rows = results[trial.name]
        learned = json.loads((trial_folder(out, trial) / "evaluation.json").read_text())["modes"]["learned"]
        assert rows["learned"]["control_return"] == pytest.approx(np.mean(learned["control_return"]))
        assert rows["periodic 2"]["savings"] == pytest.approx(0.5, abs=0.1)
        assert rows["send-on-delta 0"]["savings"] < 0.2 and rows["send-on-delta 1e+09"]["savings"] == 1.0
        # Only a trial that learned its options has their mode: the policy's most likely options.
        assert ("mode of mu" in rows) == (trial.algorithm.label == "learned")
        if "mode of mu" in rows:
            policy = MlpHybridPolicy.load(str(trial_folder(out, trial) / "policy.pt"), device="cpu")
            episodes = evaluate_episodes(policy, gym.make(spec.env), seeds, deterministic=True, sample_options=False)
            assert rows["mode of mu"]["savings"] == pytest.approx(episodes.savings)
            assert rows["mode of mu"]["control_return"] == pytest.approx(np.mean(episodes.control_returns))
    assert "### learned" in printed and "| mode of mu | 2 |" in printed
    # a further period for one algorithm's trials only, nothing else evaluated again
    only = run_benchmark(
        VOI,
        str(out),
        "--out",
        str(results_file),
        "--rates",
        "--periods",
        "3",
        "--deltas",
        "--algorithms",
        "learned",
        check=True,
    )
    more = json.loads(results_file.read_text())
    for trial in spec.trials():
        added = set(more[trial.name]) - set(results[trial.name])
        assert added == ({"periodic 3"} if trial.algorithm.label == "learned" else set()), trial.name
    assert only.stdout.count(" periodic 3: control return") == sum(
        t.algorithm.label == "learned" for t in spec.trials()
    )
    results_file.write_text(json.dumps(results))  # as before, for what follows
    bad = run_benchmark_here(VOI, str(out), "--out", str(results_file), "--algorithms", "nothing")
    assert bad.returncode == 2 and "no algorithm nothing in the study" in bad.stderr
    # A trigger that only a later seed has still counts, over the seeds that have it (the study's
    # file alone: no trial finished there, nothing evaluated)
    first = next(trial.name for trial in spec.trials() if trial.algorithm.label == "learned")
    partial = {
        name: {t: m for t, m in rows.items() if name != first or t != "periodic 2"} for name, rows in results.items()
    }
    (tmp_path / "bare").mkdir()
    (tmp_path / "bare" / "study.yml").write_text((out / "study.yml").read_text())
    (tmp_path / "partial.json").write_text(json.dumps(partial))
    summary = run_benchmark(VOI, str(tmp_path / "bare"), "--out", str(tmp_path / "partial.json"), "--deltas")
    assert summary.returncode == 0, summary.stderr
    learned_table = summary.stdout.split("### learned")[1].split("###")[0]
    assert "| periodic 2 | 1 |" in learned_table and "| random 0.5 | 2 |" in learned_table
    assert json.loads((tmp_path / "partial.json").read_text()) == partial
    # Run again: nothing left to evaluate, the same results; the algorithms side by side on a page.
    page = tmp_path / "README.md"
    page.write_text(VOI_PAGE)
    side_by_side = [*command, "--plot", "--splice", str(page), "--columns", "random", "learned"]
    again = run_benchmark(VOI, *side_by_side, check=True).stdout
    assert "control return" not in again.split("### ")[0] and json.loads(results_file.read_text()) == results
    assert (
        results_file.with_suffix(".png").stat().st_size > 0 and f"Figure: {results_file.with_suffix('.png')}" in again
    )
    text = page.read_text()
    assert text.startswith("above\n") and text.endswith("below\n") and f"on the same {spec.episodes} episodes" in text
    table = [line.split(" | ") for line in text.splitlines() if line.startswith("| ") and "---" not in line]
    assert table[0] == ["| trigger", "savings", "`random` (2 seeds)", "`learned` (2 seeds) |"]
    rows = {cells[0][2:]: cells[1:] for cells in table[1:]}
    assert set(rows) == {
        "random 0.5",
        "periodic 2",
        "send-on-delta 0",
        "send-on-delta 1e+09",
        "learned (random)",
        "learned (learned)",
        "mode of mu (learned)",
    }
    assert [float(cells[1]) for cells in table[1:]] == sorted(float(cells[1]) for cells in table[1:])
    for label, column in (("random", 1), ("learned", 2)):
        section = printed.split(f"### {label}")[1].split("###")[0]
        periodic = next(line for line in section.splitlines() if line.startswith("| periodic 2 |"))
        assert rows["periodic 2"][column].startswith(periodic.split(" | ")[3] + " (")  # its control return
        assert rows[f"learned ({label})"][3 - column].strip(" |") == ""  # own options: its own column only
    # Mistakes are refused before the sweep, the page left as it was
    for extra, message in (
        (["--splice", str(page), "--columns", "random", "nobody"], "no algorithm nobody in the study"),
        (["--splice", str(tmp_path / "missing.md")], "cannot be read as a text page"),
    ):
        refused = run_benchmark_here(VOI, *command, *extra)
        assert refused.returncode == 2 and message in refused.stderr and refused.stdout == "", refused.stderr
    for extra in (["--columns", "random"], ["--deltas", "-1"], ["--rates", "2"], ["--periods", "0"]):
        refused = run_benchmark_here(VOI, *command, *extra)
        assert refused.returncode == 2 and "error: " in refused.stderr and refused.stdout == "", extra
    assert page.read_text() == text


def test_the_side_by_side_table_shows_each_algorithms_savings_where_a_trigger_saves_differently(
    tmp_path, run_benchmark_here
):
    """The page of a study whose trials' results are given (no trial finished in the folder: nothing evaluated)."""
    labels = ("a", "b", "c", "d")
    write_study(
        tmp_path, {**TINY, "evaluation": {"episodes": 7}, "algorithms": {x: {"algo": "mappoc"} for x in labels}}
    )

    def seeds(savings: float, control: float, both: bool = True) -> list[dict[str, float]]:
        """Every seed's metrics: seed 0 and, if ``both``, seed 1."""
        rows = [
            {"control_return": control - 1, "package_travel": 0.5, "fall_rate": 0.0, "savings": savings},
            {"control_return": control + 1, "package_travel": 1.5, "fall_rate": 0.2, "savings": savings},
        ]
        return rows if both else rows[:1]

    triggers = {
        "a": {"learned": seeds(0.6, 10.0), "periodic 2": seeds(0.5, 20.0), "send-on-delta 0.1": seeds(0.9, 30.0)},
        "b": {
            "periodic 2": seeds(0.5, 40.0),
            "send-on-delta 0.1": seeds(0.7, 50.0, both=False),
            "learned": seeds(0.95, 60.0),
        },
        "c": {"periodic 2": [{**seeds(0.5, 70.0)[1], "package_travel": float("nan")}]},  # no package travel
    }
    results: dict[str, dict] = {}
    for label, rows in triggers.items():
        for trigger, per_seed in rows.items():
            for seed, metrics in enumerate(per_seed):
                results.setdefault(f"{label}/seed{seed}", {})[trigger] = metrics
    out = tmp_path / "voi.json"

    def page(*arguments: str) -> tuple[subprocess.CompletedProcess, str]:
        out.write_text(json.dumps(results))
        (tmp_path / "README.md").write_text(VOI_PAGE)
        done = run_benchmark_here(
            VOI, str(tmp_path), "--out", str(out), "--deltas", "--splice", str(tmp_path / "README.md"), *arguments
        )
        return done, (tmp_path / "README.md").read_text()

    done, text = page("--columns", "a", "b")
    assert done.returncode == 0, done.stderr
    assert "on the same 7 episodes" in text
    lines = [line for line in text.splitlines() if line.startswith("| ") and "---" not in line]
    assert lines == [
        "| trigger | savings | `a` (2 seeds) | `b` (2 seeds) |",
        "| periodic 2 | 0.500 | 20.0 [19.0, 21.0] (1.00, 0.10) | 40.0 [39.0, 41.0] (1.00, 0.10) |",
        "| learned (a) | 0.600 | 10.0 [9.0, 11.0] (1.00, 0.10) |  |",
        "| send-on-delta 0.1 | 0.800 | 30.0 [29.0, 31.0] (1.00, 0.10, savings 0.900) "
        "| 49.0 [49.0, 49.0] (0.50, 0.00, savings 0.700, 1 seed) |",
        "| learned (b) | 0.950 |  | 60.0 [59.0, 61.0] (1.00, 0.10) |",  # its own savings: in the savings column
    ]
    done, text = page("--columns", "c")
    assert done.returncode == 0 and "| `c` (1 seed) |" in text and "(n/a, 0.20) |" in text
    for arguments, message in ((["a", "a"], "named twice"), (["a", "d"], "no results of d"), ([], "no results to put")):
        if not arguments:
            results.clear()  # all algorithms (none given) of no results
        done, text = page(*(["--columns", *arguments] if arguments else []))
        assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr
        assert text == VOI_PAGE


def test_a_failing_trial_is_kept_with_its_traceback_and_the_others_go_on(tmp_path):
    study = {
        **TINY,
        "seeds": [0],
        "n_timesteps": 1024,
        "algorithms": {
            "broken": {"algo": "mappoc", "hyperparams": {"policy_kwargs": "dict(net_arch=[-3])"}},
            "random": {"algo": "ppo_random_skip"},
        },
    }
    out = tmp_path / "out"
    result = run_command("run", str(write_study(tmp_path, study)), "--dir", str(out), "--cpus", "3")
    assert result.returncode == 1
    assert "2 to run on 3 cores" in result.stdout  # Ray hands out the cores it is told, not the machine's
    broken = out / "trials" / "broken" / "seed0"
    assert read_status(broken)["status"] == "failed"
    assert "Traceback" in (broken / "error.txt").read_text() and "net_arch" in (broken / "error.txt").read_text()
    assert read_status(out / "trials" / "random" / "seed0")["status"] == "done"
    summary = summarise(out)
    assert summary["broken"]["unfinished"][0].startswith("failed")
    assert "seed 0: failed" in report_study(out, plot=False)


def test_ctrl_c_stops_a_study_with_a_checkpoint_at_the_last_rollout(tmp_path):
    # One core: the second trial waits while the first trains; checkpoints only on request.
    study = {**TINY, "seeds": [0, 1], "n_timesteps": 10**6, "checkpoint_interval": 10**6}
    study["algorithms"] = {"learned": {"algo": "mappoc"}}
    path, out = write_study(tmp_path, study), tmp_path / "out"
    first, second = out / "trials" / "learned" / "seed0", out / "trials" / "learned" / "seed1"
    with study_process("run", str(path), "--dir", str(out), "--cpus", "1") as process:
        wait_for(process, (first / "segments" / "0" / "progress.csv").is_file, "iteration")
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 1, stdout + stderr
    assert "[study] stopping" in stdout and "1 stopped" in stdout, stdout
    assert "0 running, 1 pending, 0 failed, 1 stopped" in stdout.splitlines()[-2], stdout  # Ray never started it
    assert "Failed to fetch metrics" not in stderr, stderr  # Ray's warning about the trial it never started
    status = read_status(first)
    assert status["status"] == "interrupted"
    assert 0 < status["timesteps"] < 10**6
    assert json.loads((first / "checkpoint.json").read_text())["timesteps"] == status["timesteps"]  # nothing lost
    assert read_status(second)["status"] != "running" and not (second / "segments").exists()  # never started
    assert not (out / ".stop").exists()


def test_trials_read_the_study_from_the_folder_while_the_files_it_was_started_with_change(tmp_path):
    # One core: the second trial starts after the study file is gone and its hyperparameter file is broken.
    source = tmp_path / "source"
    source.mkdir()
    conf = source / "mine.yml"
    conf.write_text((sb3_detc.zoo.HYPERPARAMS_DIR / "mappoc.yml").read_text())
    study = {
        **TINY,
        "n_timesteps": 8192,
        "checkpoint_interval": 4096,
        "algorithms": {"mine": {"algo": "mappoc", "conf": "mine.yml"}},
    }
    path, out = write_study(source, study), tmp_path / "out"
    first, second = out / "trials" / "mine" / "seed0", out / "trials" / "mine" / "seed1"
    with study_process("run", str(path), "--dir", str(out), "--cpus", "1") as process:
        wait_for(process, (first / "segments" / "0" / "progress.csv").is_file, "iteration")
        assert read_status(second)["status"] == "pending"
        path.unlink()
        conf.write_text("not: [a hyperparameter file\n")
        stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stdout + stderr
    for trial in (first, second):
        assert read_status(trial) | {"seconds": 0, "attempts": []} == {
            "status": "done",
            "budget": 8192,
            "timesteps": 8192,
            "seconds": 0,
            "attempts": [],
        }


def test_a_killed_study_resumes_from_its_checkpoints(tmp_path):
    # A short algorithm that finishes, and a long one that is killed after its first checkpoint.
    study = {
        **TINY,
        "seeds": [0],
        "checkpoint_interval": 2048,
        "algorithms": {
            "short": {"algo": "ppo_random_skip", "hyperparams": {"n_timesteps": 2048}},
            "long": {"algo": "mappoc", "hyperparams": {"n_timesteps": 12288}},
        },
    }
    del study["n_timesteps"]
    path = write_study(tmp_path, study)
    out = tmp_path / "out"
    short, long = out / "trials" / "short" / "seed0", out / "trials" / "long" / "seed0"
    with study_process("run", str(path), "--dir", str(out), output=subprocess.DEVNULL) as process:
        deadline = wait_for(
            process,
            lambda: read_status(short)["status"] == "done" and (long / "checkpoint.json").is_file(),
            "checkpoint",
        )
        # killed at the end of the context
    # Ray's trial worker has a process group of its own and ends when it notices that Ray is
    # gone: wait until the trial's files stop changing.
    stamps, quiet_since = None, time.monotonic()
    while time.monotonic() - quiet_since < 3 and time.monotonic() < deadline + 60:
        now = sorted((p.name, p.stat().st_mtime_ns) for p in long.glob("*") if p.is_file())
        if now != stamps:
            stamps, quiet_since = now, time.monotonic()
        time.sleep(0.2)
    checkpoint = json.loads((long / "checkpoint.json").read_text())["timesteps"]
    assert 0 < checkpoint < 12288
    assert read_status(long)["status"] in ("running", "interrupted")  # killed, or told to stop by Ray
    trained = read_status(long)["seconds"]  # its time up to the checkpoint at least, even when killed
    assert trained > 0
    stamp = (short / "evaluation.json").stat().st_mtime_ns

    result = run_command("run", str(path), "--dir", str(out))
    assert result.returncode == 0, result.stdout + result.stderr
    assert (short / "evaluation.json").stat().st_mtime_ns == stamp  # not run again
    status = read_status(long)
    assert status["status"] == "done" and status["timesteps"] == 12288  # the budget, not budget + steps before
    assert status["seconds"] > trained  # both attempts' time
    assert [a["start_timesteps"] for a in status["attempts"]] == [0, checkpoint]  # the second from the checkpoint
    assert sorted(p.name for p in long.iterdir()) == sorted(FINISHED_FILES)
    steps = read_progress(long)["time/total_timesteps"]
    assert np.all(np.diff(steps) > 0) and steps[-1] == 12288  # one row per iteration, none twice


def quiet_progress(monkeypatch, budgets, **kwargs):
    """A StudyProgress that prints nothing, on a clock the test sets: (progress, clock)."""
    from sb3_detc.study import runner

    clock = [0.0]
    monkeypatch.setattr(runner.time, "monotonic", lambda: clock[0])
    progress = runner.StudyProgress(budgets, stream=None, **kwargs)
    progress.show = lambda force=False: None
    return progress, clock


def test_progress_counts_trials_and_estimates_the_time_left_from_recent_progress(monkeypatch):
    progress, clock = quiet_progress(monkeypatch, {"a/seed0": 10_000, "b/seed0": 10_000}, done=3)
    lines = []
    progress.show = lambda force=False: lines.append(progress.line())
    progress.started("a/seed0")
    for t, steps in ((0, 0), (100, 100), (1000, 1000), (1700, 8000)):  # slow at first, then 10 steps/s
        clock[0] = t
        progress.result("a/seed0", steps)
    assert progress.rate() == pytest.approx(7000 / 700)  # the samples of the last RATE_WINDOW seconds
    assert progress.seconds_left() == pytest.approx((2000 + 10_000) / 10)
    assert lines[-1] == "[study] 3 done, 1 running (a/seed0 80 %), 1 pending, 0 failed; time left: 20 min"
    progress.finished("a/seed0", failed=False)
    progress.started("b/seed0")
    progress.finished("b/seed0", failed=True)
    assert lines[-1].startswith("[study] 4 done, 0 running, 0 pending, 1 failed")


def test_progress_counts_stopped_trials_as_unfinished(monkeypatch):
    progress, clock = quiet_progress(monkeypatch, {"a/seed0": 10_000, "b/seed0": 10_000})
    progress.started("a/seed0")
    for t, steps in ((0, 0), (100, 1000)):
        clock[0] = t
        progress.result("a/seed0", steps)
    progress.finished("a/seed0", failed=False, stopped=True)
    progress.started("b/seed0")
    progress.finished("b/seed0", failed=False, stopped=True)
    assert progress.line() == "[study] 0 done, 0 running, 0 pending, 0 failed, 2 stopped; time left: unknown"
    assert progress.pending == 0 and progress.done == 0


def test_progress_of_a_budget_below_one_iteration_stops_at_100_percent(monkeypatch):
    """make run's baseline trains one iteration (1024 steps) for a budget of 1 step."""
    progress, clock = quiet_progress(monkeypatch, {"a/seed0": 1, "b/seed0": 10_000})
    progress.started("a/seed0")
    progress.started("b/seed0")
    for t, steps in ((0, 0), (100, 1000)):
        clock[0] = t
        progress.result("a/seed0", steps * 1024 // 1000)
        progress.result("b/seed0", steps)
    assert "(a/seed0 100 %, b/seed0 10 %)" in progress.line()
    assert progress.seconds_left() == pytest.approx(9000 / (10 + 10.24))  # nothing left of a/seed0, not -1023


def test_intervals_are_the_same_on_every_call_and_leave_numpys_generator_alone():
    from sb3_detc.study.report import interval_estimates

    scores = {"a": np.random.default_rng(1).normal(size=(6, 2))}
    np.random.seed(5)
    expected_next = np.random.rand()
    np.random.seed(5)
    first = interval_estimates(scores)[1]["a"]
    assert np.random.rand() == expected_next
    np.testing.assert_array_equal(interval_estimates(scores)[1]["a"], first)


def stop_after_the_first_checkpoint(steps: int) -> None:
    """A trial's progress hook: stop at the first rollout from step 2048 on (the tiny study's checkpoint)."""
    if steps >= 2048:
        raise KeyboardInterrupt


def test_an_interrupted_trial_says_so_and_the_next_run_finishes_it(tmp_path):
    from sb3_detc.study.trial import run_trial

    spec = load_study(write_study(tmp_path, {**TINY, "seeds": [0], "n_timesteps": 4096}))
    trial = spec.trials()[0]
    folder = trial_folder(tmp_path / "out", trial)

    with pytest.raises(KeyboardInterrupt):
        run_trial(spec, trial, tmp_path / "out", on_progress=stop_after_the_first_checkpoint)
    assert read_status(folder)["status"] == "interrupted"
    assert not (folder / "error.txt").exists()
    assert json.loads((folder / "checkpoint.json").read_text())["timesteps"] == 2048
    # what the next attempt resumes from stays while the trial trains: the checkpoint and the first attempt's log
    assert (folder / "segments" / "0" / "progress.csv").is_file()
    assert read_progress(folder)["time/total_timesteps"][-1] == 2048  # the log up to the checkpoint
    status = run_trial(spec, trial, tmp_path / "out")
    assert status["status"] == "done" and status["timesteps"] == 4096
    assert [a["start_timesteps"] for a in status["attempts"]] == [0, 2048]
    # done: the kept files alone, one log of both attempts, each iteration once
    assert sorted(p.name for p in folder.iterdir()) == sorted(FINISHED_FILES)
    assert progress_file(folder) == folder / PROGRESS_XZ
    np.testing.assert_array_equal(read_progress(folder)["time/total_timesteps"], [1024, 2048, 3072, 4096])
    # fractions to six significant digits, whole numbers as they are
    text = lzma.decompress((folder / PROGRESS_XZ).read_bytes()).decode()
    cells = [cell.lstrip("-") for line in text.splitlines()[1:] for cell in line.split(",")]
    fractions = [cell for cell in cells if "." in cell and "e" not in cell]
    assert fractions and max(len(cell.replace(".", "").strip("0")) for cell in fractions) <= PROGRESS_DIGITS
    assert "4096" in cells and "4096.0" not in cells


def test_a_run_starts_the_longest_trials_first_and_of_equal_budgets_the_ones_it_resumes(tmp_path):
    study = {
        **TINY_BUDGETS,
        "seeds": [0, 1, 2, 3],
        "algorithms": {**TINY_BUDGETS["algorithms"], "long": {"algo": "mappoc", "hyperparams": {"n_timesteps": 4096}}},
    }
    spec = load_study(write_study(tmp_path, study))
    out = prepare_folder(spec, tmp_path / "out")
    # stopped ("interrupted"), or left "running" by a run that was killed
    left = {"learned/seed1": "interrupted", "learned/seed3": "running", "random/seed2": "interrupted"}
    for name, status in {"learned/seed0": "done", "long/seed2": "done", **left}.items():
        folder = out / "trials" / name
        folder.mkdir(parents=True)
        (folder / "status.json").write_text(json.dumps({"status": status}))
    order = [t.name for t in trials_to_run(spec, out, spec.trials())]
    assert order == [
        *("long/seed0", "long/seed1", "long/seed3"),  # the largest budget first
        *("learned/seed1", "learned/seed3", "learned/seed2"),  # what a stop or a kill left first
        *("random/seed2", "random/seed0", "random/seed1", "random/seed3"),
    ]


def test_a_trial_of_two_cores_trains_its_learner_on_one_torch_thread(tmp_path):
    """The cores are the rollout workers'; the learner's threads are ``LEARNER_THREADS``, and the caller's come back."""
    from sb3_detc.study.trial import LEARNER_THREADS, run_trial

    study = {**TINY, "seeds": [0], "n_timesteps": 1024, "algorithms": {"learned": {"algo": "mappoc", "cpus": 2}}}
    spec = load_study(write_study(tmp_path, study))
    [trial] = spec.trials()
    assert trial.algorithm.cpus == 2 and LEARNER_THREADS == 1
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        status = run_trial(spec, trial, tmp_path / "out")
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
    assert status["status"] == "done" and [a["torch_threads"] for a in status["attempts"]] == [1]


def test_segments_of_lost_checkpoints_are_dropped(tmp_path):
    for start in (0, 204800, 409600):
        (tmp_path / "segments" / str(start)).mkdir(parents=True)
    drop_stale_segments(tmp_path, 204800)  # resuming from 204800: the attempt from 409600 is stale
    assert sorted(p.name for p in (tmp_path / "segments").iterdir()) == ["0"]
    drop_stale_segments(tmp_path, 0)  # no checkpoint at all
    assert list((tmp_path / "segments").iterdir()) == []
    drop_stale_segments(tmp_path / "new", 0)  # a trial without segments


def test_an_interrupted_trial_saves_where_it_stopped(tmp_path):
    """Between periodic checkpoints, an interruption checkpoints the model as it is: nothing learned is lost."""
    from sb3_detc.study.trial import run_trial

    spec = load_study(write_study(tmp_path, {**TINY, "seeds": [0], "n_timesteps": 8192, "checkpoint_interval": 4096}))
    trial = spec.trials()[0]
    folder = trial_folder(tmp_path / "out", trial)

    def stop_at_the_third_rollout(steps: int) -> None:
        if steps >= 2048:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_trial(spec, trial, tmp_path / "out", on_progress=stop_at_the_third_rollout)
    assert read_status(folder)["status"] == "interrupted"
    assert json.loads((folder / "checkpoint.json").read_text())["timesteps"] == 2048
    assert run_trial(spec, trial, tmp_path / "out")["timesteps"] == 8192


def test_the_code_commit_names_the_checkout_and_marks_changed_files_under_the_source(tmp_path: Path) -> None:
    package = tmp_path / "repo" / "package"
    package.mkdir(parents=True)
    assert code_commit(package) is None

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=tmp_path / "repo", capture_output=True, text=True, check=True).stdout

    git("init", "-q")
    (package / "module.py").write_text("x = 1\n")
    (tmp_path / "repo" / "notes.txt").write_text("outside the package\n")
    git("add", "-A")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "first")
    head = git("rev-parse", "HEAD").strip()
    assert code_commit(package) == head
    (tmp_path / "repo" / "notes.txt").write_text("changed outside the package\n")
    assert code_commit(package) == head
    (package / "module.py").write_text("x = 2\n")
    assert code_commit(package) == head + "+modified"
    git("checkout", "-q", "--", ".")
    (package / "new.py").write_text("y = 1\n")
    assert code_commit(package) == head + "+modified"


def test_generated_text_is_spliced_between_its_own_marks_and_again_in_the_same_place(tmp_path):
    page = tmp_path / "README.md"
    start, end = "<!-- table.py: start -->", "<!-- table.py: end -->"
    other = "<!-- other.py: start -->\n\nkept\n\n<!-- other.py: end -->\n"
    page.write_text(f"# Results\n\nabove\n\n{start}\n{end}\n\nbelow\n\n{other}")
    splice(page, "table.py", "| a | b |\n")
    once = page.read_text()
    assert once == f"# Results\n\nabove\n\n{start}\n\n| a | b |\n\n{end}\n\nbelow\n\n{other}"
    splice(page, "table.py", "| a | b |\n")
    assert page.read_text() == once
    splice(page, "table.py", "| c |\n")
    assert "| a | b |" not in page.read_text() and "| c |" in page.read_text() and "kept" in page.read_text()
    for broken in (f"{start}\n", f"{end}\n{start}\n", f"{start}\n{end}\n" * 2, other):
        page.write_text(broken)
        with pytest.raises(StudyError, match="needs the lines"):
            splice(page, "table.py", "| a | b |\n")
        assert page.read_text() == broken
    for unreadable in (tmp_path / "missing.md", tmp_path):
        with pytest.raises(StudyError, match="cannot be read as a text page"):
            splice(unreadable, "table.py", "| a | b |\n")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["README.md"]  # no scratch file left


def test_a_file_replaced_atomically_is_whole_or_as_it_was(tmp_path):
    target = tmp_path / "policy.pt"
    target.write_text("old")

    def fails_halfway(path: Path) -> None:
        path.write_text("half of the new")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        replace_atomically(target, fails_halfway, "policy.tmp.pt")
    assert target.read_text() == "old"  # readers never see the half
    replace_atomically(target, lambda path: path.write_text("new"), "policy.tmp.pt")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["policy.pt"]


def test_the_front_puts_each_learned_trigger_beside_the_fixed_families_at_its_rate(tmp_path):
    families = ["periodic", "send_on_delta_max_age"]
    content = {**TINY, "evaluation": {**TINY["evaluation"], "fixed_families": families}}
    spec = load_study(write_study(tmp_path, content))
    assert spec.fixed_families == tuple(families)

    def entry(savings: float, learned: float, periodic: float, delta: float) -> dict:
        mean = {
            "savings": savings,
            "control_return": learned,
            "fixed_periodic_savings": savings,
            "fixed_periodic_control_return": periodic,
            "fixed_send_on_delta_max_age_savings": savings + 0.004,
            "fixed_send_on_delta_max_age_control_return": delta,
            "best_fixed_control_return": max(periodic, delta),
            "learned_minus_best_fixed_control_return": learned - max(periodic, delta),
        }
        return {"mean": mean, "ci95": {name: [value - 0.5, value + 0.5] for name, value in mean.items()}}

    summary = {"learned": entry(0.9, -8.0, -12.0, -8.5), "random": {"mean": {"savings": 0.5}, "ci95": {}}}
    rows = report.front(spec, summary)
    assert [row["label"] for row in rows] == ["learned"]  # the baseline compared no families
    assert rows[0]["points"] == {
        "learned": (0.9, -8.0, (-8.5, -7.5)),
        "periodic": (0.9, -12.0, (-12.5, -11.5)),
        "send_on_delta_max_age": (0.904, -8.5, (-9.0, -8.0)),
    }
    assert rows[0]["difference"] == (0.5, (0.0, 1.0))
    table = report.front_markdown(rows)
    assert table.splitlines()[2] == (
        "| learned | -8.00 [-8.50, -7.50] at 0.900 | -12.00 [-12.50, -11.50] at 0.900 "
        "| -8.50 [-9.00, -8.00] at 0.904 | 0.50 [0.00, 1.00] |"
    )
    assert plot.plot_front(rows, tmp_path / "front.png").stat().st_size > 0
    # mu thresholded at the learned rate: a learned point of its own, with its own difference
    thresholded = {
        "thresholded_savings": 0.905,
        "thresholded_control_return": -7.0,
        "thresholded_minus_best_fixed_control_return": 1.5,
    }
    summary["learned"]["mean"].update(thresholded)
    summary["learned"]["ci95"].update({name: [value - 0.5, value + 0.5] for name, value in thresholded.items()})
    [row] = report.front(spec, summary)
    assert row["points"]["thresholded"] == (0.905, -7.0, (-7.5, -6.5))
    assert row["thresholded_difference"] == (1.5, (1.0, 2.0)) and row["difference"] == (0.5, (0.0, 1.0))
    header, _, line = report.front_markdown([row]).splitlines()
    assert header == (
        "| algorithm | learned | thresholded | periodic | send_on_delta_max_age | learned minus best fixed "
        "| thresholded minus best fixed |"
    )
    assert line.startswith("| learned | -8.00 [-8.50, -7.50] at 0.900 | -7.00 [-7.50, -6.50] at 0.905 |")
    assert line.endswith("| 0.50 [0.00, 1.00] | 1.50 [1.00, 2.00] |")
    assert plot.plot_front([row], tmp_path / "front.png").stat().st_size > 0
    # with the learned difference's interval over seeds and episodes: a column beside it
    summary["learned"]["episodes_ci95"] = {"learned_minus_best_fixed_control_return": [-1.0, 2.0]}
    [row] = report.front(spec, summary)
    assert row["difference_episodes"] == (-1.0, 2.0) and "thresholded_difference_episodes" not in row
    header, _, line = report.front_markdown([row]).splitlines()
    assert header.endswith(
        "| learned minus best fixed | learned minus best fixed, over seeds and episodes "
        "| thresholded minus best fixed |"
    )
    assert line.endswith("| 0.50 [0.00, 1.00] | [-1.00, 2.00] | 1.50 [1.00, 2.00] |")


def test_the_interval_over_seeds_and_episodes_counts_what_the_seeds_share():
    """Gaps that every seed shares episode by episode: the seeds alone look sure, the episodes are not."""
    rng = np.random.default_rng(1)
    shared = rng.normal(0.0, 1.0, 400)
    values = shared + rng.normal(0.0, 0.01, (8, 400))  # 8 seeds, 400 episodes
    low, high = report.crossed_interval(values)
    assert low < values.mean() < high
    assert high - low == pytest.approx(2 * 1.96 * shared.std() / np.sqrt(400), rel=0.1)
    per_seed = values.mean(axis=1)
    assert per_seed.max() - per_seed.min() < (high - low) / 10  # what an interval over the seeds alone resamples
    independent = rng.normal(0.0, 1.0, (40, 100))  # nothing shared: about the interval of all 4000 values
    low, high = report.crossed_interval(independent)
    assert 0.95 < (high - low) / (2 * 1.96 / np.sqrt(4000)) < 1.3
    covered = 0  # seeds, episodes and the rest all vary: the interval holds the true mean 0 in about 95 % of draws
    for _ in range(400):
        draw = rng.normal(0, 0.5, (1, 50)) + rng.normal(0, 0.3, (10, 1)) + rng.normal(0, 1.0, (10, 50))
        low, high = report.crossed_interval(draw)
        covered += low < 0 < high
    assert 0.92 < covered / 400 < 0.98
    # hand-checked: both components kept (Satterthwaite 3.92 degrees of freedom), the seeds' clamped (2), the
    # episodes' clamped (2), both clamped (4)
    for values, expected in [
        ([[0, 2, 7], [3, 5, 9], [8, 9, 15]], (-1.965536, 14.854425)),
        ([[0, 4, 1], [1, 5, 0], [0, 3, 1]], (-3.370140, 6.703473)),
        ([[0, 1, 0], [4, 5, 4], [1, 0, 2]], (-3.434701, 7.212479)),
        ([[0, 3, 1], [2, 0, 3], [3, 1, 0]], (-0.273177, 3.162066)),
    ]:
        assert report.crossed_interval(np.array(values, dtype=float)) == pytest.approx(expected, abs=1e-5)
    one = np.array([[1.0, 2.0, 3.0, 4.0]])  # one seed: Student's t over its episodes, 3 degrees of freedom
    assert report.crossed_interval(one) == pytest.approx(
        (2.5 - 3.182446 * 0.645497, 2.5 + 3.182446 * 0.645497), rel=1e-5
    )
    with pytest.raises(ValueError, match="at least 2 of them, got 1"):
        report.crossed_interval(np.ones((3, 1)))


def test_the_paired_differences_are_the_seeds_episodes_against_their_best_family():
    spec, evaluations, _ = report.read_trials(ROOT / "benchmarks" / "studies" / "linear_lqr_rate")
    seeds = evaluations["predictive_imitated_90"]
    paired = report.paired_differences([seeds[s] for s in sorted(seeds)])
    assert set(paired) == {"learned", "thresholded"}
    for metric, mode in report.PAIRED:
        assert paired[mode].shape == (len(seeds), spec.episodes)
        expected = [seeds[s]["metrics"][metric] for s in sorted(seeds)]
        assert paired[mode].mean(axis=1) == pytest.approx(expected, abs=1e-6)  # the episodes' returns are rounded
    named = report.paired_differences([seeds[s] for s in sorted(seeds)], family="send_on_delta_max_age")
    expected = [
        seeds[s]["metrics"]["control_return"] - seeds[s]["metrics"]["fixed_send_on_delta_max_age_control_return"]
        for s in sorted(seeds)
    ]
    assert named["learned"].mean(axis=1) == pytest.approx(expected, abs=1e-6)
    assert report.paired_differences([]) == {}
    shorter = {**seeds[0], "modes": {**seeds[0]["modes"], "learned": {"control_return": [0.0]}}}
    others = [seeds[s] for s in sorted(seeds) if s != 0]
    assert set(report.paired_differences([shorter, *others])) == {"thresholded"}
    assert report.paired_differences([{**seeds[0], "seed": 1}, *others]) == {}  # other episodes


def test_each_seed_is_paired_with_its_own_best_family_and_the_report_gives_both_intervals(tmp_path):
    """multiwalker_rate's joint trials, one of them with another best family: each seed against its own."""
    source = ROOT / "benchmarks" / "studies" / "multiwalker_rate"
    spec, evaluations, _ = report.read_trials(source)
    seeds = [evaluations["joint_9375"][s] for s in sorted(evaluations["joint_9375"])]
    other = next(f for f in spec.fixed_families if f != seeds[1]["best_fixed"])
    mixed = [seeds[0], {**seeds[1], "best_fixed": other}, *seeds[2:]]
    paired = report.paired_differences(mixed)["learned"]
    for row, e in zip(paired, mixed, strict=True):
        best = e["modes"][f"fixed_{e['best_fixed']}"]["control_return"]
        np.testing.assert_allclose(row, np.subtract(e["modes"]["learned"]["control_return"], best))
    assert not np.allclose(paired[1], report.paired_differences(seeds)["learned"][1])
    paired = report.paired_differences(seeds)["learned"]
    summary = summarise(source)
    expected = list(report.crossed_interval(paired))
    assert summary["joint_9375"]["episodes_ci95"]["learned_minus_best_fixed_control_return"] == expected
    low, high = expected
    text = (source / "report.md").read_text()
    assert f"95 % interval over seeds and episodes (the seeds share the episodes): [{low:.2f}, {high:.2f}]." in text
    # one seed: the interval over its episodes, said so
    one = report.paired_differences([evaluations["periodic_16"][0]])["learned"]
    low, high = report.crossed_interval(one)
    assert summary["periodic_16"]["episodes_ci95"]["learned_minus_best_fixed_control_return"] == [low, high]
    assert (
        f"learned_minus_best_fixed_control_return: 95 % interval over episodes (one seed): [{low:.2f}, {high:.2f}]."
        in text
    )


def test_the_front_of_one_panel_keeps_its_long_title_and_its_legend_off_the_points(tmp_path, monkeypatch):
    """The title fits the figure's width, and the legend lies below the panel, within the saved figure."""
    import matplotlib.figure
    import matplotlib.text
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    saved = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *args, **kwargs: saved.append(fig))
    row = {
        "label": "joint_9375",
        "settings": '{"broadcast_cost": 0.25}',
        "points": {"learned": (0.93, 330.0, (320.0, 340.0)), "periodic": (0.93, 300.0, (290.0, 310.0))},
    }
    plot.plot_front([row], tmp_path / "front.png", title="sb3_detc/MultiwalkerETC-v0")
    [fig] = saved
    renderer = FigureCanvasAgg(fig).get_renderer()
    width, height = fig.bbox.width, fig.bbox.height
    [title] = [text for text in fig.findobj(matplotlib.text.Text) if text.get_text() == fig.get_suptitle()]
    assert title.get_text() == "sb3_detc/MultiwalkerETC-v0\nlearned triggers and fixed families at the same savings"
    title = title.get_window_extent(renderer)
    assert 0 <= title.x0 and title.x1 <= width and title.y1 <= height
    [ax] = fig.axes
    legend = ax.get_legend().get_window_extent(renderer)
    assert legend.y1 < ax.get_window_extent(renderer).y0 and legend.y0 >= 0


def test_a_trial_with_selection_keeps_its_best_policy_across_an_interruption(tmp_path):
    from sb3_detc.study.trial import run_trial

    selection = {"every": 1024, "episodes": 2}
    learned = {"algo": "mappoc", "hyperparams": {"target_savings": 0.5}, "selection": selection}
    spec = load_study(write_study(tmp_path, {**TINY, "seeds": [0], "n_timesteps": 4096, "algorithms": {"a": learned}}))
    (trial,) = spec.trials()
    assert spec.validation_seeds(2) == [503, 504]  # right after the evaluation's 3 episodes from 500
    folder = trial_folder(prepare_folder(spec, tmp_path / "out"), trial)

    with pytest.raises(KeyboardInterrupt):
        run_trial(spec, trial, tmp_path / "out", on_progress=stop_after_the_first_checkpoint)
    first = json.loads((folder / "selection.json").read_text())
    assert [e["timesteps"] for e in first["evaluations"]] == [1024]  # stopped at the start of the rollout from 2048
    status = run_trial(spec, trial, tmp_path / "out")
    assert status["status"] == "done"
    record = json.loads((folder / "selection.json").read_text())
    evaluations = record["evaluations"]
    assert evaluations[:1] == first["evaluations"]  # the interrupted attempt's validations stay
    assert [e["timesteps"] for e in evaluations[1:]] == [2048, 3072, 4096]  # from the checkpoint on, on schedule
    eligible = [e for e in evaluations if e["savings"] >= 0.5 - 0.01]
    assert eligible and record["kept"] == max(eligible, key=lambda e: e["control_return"])
    assert sorted(p.name for p in folder.iterdir()) == sorted((*FINISHED_FILES, "selection.json"))
    # the final policy is the kept one: it repeats its validation
    policy = MlpHybridPolicy.load(str(folder / "policy.pt"), device="cpu")
    with gym.make(spec.env) as env:
        episodes = evaluate_episodes(policy, env, [503, 504])
    assert float(np.mean(episodes.control_returns)) == pytest.approx(record["kept"]["control_return"], rel=1e-6)
    # the report says which policy each seed kept
    text = report_study(tmp_path / "out", plot=False)
    assert "best on 2 validation episodes (seeds 503 to 504)" in text
    assert f"- seed 0: kept at {record['kept']['timesteps']:,} steps of 4 validations" in text


@pytest.mark.parametrize(
    ("selection", "message"),
    [
        ({"episodes": 5}, "'selection' of 'a' must be a mapping with at least 'every'"),
        ({"every": 0}, "'selection: every' of 'a' must be an integer >= 1"),
        ({"every": 10, "often": 1}, "unknown key 'often' in 'selection' of 'a'"),
        ({"every": 10, "tolerance": 1.5}, r"'selection: tolerance' of 'a' must be a number in \[0, 1\)"),
        ({"every": 10, "seed": -1}, "'selection: seed' of 'a' must be an integer >= 0"),
        ({"every": 10, "seed": 498}, r"the validation episodes of 'a' \('selection: seed'\) overlap the evaluation's"),
    ],
)
def test_a_malformed_selection_is_refused(tmp_path, selection, message):
    content = {**TINY, "algorithms": {"a": {"algo": "mappoc", "selection": selection}}}
    with pytest.raises(StudyError, match=message):
        load_study(write_study(tmp_path, content))
    fixed = {**TINY, "algorithms": {"a": {"algo": "ppo_random_skip", "selection": {"every": 10}}}}
    with pytest.raises(StudyError, match="'a' trains under a fixed trigger .*nothing to select"):
        load_study(write_study(tmp_path, fixed))
    good = {**TINY, "algorithms": {"a": {"algo": "mappoc", "selection": {"every": 10, "seed": 7, "episodes": 2}}}}
    spec = load_study(write_study(tmp_path, good))
    assert spec.algorithms[0].selection == Selection(every=10, episodes=2, seed=7)
