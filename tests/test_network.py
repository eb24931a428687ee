"""The broadcast/hold/timer rule against a direct reading of its definition."""

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sb3_detc.network import (
    advance_timer,
    hold,
    initial_network,
    interval_window,
    others_ages,
    others_index,
    relative_views,
)


def reference_network(messages: np.ndarray, options: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Held broadcasts and ages after the last step, read off the whole history.

    ``messages`` (T + 1, N, d): message at reset (counts as received) and at steps 0..T-1.
    ``options`` (T, N).
    """
    n_steps, n_agents = options.shape
    held = np.empty(messages.shape[1:])
    age = np.empty((n_agents, 1))
    for i in range(n_agents):
        sent = np.flatnonzero(options[:, i])
        if sent.size:
            last = sent[-1]
            held[i], age[i] = messages[last + 1, i], n_steps - 1 - last
        else:
            held[i], age[i] = messages[0, i], n_steps
    return held, age


@st.composite
def histories(draw):
    n_agents = draw(st.integers(2, 6))
    n_steps = draw(st.integers(1, 30))
    dim = draw(st.integers(1, 4))
    finite = st.floats(-1e6, 1e6, allow_nan=False, width=64)
    messages = draw(arrays(np.float64, (n_steps + 1, n_agents, dim), elements=finite))
    options = draw(arrays(np.int64, (n_steps, n_agents), elements=st.integers(0, 1)))
    return messages, options


@settings(max_examples=200, deadline=None)
@given(histories())
def test_held_is_message_at_last_broadcast_and_age_counts_steps(history):
    messages, options = history
    held, age = messages[0].copy(), np.zeros((messages.shape[1], 1))
    for k, broadcast in enumerate(options):
        held = hold(held, messages[k + 1], broadcast)
        age = advance_timer(age, broadcast)
    expected_held, expected_age = reference_network(messages, options)
    np.testing.assert_array_equal(held, expected_held)  # exact, not approximately
    np.testing.assert_array_equal(age, expected_age)


@settings(max_examples=50, deadline=None)
@given(histories())
def test_numpy_and_torch_give_identical_results(history):
    messages, options = history
    held_np, age_np = messages[0], np.zeros((messages.shape[1], 1))
    held_t, age_t = torch.as_tensor(messages[0]), torch.zeros(messages.shape[1], 1, dtype=torch.float64)
    for k, broadcast in enumerate(options):
        held_np, age_np = hold(held_np, messages[k + 1], broadcast), advance_timer(age_np, broadcast)
        broadcast_t = torch.as_tensor(broadcast, dtype=torch.float64)
        held_t = hold(held_t, torch.as_tensor(messages[k + 1]), broadcast_t)
        age_t = advance_timer(age_t, broadcast_t)
    np.testing.assert_array_equal(held_t.numpy(), held_np)
    np.testing.assert_array_equal(age_t.numpy(), age_np)


def test_rule_broadcasts_over_leading_axes():
    rng = np.random.default_rng(0)
    held, current = rng.normal(size=(5, 7, 3, 2)), rng.normal(size=(5, 7, 3, 2))
    broadcast = rng.integers(0, 2, size=(5, 7, 3))
    out = hold(held, current, broadcast)
    for idx in np.ndindex(5, 7, 3):
        np.testing.assert_array_equal(out[idx], current[idx] if broadcast[idx] else held[idx])
    age = rng.integers(0, 9, size=(5, 7, 3, 1)).astype(float)
    np.testing.assert_array_equal(advance_timer(age, broadcast)[..., 0], np.where(broadcast == 1, 0, age[..., 0] + 1))


def test_others_index_lists_every_other_agent_once():
    for n in (2, 3, 7):
        idx = others_index(n)
        assert idx.shape == (n, n - 1)
        for i in range(n):
            assert sorted(idx[i]) == [j for j in range(n) if j != i]


def test_relative_views_subtract_the_receivers_own_message():
    rng = np.random.default_rng(1)
    held, own = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    others = others_index(4)
    views = relative_views(held, own, others)
    assert views.shape == (4, 3, 3)
    for i in range(4):
        for k, j in enumerate(others[i]):
            np.testing.assert_array_equal(views[i, k], held[j] - own[i])
    views_t = relative_views(torch.as_tensor(held), torch.as_tensor(own), torch.as_tensor(others))
    np.testing.assert_array_equal(views_t.numpy(), views)


def test_an_episode_starts_with_every_initial_message_received():
    messages = np.arange(6.0).reshape(3, 2)
    held, age = initial_network(messages)
    np.testing.assert_array_equal(held, messages)
    np.testing.assert_array_equal(age, np.zeros((3, 1)))
    messages[0, 0] = 99.0  # the network keeps its own copy
    assert held[0, 0] == 0.0


def test_others_ages_follow_the_others_index():
    age = np.array([[5.0], [0.0], [2.0]])
    others = others_index(3)
    np.testing.assert_array_equal(others_ages(age, others), [[0.0, 2.0], [5.0, 2.0], [5.0, 0.0]])
    batched = others_ages(torch.as_tensor(np.stack([age, age + 1])), torch.as_tensor(others))
    np.testing.assert_array_equal(batched.numpy(), [[[0, 2], [5, 2], [5, 0]], [[1, 3], [6, 3], [6, 1]]])


@given(st.integers(1, 12), st.integers(0, 12), st.lists(st.integers(0, 40), min_size=1, max_size=8))
def test_interval_window_reads_the_interval_a_broadcast_would_end(low: int, extra: int, ages: list[int]) -> None:
    high = low + extra
    age = np.array(ages, dtype=np.float64)[:, None]
    silent, broadcast = interval_window(age, low, high)
    interval = np.array(ages) + 1  # a broadcast now ends an interval of age + 1 steps
    np.testing.assert_array_equal(silent, interval < low)
    np.testing.assert_array_equal(broadcast, interval >= high)
    assert not (silent & broadcast).any()
    t_silent, t_broadcast = interval_window(torch.as_tensor(age), low, high)
    np.testing.assert_array_equal(t_silent.numpy(), silent)
    np.testing.assert_array_equal(t_broadcast.numpy(), broadcast)


def test_a_window_of_one_interval_is_the_periodic_schedule() -> None:
    """Run with the window's forced options alone, every agent broadcasts every P-th step from the reset on."""
    period, age = 4, np.zeros((3, 1))
    sent = []
    for _ in range(12):
        silent, broadcast = interval_window(age, period, period)
        assert (silent ^ broadcast).all()  # nothing is left to choose
        sent.append(broadcast.astype(float))
        age = advance_timer(age, sent[-1])
    np.testing.assert_array_equal(np.flatnonzero(np.array(sent)[:, 0]), [3, 7, 11])
    assert (np.array(sent) == np.array(sent)[:, :1]).all()  # in phase
