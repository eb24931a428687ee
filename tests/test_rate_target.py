"""MAPPOC's rate target: a price per broadcast (``target_savings``) and its rules, and mu's own-age input."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch as th
import yaml
from logged import capture_logger  # tests/logged.py
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.save_util import load_from_zip_file, save_to_zip_file

import sb3_detc  # noqa: F401  (registers the env ids)
from sb3_detc.callbacks import ControlFirstCallback, RandomSkipCallback
from sb3_detc.cli import InputError, check_hyperparams_file
from sb3_detc.mappoc import MAPPOC
from sb3_detc.mappoc.critics import CRITICS
from sb3_detc.mappoc.rewards import PRICE_RULES
from sb3_detc.mappoc.workers import RolloutWorker
from sb3_detc.triggers import PeriodicTrigger, SendOnDelta

LQR = "sb3_detc/LinearETC-LQR-v0"


class Rollouts(BaseCallback):
    """Every rollout's broadcast rate and the price after the update that followed it."""

    def __init__(self) -> None:
        super().__init__()
        self.rates: list[float] = []
        self.prices: list[float] = []

    def _on_rollout_start(self) -> None:
        if self.rates:
            self.prices.append(self.model.broadcast_price)

    def _on_rollout_end(self) -> None:
        self.rates.append(float(self.model.rollout_buffer.broadcast.mean()))

    def _on_training_end(self) -> None:
        self.prices.append(self.model.broadcast_price)

    def _on_step(self) -> bool:
        return True


def make(**kwargs: Any) -> MAPPOC:
    env = make_vec_env(LQR, n_envs=2, seed=0, wrapper_class=RolloutWorker, env_kwargs={"broadcast_cost": 0.0})
    settings = {
        "n_steps": 64,
        "batch_size": 64,
        "n_epochs": 4,
        "learning_rate": 3e-3,
        "gamma": 0.95,
        "normalize_reward": True,
        "broadcast_ent_coef": 0.0,
        "normalize_broadcast_advantage": True,
        "torch_compile": False,
        "seed": 0,
        "policy_kwargs": {"net_arch": [16], "broadcast_prob_init": 0.5, "critic": "afterstate"},
        **kwargs,
    }
    return MAPPOC("MlpHybridPolicy", env, **settings)


def test_the_price_follows_dual_ascent_and_moves_the_rate_toward_the_target() -> None:
    model = make(target_savings=0.9, broadcast_price_lr=0.5)
    rollouts = Rollouts()
    capture = capture_logger(model)
    model.learn(12 * 128, callback=rollouts)
    price = 0.0
    for rate, logged in zip(rollouts.rates, rollouts.prices, strict=True):
        price += 0.5 * (rate - 0.1)  # the rate above the target's 10 % raises the price
        assert logged == pytest.approx(price, abs=1e-6)
    # a dump at the start of iteration k + 1 shows update k's price (the last update's is not dumped)
    logged = [row["train/broadcast_price"] for row in capture.rows if "train/broadcast_price" in row]
    assert logged == pytest.approx(rollouts.prices[:-1], abs=1e-6)
    assert rollouts.rates[0] > 0.4  # mu starts undecided
    assert np.mean(rollouts.rates[-3:]) < rollouts.rates[0] - 0.15  # and broadcasts less as the price rises
    assert model.broadcast_price > 0


def test_a_price_below_zero_subsidises_broadcasts_when_the_agents_are_too_quiet() -> None:
    model = make(
        target_savings=0.2,
        broadcast_price_lr=0.5,
        policy_kwargs={"net_arch": [16], "broadcast_prob_init": 0.1, "critic": "afterstate"},
    )
    rollouts = Rollouts()
    model.learn(6 * 128, callback=rollouts)
    assert rollouts.rates[0] < 0.2 and model.broadcast_price < 0


def test_without_a_target_there_is_no_price() -> None:
    model = make()
    capture = capture_logger(model)
    model.learn(3 * 128)
    assert model.broadcast_price == 0.0 and "train/n_updates" in capture.rows[-1]
    assert not any("train/broadcast_price" in row for row in capture.rows)


def test_the_price_and_the_target_are_saved_and_restored(tmp_path) -> None:
    model = make(target_savings=0.8, broadcast_price_lr=0.25)
    model.learn(256)
    assert model.broadcast_price != 0.0
    model.save(tmp_path / "model.zip")
    loaded = MAPPOC.load(tmp_path / "model.zip", env=model.get_env())
    assert (loaded.target_savings, loaded.broadcast_price_lr) == (0.8, 0.25)
    assert loaded.broadcast_price == model.broadcast_price
    loaded.learn(128, reset_num_timesteps=False)  # trains on from the restored price
    assert loaded.broadcast_price != model.broadcast_price


@pytest.mark.parametrize("critic", CRITICS)
def test_the_price_reaches_the_rewards_and_the_critics_price(critic: str) -> None:
    """The learner's reward of a broadcast is lowered by the price; the price the critics read includes it."""
    model = make(target_savings=0.5, normalize_reward=False, policy_kwargs={"net_arch": [8], "critic": critic})
    model.broadcast_price = 0.7
    seen: dict[str, np.ndarray] = {}

    class Spy(BaseCallback):
        def _on_step(self) -> bool:
            if not seen:
                step = self.locals["step"]
                seen["rewards"] = self.locals["rewards"].copy()
                seen["env_rewards"] = self.locals["env_rewards"][step].copy()
                seen["broadcast"] = self.locals["rollout"].broadcast[step].copy()
            return True

    model.learn(64, callback=Spy())
    expected = model.reward_scale * seen["env_rewards"] - 0.7 * seen["broadcast"]
    np.testing.assert_allclose(seen["rewards"], expected, rtol=1e-6)
    assert 0 < seen["broadcast"].mean() < 1  # both options in the step: the test can tell them apart
    env_price = model.reward_transform.price(np.zeros(2, np.float32))  # the env's cost is 0 here
    np.testing.assert_allclose(model.rollout_buffer.broadcast_price, np.broadcast_to(0.7 + env_price, (64, 2, 3)))


def test_with_a_frozen_controller_only_mu_and_the_price_learn() -> None:
    model = make(target_savings=0.9, broadcast_price_lr=0.5)
    model.set_trained_policies(control_policy=False, broadcast_policy=True)
    pi = [p.clone() for p in model.policy.net_parameters("pi")]
    rollouts = Rollouts()
    model.learn(4 * 128, callback=rollouts)
    assert all(th.equal(a, b) for a, b in zip(pi, model.policy.net_parameters("pi"), strict=True))
    assert model.broadcast_price > 0 and len(rollouts.prices) == 4


def test_rollouts_of_a_passing_fixed_trigger_leave_the_price_alone() -> None:
    """The control-first recipe trains pi under random skips first: mu's rate is not the trigger's."""
    model = make(target_savings=0.9, broadcast_price_lr=0.5)
    stages = ControlFirstCallback(switch=2, skip_prob=0.5)
    rollouts = Rollouts()
    model.learn(4 * 128, callback=[stages, rollouts])
    assert rollouts.prices[:2] == [0.0, 0.0]  # stage 1: the random trigger's rollouts
    assert rollouts.prices[3] != 0.0  # stage 2: mu's


@pytest.mark.parametrize("target", [0.0, 1.0, 1.5, -0.2, True, "0.9"])
def test_a_target_outside_the_open_unit_interval_is_refused(target: Any) -> None:
    with pytest.raises(ValueError, match=r"target_savings must be a number in \(0, 1\)"):
        make(target_savings=target)


def test_a_target_with_a_fixed_trigger_is_refused() -> None:
    with pytest.raises(ValueError, match="give one of target_savings and fixed_trigger"):
        make(target_savings=0.9, fixed_trigger=PeriodicTrigger(4))
    model = make(target_savings=0.9)
    with pytest.raises(ValueError, match="give one of target_savings and fixed_trigger"):
        model.learn(64, callback=RandomSkipCallback(0.5))
    with pytest.raises(ValueError, match="broadcast_price_lr must be > 0"):
        make(target_savings=0.9, broadcast_price_lr=0.0)


def test_hyperparameter_files_set_and_check_the_target(tmp_path) -> None:
    conf = tmp_path / "mappoc.yml"
    entry = {"n_timesteps": 1000, "policy": "MlpHybridPolicy", "target_savings": 0.9, "broadcast_price_lr": 0.1}
    conf.write_text(yaml.safe_dump({LQR: entry}))
    assert check_hyperparams_file(conf, "mappoc", LQR)["target_savings"] == 0.9
    conf.write_text(yaml.safe_dump({LQR: {**entry, "target_savings": 1.5}}))
    with pytest.raises(InputError, match=r"target_savings must be a number in \(0, 1\)"):
        check_hyperparams_file(conf, "mappoc", LQR)


# ------------------------------------------------------------------ mu's own-age input
@pytest.mark.parametrize("option_age_scale", [0.0, 0.25])
def test_mu_reads_its_own_age_only_where_asked(option_age_scale: float) -> None:
    model = make(policy_kwargs={"net_arch": [8], "option_age_scale": option_age_scale})
    policy = model.policy
    obs = {key: th.as_tensor(value) for key, value in model.get_env().reset().items()}
    older = {**obs, "age": obs["age"] + 7.0}
    features, older_features = policy.option_features(obs), policy.option_features(older)
    n_trig = obs["trigger"].shape[-1]
    assert features.shape[-1] == 2 * n_trig + (option_age_scale > 0)
    if option_age_scale > 0:
        th.testing.assert_close(older_features[..., -1] - features[..., -1], th.full(features.shape[:2], 7 * 0.25))
    else:
        assert th.equal(features, older_features)


@pytest.mark.parametrize("option_age_scale", [0.0, 0.25])
def test_mu_reads_the_distance_from_its_last_broadcast_only_where_asked(option_age_scale: float, tmp_path) -> None:
    kwargs = {"net_arch": [8], "option_age_scale": option_age_scale, "option_distance_scale": 2.0}
    policy = make(policy_kwargs=kwargs).policy
    obs = {key: th.as_tensor(value) for key, value in policy.observation_space.sample().items()}
    obs = {key: value[None] for key, value in obs.items()}  # a batch of one
    features = policy.option_features(obs)
    n_trig = obs["trigger"].shape[-1]
    assert features.shape[-1] == 2 * n_trig + (option_age_scale > 0) + 1
    assert policy.chains.specs["mu"].in_features == features.shape[-1]
    distance = th.linalg.vector_norm(obs["trigger"] - obs["trigger_held"], dim=-1)
    th.testing.assert_close(features[..., -1], 2.0 * distance)
    th.testing.assert_close(th.as_tensor(SendOnDelta(0.0).distance(obs)), distance.double())  # send-on-delta's
    if option_age_scale > 0:
        th.testing.assert_close(features[..., -2], obs["age"][..., 0] * option_age_scale)
    assert make(policy_kwargs={"net_arch": [8]}).policy.option_features(obs).shape[-1] == 2 * n_trig
    policy.save(str(tmp_path / "policy.pt"))
    loaded = type(policy).load(str(tmp_path / "policy.pt"), device="cpu")
    assert loaded.option_distance_scale == 2.0
    th.testing.assert_close(loaded.broadcast_probabilities(obs), policy.broadcast_probabilities(obs))
    with pytest.raises(ValueError, match="option_distance_scale must be a finite number >= 0"):
        make(policy_kwargs={"option_distance_scale": -1.0})


def test_mu_reads_the_others_ages_only_where_asked(tmp_path) -> None:
    kwargs = {"net_arch": [8], "option_age_scale": 0.25, "option_others_age_scale": 0.5}
    policy = make(policy_kwargs=kwargs).policy
    n = policy.n_agents
    obs = {key: th.as_tensor(value)[None] for key, value in policy.observation_space.sample().items()}
    obs["age"] = th.arange(n, dtype=th.float32).reshape(1, n, 1) * 3.0  # agent j's age 3 j
    features = policy.option_features(obs)
    n_trig = obs["trigger"].shape[-1]
    assert features.shape == (1, n, 2 * n_trig + 1 + (n - 1))
    assert policy.chains.specs["mu"].in_features == features.shape[-1]
    for i in range(n):
        others = [3.0 * j * 0.5 for j in range(n) if j != i]  # the others in increasing order
        th.testing.assert_close(features[0, i, -(n - 1) :], th.tensor(others))
        th.testing.assert_close(features[0, i, 2 * n_trig], th.tensor(3.0 * i * 0.25))
    policy.save(str(tmp_path / "policy.pt"))
    loaded = type(policy).load(str(tmp_path / "policy.pt"), device="cpu")
    assert loaded.option_others_age_scale == 0.5
    th.testing.assert_close(loaded.broadcast_probabilities(obs), policy.broadcast_probabilities(obs))
    with pytest.raises(ValueError, match="option_others_age_scale must be a finite number >= 0"):
        make(policy_kwargs={"option_others_age_scale": float("nan")})


def test_an_agent_controller_on_the_others_ages_decides_from_them() -> None:
    """A policy over options set by hand to broadcast in the step after one in which agent 0 broadcast."""
    model = make(policy_kwargs={"net_arch": [8], "option_others_age_scale": 1.0})
    n_trig = model.observation_space["trigger"].shape[1]
    option_net = th.nn.Linear(2 * n_trig + 1, 2)  # two agents: agent 1 reads agent 0's age
    with th.no_grad():
        option_net.weight.zero_()
        option_net.bias.zero_()
        option_net.weight[1, -1] = -10.0
        option_net.bias[1] = 5.0  # broadcast while agent 0's age is below 0.5
    controller = model.policy.agent_controller(1)
    controller.option_net = option_net
    trigger = np.zeros(n_trig)
    assert controller.decide(trigger, trigger, True, own_age=4.0, others_age=np.array([0.0]))
    assert not controller.decide(trigger, trigger, True, own_age=4.0, others_age=np.array([2.0]))
    with pytest.raises(ValueError, match="pass others_age"):
        controller.decide(trigger, trigger)


def test_mu_with_the_distance_and_its_own_age_can_represent_send_on_delta_with_a_maximum_age() -> None:
    """A policy over options on the distance and the own age, set by hand, is send-on-delta with a maximum age."""
    model = make(policy_kwargs={"net_arch": [8], "option_age_scale": 1.0, "option_distance_scale": 1.0})
    n_trig = model.observation_space["trigger"].shape[1]
    delta, max_age, sharp = 0.3, 5, 1e4
    hidden, out = th.nn.Linear(2 * n_trig + 2, 2), th.nn.Linear(2, 2)
    with th.no_grad():
        for layer in (hidden, out):
            layer.weight.zero_()
            layer.bias.zero_()
        hidden.weight[0, -1], hidden.bias[0] = sharp, -sharp * delta  # +1 once the distance passes delta
        hidden.weight[1, -2], hidden.bias[1] = sharp, -sharp * (max_age - 1.5)  # +1 from the age max_age - 1
        out.weight[1] = 1.0
        out.bias[1] = 1.0  # broadcast logit: +1 if either is +1, -1 if neither (silent: 0)
    controllers = [model.policy.agent_controller(i) for i in range(model.policy.n_agents)]
    for controller in controllers:
        controller.option_net = th.nn.Sequential(hidden, th.nn.Tanh(), out)
    trigger = SendOnDelta(delta, max_age=max_age)
    env = model.get_env()
    obs = env.reset()
    by_distance = by_age = 0
    for _ in range(40):
        expected = trigger(obs)
        for e in range(expected.shape[0]):
            for i, controller in enumerate(controllers):
                decided = controller.decide(obs["trigger"][e, i], obs["trigger_held"][e, i], True, obs["age"][e, i, 0])
                assert decided == expected[e, i]
        moved = trigger.distance(obs) > delta
        by_distance += int(moved.sum())
        by_age += int((expected.astype(bool) & ~moved).sum())
        controls = np.zeros((len(controllers), 1), np.float32)
        obs, *_ = env.step([{"broadcast": options, "control": controls} for options in expected])
    assert by_distance > 0 and by_age > 0  # both reasons to broadcast occurred


def test_mu_with_its_own_age_can_represent_a_periodic_schedule() -> None:
    """An agent's policy over options on its trigger features and own age, set by hand, is the periodic trigger."""
    model = make(policy_kwargs={"net_arch": [8], "option_age_scale": 1.0})
    n_trig = model.observation_space["trigger"].shape[1]
    option_net = th.nn.Linear(2 * n_trig + 1, 2)
    with th.no_grad():
        option_net.weight.zero_()
        option_net.bias.zero_()
        option_net.weight[1, -1] = 10.0  # the broadcast logit grows with the own age
        option_net.bias[1] = -25.0  # and passes the silent one's between ages 2 and 3
    controller = model.policy.agent_controller(0)
    controller.option_net = option_net
    env = model.get_env()
    obs = env.reset()
    periodic = PeriodicTrigger(4)
    for _ in range(20):
        expected = periodic(obs)[0, 0]
        assert controller.decide(obs["trigger"][0, 0], obs["trigger_held"][0, 0], True, obs["age"][0, 0, 0]) == expected
        actions = [{"broadcast": periodic(obs)[i], "control": np.zeros((3, 1), np.float32)} for i in range(2)]
        obs, *_ = env.step(actions)


def test_the_price_waits_while_mu_does_not_learn() -> None:
    """A critic warming up alone (mu frozen) leaves the price where it is; it moves once mu learns."""
    model = make(target_savings=0.9, broadcast_price_lr=0.5)
    model.set_trained_policies(control_policy=False, broadcast_policy=False)
    model.learn(2 * 128)
    assert model.broadcast_price == 0.0
    model.set_trained_policies(control_policy=False, broadcast_policy=True)
    model.learn(128, reset_num_timesteps=False)
    assert model.broadcast_price != 0.0


def test_the_price_rules_step_as_documented() -> None:
    rng = np.random.default_rng(0)
    option_values = rng.normal(size=(64, 2, 3, 2))
    broadcast = (rng.random((64, 2, 3)) < 0.3).astype(np.int64)
    dual = PRICE_RULES["dual"](target_savings=0.9, lr=0.5)
    assert dual.updated(0.1, broadcast, option_values, mu_took=True) == pytest.approx(
        0.1 + 0.5 * (broadcast.mean() - 0.1)
    )
    assert dual.updated(0.1, broadcast, option_values, mu_took=False) == 0.1  # a fixed trigger's rate is not mu's
    quantile = PRICE_RULES["quantile"](target_savings=0.9, lr=0.5)
    for mu_took in (True, False):  # it reads the critic, whoever took the options
        step = quantile.updated(0.1, broadcast, option_values, mu_took) - 0.1
        gaps = option_values[..., 1] - option_values[..., 0]
        assert np.mean(gaps - step > 0) == pytest.approx(0.1, abs=1 / gaps.size)  # greedy options at the target


def test_the_quantile_price_puts_the_critics_greedy_options_at_the_target() -> None:
    """After every update the critic's greedy options on the rollout's states broadcast at the target rate."""
    model = make(target_savings=0.8, broadcast_price_rule="quantile")
    prices = []

    class Gaps(BaseCallback):
        def _on_rollout_start(self) -> None:
            if self.model.num_timesteps:
                prices.append(self.model.broadcast_price)

        def _on_step(self) -> bool:
            return True

    model.learn(4 * 128, callback=Gaps())
    assert len(set(prices)) == len(prices) == 3 and model.broadcast_price not in prices
    buffer = model.rollout_buffer
    gaps = buffer.option_values[..., 1] - buffer.option_values[..., 0] + buffer.broadcast_price  # without the price
    raw_price = buffer.broadcast_price[0, 0, 0] - prices[-1]  # the env's cost in the learner's units
    share = np.mean(gaps > model.broadcast_price + raw_price)  # the price after the last update
    assert share == pytest.approx(0.2, abs=2 / gaps.size)


def test_the_quantile_price_moves_while_a_fixed_trigger_decides() -> None:
    model = make(target_savings=0.9, broadcast_price_rule="quantile")
    rollouts = Rollouts()
    model.learn(4 * 128, callback=[ControlFirstCallback(switch=2, skip_prob=0.5), rollouts])
    assert rollouts.prices[0] != 0.0  # stage 1: the trigger's options, the critic's gaps


def test_a_price_rule_is_checked_by_name_and_against_the_critic() -> None:
    with pytest.raises(ValueError, match=r"broadcast_price_rule must be one of \['dual', 'quantile'\], got 'mean'"):
        make(target_savings=0.9, broadcast_price_rule="mean")
    with pytest.raises(ValueError, match="'option_heads' critic learns it from the rewards"):
        make(target_savings=0.9, broadcast_price_rule="quantile", policy_kwargs={"critic": "option_heads"})
    make(broadcast_price_rule="quantile", policy_kwargs={"critic": "option_heads"})  # no target: no price


def test_the_price_rule_is_saved_and_restored(tmp_path) -> None:
    model = make(target_savings=0.8, broadcast_price_rule="quantile")
    model.learn(128)
    model.save(tmp_path / "model.zip")
    loaded = MAPPOC.load(tmp_path / "model.zip", env=model.get_env())
    assert loaded.broadcast_price_rule == "quantile" and loaded.broadcast_price == model.broadcast_price
    # a model saved before the rule existed loads with dual ascent
    data, params, variables = load_from_zip_file(tmp_path / "model.zip")
    del data["broadcast_price_rule"]
    save_to_zip_file(tmp_path / "old.zip", data=data, params=params, pytorch_variables=variables)
    assert MAPPOC.load(tmp_path / "old.zip", env=model.get_env()).broadcast_price_rule == "dual"
    with pytest.raises(ValueError, match="broadcast_price_rule must be one of"):
        MAPPOC.load(tmp_path / "model.zip", env=model.get_env(), broadcast_price_rule="typo")


def test_a_target_set_after_construction_is_followed() -> None:
    """The rule is built with the model's settings at every update: a target or step size set later counts."""
    model = make()
    model.target_savings, model.broadcast_price_lr = 0.9, 0.5
    rollouts = Rollouts()
    model.learn(2 * 128, callback=rollouts)
    assert rollouts.prices[0] == pytest.approx(0.5 * (rollouts.rates[0] - 0.1), abs=1e-6)


def test_hyperparameter_files_check_the_price_rule_against_the_critic(tmp_path) -> None:
    conf = tmp_path / "mappoc.yml"
    entry = {"n_timesteps": 1000, "policy": "MlpHybridPolicy", "target_savings": 0.9}
    quantile = {**entry, "broadcast_price_rule": "quantile"}
    conf.write_text(yaml.safe_dump({LQR: {**quantile, "policy_kwargs": "dict(critic='afterstate')"}}))
    assert check_hyperparams_file(conf, "mappoc", LQR)["broadcast_price_rule"] == "quantile"
    conf.write_text(yaml.safe_dump({LQR: quantile}))  # the policy's default critic learns the price
    with pytest.raises(InputError, match="the 'option_heads' critic learns it from the rewards"):
        check_hyperparams_file(conf, "mappoc", LQR)
    conf.write_text(yaml.safe_dump({LQR: {**entry, "broadcast_price_rule": "mean"}}))
    with pytest.raises(InputError, match=r"broadcast_price_rule must be one of \['dual', 'quantile'\]"):
        check_hyperparams_file(conf, "mappoc", LQR)
