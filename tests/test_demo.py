"""The demonstration ``python -m sb3_detc.demo`` on the linear benchmark."""

from __future__ import annotations

import re

import numpy as np
import pytest

from sb3_detc import demo
from sb3_detc.envs import linear_etc_v0
from sb3_detc.envs.linear import LQRController

SCHEMES = ("periodic", "random skip p=0.5", "random skip p=0.8", "every 4th step")


def table_rows(output: str) -> dict[str, list[str]]:
    """Rows of the first printed table whose first cell is a scheme name: {scheme: other cells}."""
    rows: dict[str, list[str]] = {}
    for line in output.splitlines():
        cells = re.split(r"\s{2,}", line.strip())
        if cells[0] in SCHEMES and cells[0] not in rows:
            rows[cells[0]] = cells[1:]
    return rows


def test_main_prints_every_scheme_with_its_savings(capsys: pytest.CaptureFixture[str]) -> None:
    results = demo.main(["--episodes", "1"])
    output = capsys.readouterr().out
    rows = table_rows(output)
    assert set(rows) == set(SCHEMES)
    for cells in rows.values():
        assert len(cells) == 5  # broadcasts, savings, cost (all), cost (k >= 50), ratio
    savings = {name: float(cells[1]) for name, cells in rows.items()}
    assert rows["periodic"][0] == "200.0" and rows["periodic"][1] == "0.00"
    assert rows["every 4th step"][0] == "50.0" and rows["every 4th step"][1] == "0.75"
    # 600 agent-steps with skip probability 0.8: standard deviation of Gamma about 0.016.
    assert abs(savings["random skip p=0.8"] - 0.8) < 0.06
    assert abs(savings["random skip p=0.5"] - 0.5) < 0.08
    # The returned statistics are the printed ones.
    assert [r.name for r in results] == list(SCHEMES)
    for r in results:
        assert f"{r.savings:.2f}" == rows[r.name][1]
        assert r.broadcasts.shape == (1, 3) and r.costs.shape == (1, demo.EPISODE_STEPS)
    # Every scheme keeps the loop stable, near the LQR bound (ratio after the transient; one short
    # episode with rare velocity kicks is a noisy estimate).
    for cells in rows.values():
        assert 0.5 < float(cells[4]) < 3.0
    assert "held" in output and "comm_cost" in output


def test_per_agent_broadcast_counts_follow_n_agents(capsys: pytest.CaptureFixture[str]) -> None:
    results = demo.main(["--episodes", "2", "--n-agents", "4", "--seed", "3"])
    output = capsys.readouterr().out
    assert "agent_3" in output and "seeds 3..4" in output
    periodic = results[0]
    np.testing.assert_array_equal(periodic.broadcasts, np.full((2, 4), demo.EPISODE_STEPS))
    every_4th = results[3]
    np.testing.assert_array_equal(every_4th.broadcasts, np.full((2, 4), demo.EPISODE_STEPS // 4))


def test_view_is_own_state_plus_held_broadcasts_after_this_step() -> None:
    env = linear_etc_v0.joint_env(max_cycles=20)
    controller = LQRController(env.network.system)
    obs, _ = env.reset(seed=1)
    silent = np.zeros(3, dtype=np.int64)
    for _ in range(3):  # let the held broadcasts go stale
        obs, *_ = env.step({"comm": silent, "control": np.zeros((3, 1))})
    assert not np.allclose(obs["held"], obs["message"])
    # Everyone broadcasts: every view is the true joint state, i.e. centralised LQR.
    everyone = np.ones(3, dtype=np.int64)
    np.testing.assert_allclose(demo.networked_control(controller, obs, everyone), controller(obs["local"]))
    # Only agent 1 broadcasts: agent 0 sees its own state, agent 1's current and agent 2's stale one.
    comm = np.array([0, 1, 0])
    u = demo.networked_control(controller, obs, comm)
    view_0 = np.stack([obs["local"][0], obs["message"][1], obs["held"][2]])
    view_2 = np.stack([obs["held"][0], obs["message"][1], obs["local"][2]])
    np.testing.assert_allclose(u[0], controller(view_0)[0])
    np.testing.assert_allclose(u[2], controller(view_2)[2])
    assert not np.allclose(u, controller(obs["local"]))


@pytest.mark.parametrize("argv", [["--episodes", "0"], ["--n-agents", "1"]])
def test_bad_arguments_exit(argv: list[str]) -> None:
    with pytest.raises(SystemExit):
        demo.main(argv)
