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
