"""Files saved under earlier names (``comm``, ``comm_cost``, ``option_*``) load and read under the current ones."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.plot import read_progress
from sb3_detc.renamed import RENAMED, renamed_action_space, renamed_column, renamed_keys
from sb3_detc.study.spec import load_study, same_study

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "sb3_detc/LinearETC-v0"


def old_action_space(space: spaces.Dict) -> spaces.Dict:
    return spaces.Dict({"comm" if key == "broadcast" else key: value for key, value in space.spaces.items()})


def test_names_are_mapped_and_new_names_win() -> None:
    assert renamed_keys({"comm_cost": 0.5, "gamma": 0.9}) == {"gamma": 0.9, "broadcast_cost": 0.5}
    assert renamed_keys({"option_ent_coef": 0.1, "broadcast_ent_coef": 0.2}) == {"broadcast_ent_coef": 0.2}
    assert renamed_column("train/option_ent_coef") == "train/broadcast_ent_coef"
    assert renamed_column("curriculum/option_ent_coef") == "curriculum/broadcast_ent_coef"
    assert renamed_column("comm/savings") == "comm/savings"
    assert renamed_column("option_ent_coef") == "broadcast_ent_coef"
    current = spaces.Dict({"broadcast": spaces.MultiDiscrete([2, 2]), "control": spaces.Box(-1, 1, (2, 1))})
    assert renamed_action_space(old_action_space(current)) == current
    assert list(renamed_action_space(old_action_space(current)).spaces) == ["broadcast", "control"]
    assert renamed_action_space(current) is current


def test_a_model_saved_under_earlier_names_loads_with_its_values(tmp_path) -> None:
    env = make_vec_env(ENV_ID, n_envs=1, seed=0)
    model = MAPPOC(
        "MlpHybridPolicy", env, n_steps=16, batch_size=16, n_epochs=1, policy_kwargs={"net_arch": [8]}, seed=0
    )
    model.learn(16)
    saved = {"broadcast_ent_coef": 0.07, "clip_range_broadcast": 0.3, "normalize_broadcast_advantage": True}
    for new, value in saved.items():
        setattr(model, new, value)
    for old, new in RENAMED.items():  # what a model of an earlier version saved
        if hasattr(model, new):
            setattr(model, old, getattr(model, new))
            delattr(model, new)
    model.action_space = old_action_space(model.action_space)
    model.save(tmp_path / "old.zip")

    loaded = MAPPOC.load(tmp_path / "old.zip", env=env)
    assert list(loaded.action_space.spaces) == ["broadcast", "control"]
    for new, value in saved.items():
        assert getattr(loaded, new) == value
    assert not any(hasattr(loaded, old) for old in RENAMED)  # the old names are gone, also from its next save
    assert MAPPOC.load(tmp_path / "old.zip", clip_range_broadcast=0.1).clip_range_broadcast == 0.1  # given wins
    assert MAPPOC.load(tmp_path / "old.zip", clip_range_option=0.1).clip_range_broadcast == 0.1  # under either name
    given = MAPPOC.load(tmp_path / "old.zip", custom_objects={"broadcast_ent_coef": 0.5})
    assert given.broadcast_ent_coef == 0.5
    obs = env.reset()
    th.manual_seed(1)
    expected = model.predict(obs, deterministic=True)[0]
    th.manual_seed(1)
    for a, b in zip(loaded.predict(obs, deterministic=True)[0], expected, strict=True):
        np.testing.assert_array_equal(a["control"], b["control"])
    loaded.learn(16)  # trains on


def test_a_policy_saved_under_earlier_names_loads(tmp_path) -> None:
    env = make_vec_env(ENV_ID, n_envs=1, seed=0)
    policy = MAPPOC("MlpHybridPolicy", env, policy_kwargs={"net_arch": [8]}, seed=0).policy
    policy.save(str(tmp_path / "policy.pt"))
    saved = th.load(tmp_path / "policy.pt", weights_only=False)
    saved["data"]["action_space"] = old_action_space(saved["data"]["action_space"])
    del saved["data"]["sample_options"]  # saved as the switch of the opposite meaning
    saved["data"]["deterministic_options"] = False  # "deterministic predictions sample the options"
    th.save(saved, tmp_path / "old.pt")
    loaded = MlpHybridPolicy.load(str(tmp_path / "old.pt"))
    assert loaded.action_space == policy.action_space
    assert loaded.sample_options is True  # evaluated with sampled options, as it was
    policy.sample_options = True  # the same predictions from the same weights
    obs = env.reset()
    th.manual_seed(1)
    expected = policy.predict(obs, deterministic=True)[0]
    th.manual_seed(1)
    got = loaded.predict(obs, deterministic=True)[0]
    for a, b in zip(expected, got, strict=True):
        np.testing.assert_array_equal(a["control"], b["control"])


STUDY_POLICIES = sorted(ROOT.glob("benchmarks/studies/*/trials/*/seed*/policy.pt"))


def test_the_committed_study_policies_are_found() -> None:
    """The test below runs once per policy: an empty glob (files moved, pattern wrong) would skip it silently."""
    found = {path.relative_to(ROOT / "benchmarks" / "studies").as_posix() for path in STUDY_POLICIES}
    committed = {  # the policies committed when this test was written; finished seeds add more
        f"{study}/trials/{algorithm}/seed{seed}/policy.pt"
        for study, algorithms, n_seeds in [
            ("linear", ("mappoc", "ppo_random_skip"), 5),
            ("linear_lqr", ("mappoc", "ppo_random_skip"), 10),
            ("linear_normalised", ("mappoc", "ppo_random_skip"), 5),
            ("multiwalker_paper", ("mappoc_paper", "mappoc_paper_overlap", "random_skip_paper", "control_first"), 4),
        ]
        for algorithm in algorithms
        for seed in range(n_seeds)
    }
    assert len(committed) == 56
    assert sorted(committed - found) == []


@pytest.mark.parametrize("path", STUDY_POLICIES, ids=str)
def test_every_committed_study_policy_loads(path: Path) -> None:
    policy = MlpHybridPolicy.load(str(path), device="cpu")
    assert set(policy.action_space.spaces) == {"broadcast", "control"}


def test_logs_of_earlier_versions_read_under_current_names(tmp_path) -> None:
    (tmp_path / "progress.csv").write_text(
        "time/iterations,time/total_timesteps,train/option_ent_coef,comm/savings\n1,16,0.01,0.5\n2,32,0.02,0.6\n"
    )
    columns = read_progress(tmp_path)
    np.testing.assert_array_equal(columns["train/broadcast_ent_coef"], [0.01, 0.02])
    assert "train/option_ent_coef" not in columns and "comm/savings" in columns


def test_environment_arguments_and_study_files_of_earlier_versions(tmp_path) -> None:
    env = gym.make("sb3_detc/LinearETC-v0", comm_cost=0.5)  # as saved rl-zoo3 configurations have it
    assert env.unwrapped.broadcast_cost == 0.5
    env.close()
    study = {
        "env": "sb3_detc/LinearETC-LQR-v0",
        "seeds": [0],
        "n_timesteps": 1024,
        "algorithms": {"a": {"algo": "mappoc", "hyperparams": {"option_ent_coef": 0.2}}},
    }
    (tmp_path / "old.yml").write_text(yaml.safe_dump(study))
    assert load_study(tmp_path / "old.yml").algorithms[0].hyperparams == {"broadcast_ent_coef": 0.2}
    current = {**study, "algorithms": {"a": {"algo": "mappoc", "hyperparams": {"broadcast_ent_coef": 0.2}}}}
    assert same_study(study, current)
    assert not same_study(study, {**current, "algorithms": {"a": {"algo": "mappoc"}}})
