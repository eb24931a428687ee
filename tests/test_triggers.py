"""Tests of the fixed triggers: schedules, rules, predictive triggering, the tuner, and triggers in rollout workers."""

from __future__ import annotations

import math
import pickle
from functools import partial

import gymnasium
import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.envs.linear import HeldStatePredictor, LinearSystem
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.workers import RolloutWorker
from sb3_detc.network import advance_timer
from sb3_detc.triggers import (
    TRIGGER_FAMILIES,
    DitheredTrigger,
    PeriodicTrigger,
    PredictiveTrigger,
    ReceiverPredictions,
    SavingsNotReached,
    SendOnDelta,
    bracket_trigger,
    evaluate_trigger,
    family_max_age,
    lqr_on_held_states,
    lqr_on_predicted_states,
    tune_trigger,
    tune_trigger_on_env,
)

SYSTEM = LinearSystem()


def schedule(trigger, n_agents: int, n_steps: int, age: np.ndarray | None = None) -> np.ndarray:
    """Options (n_steps, N) of a trigger that reads only ages, driven from the reset (all ages 0) or from ``age``."""
    age = np.zeros((1, n_agents, 1)) if age is None else np.asarray(age, dtype=np.float64)[None]
    options = []
    for _ in range(n_steps):
        decided = trigger({"age": age.astype(np.float32)})[0]
        options.append(decided)
        age = advance_timer(age, decided[None])
    return np.array(options)


def random_obs(rng: np.random.Generator, batch: int = 5, n_agents: int = 3) -> dict[str, np.ndarray]:
    """A batch of joint observations of the linear system with random states and ages."""
    state = rng.normal(size=(batch, n_agents, 2)).astype(np.float32)
    held = rng.normal(size=(batch, n_agents, 2)).astype(np.float32)
    return {
        "local": state,
        "message": state,
        "held": held,
        "age": rng.integers(0, 12, size=(batch, n_agents, 1)).astype(np.float32),
        "trigger": state,
        "trigger_held": held,
    }


# ------------------------------------------------------------------ periodic
def test_periodic_in_phase_broadcasts_every_period_with_all_agents_together():
    options = schedule(PeriodicTrigger(4), n_agents=3, n_steps=40)
    expected = np.zeros(40, np.int64)
    expected[3::4] = 1  # steps 3, 7, ..., 39
    np.testing.assert_array_equal(options, np.repeat(expected[:, None], 3, axis=1))


def test_periodic_staggered_schedule_of_three_agents_by_hand():
    # Offsets floor(i * 3 / 3) = 0, 1, 2: agent 0 at steps 2, 5, 8; agent 1 at 1, 4, 7; agent 2 at 0, 3, 6.
    options = schedule(PeriodicTrigger(3, staggered=True), n_agents=3, n_steps=9)
    expected = np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0]] * 3)
    np.testing.assert_array_equal(options, expected)
    np.testing.assert_array_equal(PeriodicTrigger(3, staggered=True).offsets(3), [0, 1, 2])


@pytest.mark.parametrize(
    ("n_agents", "period"),
    # (2, 5): a phase rule "fire early while the own age is the largest" would fire again in steady state there.
    [(2, 5), (3, 4), (3, 10), (4, 4), (5, 2), (7, 3), (3, 1), (2, 16)],
)
def test_periodic_staggered_keeps_exact_rates_and_phases_over_long_episodes(n_agents, period):
    n_periods = 25
    options = schedule(PeriodicTrigger(period, staggered=True), n_agents, n_periods * period)
    offsets = np.arange(n_agents) * period // n_agents
    for i in range(n_agents):
        steps = np.flatnonzero(options[:, i])
        # First broadcast at period - 1 - o_i, then exactly one every period: a rate of 1 / period.
        np.testing.assert_array_equal(steps, np.arange(period - 1 - offsets[i], n_periods * period, period))
    # Spread over the period: at most ceil(N / period) agents in any step.
    assert options.sum(axis=1).max() == math.ceil(n_agents / period)


def test_periodic_staggered_restarts_its_clock_when_agent_0_is_too_old():
    # Agent 0's age is past the period (e.g. another trigger ran before): only the offset-0 agents broadcast
    # now (agents 0 and 1 of 4 with period 2, offsets 0, 0, 1, 1), then the schedule runs from there.
    options = schedule(PeriodicTrigger(2, staggered=True), n_agents=4, n_steps=5, age=[[37], [3], [5], [0]])
    expected = [[1, 1, 0, 0], [0, 0, 1, 1], [1, 1, 0, 0], [0, 0, 1, 1], [1, 1, 0, 0]]
    np.testing.assert_array_equal(options, expected)


# ------------------------------------------------------------------ send-on-delta with a maximum age
def test_max_age_forces_a_broadcast_and_the_delta_rule_still_holds():
    # Agent 0 moved by 0.5 (above delta = 0.3), agents 1 and 2 by 0.1 (below); ages 0, 1 and 2.
    trigger_held = np.zeros((1, 3, 2), np.float32)
    trigger = np.array([[[0.5, 0.0], [0.1, 0.0], [0.0, 0.1]]], np.float32)
    obs = {"trigger": trigger, "trigger_held": trigger_held, "age": np.array([[[0.0], [1.0], [2.0]]], np.float32)}
    np.testing.assert_array_equal(SendOnDelta(0.3)(obs), [[1, 0, 0]])
    # max_age = 3: an agent whose age would reach 3 (age 2 now) broadcasts although it barely moved.
    np.testing.assert_array_equal(SendOnDelta(0.3, max_age=3)(obs), [[1, 0, 1]])
    np.testing.assert_array_equal(SendOnDelta(0.3, max_age=2)(obs), [[1, 1, 1]])
    # A still system and a huge delta: the maximum age alone decides, as a periodic trigger with that period.
    still = schedule(lambda o: SendOnDelta(1e9, max_age=4)({**o, **still_features}), n_agents=3, n_steps=20)
    np.testing.assert_array_equal(still, schedule(PeriodicTrigger(4), n_agents=3, n_steps=20))


still_features = {"trigger": np.zeros((1, 3, 2), np.float32), "trigger_held": np.zeros((1, 3, 2), np.float32)}


# ------------------------------------------------------------------ common to the stateless triggers
STATELESS = [
    PeriodicTrigger(3),
    PeriodicTrigger(4, staggered=True),
    SendOnDelta(0.5),
    SendOnDelta(0.5, norm=np.inf, max_age=6),
    PredictiveTrigger(SYSTEM, 0.5),
]


@pytest.mark.parametrize("trigger", STATELESS, ids=repr)
def test_stateless_triggers_fork_to_themselves_and_give_their_options_as_probabilities(trigger):
    obs = random_obs(np.random.default_rng(0))
    options = trigger(obs)
    assert options.shape == (5, 3) and options.dtype == np.int64
    assert trigger.fork(7) is trigger
    np.testing.assert_array_equal(trigger.broadcast_probability(obs), options.astype(np.float64))
    # A pure function of the observation: row by row as in a batch, and the same after pickling.
    np.testing.assert_array_equal(
        np.concatenate([trigger({k: v[b : b + 1] for k, v in obs.items()}) for b in range(5)]), options
    )
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(trigger))(obs), options)


# ------------------------------------------------------------------ dithered
def test_a_dithered_trigger_skips_and_adds_broadcasts_at_its_rates_and_forks_independently():
    followed = PeriodicTrigger(4)
    obs = {"age": np.tile(np.arange(4, dtype=np.float32)[:, None, None], (25_000, 3, 1))}  # ages 0-3, agent by agent
    due = followed(obs) == 1  # age 3: due
    dithered = DitheredTrigger(followed, skip_prob=0.2, extra_prob=0.05, seed=1)
    options = dithered(obs)
    assert options.dtype == np.int64 and set(np.unique(options)) == {0, 1}
    assert abs(options[due].mean() - 0.8) < 0.01 and abs(options[~due].mean() - 0.05) < 0.005
    np.testing.assert_allclose(dithered.broadcast_probability(obs), np.where(due, 0.8, 0.05))
    # copies for the rollout workers draw their own deviations, the same for the same seed
    first, again, other = (dithered.fork(seed)(obs) for seed in (5, 5, 6))
    np.testing.assert_array_equal(first, again)
    assert (first != other).any()
    # no deviations: the followed trigger itself
    np.testing.assert_array_equal(DitheredTrigger(followed, 0.0, 0.0)(obs), followed(obs))
    for bad in ({"skip_prob": 1.5}, {"extra_prob": -0.1}, {"skip_prob": True}):
        with pytest.raises(ValueError, match="must be in \\[0, 1\\]"):
            DitheredTrigger(followed, **{"skip_prob": 0.1, "extra_prob": 0.1, **bad})


# ------------------------------------------------------------------ predictive triggering
# A tiny system by hand: 2 agents, dt = 1, so A = [[1, 1], [0, 1]] and B = [0.5, 1] per agent (episodes of one
# step: the ages below extend the precomputed powers). A chosen gain K = [[1, 1, 0.5, 0], [0.2, 0, 0, 0]]:
# agent 0's own block K_00 = [1, 1], agent 1's K_11 = [0, 0].
TINY = LinearSystem(n_agents=2, dt=1.0, max_cycles=1)
GAIN = np.array([[1.0, 1.0, 0.5, 0.0], [0.2, 0.0, 0.0, 0.0]])
# Phi_0 = A - B K_00 = [[1 - 0.5, 1 - 0.5], [0 - 1, 1 - 1]] = [[0.5, 0.5], [-1, 0]]; Phi_1 = A (open loop).
# Agent 0 held (1, 0) and age 1 (before this step): silent, its age becomes 2 and
#   Phi_0 (1, 0) = (0.5, -1), Phi_0 (0.5, -1) = (0.25 - 0.5, -0.5) = (-0.25, -0.5).
# Agent 1 held (0, 1) and age 2: silent, its age becomes 3 and A^3 (0, 1) = (3, 1).
TINY_OBS = {
    "held": np.array([[[1.0, 0.0], [0.0, 1.0]]], np.float32),
    "age": np.array([[[1.0], [2.0]]], np.float32),
    # Current states: agent 0 is 0.1 off its prediction, agent 1 (0.3, 0.4) off, i.e. 0.5 in the Euclidean norm.
    "message": np.array([[[-0.25, -0.4], [3.3, 1.4]]], np.float32),
}
TINY_OBS["local"] = TINY_OBS["trigger"] = TINY_OBS["message"]


def test_held_state_prediction_by_hand():
    predictor = HeldStatePredictor(TINY, GAIN)
    np.testing.assert_allclose(predictor.closed_loop, [[[0.5, 0.5], [-1.0, 0.0]], [[1.0, 1.0], [0.0, 1.0]]])
    predicted = predictor(TINY_OBS["held"], TINY_OBS["age"] + 1)
    np.testing.assert_allclose(predicted, [[[-0.25, -0.5], [3.0, 1.0]]], atol=1e-12)
    # Age 0: the held broadcast itself; the LQR gain by default.
    np.testing.assert_allclose(predictor(TINY_OBS["held"], np.zeros((1, 2, 1))), TINY_OBS["held"])
    assert HeldStatePredictor(TINY).closed_loop.shape == (2, 2, 2)


def test_predictive_trigger_by_hand():
    np.testing.assert_allclose(PredictiveTrigger(TINY, 0.15, gain=GAIN).error(TINY_OBS), [[0.1, 0.5]], atol=1e-6)
    deviation = PredictiveTrigger(TINY, 0.15, gain=GAIN).deviation(TINY_OBS)  # message minus prediction
    np.testing.assert_allclose(deviation, [[[0.0, 0.1], [0.3, 0.4]]], atol=1e-6)
    # Errors 0.1 and 0.5: delta 0.05 -> both broadcast; 0.15 -> agent 1 only; 0.6 -> none.
    for delta, expected in ((0.05, [[1, 1]]), (0.15, [[0, 1]]), (0.6, [[0, 0]])):
        np.testing.assert_array_equal(PredictiveTrigger(TINY, delta, gain=GAIN)(TINY_OBS), expected)
    # In the maximum norm agent 1 is 0.4 off: delta 0.45 keeps it silent.
    np.testing.assert_array_equal(PredictiveTrigger(TINY, 0.45, norm=np.inf, gain=GAIN)(TINY_OBS), [[0, 0]])


def test_lqr_on_predicted_states_by_hand():
    obs = {key: value[0] for key, value in TINY_OBS.items()}
    # Agent 1 broadcasts: receivers hold (3.3, 1.4) with age 0; agent 0 is predicted at (-0.25, -0.5).
    # u_0 = -(1 * -0.25 + 1 * -0.4 + 0.5 * 3.3) = -1.0 (its own current state, agent 1's broadcast);
    # u_1 = -(0.2 * -0.25) = 0.05 (agent 0's prediction).
    controls = lqr_on_predicted_states(TINY, GAIN)(obs, np.array([0, 1]))
    np.testing.assert_allclose(controls, [[-1.0], [0.05]], atol=1e-6)


def test_lqr_on_predicted_states_with_broadcasts_every_step_is_lqr_on_held_states():
    env = gymnasium.make("sb3_detc/LinearETC-v0")
    always = PeriodicTrigger(1)
    predicted = evaluate_trigger(env, always, lqr_on_predicted_states(env), n_episodes=2, seed=3)
    held = evaluate_trigger(env, always, lqr_on_held_states(env), n_episodes=2, seed=3)
    assert predicted.cost == pytest.approx(held.cost, rel=1e-9)


def test_receiver_predictions_show_what_the_receivers_believe_and_turn_send_on_delta_into_predictive_triggering():
    plain = gymnasium.make("sb3_detc/LinearETC-LQR-v0", prediction=True)
    shown = gymnasium.make("sb3_detc/LinearETC-LQR-v0", prediction=True, predicted_held=True)
    predictor = HeldStatePredictor(SYSTEM)
    predictive, on_delta = PredictiveTrigger(SYSTEM, 0.05), SendOnDelta(0.05)
    rng = np.random.default_rng(0)
    (obs, _), (seen, _) = plain.reset(seed=4), shown.reset(seed=4)
    decided = []
    for _ in range(40):
        # every key as without the wrapper but what is held: the prediction if the agent stays silent now
        for key in ("local", "message", "age", "trigger"):
            np.testing.assert_array_equal(seen[key], obs[key])
        for key in ("held", "trigger_held"):
            np.testing.assert_allclose(seen[key], predictor(obs["held"], obs["age"] + 1), atol=1e-6)
        batch = {key: value[None] for key, value in seen.items()}
        decided.append(predictive({key: value[None] for key, value in obs.items()})[0])
        np.testing.assert_array_equal(on_delta(batch)[0], decided[-1])
        n = len(obs["held"])
        action = {"broadcast": rng.integers(0, 2, n), "control": np.zeros((n, 1), np.float32)}
        (obs, *_), (seen, *_) = plain.step(action), shown.step(action)
    assert 0 < np.mean(decided) < 1  # both options were compared
    with pytest.raises(ValueError, match="predicted_held=True needs prediction=True"):
        gymnasium.make("sb3_detc/LinearETC-LQR-v0", predicted_held=True)
    # what reads held as the broadcasts refuses the env that shows predictions there (no prediction twice)
    for reads_held in (
        partial(PredictiveTrigger, delta=0.1),
        lqr_on_predicted_states,
        lqr_on_held_states,
        ReceiverPredictions,
    ):
        with pytest.raises(ValueError, match="shows the receivers' predictions in their place"):
            reads_held(shown)


# ------------------------------------------------------------------ tuner
@pytest.fixture(scope="module")
def env() -> gymnasium.Env:
    return gymnasium.make("sb3_detc/LinearETC-v0")


@pytest.mark.parametrize("family", TRIGGER_FAMILIES)
def test_tuner_reaches_the_target_within_its_tolerance_on_the_linear_system(env, family):
    trigger, point = tune_trigger_on_env(env, family, 0.9, n_episodes=3, seed=1, tolerance=0.005)
    assert abs(point.savings - 0.9) <= 0.005
    assert point.label == repr(trigger) and point.episodes == 3
    # The point is the trigger's own on those episodes (with the control law that goes with the family).
    control = lqr_on_predicted_states(env) if family == "predictive" else lqr_on_held_states(env)
    assert evaluate_trigger(env, trigger, control, n_episodes=3, seed=1, label=repr(trigger)) == point
    if family.startswith("periodic"):
        assert trigger.period == 10 and trigger.staggered == family.endswith("staggered")
    if family == "send_on_delta_max_age":
        assert trigger.max_age == family_max_age(0.9) == 20


def test_tuner_bisects_a_threshold_to_the_target():
    # Savings 1 - exp(-delta) reach 0.75 at delta = ln 4 = 1.386: from 1 (0.63) to 2 (0.86), then bisection.
    tried = []

    def savings_of(trigger):
        tried.append(trigger.delta)
        return 1 - math.exp(-trigger.delta)

    trigger, savings = tune_trigger(SendOnDelta, savings_of, 0.75, tolerance=1e-4)
    assert abs(savings - 0.75) <= 1e-4 and trigger.delta == pytest.approx(math.log(4), rel=1e-3)
    assert tried[:2] == [1.0, 2.0] and all(1.0 <= delta <= 2.0 for delta in tried)
    with pytest.raises(SavingsNotReached, match="in 3 evaluations; closest"):
        tune_trigger(SendOnDelta, savings_of, 0.75, tolerance=1e-4, max_iterations=3)


def test_tuner_refuses_a_periodic_target_between_two_periods():
    # Savings 0.6 lie between period 2 (0.5) and period 3 (0.667): no period within 0.01.
    with pytest.raises(SavingsNotReached, match="period 2 gives 0.5000, period 3 gives 0.6667"):
        tune_trigger("periodic", lambda trigger: 1 - 1 / trigger.period, 0.6)
    trigger, savings = tune_trigger("periodic_staggered", lambda trigger: 1 - 1 / trigger.period, 0.6, tolerance=0.1)
    assert trigger.period == 3 and trigger.staggered and savings == pytest.approx(2 / 3)


def test_a_bracket_encloses_the_target_with_two_thresholds_at_most_the_tolerance_apart():
    def savings_of(trigger):
        return 1 - math.exp(-trigger.delta)

    bracket = bracket_trigger(SendOnDelta, savings_of, 0.75, tolerance=1e-3)
    assert bracket.lower_savings < 0.75 <= bracket.upper_savings <= bracket.lower_savings + 1e-3
    assert bracket.lower.delta == bracket.lower_parameter < math.log(4)
    assert math.log(4) <= bracket.upper.delta == bracket.upper_parameter
    assert (savings_of(bracket.lower), savings_of(bracket.upper)) == (bracket.lower_savings, bracket.upper_savings)
    # a start near the target and a small step find it in few evaluations
    tried = []
    bracket_trigger(SendOnDelta, lambda t: tried.append(t) or savings_of(t), 0.75, 1e-3, initial=1.38, factor=1.01)
    assert len(tried) <= 5
    # one that meets the target is both ends
    exact = bracket_trigger(SendOnDelta, lambda trigger: 0.5 if trigger.delta >= 1 else 0.25, 0.5)
    assert exact.lower is exact.upper and exact.lower.delta == 1.0
    with pytest.raises(SavingsNotReached, match="no two triggers enclose savings 0.9 in 4 evaluations"):
        bracket_trigger(SendOnDelta, lambda trigger: 0.5, 0.9, max_iterations=4)


def test_a_periodic_bracket_steps_to_the_two_neighbouring_periods_that_enclose_the_target():
    def savings_of(trigger):
        return 1 - 1 / trigger.period

    bracket = bracket_trigger("periodic_staggered", savings_of, 0.6)
    assert (bracket.lower.period, bracket.upper.period) == (2, 3) and bracket.upper.staggered
    assert (bracket.lower_savings, bracket.upper_savings) == (0.5, pytest.approx(2 / 3))
    exact = bracket_trigger("periodic", savings_of, 0.75)
    assert exact.lower is exact.upper and exact.lower.period == 4
    # savings on real episodes differ from 1 - 1 / period: the search steps on from floor(1 / (1 - target)) = 3
    tried = []

    def shifted(trigger):
        tried.append(trigger.period)
        return 1 - 1 / trigger.period - 0.02

    bracket = bracket_trigger("periodic", shifted, 0.74)
    assert tried == [3, 4, 5] and (bracket.lower.period, bracket.upper.period) == (4, 5)
    tried.clear()
    assert bracket_trigger("periodic", shifted, 0.45).upper.period == 2 and tried == [1, 2]
    with pytest.raises(SavingsNotReached, match="no two triggers enclose savings 0.5 in 3 evaluations"):
        bracket_trigger("periodic", lambda trigger: 0.0, 0.5, max_iterations=3)


# ------------------------------------------------------------------ bad inputs
@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: PeriodicTrigger(0), "period must be an integer >= 1"),
        (lambda: PeriodicTrigger(2.5), "period must be an integer >= 1"),
        (lambda: PeriodicTrigger(3, staggered="yes"), "staggered must be a bool"),
        (lambda: SendOnDelta(0.1, max_age=0), "max_age must be an integer >= 1"),
        (lambda: SendOnDelta(0.1, max_age=True), "max_age must be an integer >= 1"),
        (lambda: SendOnDelta(-1.0), "delta must be a finite number >= 0"),
        (lambda: PredictiveTrigger(SYSTEM, float("nan")), "delta must be a finite number >= 0"),
        (lambda: PredictiveTrigger(SYSTEM, 0.1, norm=0.5), "norm must be a number >= 1"),
        (lambda: PredictiveTrigger(gymnasium.make("CartPole-v1"), 0.1), "PredictiveTrigger needs a LinearSystem"),
        (lambda: PredictiveTrigger(SYSTEM, 0.1, gain=np.zeros((3, 3))), "gain must have shape"),
        (lambda: lqr_on_predicted_states(gymnasium.make("CartPole-v1")), "lqr_on_predicted_states needs"),
        (lambda: HeldStatePredictor(SYSTEM)(np.zeros((3, 2)), -np.ones((3, 1))), "whole numbers of steps >= 0"),
        (lambda: HeldStatePredictor(SYSTEM)(np.zeros((3, 2)), np.full((3, 1), 0.5)), "whole numbers of steps"),
        (lambda: HeldStatePredictor(SYSTEM)(np.zeros((2, 2)), np.zeros((2, 1))), "held must have shape"),
        (lambda: tune_trigger("sometimes", len, 0.9), "family must be one of"),
        (lambda: tune_trigger(3, len, 0.9), "family must be one of"),
        (lambda: tune_trigger("periodic", len, 1.0), r"target_savings must be in \(0, 1\)"),
        (lambda: tune_trigger("periodic", len, 0.9, tolerance=0), r"tolerance must be in \(0, 1\)"),
        (lambda: tune_trigger("send_on_delta", len, 0.9, max_iterations=0), "max_iterations must be an integer"),
        (lambda: tune_trigger("send_on_delta", len, 0.9, initial=0), "initial must be a finite number > 0"),
        (lambda: tune_trigger("predictive", len, 0.9), "the family 'predictive' needs a LinearSystem"),
        (lambda: bracket_trigger("send_on_delta", len, 0.9, factor=1.0), "factor must be a finite number > 1"),
        (lambda: bracket_trigger("periodic", len, 0.0), r"target_savings must be in \(0, 1\)"),
    ],
)
def test_bad_inputs_are_refused_with_one_clear_line(build, match):
    with pytest.raises(ValueError, match=match) as raised:
        build()
    assert "\n" not in str(raised.value)


# ------------------------------------------------------------------ in MAPPOC's rollout workers
@pytest.mark.parametrize("trigger", [PeriodicTrigger(4, staggered=True), PredictiveTrigger(SYSTEM, 0.2)], ids=repr)
def test_a_fixed_trigger_decides_in_the_rollout_workers(trigger):
    env = make_vec_env(
        "sb3_detc/LinearETC-v0",
        n_envs=2,
        seed=0,
        env_kwargs={"max_cycles": 20},
        wrapper_class=RolloutWorker,
    )
    model = MAPPOC("MlpHybridPolicy", env, n_steps=16, batch_size=16, n_epochs=1, seed=0, fixed_trigger=trigger)
    model.learn(32)
    assert model.sampler.last_in_workers
    buffer = model.rollout_buffer
    # Stateless: the options of every row of the buffer are the trigger's on that row's observation.
    rows = {key: value.reshape(-1, *value.shape[2:]) for key, value in buffer.observations.items()}
    np.testing.assert_array_equal(buffer.broadcast.reshape(-1, 3), trigger(rows))
    assert 0 < buffer.broadcast.mean() < 1
