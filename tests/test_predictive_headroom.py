"""``benchmarks/predictive_headroom.py``: predictive triggering on the error weighted by what it costs."""

from __future__ import annotations

import numpy as np
import pytest

from sb3_detc.envs.linear import LinearSystem, lqr_gain
from sb3_detc.triggers import PredictiveTrigger

SCRIPT = "predictive_headroom.py"


@pytest.fixture(scope="module")
def headroom(benchmark_module):
    """The benchmark script as a module."""
    return benchmark_module(SCRIPT)


def growth_of_the_q_function(system: LinearSystem, agent: int, error: np.ndarray, rng: np.random.Generator) -> float:
    """How much the team's Q-function grows when the others act on agent's state seen off by ``error``."""
    gain, riccati = lqr_gain(system)
    a, b, q, r, _ = system.joint_matrices()
    x = rng.standard_normal(2 * system.n_agents)

    def q_function(u: np.ndarray) -> float:
        after = a @ x + b @ u
        return float(x @ q @ x + u @ r @ u + after @ riccati @ after)

    seen = x.copy()
    seen[2 * agent : 2 * agent + 2] -= error  # what the others believe of the agent
    controls = -gain @ x
    others = [j for j in range(system.n_agents) if j != agent]
    controls[others] = -(gain @ seen)[others]  # the agent itself acts on its current state
    return q_function(controls) - q_function(-gain @ x)


def test_the_one_step_weights_are_the_cost_to_go_of_the_others_controls_acting_on_the_error(headroom) -> None:
    """Completing the square: with the controls off the LQR law by du, the Q-function grows by du'(R + B'PB)du."""
    system = LinearSystem()
    weights = headroom.error_cost_weights(system, horizon=1)
    rng = np.random.default_rng(0)
    for agent in range(system.n_agents):
        error = rng.standard_normal(2)
        grown = growth_of_the_q_function(system, agent, error, rng)
        assert grown == pytest.approx(error @ weights[agent] @ error, rel=1e-9)
        assert grown > 0


def test_longer_horizons_add_the_cost_of_the_error_as_the_prediction_carries_it(headroom) -> None:
    """Over two steps: the error now, then as the agent's own closed loop carries it to the next step."""
    system = LinearSystem()
    weights = headroom.error_cost_weights(system, horizon=2)
    gain, _ = lqr_gain(system)
    a, b, *_ = system.joint_matrices()
    rng = np.random.default_rng(2)
    for agent in range(system.n_agents):
        own = slice(2 * agent, 2 * agent + 2)
        closed_loop = a[own, own] - b[own, agent : agent + 1] @ gain[agent : agent + 1, own]
        error = rng.standard_normal(2)
        grown = sum(growth_of_the_q_function(system, agent, e, rng) for e in (error, closed_loop @ error))
        assert grown == pytest.approx(error @ weights[agent] @ error, rel=1e-9)
    # Every other agent's control weighs the middle agent's state more than an end agent's: its error costs more.
    one = headroom.error_cost_weights(system, 1)
    assert np.trace(one[1]) > np.trace(one[0]) == pytest.approx(np.trace(one[2]))


def test_identity_weights_give_predictive_triggering(headroom) -> None:
    system = LinearSystem()
    rng = np.random.default_rng(1)
    obs = {
        "held": rng.standard_normal((4, 3, 2)),
        "message": rng.standard_normal((4, 3, 2)),
        "age": rng.integers(0, 5, (4, 3, 1)).astype(np.float32),
    }
    weighted = headroom.CostWeightedPredictive(system, 0.8, np.broadcast_to(np.eye(2), (3, 2, 2)))
    euclidean = PredictiveTrigger(system, 0.8)
    np.testing.assert_allclose(weighted.error(obs), euclidean.error(obs), rtol=1e-12)
    np.testing.assert_array_equal(weighted(obs), euclidean(obs))


def test_both_rules_reach_the_target_on_the_same_episodes(run_benchmark) -> None:
    done = run_benchmark(SCRIPT, "--episodes", "3", "--horizons", "1", check=True)
    row = next(line for line in done.stdout.splitlines() if line.startswith("| 0.9 | 1 |"))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert abs(float(cells[2]) - 0.9) <= 0.002 and abs(float(cells[4]) - 0.9) <= 0.002
    gain, low, high = (float(value.strip("[],")) for value in cells[6].split())
    assert gain == pytest.approx(float(cells[5]) - float(cells[3]), abs=2e-3) and low < gain < high
