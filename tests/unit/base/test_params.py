import enum
from dataclasses import dataclass

import pytest

from cubetrack.core.errors import ConfigError
from cubetrack.core.params import param, params_from_table, params_to_table


class Mode(enum.Enum):
    A = "a"
    B = "b"


@dataclass(frozen=True)
class P:
    mode: Mode = param(Mode.A, "mode")
    rate_hz: float = param(1.0, "Hz")
    count: int = param(3, "n")
    flag: bool = param(False, "flag")
    ids: tuple[int, ...] = param((1, 2), "ids")


def test_table_round_trip():
    p = params_from_table(P, {"mode": "b", "rate_hz": 2, "ids": [4]}, "[x]")
    assert p == P(Mode.B, 2.0, 3, False, (4,))
    assert params_from_table(P, params_to_table(p), "[x]") == p


@pytest.mark.parametrize("table,match", [
    ({"bogus": 1}, r"\[x\]: unknown key\(s\) bogus"),
    ({"mode": "c"}, r"\[x\]\.mode: 'c' is not one of 'a', 'b'"),
    ({"count": 1.5}, "expected an integer"),
    ({"flag": 1}, "expected true or false"),
    ({"rate_hz": "fast"}, "expected a number"),
])
def test_bad_values_are_refused_with_the_key(table, match):
    with pytest.raises(ConfigError, match=match):
        params_from_table(P, table, "[x]")
