"""Settings declared once: the base of the processes' parameter groups and of the site file's.

A group is a frozen pydantic model whose fields carry their bounds and their units in their
names (``stats_period_s: float = Field(10.0, gt=0)``). The site file's models embed or
reuse these declarations and the command lines fill the same models, so a setting has one
default, one range and one message. A bad value raises :class:`SettingError` (a
``ValueError``) in one line naming the setting::

    max_frames: Input should be greater than or equal to 1, got 0

:func:`check_setting` checks one value against a model's declaration of it, for a command-line
flag that overrides a site file's setting (``--mask-scale`` and ``carving.mask_scale``).
"""

from __future__ import annotations

import copy
import math
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError

__all__ = ["NON_NEGATIVE", "Settings", "SettingError", "bounds_in", "bounds_of", "check_declared", "check_setting",
           "declared", "default_of", "field_name",
           "group_of", "problem", "validated"]


NON_NEGATIVE = {"ge": 0.0, "allow_inf_nan": False}
"""Field bounds of an amount that may be zero but is finite (seconds, metres, evidence):
``settle_s: float = Field(3.0, **NON_NEGATIVE)``."""


class SettingError(ValueError):
    """A setting outside its declared range, named in the message."""


class Settings(BaseModel):
    """A frozen parameter group: unknown names refused, each field its own bounds."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)

    def __init__(self, **values: Any) -> None:
        try:
            super().__init__(**values)
        except ValidationError as exc:
            raise SettingError(one_line(exc)) from None


def one_line(exc: ValidationError, *, prefix: str = "") -> str:
    """The first problem of ``exc`` in one line: ``name: problem, got value`` (and how many more)."""
    errors = exc.errors()
    err = errors[0]
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    if not err["loc"]:   # a check across fields says what it checked in its own words
        return f"{prefix}{problem(err)}{more}"
    got = "" if err["type"] in ("missing", "extra_forbidden") else f", got {err.get('input')!r}"
    return f"{prefix}{field_name(err['loc'])}: {problem(err)}{got}{more}"


def check_setting(model: type[BaseModel], name: str, value: Any, *, flag: str) -> Any:
    """``value`` validated against ``model``'s declaration of the field ``name`` (its type and
    bounds); SettingError naming ``flag`` (the command-line option that gave it) otherwise."""
    field = model.model_fields[name]
    try:
        return TypeAdapter(Annotated[field.annotation, field]).validate_python(value)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise SettingError(f"{flag}: {problem(err)}, got {value!r}") from None


def check_declared(params: Any, model: type[BaseModel], *names: str) -> None:
    """Check each named field of the frozen parameter group ``params`` against ``model``'s
    declaration of it (:func:`check_setting`) and store the checked value."""
    for name in names:
        object.__setattr__(params, name, check_setting(model, name, getattr(params, name), flag=name))


def group_of(value: Any, model: type[BaseModel], *, name: str = "params") -> Any:
    """``value`` when it is a ``model`` (a stage takes its own parameter group only); a
    SettingError naming ``name`` and both types otherwise."""
    if not isinstance(value, model):
        raise SettingError(f"{name} must be {model.__name__}, got {type(value).__name__}")
    return value


def validated(model: type[BaseModel], **values: Any) -> BaseModel:
    """``model`` built from ``values`` (the others at their declared defaults): how a stage checks
    the settings a site file's model declares for it, with the same ranges and messages; a
    SettingError naming the first bad one otherwise."""
    try:
        return model(**values)
    except ValidationError as exc:
        raise SettingError(one_line(exc)) from None


def declared(model: type[BaseModel], name: str) -> Any:
    """``model``'s declaration of the field ``name`` (default, bounds, description), for a stage's
    parameter group to take as its own: ``long_lie_s: float = declared(EventSettings, "long_lie_s")``."""
    return copy.copy(model.model_fields[name])


def bounds_of(model: type[BaseModel], name: str) -> tuple[float, float]:
    """The closed range ``(low, high)`` ``model`` declares for its field ``name`` (``-inf`` or ``inf``
    where it declares none; an open bound, ``gt`` or ``lt``, as its limit)."""
    return bounds_in(model.model_fields[name].metadata)


def bounds_in(metadata) -> tuple[float, float]:
    """:func:`bounds_of` for a field's constraints themselves (``FieldInfo.metadata``, or those of an
    ``Annotated`` element of a list)."""
    low, high = -math.inf, math.inf
    for bound in metadata:
        low = max(low, getattr(bound, "ge", -math.inf), getattr(bound, "gt", -math.inf))
        high = min(high, getattr(bound, "le", math.inf), getattr(bound, "lt", math.inf))
    return float(low), float(high)


def default_of(model: type[BaseModel], name: str) -> Any:
    """The declared default of ``model``'s field ``name`` (a stage's keyword default is the site's)."""
    return model.model_fields[name].get_default(call_default_factory=True)


def field_name(loc: tuple) -> str:
    """A pydantic error location as a dotted name with list indices: ``cameras[2].fps``."""
    name = ""
    for part in loc:
        if isinstance(part, int):
            name += f"[{part}]"
        else:
            name += ("." if name else "") + str(part)
    return name or "(top level)"


def problem(err: dict) -> str:
    """What is wrong, in words, from one pydantic error."""
    if err["type"] == "extra_forbidden":
        return "unknown field (check the spelling against the documented site file)"
    if err["type"] == "missing":
        return "required field is missing"
    return err["msg"].removeprefix("Value error, ")
