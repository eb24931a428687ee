"""rl-zoo3 integration: hyperparameter files, the train/enjoy/plot/record_video command lines, bad input."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
from rl_zoo3.utils import get_callback_list
from stable_baselines3.common.env_util import make_vec_env

from sb3_detc import MAPPOC, compare, enjoy, plot, record_video, train, zoo
from sb3_detc.callbacks import CommMetricsCallback, ControlFirstCallback, CurriculumCallback, RandomSkipCallback
from sb3_detc.cli import ZOO_KEYS, InputError, check_hyperparams_file, check_train_arguments

LINEAR = "sb3_detc/LinearETC-v0"
LINEAR_LQR = "sb3_detc/LinearETC-LQR-v0"
MULTIWALKER = "sb3_detc/MultiwalkerETC-v0"
ENVS = (LINEAR, LINEAR_LQR, MULTIWALKER)


def cli(module: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``python -m <module> <args>`` headless in ``cwd``."""
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}
    return subprocess.run(
        [sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True, check=False
    )


def run_folder(logs: Path, algo: str, env_id: str, run_id: int) -> Path:
    return logs / algo / f"{env_id.replace('/', '-')}_{run_id}"


# ----------------------------------------------------------------------------- hyperparameter files
@pytest.mark.parametrize("algo", sorted(zoo.ALGORITHMS))
@pytest.mark.parametrize("env_id", ENVS)
def test_hyperparameter_files_build_models(algo: str, env_id: str) -> None:
    entry = check_hyperparams_file(zoo.HYPERPARAMS_DIR / f"{algo}.yml", algo, env_id)
    kwargs = {k: v for k, v in entry.items() if k not in ZOO_KEYS}
    kwargs["policy_kwargs"] = eval(kwargs["policy_kwargs"])  # rl-zoo3 evaluates the string the same way
    env = make_vec_env(env_id, n_envs=entry.get("n_envs", 1), env_kwargs=entry.get("env_kwargs"))
    model = zoo.ALGORITHMS[algo](env=env, **kwargs)
    assert isinstance(model, MAPPOC) and model.n_agents == 3
    callbacks = get_callback_list(entry)
    assert any(isinstance(c, CommMetricsCallback) for c in callbacks)
    if algo == "ppo_random_skip":
        assert any(isinstance(c, RandomSkipCallback) for c in callbacks)
    env.close()


@pytest.mark.parametrize("algo", sorted(zoo.ALGORITHMS))
def test_multiwalker_entries_train_without_a_cxx_compiler(algo: str) -> None:
    """The paper's entries compile where a compiler exists and fall back to eager steps, not an error, elsewhere."""
    from torch._inductor import config

    entry = check_hyperparams_file(zoo.HYPERPARAMS_DIR / f"{algo}.yml", algo, MULTIWALKER)
    kwargs = {k: v for k, v in entry.items() if k not in ZOO_KEYS}
    kwargs["policy_kwargs"] = eval(kwargs["policy_kwargs"])
    env = make_vec_env(MULTIWALKER, n_envs=1, env_kwargs=entry.get("env_kwargs"))
    with config.patch({"cpp.cxx": ("no-such-cxx-compiler",)}):
        model = zoo.ALGORITHMS[algo](env=env, **kwargs)  # with torch_compile=True: RuntimeError
    assert model.torch_compile == "auto" and type(model.gradient_step).__name__ == "GradientStep"
    env.close()


@pytest.mark.parametrize("vec_env", ["dummy", "subproc"])
def test_rollout_worker_entries_train_in_worker_processes_and_evaluate_as_vec_env_says(
    tmp_path: Path, vec_env: str
) -> None:
    from argparse import Namespace

    from stable_baselines3.common.callbacks import EvalCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    manager = zoo.ExperimentManager(
        Namespace(),
        "mappoc",
        MULTIWALKER,
        str(tmp_path),
        eval_freq=1000,
        log_interval=-1,  # rl-zoo3's command-line default
        vec_env_type=vec_env,
        n_timesteps=2048,
        config=str(zoo.HYPERPARAMS_DIR / "mappoc.yml"),
    )
    model, _ = manager.setup_experiment()  # the envs, the model and the callbacks
    (evaluation,) = [callback for callback in manager.callbacks if isinstance(callback, EvalCallback)]
    try:
        assert isinstance(model.get_env(), SubprocVecEnv)
        assert type(evaluation.eval_env) is {"dummy": DummyVecEnv, "subproc": SubprocVecEnv}[vec_env]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            manager.learn(model)  # one iteration, with evaluations: no warning that the classes differ
        assert evaluation.n_calls > 0 and model.num_timesteps == 2048
        assert not [w for w in caught if "not of the same type" in str(w.message)]
    finally:
        model.get_env().close()
        evaluation.eval_env.close()


def test_a_model_loaded_to_continue_counts_on_and_its_class_stays_as_it_is(tmp_path: Path) -> None:
    from argparse import Namespace

    from stable_baselines3.common.callbacks import BaseCallback

    own_learn = MAPPOC.__dict__["learn"]

    class Seen(BaseCallback):
        """What training starts from: the step count, and whether MAPPOC and the model are as they were."""

        def _on_training_start(self) -> None:
            self.start = self.model.num_timesteps
            self.untouched = MAPPOC.__dict__["learn"] is own_learn and "learn" not in vars(self.model)

        def _on_step(self) -> bool:
            return True

    def manager(trained_agent: str = "") -> zoo.ExperimentManager:
        return zoo.ExperimentManager(
            Namespace(),
            "mappoc",
            LINEAR,
            str(tmp_path),
            n_timesteps=64,
            eval_freq=-1,
            log_interval=-1,
            hyperparams={"n_envs": 1, "n_steps": 64, "batch_size": 64, "n_epochs": 1},
            trained_agent=trained_agent,
            verbose=0,
            config=str(zoo.HYPERPARAMS_DIR / "mappoc.yml"),
            device="cpu",
        )

    first = manager()
    model, _ = first.setup_experiment()
    first.learn(model)
    saved = tmp_path / "saved.zip"
    model.save(saved)
    more = manager(str(saved))
    model, _ = more.setup_experiment()
    seen = Seen()
    more.callbacks.append(seen)
    more.learn(model)
    assert seen.start == 64 and model.num_timesteps == 128  # counting on from the saved model's 64 steps
    assert seen.untouched
    assert MAPPOC.__dict__["learn"] is own_learn


def test_the_evaluation_runs_its_episodes_side_by_side_unless_told_otherwise() -> None:
    def n_eval_envs(*argv: str) -> list[str]:
        args = check_train_arguments(["--env", LINEAR, *argv])
        return [args[i + 1] for i, arg in enumerate(args) if arg == "--n-eval-envs"]

    assert n_eval_envs() == ["5"]  # rl-zoo3's 5 evaluation episodes
    assert n_eval_envs("--eval-episodes", "8") == ["8"]
    assert n_eval_envs("--n-eval-envs", "1") == ["1"]  # the user's choice, alone
    assert n_eval_envs("--algo", "ppo") == []  # rl-zoo3's own algorithms keep its defaults


def test_multiwalker_entry_has_the_paper_settings() -> None:
    entry = check_hyperparams_file(zoo.HYPERPARAMS_DIR / "mappoc.yml", "mappoc", MULTIWALKER)
    assert entry["n_steps"] * entry["n_envs"] == 2048
    assert entry["n_timesteps"] == 3000 * 2048
    assert (entry["learning_rate"], entry["batch_size"], entry["n_epochs"]) == (3e-5, 32, 10)
    assert entry["env_kwargs"]["broadcast_cost"] == 0.25
    assert eval(entry["policy_kwargs"])["net_arch"] == [96, 96, 96]
    assert any(isinstance(c, CurriculumCallback) for c in get_callback_list(entry))
    assert entry["env_wrapper"] == "sb3_detc.mappoc.workers.RolloutWorker"  # fast setting


def test_linear_entry_trains_control_first_then_the_trigger_within_the_budget() -> None:
    entry = check_hyperparams_file(zoo.HYPERPARAMS_DIR / "mappoc.yml", "mappoc", LINEAR)
    (stages,) = [c for c in get_callback_list(entry) if isinstance(c, ControlFirstCallback)]
    iterations = entry["n_timesteps"] / (entry["n_steps"] * entry["n_envs"])
    assert 0 < stages.switch < iterations
    assert stages.trigger_normalize_reward and not entry.get("normalize_reward", False)
    assert eval(entry["policy_kwargs"])["age_scale"] == 0.0


def test_register_adds_algorithms_and_samplers_and_importing_does_not() -> None:
    script = (
        "from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER\n"
        "from rl_zoo3.utils import ALGOS\n"
        "from sb3_detc import MAPPOC, cli, zoo\n"
        "assert 'mappoc' not in ALGOS and 'mappoc' not in HYPERPARAMS_SAMPLER\n"
        "assert cli.algorithm_class('mappoc') is MAPPOC  # the checks know the names without registering\n"
        "zoo.register()\n"
        "assert ALGOS['mappoc'] is MAPPOC and ALGOS['ppo_random_skip'] is MAPPOC\n"
        "assert HYPERPARAMS_SAMPLER['mappoc'] is zoo.sample_mappoc_params\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


def test_sampled_parameters_build_a_model() -> None:
    optuna = pytest.importorskip("optuna")
    trial = optuna.trial.FixedTrial(
        {
            "learning_rate": 1e-4,
            "n_steps": 128,
            "batch_size": 256,
            "n_epochs": 5,
            "gamma": 0.99,
            "gae_lambda": 0.95,
            "clip_range": 0.2,
            "clip_range_broadcast": 0.2,
            "broadcast_ent_coef": 0.01,
            "max_grad_norm": 0.5,
            "reward_scale": 0.01,
            "team_reward": True,
            "normalize_broadcast_advantage": True,
            "net_arch": "paper",
            "critic": "afterstate",
        }
    )
    params = zoo.sample_mappoc_params(trial, 0, 1, {})
    assert params["batch_size"] == 128  # at most one rollout
    assert params["policy_kwargs"]["net_arch"] == [96, 96, 96]
    assert params["policy_kwargs"]["critic"] == "afterstate" and params["normalize_broadcast_advantage"]
    model = MAPPOC("MlpHybridPolicy", make_vec_env(LINEAR, n_envs=1), **params)
    assert model.n_steps == 128


# ----------------------------------------------------------------------------- end to end
def test_train_continue_enjoy_plot_through_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    logs = tmp_path / "logs"
    common = ["--env", LINEAR, "-f", str(logs), "--num-threads", "1", "--eval-freq", "-1", "--verbose", "0"]
    tensorboard = ["--tensorboard-log", str(tmp_path / "tb")]  # tensorboard comes with the zoo extra
    first = cli("sb3_detc.train", "--algo", "mappoc", "-n", "256", "--seed", "1", *common, *tensorboard, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    assert list((tmp_path / "tb").rglob("events.out.tfevents.*"))
    run = run_folder(logs, "mappoc", LINEAR, 1)
    model = run / "sb3_detc-LinearETC-v0.zip"
    assert model.is_file()
    with (run / "progress.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 1 and float(rows[0]["time/iterations"]) == 1
    assert 0 <= float(rows[0]["comm/savings"]) <= 1

    more = cli("sb3_detc.train", "--algo", "mappoc", "-n", "256", "-i", str(model), *common, cwd=tmp_path)
    assert more.returncode == 0, more.stderr
    assert "Loading pretrained agent" in more.stdout
    continued = run_folder(logs, "mappoc", LINEAR, 2)
    assert (continued / "sb3_detc-LinearETC-v0.zip").is_file()
    with (continued / "progress.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert float(rows[0]["time/total_timesteps"]) == 2048  # counting on from the saved model's 1024 steps
    assert MAPPOC.load(continued / "sb3_detc-LinearETC-v0.zip").num_timesteps == 2048
    # a saved model with its run's settings, as python -m sb3_detc.evaluate finds them (args.yml, config.yml)
    from sb3_detc.evaluate import load_saved
    from sb3_detc.evaluation import evaluate_episodes

    saved = load_saved(model)
    assert saved.env_id == LINEAR and saved.trigger is None
    first_returns = evaluate_episodes(saved.policy, LINEAR, [0, 1]).returns
    assert (evaluate_episodes(load_saved(continued / model.name).policy, LINEAR, [0, 1]).returns != first_returns).any()
    with pytest.raises(InputError, match="no such file"):
        load_saved(run / "rl_model_1_steps.zip")

    baseline = cli("sb3_detc.train", "--algo", "ppo_random_skip", "-n", "256", *common, cwd=tmp_path)
    assert baseline.returncode == 0, baseline.stderr

    shown = cli("sb3_detc.enjoy", "--env", LINEAR, "-f", str(logs), "-n", "150", cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    assert "Episode Reward" in shown.stdout and "does not render" in shown.stdout

    assert "does not render" in bad(record_video.main, ["-f", str(logs)], capsys)

    figure = tmp_path / "figure.png"
    drawn = cli("sb3_detc.plot", "-f", str(logs), "--env", LINEAR, "-o", str(figure), cwd=tmp_path)
    assert drawn.returncode == 0, drawn.stderr
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_video_marks_broadcasts(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    trained = cli(
        "sb3_detc.train",
        *("--algo", "mappoc", "--env", MULTIWALKER, "-f", str(logs), "-n", "64", "--eval-freq", "-1", "--seed", "0"),
        *("--num-threads", "1", "--verbose", "0", "-params", "n_steps:64", "n_epochs:1", "torch_compile:False"),
        cwd=tmp_path,
    )
    assert trained.returncode == 0, trained.stderr
    videos = tmp_path / "videos"
    recorded = cli(
        "sb3_detc.record_video",
        *("--env", MULTIWALKER, "-f", str(logs), "-n", "20", "-o", str(videos)),
        cwd=tmp_path,
    )
    assert recorded.returncode == 0, recorded.stderr
    (video,) = videos.glob("*.mp4")
    import imageio.v2 as imageio  # with imageio-ffmpeg: what moviepy, which writes the video, depends on

    from sb3_detc.envs.multiwalker import BROADCAST_COLOR

    def green_pixels(frame: np.ndarray) -> int:
        """Pixels of the broadcast mark's green (up to the video's compression); the terrain's green is far from it."""
        return int((np.abs(frame.astype(np.int16) - BROADCAST_COLOR).max(axis=-1) <= 30).sum())

    with imageio.get_reader(video, format="ffmpeg") as reader:
        marked = np.array([green_pixels(frame) for frame in reader])
    assert len(marked) == 21  # the reset and 20 steps
    assert marked[0] == 0  # the reset's frame: no options yet, only the silent rings
    assert marked.max() > 50  # a disc above a walker that broadcast


def test_rendered_frames_mark_who_broadcast() -> None:
    import gymnasium as gym

    from sb3_detc.envs.multiwalker import BROADCAST_COLOR, SILENT_COLOR

    env = gym.make(MULTIWALKER, render_mode="rgb_array")
    env.reset(seed=0)
    action = {"broadcast": np.array([1, 0, 1]), "control": np.zeros((3, 4), np.float32)}
    env.step(action)
    frame = env.render()
    assert np.all(frame == BROADCAST_COLOR, axis=-1).sum() > 50  # two discs
    assert np.all(frame == SILENT_COLOR, axis=-1).sum() > 10  # one ring
    env.step({**action, "broadcast": np.zeros(3, np.int64)})
    assert not np.all(env.render() == BROADCAST_COLOR, axis=-1).any()
    env.close()


def test_compare_reports_over_seeds_with_intervals_and_a_figure(tmp_path: Path) -> None:
    folder = tmp_path / "compare"
    command = [sys.executable, "-m", "sb3_detc.compare", "-n", "2048", "--seeds", "0", "1", "--dir", str(folder)]
    result = subprocess.run([*command, "--eval-episodes", "2"], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    assert (
        "| mappoc | 2 |" in out
        and "| ppo_random_skip | 2 |" in out
        and "| ppo_random_skip at mappoc's rate | 2 |" in out
    )
    assert "learned better in" in out and "of 2 seeds" in out
    assert "the baseline has nothing to learn, so it trains one iteration" in out
    assert (folder / "curves.png").is_file() and (folder / "summary.json").is_file()
    assert f"Figure: {folder / 'curves.png'}" in out
    assert f"Final policies: {folder / 'estimates.png'}" in out and (folder / "estimates.png").is_file()
    # the same settings again: nothing trains; other settings in the same folder: refused
    again = subprocess.run([*command, "--eval-episodes", "2"], capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "all 4 trials are done" in again.stdout
    other = subprocess.run([*command, "--eval-episodes", "3"], capture_output=True, text=True, timeout=600)
    assert other.returncode == 2 and "other settings" in other.stderr


def test_compare_without_curves_says_so(tmp_path: Path) -> None:
    folder = tmp_path / "compare"
    command = [sys.executable, "-m", "sb3_detc.compare", "-n", "1024", "--seeds", "0", "--eval-episodes", "1"]
    result = subprocess.run([*command, "--dir", str(folder)], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "| mappoc | 1 |" in result.stdout  # one iteration of 8 x 128 steps each: nothing to draw
    assert "No training curves: every run trained one iteration" in result.stdout and "Figure:" not in result.stdout
    assert not (folder / "curves.png").exists()
    assert f"Final policies: {folder / 'estimates.png'}" in result.stdout and (folder / "estimates.png").is_file()


# ----------------------------------------------------------------------------- bad input
def bad(main, argv: list[str], capsys: pytest.CaptureFixture) -> str:
    """Run a command line that must fail; return its single error line."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_compare_refuses_bad_settings_before_it_writes(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    folder = tmp_path / "compare"
    for argv in (["--seeds", "-1"], ["--seeds", "0", "0"], ["-n", "0"]):
        bad(compare.main, [*argv, "--dir", str(folder)], capsys)
        assert not folder.exists(), argv
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert "not empty and has no study.yml" in bad(compare.main, ["-n", "64", "--dir", str(other)], capsys)
    assert sorted(path.name for path in other.iterdir()) == ["notes.txt"]


def test_unknown_algorithm_and_environment(capsys: pytest.CaptureFixture) -> None:
    assert "unknown algorithm 'mapoc' (did you mean 'mappoc'?)" in bad(train.main, ["--algo", "mapoc"], capsys)
    line = bad(train.main, ["--env", "sb3_detc/LinearETC-v9"], capsys)
    assert "unknown environment 'sb3_detc/LinearETC-v9' (did you mean 'sb3_detc/LinearETC-v0'?)" in line
    assert "unknown environment" in bad(enjoy.main, ["--env", "Nope-v0"], capsys)


def write(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("sb3_detc/LinearETC-v0:\n  n_timesteps: 100\n   policy: x\n", "not valid YAML at line 3"),
        ("- just\n- a list\n", "expected a mapping"),
        ("sb3_detc/MultiwalkerETC-v0: {n_timesteps: 1, policy: MlpHybridPolicy}\n", "no entry for"),
        (
            "sb3_detc/LinearETC-v0: {n_timesteps: 1, policy: MlpHybridPolicy, learnig_rate: 0.1}\n",
            "unknown hyperparameter 'learnig_rate' (did you mean 'learning_rate'?)",
        ),
        ("sb3_detc/LinearETC-v0: {policy: MlpHybridPolicy}\n", "missing hyperparameter 'n_timesteps'"),
        (
            "sb3_detc/LinearETC-v0: {n_timesteps: 1, policy: MlpHybridPolicy, callback: sb3_detc.callbacks.Nope}\n",
            "unknown callback 'sb3_detc.callbacks.Nope'",
        ),
        (
            "sb3_detc/LinearETC-v0:\n  n_timesteps: 1\n  policy: MlpHybridPolicy\n  callback:\n"
            "    - sb3_detc.callbacks.BroadcastEntropySchedule: {intial: 0.1}\n",
            "unexpected keyword argument 'intial'",
        ),
    ],
)
def test_bad_hyperparameter_files(tmp_path: Path, capsys: pytest.CaptureFixture, text: str, message: str) -> None:
    conf = write(tmp_path / "bad.yml", text)
    assert message in bad(train.main, ["-conf", conf, "-f", str(tmp_path / "logs")], capsys)


def test_bad_values_inside_rl_zoo_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    conf = write(tmp_path / "bad.yml", "sb3_detc/LinearETC-v0: {n_timesteps: 1, policy: MlpHybridPolicy, n_steps: 0}\n")
    assert "n_steps" in bad(train.main, ["-conf", conf, "-f", str(tmp_path / "logs"), "--eval-freq", "-1"], capsys)


@pytest.mark.parametrize(
    ("params", "message"),
    [
        (["n_steps:0"], "n_steps must be a positive integer, got 0"),
        (["gamma:'high'"], "gamma must be in (0, 1], got 'high'"),
        (["n_steps:many"], "-params 'n_steps:many': expected key:value with a Python value (NameError"),
        (["learnig_rate:0.1"], "unknown hyperparameter 'learnig_rate' (did you mean 'learning_rate'?)"),
        (["policy:'MlpPolicy'"], "unknown policy 'MlpPolicy'"),
        (["learning_rate:'fast'"], "learning_rate must be a number or a linear schedule 'lin_<initial value>'"),
        (["policy_kwargs:'dict(net_arc=[8])'"], "unknown policy_kwargs key 'net_arc' (did you mean 'net_arch'?)"),
        (["policy_kwargs:'dict(net_arch=[8]'"], "policy_kwargs 'dict(net_arch=[8]' is not a Python expression"),
        (["n_timesteps:'1e6'"], "n_timesteps must be a number >= 0, got '1e6' (YAML reads 1e6 as text"),
        (["n_envs:0"], "n_envs must be a positive integer"),
        (["clip_range:'lin_-0.2'"], "clip_range must be > 0 or a schedule, got -0.2"),
        (["broadcast_ent_coef:-1"], "broadcast_ent_coef must be >= 0 or a schedule, got -1"),
        (["env_wrapper:'sb3_detc.envs.Nope'"], "unknown env wrapper 'sb3_detc.envs.Nope'"),
        (["normalize:True"], "MAPPOC cannot use a VecNormalize that normalises the observations 'message'"),
        (["normalize:\"dict(norm_obs_keys=['local', 'age'])\""], "normalises the observations 'age'"),
    ],
)
def test_bad_values_are_found_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture, params: list[str], message: str
) -> None:
    argv = ["-f", str(tmp_path / "logs"), "-n", "64", "--eval-freq", "-1", "--num-threads", "1", "-params", *params]
    assert message in bad(train.main, argv, capsys)


def test_linear_schedules_pass_the_checks() -> None:
    overrides = {"learning_rate": "lin_0.001", "clip_range": "lin_0.2"}
    entry = check_hyperparams_file(zoo.HYPERPARAMS_DIR / "mappoc.yml", "mappoc", LINEAR, overrides)
    assert entry["learning_rate"] == "lin_0.001"  # rl-zoo3 builds the schedule


def test_observation_normalization_of_the_local_state_passes_the_checks() -> None:
    for normalize in ("dict(norm_obs_keys=['local'])", "dict(norm_obs=False, norm_reward=True)", False):
        check_hyperparams_file(zoo.HYPERPARAMS_DIR / "mappoc.yml", "mappoc", LINEAR, {"normalize": normalize})


def test_malformed_arguments_and_other_conf_files(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert "argument --env: expected one argument" in bad(train.main, ["--env"], capsys)
    assert "--env-kwargs 'broadcast_cost'" in bad(train.main, ["--env-kwargs", "broadcast_cost"], capsys)
    assert "no module to import" in bad(train.main, ["-conf", "no_such_module.hyperparams"], capsys)
    assert "'missing.py' not found" in bad(train.main, ["-conf", "missing.py"], capsys)
    conf = write(tmp_path / "conf.py", f"hyperparams = {{{LINEAR!r}: {{'n_timesteps': 1, 'policy': 'Nope'}}}}\n")
    assert "unknown policy 'Nope'" in bad(train.main, ["-conf", conf], capsys)


def test_missing_models(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    logs = str(tmp_path / "logs")
    assert "no trained mappoc model for sb3_detc/LinearETC-v0" in bad(enjoy.main, ["-f", logs], capsys)
    assert "no trained mappoc model" in bad(record_video.main, ["--env", MULTIWALKER, "-f", logs], capsys)
    missing = str(tmp_path / "missing.zip")
    assert "no saved model" in bad(train.main, ["-i", missing, "-f", logs], capsys)
    assert "no runs of mappoc, ppo_random_skip" in bad(plot.main, ["-f", logs], capsys)
    assert "folder was not found" in bad(enjoy.main, ["-f", logs, "--exp-id", "3"], capsys)
    (tmp_path / "logs" / "mappoc").mkdir(parents=True)
    checkpoint = ["-f", logs, "--exp-id", "-1", "--load-last-checkpoint"]
    assert "No checkpoint found for mappoc" in bad(record_video.main, checkpoint, capsys)


def test_smooth_averages_the_trailing_window_and_skips_nan() -> None:
    values = np.array([1.0, np.nan, 3.0, 5.0, np.nan])
    np.testing.assert_allclose(plot.smooth(values, 2), [1.0, 1.0, 3.0, 4.0, 5.0])
    assert np.isnan(plot.smooth(np.array([np.nan, 1.0]), 1)[0])


def test_a_curve_says_how_many_of_its_runs_end_before_the_longest() -> None:
    assert plot.curve_label("mappoc", [3000]) == "mappoc (1 run)"
    assert plot.curve_label("mappoc", [3000, 3000]) == "mappoc (2 runs)"
    assert plot.curve_label("mappoc", [3000, 734, 3000]) == "mappoc (3 runs, 1 ends earlier)"
    assert plot.curve_label("mappoc", [10, 734, 3000]) == "mappoc (3 runs, 2 end earlier)"


def test_iterations_of_a_continued_run_count_on(tmp_path: Path) -> None:
    rows = ["time/iterations,time/total_timesteps,comm/savings"]
    rows += [f"{k},{(1000 + k) * 2048},0.5" for k in (1, 2, 3)]  # continued from 1000 iterations of 2048 steps
    (tmp_path / "progress.csv").write_text("\n".join(rows) + "\n")
    np.testing.assert_array_equal(plot.read_progress(tmp_path)["iteration"], [1001, 1002, 1003])


def test_curriculum_phases_from_the_logs() -> None:
    iterations = np.arange(1.0, 7.0)
    phases = {"iteration": iterations, "curriculum/phase": np.array(["I", "I", "II", "II", "III", "done"])}
    assert plot.curriculum_phases(phases) == [(3.0, "II"), (5.0, "III"), (6.0, "done")]
    coef = {"iteration": iterations, "curriculum/broadcast_ent_coef": np.array([0.1, 0.1, 0.05, 0.001, 0.001, 0.001])}
    assert plot.curriculum_phases(coef) == [(3.0, "entropy decay"), (4.0, "decayed")]
    stage = {"iteration": iterations, "curriculum/stage": np.array([1.0, np.nan, 1.0, 2.0, np.nan, 2.0])}
    assert plot.curriculum_phases(stage) == [(4.0, "stage 2")]
    assert plot.curriculum_phases({"iteration": iterations}) == []


def test_return_axis_turns_logarithmic_only_over_orders_of_magnitude() -> None:
    assert plot.symlog_threshold(np.array([-150000.0, -2000.0, -50.0, np.nan])) == 50.0
    assert plot.symlog_threshold(np.array([-30.0, -20.0, -5.0])) is None
    assert plot.symlog_threshold(np.array([0.55, 0.6, np.nan])) is None
    assert plot.symlog_threshold(np.array([np.nan, 0.0])) is None
    # Returns that rise through zero to a few hundred stay linear: the few values near zero do not count.
    rising = np.concatenate([np.linspace(-100.0, 100.0, 20), np.linspace(100.0, 600.0, 2980)])
    assert plot.symlog_threshold(rising) is None


def test_estimate_axis_turns_logarithmic_only_for_outliers() -> None:
    # One failed seed far below the others: symmetric log, linear up to the median magnitude.
    assert plot.outlier_symlog_threshold(np.array([-323213.0, -10.3, -8.6, -12.5, -10.2, np.nan])) == 10.3
    # Differences near zero (learned minus random) stay linear, however small some of them are.
    assert plot.outlier_symlog_threshold(np.array([1.21, 0.94, 1.6, -0.001, 0.02])) is None
    assert plot.outlier_symlog_threshold(np.array([0.0, 0.0, np.nan])) is None
    assert plot.outlier_symlog_threshold(np.array([np.nan])) is None


def test_estimates_figure_draws_a_row_per_label_and_a_panel_per_metric_someone_has() -> None:
    estimates = {
        "learned": {
            "control_return": (-10.0, -11.0, -9.0, [-9.0, -10.0, -11.0]),
            "learned_minus_random_control_return": (1.0, -0.5, 2.5, [2.5, 0.5, 0.0]),
        },
        "failing": {"control_return": (-5000.0, -15000.0, -10.0, [-10.0, -15000.0])},
    }
    panels = [
        ("control_return", "control return"),
        ("savings", "savings"),  # no label has it: left out
        ("learned_minus_random_control_return", "learned - random"),
    ]
    fig = plot.estimates_figure(estimates, panels, title="T")
    returns, difference = fig.axes
    assert [ax.get_xlabel() for ax in fig.axes] == ["control return (symlog)", "learned - random"]
    assert returns.get_xscale() == "symlog" and difference.get_xscale() == "linear"
    assert [t.get_text() for t in returns.get_yticklabels()] == ["learned", "failing"]
    assert returns.get_ylim() == (1.5, -0.5)  # first label on top
    # Per drawn row: the interval, the seeds, the mean; the difference panel adds its zero line.
    assert len(returns.lines) == 6 and len(difference.lines) == 4
    seeds = [line for line in difference.lines if line.get_marker() == "o"]
    assert [list(line.get_xdata()) for line in seeds] == [[2.5, 0.5, 0.0]]
    assert any(list(line.get_xdata()) == [0.0, 0.0] for line in difference.lines if line.get_linestyle() == "--")
    on_failing_row = [line for line in returns.lines if list(line.get_ydata()) == [1, 1]]
    bands = [list(line.get_xdata()) for line in on_failing_row if line.get_marker() != "o"]
    assert bands == [[-15000.0, -10.0]]  # the failing label's interval, on its row
    plt.close(fig)


def test_the_comparison_trains_a_baseline_with_nothing_to_learn_one_iteration() -> None:
    fixed = compare.comparison_study(LINEAR_LQR, [0, 1], None, 5)["algorithms"]
    assert compare.controls_fixed(LINEAR_LQR) and not compare.controls_fixed(LINEAR)
    assert fixed["ppo_random_skip"]["hyperparams"] == {"n_timesteps": 1} and "hyperparams" not in fixed["mappoc"]
    learned = compare.comparison_study(LINEAR, [0], 4096, 5)["algorithms"]
    assert all(algorithm["hyperparams"] == {"n_timesteps": 4096} for algorithm in learned.values())
