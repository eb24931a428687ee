"""Evaluation: episodes side by side and one after another, the protocol of modes, the shared episode counter."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from logged import capture_logger  # tests/logged.py
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import obs_as_tensor

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc import evaluation
from sb3_detc.callbacks import CommMetricsCallback
from sb3_detc.envs.linear_etc_v0 import joint_env
from sb3_detc.evaluation import evaluate_episodes
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.policies import MlpHybridPolicy
from sb3_detc.triggers import (
    FixedControl,
    PeriodicTrigger,
    PredictiveTrigger,
    RandomTrigger,
    SendOnDelta,
    StatelessTrigger,
    lqr_on_predicted_states,
)

ENV_ID = "sb3_detc/LinearETC-v0"
SETTINGS = {"n_agents": 2, "max_cycles": 15}


@pytest.fixture(scope="module")
def policy():
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **SETTINGS), n_steps=16, policy_kwargs={"net_arch": [8]}, seed=0)
    return model.policy


@pytest.mark.parametrize("trigger", [PeriodicTrigger(3), RandomTrigger(1.0)])
def test_side_by_side_matches_one_after_another(monkeypatch: pytest.MonkeyPatch, policy, trigger) -> None:
    """Deterministic episodes give the same results in copies of the env as in one env, in the order of the seeds."""
    monkeypatch.setattr(evaluation, "MAX_SIDE_BY_SIDE", 2)  # 5 episodes in 2 envs: finished ones make room
    seeds = [7, 3, 11, 5, 9]
    made = gym.make(ENV_ID, **SETTINGS)
    side_by_side = evaluate_episodes(policy, made, seeds, fixed_trigger=trigger)
    alone = joint_env(**SETTINGS)
    assert alone.spec is None  # cannot be copied: one episode after another
    one_by_one = evaluate_episodes(policy, alone, seeds, fixed_trigger=trigger)
    for field in evaluation.Episodes.__dataclass_fields__:
        np.testing.assert_allclose(getattr(side_by_side, field), getattr(one_by_one, field), rtol=1e-6, err_msg=field)
    first = evaluate_episodes(policy, made, seeds[:1], fixed_trigger=trigger)
    assert side_by_side.returns[0] == pytest.approx(first.returns[0])  # episode k belongs to seeds[k]
    assert len(np.unique(side_by_side.returns)) == len(seeds)


def test_sampled_options_side_by_side_are_recorded_per_episode(policy) -> None:
    episodes = evaluate_episodes(policy, gym.make(ENV_ID, **SETTINGS), [1, 2, 3], sample_options=True)
    assert episodes.broadcasts.shape == (3, 2) and (episodes.lengths == SETTINGS["max_cycles"]).all()
    broadcasts = episodes.broadcasts
    assert np.array_equal(broadcasts, np.round(broadcasts)) and ((broadcasts >= 0) & (broadcasts <= 15)).all()
    assert 0 < broadcasts.sum() < 3 * 2 * 15  # sampled options: some broadcasts, not at every step
    # Savings: one minus the broadcasts per agent-step, over 3 episodes x 2 agents x 15 steps.
    assert episodes.savings == pytest.approx(1 - broadcasts.sum() / 90, abs=1e-12)
    # Known options: every third step, 5 broadcasts per agent and episode.
    periodic = evaluate_episodes(policy, gym.make(ENV_ID, **SETTINGS), [1, 2, 3], fixed_trigger=PeriodicTrigger(3))
    np.testing.assert_array_equal(periodic.broadcasts, np.full((3, 2), 5))
    assert periodic.savings == pytest.approx(2 / 3, abs=1e-12)


@pytest.mark.parametrize("sample_options", [False, True])
def test_deterministic_episodes_take_options_as_the_policy_says(sample_options: bool) -> None:
    """Deterministic episodes take the most likely options, or samples where the policy's ``sample_options`` says."""
    model = MAPPOC(
        "MlpHybridPolicy",
        gym.make(ENV_ID, **SETTINGS),
        policy_kwargs={"net_arch": [8], "broadcast_prob_init": 0.5, "sample_options": sample_options},
        seed=0,
    )
    runs = []
    for first in (1, 101):  # the first episode's seed seeds the draws: episodes 2 and 3 are the same
        runs.append(evaluate_episodes(model.policy, gym.make(ENV_ID, **SETTINGS), [first, 2, 3]).broadcasts[1:])
    assert np.array_equal(runs[0], runs[1]) is not sample_options


def test_seeded_episodes_draw_the_same_options_and_leave_the_global_generator() -> None:
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **SETTINGS), policy_kwargs={"net_arch": [8]}, seed=0)
    th.manual_seed(5)
    state = th.random.get_rng_state()
    runs = [
        evaluate_episodes(model.policy, gym.make(ENV_ID, **SETTINGS), [1, 2, 3], deterministic=False) for _ in range(2)
    ]
    assert th.equal(th.random.get_rng_state(), state)
    np.testing.assert_array_equal(runs[0].broadcasts, runs[1].broadcasts)
    np.testing.assert_array_equal(runs[0].returns, runs[1].returns)


def test_evaluate_communication_seeds_every_episode() -> None:
    """Episode k of an evaluation with seed s is the episode seeded s + k: other triggers see the same episodes."""
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **SETTINGS), policy_kwargs={"net_arch": [8]}, seed=0)
    report = evaluation.evaluate_communication(model, gym.make(ENV_ID, **SETTINGS), 3, seed=7)
    episodes = evaluate_episodes(model.policy, gym.make(ENV_ID, **SETTINGS), [7, 8, 9])
    assert report.mean_control_return == pytest.approx(float(np.mean(episodes.control_returns)))
    assert report.savings == pytest.approx(episodes.savings)


def test_binary_entropy_hand_values() -> None:
    np.testing.assert_allclose(evaluation.binary_entropy([0.0, 0.5, 1.0, 0.25]), [0, 1, 0, 0.8112781244591328])


def zeroed_mu(policy, p_broadcast: float) -> None:
    """Make ``mu`` ignore the state: no weights into its output layer, a bias for ``p_broadcast`` in every state."""
    views = policy.net_parameters("mu")
    weights, biases = views[: len(views) // 2], views[len(views) // 2 :]
    weights[-1].zero_()
    biases[-1].zero_()
    biases[-1][..., 1] = float(np.log(p_broadcast / (1 - p_broadcast)))


def sharpened_mu(policy, scale: float = 1e4) -> None:
    """Make ``mu`` follow the state: its outputs scaled up, so its probabilities leave 0.5 for 0 or 1 by state."""
    views = policy.net_parameters("mu")
    views[len(views) // 2 - 1].mul_(scale)


@pytest.mark.parametrize("trigger", [RandomTrigger(0.7, seed=1), RandomTrigger(0.0)])
def test_a_trigger_that_ignores_the_state_carries_no_information_about_it(policy, trigger) -> None:
    episodes = evaluate_episodes(policy, gym.make(ENV_ID, **SETTINGS), [1, 2, 3], fixed_trigger=trigger)
    np.testing.assert_allclose(episodes.broadcast_probability, 1 - trigger.skip_prob)
    assert episodes.option_state_information == pytest.approx(0.0, abs=1e-12)


class SoftPeriodic(PeriodicTrigger):
    """A periodic trigger that tells a probability of its own instead of its options."""

    def broadcast_probability(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.full(obs["age"].shape[:-1], 0.25)


def test_a_stateless_trigger_records_its_options_or_its_own_probabilities(policy) -> None:
    env = gym.make(ENV_ID, **SETTINGS)
    plain = evaluate_episodes(policy, env, [1, 2], fixed_trigger=PeriodicTrigger(3))
    np.testing.assert_allclose(plain.broadcast_probability.mean(axis=0), 1 - plain.agent_savings)  # its options
    assert isinstance(SoftPeriodic(3), StatelessTrigger)
    soft = evaluate_episodes(policy, env, [1, 2], fixed_trigger=SoftPeriodic(3))
    np.testing.assert_allclose(soft.broadcast_probability, 0.25)
    np.testing.assert_array_equal(soft.agent_savings, plain.agent_savings)


def test_a_deterministic_trigger_of_the_state_carries_the_entropy_of_its_rate() -> None:
    """Options that follow the state alone: ``I(O; S) = H(rate) - 0``, the rate of every agent over the episodes."""
    model = MAPPOC("MlpHybridPolicy", gym.make(ENV_ID, **SETTINGS), policy_kwargs={"net_arch": [8]}, seed=0)
    episodes = evaluate_episodes(model.policy, gym.make(ENV_ID, **SETTINGS), [1, 2, 3], fixed_trigger=SendOnDelta(0.1))
    rates = 1 - episodes.agent_savings
    assert 0.1 < rates.min() and rates.max() < 0.9  # broadcasts in some steps only
    expected = float(np.mean(evaluation.binary_entropy(rates)))
    assert episodes.option_state_information == pytest.approx(expected, rel=1e-9)


def test_the_dependence_of_mu_on_the_state() -> None:
    """A policy over options that ignores the state has none; one whose options follow the state has some."""
    env = gym.make(ENV_ID, **SETTINGS)
    model = MAPPOC("MlpHybridPolicy", env, policy_kwargs={"net_arch": [8], "sample_options": True}, seed=0)
    zeroed_mu(model.policy, 0.3)
    ignoring = evaluate_episodes(model.policy, env, [1, 2, 3])
    np.testing.assert_allclose(ignoring.broadcast_probability, 0.3, rtol=1e-6)
    assert ignoring.option_state_information == pytest.approx(0.0, abs=1e-6)
    assert 0.5 < ignoring.savings < 0.9  # sampled at 30 %

    model = MAPPOC("MlpHybridPolicy", env, policy_kwargs={"net_arch": [8], "sample_options": True}, seed=0)
    sharpened_mu(model.policy)
    following = evaluate_episodes(model.policy, env, [1, 2, 3])
    assert following.option_state_information > 0.1
    assert np.all(following.option_entropy < 0.5)  # nearly sure of its option in every state


@pytest.mark.parametrize("sample_options", [True, False])
def test_the_protocol_names_its_options_and_runs_the_mode_of_mu(sample_options: bool) -> None:
    env = gym.make(ENV_ID, **SETTINGS)
    model = MAPPOC(
        "MlpHybridPolicy",
        env,
        policy_kwargs={"net_arch": [8], "broadcast_prob_init": 0.5, "sample_options": sample_options},
        seed=0,
    )
    sharpened_mu(model.policy, 300)  # depends on the state, still undecided in some states
    result = evaluation.evaluate_policy_modes(model.policy, env, 3, 40)
    assert list(result["modes"]) == [mode for mode in evaluation.MODES if mode != "thresholded"]  # no families
    assert result["options"] == ("sampled" if sample_options else "mode")
    # The mode of mu: the most likely options on the same episodes.
    mode = evaluate_episodes(model.policy, env, [40, 41, 42], sample_options=False)
    assert result["modes"]["mode"]["control_return"] == pytest.approx(mode.control_returns.tolist())
    assert result["metrics"]["mode_savings"] == pytest.approx(mode.savings)
    assert result["metrics"]["mode_control_return"] == pytest.approx(float(np.mean(mode.control_returns)))
    learned = evaluate_episodes(model.policy, env, [40, 41, 42], sample_options=sample_options)
    assert result["metrics"]["control_return"] == pytest.approx(float(np.mean(learned.control_returns)))
    assert (result["modes"]["learned"] == result["modes"]["mode"]) is not sample_options
    assert result["metrics"]["option_state_information"] == pytest.approx(learned.option_state_information)
    assert result["metrics"]["option_state_information"] > 0.01
    # Either setting can be asked for: the learned mode then samples, or takes the most likely options.
    other = evaluation.evaluate_policy_modes(model.policy, env, 3, 40, sample_options=not sample_options)
    assert other["options"] == ("mode" if sample_options else "sampled")
    assert other["modes"]["mode"] == result["modes"]["mode"]


def test_a_policy_trained_with_a_fixed_trigger_has_no_mode_row() -> None:
    env = gym.make(ENV_ID, **SETTINGS)
    model = MAPPOC("MlpHybridPolicy", env, policy_kwargs={"net_arch": [8]}, seed=0)
    seen = []
    result = evaluation.evaluate_policy_modes(
        model.policy, env, 3, 40, own_trigger=RandomTrigger(0.6), on_mode=lambda mode, _: seen.append(mode)
    )
    assert seen == list(result["modes"]) == ["learned", "random_same_rate", "periodic", "never"]
    assert result["options"] == "fixed trigger"
    assert not any(key.startswith("mode_") for key in result["metrics"])
    assert result["metrics"]["option_state_information"] == pytest.approx(0.0, abs=1e-12)


def test_the_callback_counts_the_episodes_as_the_evaluation_does() -> None:
    """CommMetricsCallback and evaluate_episodes share the counter: the same episodes give the same numbers."""
    xi = 0.1
    settings = {**SETTINGS, "broadcast_cost": xi}
    envs = make_vec_env(ENV_ID, n_envs=2, env_kwargs=settings)
    policy_kwargs = {"net_arch": [8], "broadcast_prob_init": 0.5}
    model = MAPPOC("MlpHybridPolicy", envs, n_steps=SETTINGS["max_cycles"], policy_kwargs=policy_kwargs, seed=0)
    sharpened_mu(model.policy)
    capture = capture_logger(model)
    callback = CommMetricsCallback()
    callback.init_callback(model)
    envs.seed(7)  # env i: seed 7 + i
    obs = envs.reset()
    callback.on_training_start({}, {})
    callback.on_rollout_start()
    for _ in range(SETTINGS["max_cycles"]):  # one episode in each env, the mean controls and most likely options
        obs, _, dones, infos = envs.step(model.predict(obs, deterministic=True)[0])
        callback.update_locals({"infos": infos, "dones": dones})
        callback.on_step()
    callback.on_rollout_end()
    logged = model.logger.name_to_value
    assert capture.rows == []  # the values wait in the logger

    episodes = evaluate_episodes(model.policy, gym.make(ENV_ID, **settings), [7, 8])
    assert 0.1 < episodes.savings < 0.9 and logged["comm/episodes"] == 2
    assert logged["comm/savings"] == pytest.approx(episodes.savings, abs=1e-12)
    for i, savings in enumerate(episodes.agent_savings):
        assert logged[f"comm/savings_agent_{i}"] == pytest.approx(savings, abs=1e-12)
        assert logged[f"comm/ep_return_agent_{i}"] == pytest.approx(episodes.agent_returns[:, i].mean())
        assert logged[f"comm/ep_control_return_agent_{i}"] == pytest.approx(episodes.agent_control_returns[:, i].mean())
    assert logged["comm/ep_return"] == pytest.approx(episodes.returns.mean())
    assert logged["comm/ep_control_return"] == pytest.approx(episodes.control_returns.mean())
    cost = xi * episodes.broadcasts.sum() / episodes.broadcasts.size  # per agent and episode
    assert logged["comm/ep_control_return"] - logged["comm/ep_return"] == pytest.approx(cost)


def test_the_protocol_compares_fixed_families_tuned_to_the_learned_rate() -> None:
    """A trial trained with every 4th step's broadcasts: every family reaches its 75 % on the same episodes."""
    env = gym.make("sb3_detc/LinearETC-LQR-v0", n_agents=3, max_cycles=40)
    policy = MAPPOC("MlpHybridPolicy", env, policy_kwargs={"net_arch": [8]}, seed=0).policy
    families = ("periodic", "periodic_staggered", "send_on_delta_max_age", "predictive")
    result = evaluation.evaluate_policy_modes(
        policy, env, 6, 100, own_trigger=PeriodicTrigger(4), fixed_families=families, tune_episodes=3
    )
    metrics, modes = result["metrics"], result["modes"]
    assert metrics["savings"] == 0.75
    assert result["fixed"]["periodic"] == "PeriodicTrigger(period=4, staggered=False)"  # meets the rate alone
    for family in families:  # every family at exactly the learned rate on the same episodes
        assert metrics[f"fixed_{family}_savings"] == pytest.approx(metrics["savings"], abs=1e-12), family
        assert modes[f"fixed_{family}"]["savings"] == metrics[f"fixed_{family}_savings"]
    # the in-phase family is the trial's own trigger: the same episodes, the same control returns
    assert modes["fixed_periodic"]["control_return"] == modes["learned"]["control_return"]
    best = result["best_fixed"]
    assert metrics["best_fixed_control_return"] == max(metrics[f"fixed_{f}_control_return"] for f in families)
    paired = np.subtract(modes["learned"]["control_return"], modes[f"fixed_{best}"]["control_return"])
    assert metrics["learned_minus_best_fixed_control_return"] == pytest.approx(paired.mean())


def test_a_rate_between_two_periods_is_met_by_their_mixture() -> None:
    """Random skips save between periods 2 and 3: the periodic family is both, mixed to the same savings."""
    env = gym.make(ENV_ID, **SETTINGS)
    policy = MAPPOC("MlpHybridPolicy", env, policy_kwargs={"net_arch": [8]}, seed=0).policy
    result = evaluation.evaluate_policy_modes(
        policy, env, 4, 7, own_trigger=RandomTrigger(0.6, seed=1), fixed_families=("periodic",), tune_episodes=2
    )
    metrics, modes = result["metrics"], result["modes"]
    assert 0.51 < metrics["savings"] < 0.656
    found = re.fullmatch(
        r"(\S+) x PeriodicTrigger\(period=2, .*\) \+ (\S+) x PeriodicTrigger\(period=3, .*\)",
        result["fixed"]["periodic"],
    )
    assert found and float(found[1]) + float(found[2]) == pytest.approx(1.0, abs=1e-3)
    assert metrics["fixed_periodic_savings"] == pytest.approx(metrics["savings"], abs=1e-12)
    runs = [evaluate_episodes(policy, env, range(7, 11), fixed_trigger=PeriodicTrigger(p)) for p in (2, 3)]
    weight = float(found[1])
    expected = weight * runs[0].control_returns + (1 - weight) * runs[1].control_returns
    assert modes["fixed_periodic"]["control_return"] == pytest.approx(expected.tolist(), rel=1e-3)


def test_a_mixture_of_two_triggers_meets_the_savings_in_expectation() -> None:
    """Two triggers' episodes of different lengths: the weight solves broadcasts = rate x agent-steps."""

    def episodes(lengths, broadcasts, control_return) -> evaluation.Episodes:
        n = len(lengths)
        returns = np.full((n, 2), control_return, dtype=np.float64)
        return evaluation.Episodes(
            agent_returns=returns - 1.0,
            agent_control_returns=returns,
            lengths=np.array(lengths),
            broadcasts=np.array(broadcasts),
            terminated=np.array([True] * n),
            failed=np.array([True, False][:n]),
            package_travel=np.full(n, np.nan),
            broadcast_probability=np.full((n, 2), np.nan),
            option_entropy=np.full((n, 2), np.nan),
        )

    lower = episodes([10, 10], [[5, 5], [5, 5]], -1.0)  # 20 broadcasts in 40 agent-steps: savings 0.5
    upper = episodes([20, 10], [[3, 3], [2, 2]], -3.0)  # 10 in 60: savings 5/6
    mixed, weight = evaluation.Episodes.mixture(lower, upper, 0.75)
    # w 20 + (1 - w) 10 = 0.25 (w 40 + (1 - w) 60)  ->  w = 5 / 15
    assert weight == pytest.approx(1 / 3)
    assert mixed.savings == pytest.approx(0.75)
    np.testing.assert_allclose(mixed.control_returns, [-7 / 3, -7 / 3])
    np.testing.assert_allclose(mixed.lengths, [50 / 3, 10])
    np.testing.assert_allclose(mixed.failed, [1.0, 0.0])
    assert evaluation.Episodes.mixture(lower, lower, 0.5)[1] == 1.0  # one trigger that meets it alone
    assert (
        evaluation.Episodes.mixture(lower, upper, 0.5)[1] == 1.0
        and evaluation.Episodes.mixture(lower, upper, 5 / 6)[1] == 0.0
    )
    with pytest.raises(ValueError, match=r"savings 0.9 are not between the two triggers' \(0.5, 0.833333\)"):
        evaluation.Episodes.mixture(lower, upper, 0.9)


def _soft_policy(env: gym.Env) -> MlpHybridPolicy:
    """A policy over options that broadcasts with a probability near 0.5 in every state, options sampled."""
    kwargs = {"net_arch": [8], "sample_options": True, "option_age_scale": 0.1}
    return MAPPOC("MlpHybridPolicy", env, policy_kwargs=kwargs, seed=0).policy


def test_thresholded_options_broadcast_where_mu_reaches_the_threshold() -> None:
    env = gym.make("sb3_detc/LinearETC-LQR-v0", n_agents=3, max_cycles=40)
    policy = _soft_policy(env)
    observations = [env.reset(seed=seed)[0] for seed in range(16)]
    batch = {key: np.stack([obs[key] for obs in observations]) for key in observations[0]}
    obs = obs_as_tensor(batch, policy.device)
    with th.no_grad():
        probability = policy.broadcast_probabilities(obs).numpy()
        mode, _ = policy.sample_actions(obs, deterministic=True, sample_options=False)
    threshold = float(np.median(probability))
    options = evaluation.ThresholdedOptions(policy, threshold)(batch)
    np.testing.assert_array_equal(options, probability >= threshold)
    assert 0 < options.mean() < 1  # both options occur at the median
    # the threshold 0.5 is the most likely option; above 1, never
    np.testing.assert_array_equal(evaluation.ThresholdedOptions(policy, 0.5)(batch), mode.numpy())
    assert not evaluation.ThresholdedOptions(policy, 1.5)(batch).any()
    assert repr(evaluation.ThresholdedOptions(policy, 0.25)) == "ThresholdedOptions(threshold=0.25)"
    for bad in (0.0, -0.1, float("nan"), True):
        with pytest.raises(ValueError, match="threshold must be a finite number > 0"):
            evaluation.ThresholdedOptions(policy, bad)


def test_the_protocol_runs_mu_thresholded_at_the_learned_rate_beside_the_families() -> None:
    env = gym.make("sb3_detc/LinearETC-LQR-v0", n_agents=3, max_cycles=40)
    policy = _soft_policy(env)
    result = evaluation.evaluate_policy_modes(policy, env, 6, 100, fixed_families=("send_on_delta",), tune_episodes=6)
    metrics, modes = result["metrics"], result["modes"]
    # two thresholds mixed at exactly the sampled options' savings on the six episodes, where the mode is not
    assert metrics["thresholded_savings"] == pytest.approx(metrics["savings"], abs=1e-12)
    assert abs(metrics["mode_savings"] - metrics["savings"]) > 0.1
    found = re.fullmatch(
        r"(\S+) x ThresholdedOptions\(threshold=(\S+)\) \+ (\S+) x ThresholdedOptions\(threshold=(\S+)\)",
        result["thresholded"],
    )
    weight, lower, upper = float(found[1]), float(found[2]), float(found[4])
    assert 0 < weight < 1 and float(found[3]) == pytest.approx(1 - weight, abs=1e-3) and lower < upper
    runs = [
        evaluate_episodes(policy, env, range(100, 106), fixed_trigger=evaluation.ThresholdedOptions(policy, threshold))
        for threshold in (lower, upper)
    ]
    assert runs[0].savings < metrics["savings"] < runs[1].savings
    again, exact_weight = evaluation.Episodes.mixture(*runs, metrics["savings"])
    assert exact_weight == pytest.approx(weight, abs=5e-4)
    assert modes["thresholded"]["control_return"] == pytest.approx(again.control_returns.tolist(), rel=1e-6)
    paired = np.subtract(modes["thresholded"]["control_return"], modes["fixed_send_on_delta"]["control_return"])
    assert metrics["thresholded_minus_best_fixed_control_return"] == pytest.approx(paired.mean())
    # without families, or with the fixed trigger the policy trained with, there is no mu to compare
    assert "thresholded" not in evaluation.evaluate_policy_modes(policy, env, 2, 100)["modes"]
    own = evaluation.evaluate_policy_modes(
        policy, env, 2, 100, own_trigger=PeriodicTrigger(2), fixed_families=("send_on_delta",), tune_episodes=2
    )
    assert "thresholded" not in own and "thresholded" not in own["modes"]


def test_mu_thresholded_is_left_out_with_its_reason_where_there_is_no_rate_to_tune_to() -> None:
    """A policy over options that never broadcasts saves everything: no threshold to tune, the rest goes on."""
    env = gym.make("sb3_detc/LinearETC-LQR-v0", n_agents=3, max_cycles=20)
    kwargs = {"net_arch": [8], "broadcast_prob_init": 1e-4}
    policy = MAPPOC("MlpHybridPolicy", env, policy_kwargs=kwargs, seed=0).policy
    result = evaluation.evaluate_policy_modes(policy, env, 2, 100, fixed_families=("send_on_delta",), tune_episodes=2)
    assert result["metrics"]["savings"] == 1.0
    assert result["thresholded"].startswith("left out: target_savings must be in (0, 1)")
    assert "thresholded" not in result["modes"] and not any(k.startswith("thresholded") for k in result["metrics"])


def test_a_family_that_cannot_reach_the_rate_or_run_in_the_env_is_left_out_with_its_reason() -> None:
    env = gym.make(ENV_ID, **SETTINGS)
    policy = MAPPOC("MlpHybridPolicy", env, policy_kwargs={"net_arch": [8]}, seed=0).policy
    result = evaluation.evaluate_policy_modes(
        policy, env, 4, 7, own_trigger=RandomTrigger(0.0, seed=1), fixed_families=("periodic",), tune_episodes=2
    )
    assert result["metrics"]["savings"] == 0.0  # no rate below every period's: nothing encloses it
    assert result["fixed"]["periodic"] == "left out: target_savings must be in (0, 1), got 0.0."
    assert "fixed_periodic_control_return" not in result["metrics"] and result["best_fixed"] is None
    with pytest.raises(ValueError, match="fixed_families must be names from"):
        evaluation.evaluate_policy_modes(policy, env, 2, 7, fixed_families=("sometimes",))
    multiwalker = gym.make("sb3_detc/MultiwalkerETC-v0")
    with pytest.raises(ValueError):
        evaluation.fixed_family_env(multiwalker, "predictive")  # no linear system to predict with
    assert evaluation.fixed_family_env(multiwalker, "periodic") is multiwalker


def test_predictive_triggering_runs_with_lqr_on_the_predicted_states_in_every_copy() -> None:
    """Side by side, the copies of the predictive family's env act on the predicted states too."""
    env = gym.make("sb3_detc/LinearETC-LQR-v0", n_agents=3, max_cycles=30)
    policy = MAPPOC("MlpHybridPolicy", env, policy_kwargs={"net_arch": [8]}, seed=0).policy
    trigger = PredictiveTrigger(env, 0.3)
    seeds = [5, 6, 7, 8]
    side_by_side = evaluate_episodes(
        policy, evaluation.fixed_family_env(env, "predictive"), seeds, fixed_trigger=trigger
    )
    joint = joint_env(n_agents=3, max_cycles=30)  # no spec: one episode after another
    one_by_one = evaluate_episodes(
        policy, FixedControl(joint, lqr_on_predicted_states(joint)), seeds, fixed_trigger=trigger
    )
    np.testing.assert_allclose(side_by_side.control_returns, one_by_one.control_returns, rtol=1e-6)
    held = evaluate_episodes(policy, env, seeds, fixed_trigger=trigger)
    assert not np.allclose(held.control_returns, one_by_one.control_returns)  # the controllers differ
    # from the env that shows the receivers' predictions as held, the family runs on the held broadcasts
    shown = gym.make("sb3_detc/LinearETC-LQR-v0", n_agents=3, max_cycles=30, prediction=True, predicted_held=True)
    from_shown = evaluate_episodes(
        policy, evaluation.fixed_family_env(shown, "predictive"), seeds, fixed_trigger=trigger
    )
    np.testing.assert_allclose(from_shown.control_returns, one_by_one.control_returns, rtol=1e-6)


@pytest.mark.parametrize("control", [None, "lqr_on_predicted_states", "a law"])
def test_a_fixed_control_put_around_by_hand_is_made_again_and_runs_side_by_side(
    monkeypatch: pytest.MonkeyPatch, control
) -> None:
    """A FixedControl around a made env records its law in the spec: copies act as the env does."""
    made = gym.make(ENV_ID, n_agents=3, max_cycles=30)
    law = lqr_on_predicted_states(made) if control == "a law" else control
    wrapped = FixedControl(made, law)
    copy = gym.make(wrapped.spec)
    assert isinstance(copy, FixedControl) and copy.spec.kwargs == made.spec.kwargs
    if control == "a law":
        assert copy.control is law  # a law given as a function is shared
    policy = MAPPOC("MlpHybridPolicy", made, policy_kwargs={"net_arch": [8]}, seed=0).policy
    trigger, seeds = PeriodicTrigger(4), [5, 6, 7, 8]
    made_again = []
    original_make = gym.make
    monkeypatch.setattr(gym, "make", lambda *args, **kwargs: made_again.append(args) or original_make(*args, **kwargs))
    side_by_side = evaluate_episodes(policy, wrapped, seeds, fixed_trigger=trigger)
    assert len(made_again) == len(seeds) - 1  # copies, not one episode after another
    monkeypatch.undo()
    joint = joint_env(n_agents=3, max_cycles=30)  # no spec: one episode after another
    one_by_one = evaluate_episodes(policy, FixedControl(joint, law), seeds, fixed_trigger=trigger)
    np.testing.assert_allclose(side_by_side.control_returns, one_by_one.control_returns, rtol=1e-6)


def test_a_fixed_control_shares_a_callable_object_with_its_copy() -> None:
    """The law is not deep-copied (it may hold an env): the wrapper and the spec's copy use the one given."""

    class Law:
        def __init__(self, env: gym.Env) -> None:
            self.law = lqr_on_predicted_states(env)

        def __call__(self, obs, broadcast):
            return self.law(obs, broadcast)

    made = gym.make(ENV_ID, n_agents=3, max_cycles=30)
    law = Law(made)
    wrapped = FixedControl(made, law)
    assert wrapped.control is law
    copy = gym.make(wrapped.spec)
    assert copy.control is law


def test_the_env_that_shows_the_receivers_predictions_is_made_again_from_its_spec() -> None:
    """gym.make(spec) of the registered env with ReceiverPredictions gives the same wrappers and observations."""
    shown = gym.make("sb3_detc/LinearETC-LQR-v0", n_agents=3, prediction=True, predicted_held=True)
    copy = gym.make(shown.spec)
    assert str(copy) == str(shown) and copy.spec.additional_wrappers == shown.spec.additional_wrappers
    first, _ = shown.reset(seed=3)
    again, _ = copy.reset(seed=3)
    step = {"broadcast": np.zeros(3, dtype=np.int64), "control": np.zeros((3, 1), dtype=np.float32)}
    for _ in range(5):
        first, *_ = shown.step(step)
        again, *_ = copy.step(step)
    for key in first:
        np.testing.assert_array_equal(first[key], again[key], err_msg=key)


def test_a_fixed_control_refuses_an_unknown_law_name() -> None:
    with pytest.raises(ValueError, match=r"unknown control law 'lqr'; the named laws are \['lqr_on_held_states'"):
        FixedControl(gym.make(ENV_ID), "lqr")


def test_per_episode_values_are_kept_as_the_shortest_decimals_of_their_float32_values() -> None:
    values = np.array([-9.123456789012345, 1.0, 123456.789, 1e-9, np.nan])
    kept = evaluation.float32_list(values)
    assert kept[:4] == [-9.123457, 1.0, 123456.79, 1e-09] and np.isnan(kept[4])
    np.testing.assert_array_equal(np.float32(kept), np.float32(values))  # the same float32 values
