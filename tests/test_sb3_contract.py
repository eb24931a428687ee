"""SB3's contract for algorithms and policies, in the form of SB3's own checks (save/load, predict, eval mode)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from torch import nn

from sb3_detc import MAPPOC
from sb3_detc.mappoc.policies import MlpHybridPolicy

ENV_ID = "sb3_detc/LinearETC-v0"
ENV_KWARGS = {"n_agents": 3, "max_cycles": 20}


class NoisyInputsPolicy(MlpHybridPolicy):
    """The inputs of ``mu`` and ``pi`` pass batch norm and dropout, as a custom features extractor's would.

    Without parameters (``affine=False``): an update builds the networks' inputs once for all its gradient steps.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        n_trig = self.observation_space["trigger"].shape[1]
        self.option_norm = nn.BatchNorm1d(2 * n_trig, affine=False)
        self.dropout = nn.Dropout(0.5)

    def option_features(self, obs: dict[str, th.Tensor]) -> th.Tensor:
        features = super().option_features(obs)
        flat = self.option_norm(features.reshape(-1, features.shape[-1]))
        return self.dropout(flat).reshape(features.shape)

    def control_features(self, obs: dict[str, th.Tensor], broadcast: th.Tensor) -> th.Tensor:
        return self.dropout(super().control_features(obs, broadcast))


def make_model(policy: Any = "MlpHybridPolicy", **policy_kwargs: Any) -> MAPPOC:
    env = make_vec_env(ENV_ID, n_envs=2, seed=0, env_kwargs=ENV_KWARGS)
    return MAPPOC(
        policy,
        env,
        n_steps=16,
        batch_size=16,
        n_epochs=2,
        learning_rate=1e-3,
        policy_kwargs={"net_arch": [16], "broadcast_prob_init": 0.5, **policy_kwargs},
        seed=0,
        device="cpu",
    )


def observations(model: MAPPOC, steps: int = 8) -> list[dict[str, np.ndarray]]:
    """Batches of observations (2 envs each) met under the model's own sampled actions."""
    env = model.get_env()
    obs = env.reset()
    met = []
    for _ in range(steps):
        met.append(obs)
        actions, _ = model.predict(obs, deterministic=False)
        obs, *_ = env.step(actions)
    return met


def deterministic_actions(predictor: Any, batches: list[dict[str, np.ndarray]], seed: int = 0) -> list[np.ndarray]:
    """Options and controls side by side for every env of every batch, PyTorch's generator seeded first."""
    th.manual_seed(seed)
    out = []
    for obs in batches:
        actions, _ = predictor.predict(obs, deterministic=True)
        out.append(np.stack([np.concatenate([a["broadcast"][:, None], a["control"]], axis=1) for a in actions]))
    return out


def assert_same(first: list[np.ndarray], second: list[np.ndarray]) -> None:
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)


def mode_options(policy: MlpHybridPolicy, batches: list[dict[str, np.ndarray]]) -> list[np.ndarray]:
    """The most likely options (B, N) of every batch."""
    modes = []
    for obs in batches:
        tensor, _ = policy.obs_to_tensor(obs)
        with th.no_grad():
            broadcast, _ = policy.sample_actions(tensor, deterministic=True, sample_options=False)
        modes.append(broadcast.numpy())
    return modes


@pytest.mark.parametrize("sample_options", [False, True])
def test_deterministic_predictions_repeat_and_survive_save_and_load(tmp_path, sample_options: bool) -> None:
    """SB3's test_save_load: the same deterministic actions before and after saving, for the model and the policy.

    A trigger deployed with sampled options repeats them under the same state of PyTorch's generator.
    """
    model = make_model(sample_options=sample_options)
    model.learn(32)
    batches = observations(model)
    expected = deterministic_actions(model, batches)
    assert_same(deterministic_actions(model, batches), expected)
    other = deterministic_actions(model, batches, seed=123)
    # mu near 50 %: every step has agents whose options a sample would flip
    modes = mode_options(model.policy, batches)
    flipped = [not np.array_equal(a[..., 0], m) for a, m in zip(other, modes, strict=True)]
    assert any(flipped) is sample_options

    model.save(tmp_path / "model.zip")
    loaded = MAPPOC.load(tmp_path / "model.zip", device="cpu")
    assert loaded.policy.sample_options is sample_options
    assert_same(deterministic_actions(loaded, batches), expected)

    model.policy.save(str(tmp_path / "policy.pt"))
    alone = MlpHybridPolicy.load(str(tmp_path / "policy.pt"), device="cpu")
    assert alone.sample_options is sample_options
    assert_same(deterministic_actions(alone, batches), expected)


def test_predictions_take_the_eval_mode_of_dropout_and_batch_norm() -> None:
    """SB3's test_train_eval_mode: predict and rollouts run in eval mode; training in training mode."""
    model = make_model(NoisyInputsPolicy)
    model.learn(32)  # rollouts (eval mode) and updates (training mode)
    policy = model.policy
    assert policy.option_norm.num_batches_tracked > 0  # the updates ran in training mode
    batches = observations(model)
    statistics = policy.option_norm.running_mean.clone()
    expected = deterministic_actions(model, batches)
    assert_same(deterministic_actions(model, batches), expected)
    assert not policy.training
    th.testing.assert_close(policy.option_norm.running_mean, statistics)  # predict left the statistics alone
    # In training mode the dropout acts: the same call gives other means (the test could fail)
    policy.set_training_mode(True)
    obs = {key: th.as_tensor(value) for key, value in batches[0].items()}
    with th.no_grad():
        _, first = policy.sample_actions(obs, deterministic=True)
        _, second = policy.sample_actions(obs, deterministic=True)
    assert not th.equal(first, second)
    policy.set_training_mode(False)
    before = policy.option_norm.num_batches_tracked.clone()
    model.learn(16)  # one rollout and one update
    assert policy.option_norm.num_batches_tracked > before
    assert_same(deterministic_actions(model, batches[:1]), deterministic_actions(model, batches[:1]))
