"""What the logger of a model dumps, kept for the tests (imported by test modules; ``tests/`` is on the path)."""

from __future__ import annotations

from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.logger import KVWriter, Logger


class Capture(KVWriter):
    """Keeps every dump of the logger (one per iteration with ``log_interval=1``)."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        self.rows.append(dict(key_values))

    def close(self) -> None:
        pass


def capture_logger(model: BaseAlgorithm) -> Capture:
    """Give a model a logger that writes only to a :class:`Capture`.

    :param model: the model
    :return: the capture, whose ``rows`` fill as the model learns
    """
    capture = Capture()
    model.set_logger(Logger(None, [capture]))
    return capture
