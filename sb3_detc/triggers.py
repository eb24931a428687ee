"""Non-learned communication triggers, usable wherever MAPPOC accepts an option override.

A trigger maps a batch of joint observations (dict of arrays shaped (B, N, ...)) to
options (B, N) in {0, 1}.
"""

from __future__ import annotations

import numpy as np


class RandomTrigger:
    """Every agent broadcasts independently with probability ``1 - skip_prob`` (the paper's baseline).

    :param skip_prob: probability of staying silent in a step (paper: about 0.5)
    :param seed: seed of the trigger's own random generator
    """

    def __init__(self, skip_prob: float, seed: int | None = None) -> None:
        if not 0.0 <= skip_prob <= 1.0:
            raise ValueError(f"skip_prob must be in [0, 1], got {skip_prob!r}.")
        self.skip_prob = float(skip_prob)
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N)."""
        shape = obs["age"].shape[:-1]
        return (self.rng.random(shape) >= self.skip_prob).astype(np.int64)


class PeriodicTrigger:
    """Every agent broadcasts every ``period``-th step, counted per episode; all agents at the same steps.

    Stateless: an agent broadcasts when its age of information reaches ``period - 1``, i.e.
    when ``age + 1 >= period`` (``age`` is the timer before this step's decision). Since the
    initial message of an episode counts as received (age 0 at reset), the broadcasts fall
    on the steps ``period - 1, 2 period - 1, ...`` of every episode (step 0 is the first
    step), so under this trigger all agents broadcast at the same steps. ``period=1`` is
    periodic communication every step (no savings); savings are ``1 - 1 / period``.

    :param period: steps between two broadcasts of an agent (an integer >= 1)
    """

    def __init__(self, period: int) -> None:
        if isinstance(period, bool) or not isinstance(period, (int, np.integer)) or period < 1:
            raise ValueError(f"period must be an integer >= 1, got {period!r}.")
        self.period = int(period)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N)."""
        age = np.asarray(obs["age"])[..., 0]
        # Ages are whole numbers of steps (float32 in the observation): compare with half a step of margin.
        return (age + 1 > self.period - 0.5).astype(np.int64)


class SendOnDelta:
    """Send-on-delta: an agent broadcasts when its trigger features moved more than ``delta`` since its last broadcast.

    Agent i broadcasts when ``||trigger_i - trigger_held_i|| > delta`` (strictly), where
    ``trigger_held_i`` are the trigger features at the agent's own last broadcast (or at the
    reset), both read from the joint observation. The classic event-triggered reference:
    ``delta = 0`` broadcasts whenever anything changed, a large ``delta`` never.

    :param delta: threshold (a finite number >= 0), in the units of the trigger features
    :param norm: order of the vector norm (``numpy.linalg.norm``'s ``ord``): a number >= 1
        or ``numpy.inf`` (default 2, the Euclidean norm)
    """

    def __init__(self, delta: float, norm: float = 2) -> None:
        if isinstance(delta, bool) or not np.isfinite(delta) or delta < 0:
            raise ValueError(f"delta must be a finite number >= 0, got {delta!r}.")
        if isinstance(norm, bool) or not (norm == np.inf or (np.isfinite(norm) and norm >= 1)):
            raise ValueError(f"norm must be a number >= 1 or numpy.inf, got {norm!r}.")
        self.delta = float(delta)
        self.norm = norm

    def distance(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """How far every agent's trigger features moved since its last broadcast, (B, N)."""
        moved = np.asarray(obs["trigger"], dtype=np.float64) - np.asarray(obs["trigger_held"], dtype=np.float64)
        return np.linalg.norm(moved, ord=self.norm, axis=-1)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Options for a batch of joint observations, (B, N)."""
        return (self.distance(obs) > self.delta).astype(np.int64)
