"""Plain values: numpy made plain Python, non-finite floats None, for JSON and msgpack."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from common.plain import plain_value


def test_plain_value_makes_numpy_and_non_finite_plain() -> None:
    got = plain_value({"a": np.float32(1.5), "b": np.bool_(True), "c": (np.int16(2), math.inf), 3: np.arange(2)})
    assert got == {"a": 1.5, "b": True, "c": [2, None], "3": [0, 1]}
    assert type(got["a"]) is float and type(got["b"]) is bool and type(got["c"][0]) is int


def test_plain_value_of_nested_arrays_and_plain_python() -> None:
    got = plain_value([np.array([[1.0, np.nan], [2.5, -np.inf]]), np.float64(0.1), 7, True, None, "x"])
    assert got == [[[1.0, None], [2.5, None]], 0.1, 7, True, None, "x"]
    assert json.dumps(got, allow_nan=False) == '[[[1.0,null],[2.5,null]],0.1,7,true,null,"x"]'.replace(",", ", ")


def test_plain_value_gives_other_objects_as_text() -> None:
    assert plain_value({"path": Path("a/b")}) == {"path": "a/b"}
