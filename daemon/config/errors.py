"""Validation errors as one readable line each: file, dotted field, what is expected, what was
given, and a 'did you mean' hint for a misspelt key::

    config/sim.toml: robot.max_speed_m_s: must be > 0 (got -1)
"""

from __future__ import annotations

import difflib
import types
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError

from wristscan.daemon.config.hardware import TAGGED_SENSOR_MODELS
from wristscan.daemon.config.values import render_value

__all__ = ["ConfigError", "format_validation_error"]


class ConfigError(ValueError):
    """A config file that cannot be used; ``problems`` holds one readable line per error,
    each starting with the file name."""

    def __init__(self, source: str, problems: Sequence[str]) -> None:
        self.source = source
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


def _num(x: Any) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _unwrap_model(annotation: Any) -> type[BaseModel] | None:
    """The model class a field holds (through ``Optional`` and ``Annotated``), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if get_origin(annotation) in (Union, Annotated) or isinstance(annotation, types.UnionType):
        for arg in get_args(annotation):
            found = _unwrap_model(arg)
            if found is not None:
                return found
    return None


def _model_at(root: type[BaseModel], loc: Sequence[int | str]) -> type[BaseModel] | None:
    """The model class at ``loc`` in ``root``, None when ``loc`` is not a section."""
    model: type[BaseModel] | None = root
    for part in loc:
        if isinstance(part, str) and part in TAGGED_SENSOR_MODELS:
            model = TAGGED_SENSOR_MODELS[part]
            continue
        if model is None or not isinstance(part, str) or part not in model.model_fields:
            return None
        model = _unwrap_model(model.model_fields[part].annotation)
    return model


def _annotation_at(root: type[BaseModel], loc: Sequence[int | str]) -> Any:
    parent = _model_at(root, loc[:-1])
    if parent is None or not isinstance(loc[-1], str) or loc[-1] not in parent.model_fields:
        return None
    return parent.model_fields[loc[-1]].annotation


def _fields_at(root: type[BaseModel], loc: Sequence[int | str]) -> list[str]:
    """Field names of the model at ``loc`` (for 'did you mean' hints); empty when unknown."""
    model = _model_at(root, loc)
    return list(model.model_fields) if model is not None else []


def _path_text(loc: Sequence[int | str]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part.startswith("<") and part.endswith(">"):
            continue  # a union tag, not part of the file's structure
        else:
            out += f".{part}" if out else part
    return out


_TYPE_TEXT = {
    "float_type": "must be a number",
    "float_parsing": "must be a number",
    "finite_number": "must be a finite number",
    "int_type": "must be an integer",
    "int_parsing": "must be an integer",
    "int_from_float": "must be an integer",
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be a string",
    "list_type": "must be an array",
    "tuple_type": "must be an array",
    "dict_type": "must be a table",
    "model_type": "must be a table",
    "model_attributes_type": "must be a table",
    "path_type": "must be a path string",
}


def _problem(source: str, err: Mapping[str, Any], root: type[BaseModel]) -> str:
    loc = [p for p in err["loc"]]
    kind = err["type"]
    ctx = err.get("ctx") or {}
    got = True
    if kind == "cross_field":
        loc += str(ctx["field"]).split(".")
        msg = str(err["msg"])
        got = False
    elif kind == "missing":
        section = _unwrap_model(_annotation_at(root, loc)) is not None
        msg = "section missing" if section else "required, but not given"
        got = False
    elif kind == "extra_forbidden":
        name = str(loc[-1])
        close = difflib.get_close_matches(name, _fields_at(root, loc[:-1]), n=1, cutoff=0.6)
        msg = "unknown field" + (f" (did you mean {close[0]!r}?)" if close else "")
        got = False
    elif kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        op = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<"}.get(kind, "<=")
        bound = next(iter(ctx.values()))
        msg = f"must be {op} {_num(bound)}"
    elif kind == "literal_error":
        msg = f"must be {ctx.get('expected', '')}"
    elif kind == "string_too_short":
        n = ctx.get("min_length", 1)
        msg = "must not be empty" if n == 1 else f"must have at least {n} characters"
    elif kind == "value_error":
        msg = str(ctx.get("error", err["msg"]))
        # Messages that quote the offending value already say what was given.
        got = not (isinstance(err.get("input"), str) and repr(err["input"]) in msg)
    elif kind in _TYPE_TEXT:
        msg = _TYPE_TEXT[kind]
    else:
        text = str(err["msg"])
        msg = text[:1].lower() + text[1:]
    if got and "input" in err:
        msg += f" (got {render_value(err['input'])})"
    where = _path_text(loc)
    return f"{source}: {where}: {msg}" if where else f"{source}: {msg}"


def format_validation_error(
    exc: ValidationError, source: str, root: type[BaseModel] | None = None
) -> list[str]:
    """One readable line per error of ``exc``: ``"<source>: <dotted.field>: <what is expected>
    (got <value>)"``. ``root`` (the validated model) enables 'did you mean' hints."""
    model = root if root is not None else BaseModel
    return [_problem(source, e, model) for e in exc.errors(include_url=False)]
