"""Drivers found by name: a built-in table plus entry points, imported only when asked for.

Third-party packages add drivers through the entry-point groups ``wristscan.sensors``,
``wristscan.robots`` and ``wristscan.tables`` (``name = "package.module:Class"``). A driver whose
optional dependency is missing raises :class:`~wristscan.drivers.base.DriverNotAvailable` naming
the extra to install, instead of an ImportError from deep inside.
"""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Literal

from wristscan.drivers.base import Device, DriverNotAvailable

__all__ = ["DriverInfo", "Kind", "describe", "load", "names"]

log = logging.getLogger(__name__)

Kind = Literal["sensors", "robots", "tables"]
KINDS: tuple[Kind, ...] = ("sensors", "robots", "tables")


@dataclass(frozen=True)
class _Builtin:
    target: str
    """``module:Class``"""
    extra: str | None = None
    """The pip extra that provides its optional dependencies."""
    description: str = ""


# Module paths are relative to this package; the classes are imported lazily.
BUILTIN: dict[Kind, dict[str, _Builtin]] = {
    "sensors": {
        "lpf1-udp": _Builtin(".sensor_lpf1:Lpf1UdpSensor", None, "LPF1 over UDP"),
        "lpf1-tcp": _Builtin(".sensor_lpf1:Lpf1TcpSensor", None, "LPF1 over TCP"),
        "lpf1-serial": _Builtin(".sensor_lpf1:Lpf1SerialSensor", None, "LPF1 over serial (COBS)"),
        "rf627-udp": _Builtin(".sensor_rf627:Rf627Sensor", None, "Riftek RF627 UDP stream"),
        "scip": _Builtin(".sensor_scip:ScipSensor", None, "Hokuyo SCIP 2.0 (serial or TCP)"),
        "gocator": _Builtin(".sensor_gocator:GocatorSensor", None, "LMI Gocator Protocol (TCP)"),
    },
    "robots": {
        "ur-rtde": _Builtin(".ur.robot:URRobot", None, "Universal Robots over RTDE (ur-rtde)"),
    },
    "tables": {
        "modbus": _Builtin(".table_modbus:ModbusTable", None, "Rotary table over Modbus TCP/RTU"),
    },
}


@dataclass(frozen=True)
class DriverInfo:
    kind: Kind
    name: str
    target: str
    origin: str
    """``builtin`` or the distribution that registered the entry point."""
    description: str
    loadable: bool
    reason: str | None
    extra: str | None


def _entry_points(kind: Kind) -> dict[str, tuple[str, str]]:
    found: dict[str, tuple[str, str]] = {}
    for ep in entry_points(group=f"wristscan.{kind}"):
        dist = ep.dist.name if ep.dist is not None else "?"
        found[ep.name] = (ep.value, dist)
    return found


def names(kind: Kind) -> list[str]:
    """Every driver name of a kind: built-in ones first, then entry points."""
    return list(BUILTIN[kind]) + sorted(set(_entry_points(kind)) - set(BUILTIN[kind]))


def _import(target: str) -> type[Device[object]]:
    module_name, _, attr = target.partition(":")
    module = importlib.import_module(module_name, package=__package__)
    cls = getattr(module, attr)
    if not (isinstance(cls, type) and issubclass(cls, Device)):
        raise TypeError(f"{target} is not a wristscan driver class")
    return cls


def load(kind: Kind, name: str) -> type[Device[object]]:
    """The driver class registered as ``name``; raises ``KeyError`` listing the known names, or
    :class:`DriverNotAvailable` naming the extra to install."""
    if kind not in KINDS:
        raise KeyError(f"unknown driver kind {kind!r}; expected one of {', '.join(KINDS)}")
    builtin = BUILTIN[kind].get(name)
    if builtin is not None:
        target, extra = builtin.target, builtin.extra
    else:
        eps = _entry_points(kind)
        if name not in eps:
            raise KeyError(f"no {kind[:-1]} driver {name!r}; known: {', '.join(names(kind))}")
        target, extra = eps[name][0], None
    try:
        return _import(target)
    except ImportError as exc:
        hint = f"pip install 'wristscan[{extra}]'" if extra else "its package"
        raise DriverNotAvailable(
            f"{kind[:-1]} driver {name!r} cannot load: {exc.name or exc} is missing; install {hint}"
        ) from exc


def describe() -> list[DriverInfo]:
    """Every registered driver and whether it loads here."""
    out: list[DriverInfo] = []
    for kind in KINDS:
        eps = _entry_points(kind)
        for name in names(kind):
            b = BUILTIN[kind].get(name)
            target = b.target if b else eps[name][0]
            origin = "builtin" if b else eps[name][1]
            try:
                load(kind, name)
                ok, reason = True, None
            except (DriverNotAvailable, KeyError, TypeError, AttributeError, ImportError) as exc:
                ok, reason = False, str(exc)
            out.append(
                DriverInfo(
                    kind=kind,
                    name=name,
                    target=target,
                    origin=origin,
                    description=b.description if b else "",
                    loadable=ok,
                    reason=reason,
                    extra=b.extra if b else None,
                )
            )
    return out
