"""The command lines as a user runs them: bad input is one line, errors while running keep their traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest

import sb3_detc  # noqa: F401  (registers the ids)

LINEAR = "sb3_detc/LinearETC-v0"

#: A short run: one rollout of 64 steps per env, one epoch.
SHORT = "  n_timesteps: 256\n  policy: MlpHybridPolicy\n  n_envs: 2\n  n_steps: 64\n  batch_size: 64\n  n_epochs: 1\n"


def cli(module: str, *args: str, cwd: Path, pythonpath: Path | None = None) -> subprocess.CompletedProcess:
    """Run ``python -m <module> <args>`` headless in ``cwd`` (with ``pythonpath`` in front of the import path)."""
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}
    if pythonpath is not None:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(pythonpath), env.get("PYTHONPATH")]))
    return subprocess.run(
        [sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True, check=False
    )


def one_line(result: subprocess.CompletedProcess) -> str:
    """The single error line of a command refused for bad input (exit code 2, no traceback)."""
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


def common(logs: Path) -> list[str]:
    return ["-f", str(logs), "--num-threads", "1", "--eval-freq", "-1", "--verbose", "0"]


# ----------------------------------------------------------------------------- bad input and errors while running
def test_unknown_environment_is_one_line_with_exit_code_2(tmp_path: Path) -> None:
    line = one_line(cli("sb3_detc.train", "--env", "sb3_detc/LinearETC-v9", *common(tmp_path / "logs"), cwd=tmp_path))
    assert line.startswith("python -m sb3_detc.train: error: unknown environment 'sb3_detc/LinearETC-v9'")
    assert "--gym-packages" in line


def test_error_while_training_ends_with_its_traceback(tmp_path: Path) -> None:
    (tmp_path / "exploding.py").write_text(
        "from stable_baselines3.common.callbacks import BaseCallback\n\n\n"
        "class Explode(BaseCallback):\n"
        "    def _on_step(self) -> bool:\n"
        "        raise ValueError('boom while training')\n"
    )
    conf = tmp_path / "conf.yml"
    conf.write_text(f"{LINEAR}:\n{SHORT}  callback: exploding.Explode\n")
    result = cli("sb3_detc.train", "-conf", str(conf), *common(tmp_path / "logs"), cwd=tmp_path, pythonpath=tmp_path)
    assert result.returncode not in (0, 2), result.stderr
    assert "Traceback (most recent call last)" in result.stderr
    assert "in _on_step" in result.stderr and "exploding.py" in result.stderr
    assert result.stderr.strip().splitlines()[-1] == "ValueError: boom while training"
    assert "error:" not in result.stderr


def test_argparse_errors_as_usual(tmp_path: Path) -> None:
    result = cli("sb3_detc.train", "--n-timesteps", "many", cwd=tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "usage:" in result.stderr and "argument -n/--n-timesteps: invalid int value: 'many'" in result.stderr


# ----------------------------------------------------------------------------- --gym-packages
def write_package(root: Path) -> Path:
    """A package ``myteam`` that registers ``myteam/Linear-v0``: sb3-detc's LQR linear env under another name."""
    package = root / "myteam"
    package.mkdir(parents=True)
    entry_point = gym.spec("sb3_detc/LinearETC-LQR-v0").entry_point
    (package / "__init__.py").write_text(
        f"import gymnasium\n\ngymnasium.register('myteam/Linear-v0', entry_point={entry_point!r})\n"
    )
    return root


def test_environments_of_gym_packages(tmp_path: Path) -> None:
    path = write_package(tmp_path / "site")
    logs = tmp_path / "logs"
    conf = tmp_path / "conf.yml"
    conf.write_text(f"myteam/Linear-v0:\n{SHORT}")
    args = ["--env", "myteam/Linear-v0", "-conf", str(conf), *common(logs)]

    assert "unknown environment 'myteam/Linear-v0'" in one_line(cli("sb3_detc.train", *args, cwd=tmp_path))
    trained = cli("sb3_detc.train", *args, "--gym-packages", "myteam", cwd=tmp_path, pythonpath=path)
    assert trained.returncode == 0, trained.stderr
    assert (logs / "mappoc" / "myteam-Linear-v0_1" / "myteam-Linear-v0.zip").is_file()

    model = ["--env", "myteam/Linear-v0", "-f", str(logs), "--gym-packages", "myteam"]
    shown = cli("sb3_detc.enjoy", *model, "-n", "50", cwd=tmp_path, pythonpath=path)
    assert shown.returncode == 0, shown.stderr
    assert "does not render" in shown.stdout
    # rl-zoo3's record_video has no --gym-packages: the id is known, the env just draws nothing
    line = one_line(cli("sb3_detc.record_video", *model, cwd=tmp_path, pythonpath=path))
    assert "myteam/Linear-v0 does not render" in line


def test_gym_packages_that_cannot_be_imported(tmp_path: Path) -> None:
    for module in ("sb3_detc.train", "sb3_detc.enjoy", "sb3_detc.record_video"):
        line = one_line(cli(module, "--gym-packages", "no_such_team", "-f", str(tmp_path / "logs"), cwd=tmp_path))
        assert "--gym-packages: cannot import 'no_such_team'" in line


def test_algorithm_arguments_are_what_rl_zoo3_passes_to_the_algorithm() -> None:
    from sb3_detc import MAPPOC
    from sb3_detc.cli import InputError, algorithm_arguments, check_hyperparams_file
    from sb3_detc.zoo import HYPERPARAMS_DIR

    entry = check_hyperparams_file(HYPERPARAMS_DIR / "mappoc.yml", "mappoc", "sb3_detc/LinearETC-LQR-v0")
    arguments = algorithm_arguments(entry, "mappoc.yml")
    assert not arguments.keys() & {"n_timesteps", "n_envs", "env_kwargs", "callback", "policy"}
    assert arguments["policy_kwargs"]["critic"] == "afterstate"  # the entry's "dict(...)" evaluated
    model = MAPPOC(entry["policy"], gym.make("sb3_detc/LinearETC-LQR-v0"), **arguments)
    assert model.n_steps == entry["n_steps"] and model.policy.critic == "afterstate"
    with pytest.raises(InputError, match=r"^a\.yml \[x\]: policy_kwargs"):
        algorithm_arguments({"policy_kwargs": "dict(net_arch="}, "a.yml [x]")
