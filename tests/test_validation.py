"""Tests of the shared integer checks."""

import numpy as np
import pytest

from sb3_detc.validation import check_integer, is_integer


@pytest.mark.parametrize("value", [1, 5, np.int64(3), np.int32(1)])
def test_integers_at_least_the_minimum_pass(value):
    assert is_integer(value, 1)
    assert check_integer("n", value) == int(value)
    assert type(check_integer("n", value)) is int


@pytest.mark.parametrize("value", [0, -1, True, False, 1.0, "2", None, np.float64(2.0)])
def test_other_values_are_refused_with_the_name(value):
    assert not is_integer(value, 1)
    with pytest.raises(ValueError, match=r"^period must be an integer >= 1, got "):
        check_integer("period", value)


def test_minimum_is_inclusive_and_optional():
    assert is_integer(2, 2) and not is_integer(1, 2)
    assert is_integer(-7) and not is_integer(True)
    with pytest.raises(ValueError, match="n_agents must be an integer >= 2, got 1"):
        check_integer("n_agents", 1, minimum=2)
