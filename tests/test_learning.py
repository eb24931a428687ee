"""Short learning runs on the linear env: both levels of MAPPOC move the way their rewards say.

Kept to seconds; how well MAPPOC learns (cost against the LQR bound, savings, learned
trigger against random skipping at equal communication) is measured in ``benchmarks/``.
"""

from __future__ import annotations

import gymnasium as gym
import pytest
from stable_baselines3.common.env_util import make_vec_env

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc import MAPPOC
from sb3_detc.evaluation import evaluate_communication
from sb3_detc.triggers import FixedControl, RandomTrigger

ENV_ID = "sb3_detc/LinearETC-v0"
SETTINGS = {
    "n_steps": 256,
    "batch_size": 128,
    "n_epochs": 5,
    "learning_rate": 1e-3,
    "max_grad_norm": 0.5,
    "normalize_reward": True,
    "reward_scale": 1.0,
    "team_reward": True,
    "broadcast_ent_coef": 0.0,
}


@pytest.mark.parametrize("critic", ["afterstate", "centred"])
def test_option_policy_learns_to_save_costly_communication(critic: str) -> None:
    """With a communication cost far above the value of a broadcast, mu learns to stay silent.

    The critics that add the known price of a broadcast to their option values, with option
    advantages normalised: the price is tiny in normalised reward units, but mu moves at
    the rate the learning rate sets.
    """
    env_kwargs = {"broadcast_cost": 1.0, "max_cycles": 50}
    env = make_vec_env(ENV_ID, n_envs=2, seed=0, env_kwargs=env_kwargs, wrapper_class=FixedControl)
    policy_kwargs = {"net_arch": [32, 32], "critic": critic}
    model = MAPPOC(
        "MlpHybridPolicy", env, seed=0, policy_kwargs=policy_kwargs, normalize_broadcast_advantage=True, **SETTINGS
    )
    eval_env = FixedControl(gym.make(ENV_ID, **env_kwargs))
    before = evaluate_communication(model, eval_env, 4, sample_options=True, seed=1)
    model.learn(12_000)
    after = evaluate_communication(model, eval_env, 4, sample_options=True, seed=1)
    assert 0.4 < before.savings < 0.6  # undecided at the start
    assert after.savings > 0.8
    assert after.mean_return > before.mean_return


def test_control_policy_learns_with_random_skips() -> None:
    """The control policy learns to stabilise the team: its cost falls far below the untrained policy's."""
    env_kwargs = {"broadcast_cost": 0.0, "max_cycles": 50}
    env = make_vec_env(ENV_ID, n_envs=2, seed=0, env_kwargs=env_kwargs)
    model = MAPPOC("MlpHybridPolicy", env, seed=0, policy_kwargs={"net_arch": [32, 32]}, **SETTINGS)
    model.set_fixed_trigger(RandomTrigger(0.5, seed=0))
    eval_env = gym.make(ENV_ID, **env_kwargs)

    def control_return() -> float:
        report = evaluate_communication(
            model, eval_env, 4, deterministic=True, fixed_trigger=RandomTrigger(0.5, seed=2), seed=1
        )
        return report.mean_control_return

    before = control_return()
    model.learn(30_000)
    after = control_return()
    assert after > 0.5 * before  # returns are negative costs: the cost at least halves
