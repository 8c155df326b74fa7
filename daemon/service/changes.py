"""What a reload changes: the fields of two configurations that differ, and what must be rebuilt
for them (the calibration alone, the pipeline, the devices, the zenoh session or its face)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from wristscan.daemon.config import Config
from wristscan.daemon.config.values import render_value

__all__ = ["ALL_DEVICES", "Changes", "config_changes", "diff_fields"]

ALL_DEVICES = frozenset({"sensor", "robot", "table"})

_FACE_FIELDS = ("prefix", "congestion_control", "status_period_s")
"""``[zenoh]`` fields served by the daemon's publishers, not by its session."""


def diff_fields(old: Any, new: Any, path: str = "") -> list[tuple[str, Any, Any]]:
    """``(dotted.field, old, new)`` for every leaf that differs (sections added or removed are
    one entry)."""
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        out: list[tuple[str, Any, Any]] = []
        for k in list(old) + [k for k in new if k not in old]:
            sub = f"{path}.{k}" if path else str(k)
            out += diff_fields(old.get(k), new.get(k), sub)
        return out
    return [] if old == new else [(path, old, new)]


@dataclass(frozen=True)
class Changes:
    fields: list[tuple[str, Any, Any]]

    def sections(self) -> set[str]:
        return {f.split(".", 1)[0] for f, _, _ in self.fields}

    @property
    def device_kinds(self) -> frozenset[str]:
        """The devices (``sensor``, ``robot``, ``table``) whose sections changed: these are
        closed and opened again, the others stay open."""
        return frozenset(self.sections() & ALL_DEVICES)

    @property
    def devices(self) -> bool:
        return bool(self.device_kinds)

    @property
    def pipeline(self) -> bool:
        """A new pipeline is needed (with the same devices, when they do not change)."""
        sections = self.sections() & {"sync", "pipeline", "zenoh", "ros2"}
        return self.devices or bool(sections) or "cell.name" in self.names()

    @property
    def session(self) -> bool:
        """The zenoh session itself changes (endpoints, mode, its extra configuration...)."""
        return any(
            f.startswith("zenoh.") and f.split(".")[1] not in _FACE_FIELDS
            for f, _, _ in self.fields
        )

    @property
    def face(self) -> bool:
        """The daemon's publishers and queryables must be declared again."""
        return self.session or any(
            f.startswith("zenoh.") and f.split(".")[1] in _FACE_FIELDS for f, _, _ in self.fields
        )

    @property
    def ros2(self) -> bool:
        return self.session or "ros2" in self.sections() or "cell.name" in self.names()

    def names(self) -> list[str]:
        return [f for f, _, _ in self.fields]

    def describe(self, limit: int = 12) -> str:
        """``sensor.options.port 50002 -> 50003, ...`` (at most ``limit`` fields)."""
        parts = [
            f"{f} {render_value(a, 40)} -> {render_value(b, 40)}" for f, a, b in self.fields[:limit]
        ]
        if len(self.fields) > limit:
            parts.append(f"and {len(self.fields) - limit} more")
        return ", ".join(parts)


def config_changes(old: Config, new: Config) -> Changes:
    """The fields that differ between two validated configurations (``sim`` is ignored: the
    daemon does not run the simulated cell)."""
    a = old.model_dump(mode="json", exclude={"sim"})
    b = new.model_dump(mode="json", exclude={"sim"})
    return Changes(diff_fields(a, b))
