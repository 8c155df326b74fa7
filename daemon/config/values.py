"""The value types every config section is built from, and the base model of the sections.

Strict scalars: TOML is typed, so "5" for a number or 1 for a boolean is a mistake worth
reporting rather than coercing (ints are still accepted where a float is expected). Host names,
UR model names and fixed-length vectors are checked here once for every section that uses them.
"""

from __future__ import annotations

import difflib
import ipaddress
import json
import re
from collections.abc import Callable
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, Strict
from pydantic_core import PydanticCustomError

from wristscan.calib import kinematics

Float = Annotated[float, Strict()]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]

NonNegFloat = Annotated[Float, Field(ge=0)]
Probability = Annotated[Float, Field(ge=0, le=1)]
Port = Annotated[Int, Field(ge=1, le=65535)]
Baudrate = Annotated[Int, Field(ge=50, le=12_000_000)]
RegisterAddress = Annotated[Int, Field(ge=0, le=65535)]


def fixed_length(n: int, what: str) -> Callable[[Any], Any]:
    """A before-validator: a list or tuple must hold ``n`` items (``what`` names them)."""

    def check(value: Any) -> Any:
        if isinstance(value, list | tuple) and len(value) != n:
            raise ValueError(f"expected {n} numbers {what}")
        return value

    return check


Vec3 = Annotated[tuple[Float, Float, Float], BeforeValidator(fixed_length(3, "[x, y, z]"))]
Pose6 = Annotated[
    tuple[Float, Float, Float, Float, Float, Float],
    BeforeValidator(fixed_length(6, "[x, y, z, rx, ry, rz] (m, rad)")),
]
Joints6 = Annotated[
    tuple[Float, Float, Float, Float, Float, Float],
    BeforeValidator(fixed_length(6, "(one per joint)")),
]

_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"^(?=.{{1,253}}$){_LABEL}(\.{_LABEL})*$")
CELL_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
"""A cell name: it becomes a zenoh key chunk (``wristscan/<cell.name>``)."""


def _check_host(value: str) -> str:
    try:
        ipaddress.ip_address(value)
    except ValueError:
        if not _HOSTNAME.match(value):
            raise ValueError("not an IP address or host name") from None
    return value


def _check_optional_host(value: str | None) -> str | None:
    return None if value is None else _check_host(value)


def _check_ur_model(v: str) -> str:
    if v not in kinematics.UR_MODELS:
        close = difflib.get_close_matches(v, list(kinematics.UR_MODELS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown UR model {v!r}{hint}; known: {', '.join(kinematics.UR_MODELS)}")
    return v


Host = Annotated[Str, AfterValidator(_check_host)]
"""An IP address or a host name."""
OptionalHost = Annotated[Str | None, AfterValidator(_check_optional_host)]
URModelName = Annotated[Str, AfterValidator(_check_ur_model)]
"""A key of :data:`wristscan.calib.kinematics.UR_MODELS`."""


def cross_field(field: str, message: str) -> PydanticCustomError:
    """An error about a field found by a check across fields; ``field`` is relative to the model
    that raises it (the formatter appends it to the error location)."""
    return PydanticCustomError("cross_field", message, {"field": field})


class StrictModel(BaseModel):
    """Base of every section: unknown keys are errors, values are finite, objects frozen."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, allow_inf_nan=False, validate_default=False
    )


def render_value(value: Any, limit: int = 60) -> str:
    """A value as it would be written in TOML (shortened)."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, str):
        text = json.dumps(value)
    elif isinstance(value, int | float):
        text = repr(value)
    elif isinstance(value, list | tuple):
        text = "[" + ", ".join(render_value(v, limit) for v in value) + "]"
    elif isinstance(value, dict):
        text = "a table"
    else:
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
