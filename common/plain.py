"""Plain Python values out of numpy ones, for JSON, msgpack and the wire models."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def plain_value(value: Any) -> Any:
    """``value`` with numpy scalars/arrays made plain Python and non-finite floats made None.

    Dicts keep their keys (made ``str``), tuples become lists: what JSON,
    msgpack and the wire models all take. Anything else that is not a
    string, bool, int, float or None becomes its ``str``.
    """
    if isinstance(value, Mapping):
        return {str(k): plain_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_value(v) for v in value]
    if isinstance(value, (str, bool)) or value is None:
        return value
    if hasattr(value, "tolist") and not isinstance(value, (int, float)):  # numpy scalar or array
        return plain_value(value.tolist())
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value) if math.isfinite(value) else None
    return str(value)
