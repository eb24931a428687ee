"""Checks of integer settings shared by the package's modules (one rule for what counts as an integer)."""

from __future__ import annotations

from typing import Any

import numpy as np


def is_integer(value: Any, minimum: int | None = None) -> bool:
    """Whether ``value`` is an integer (a Python or NumPy one, not a bool), at least ``minimum`` if given.

    :param value: the value to check
    :param minimum: the smallest allowed value, or None for any integer
    :return: True for an int or NumPy integer other than a bool that is ``>= minimum``
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        return False
    return minimum is None or value >= minimum


def check_integer(name: str, value: Any, minimum: int = 1) -> int:
    """Check an integer setting (a count, a period, a number of agents) and return it as an ``int``.

    :param name: the setting's name, for the message
    :param value: the value
    :param minimum: the smallest allowed value
    :return: ``value`` as an ``int``
    :raises ValueError: if ``value`` is not an integer (see :func:`is_integer`) ``>= minimum``
    """
    if not is_integer(value, minimum):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}.")
    return int(value)
