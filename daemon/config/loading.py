"""The whole file: the root :class:`Config` model and reading it from TOML text, a file or the
embedded default (``default_sim.toml``, package data of ``wristscan.daemon``, a copy of
``config/sim.toml``).

A file must start with ``schema_version = 1``; that is checked first, so that a file for another
version gets one clear line rather than a list of unknown keys.
"""

from __future__ import annotations

import os
import re
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, PrivateAttr, ValidationError, model_validator

from wristscan.daemon.config.archive import ArchiveConfig
from wristscan.daemon.config.errors import ConfigError, format_validation_error
from wristscan.daemon.config.hardware import CellConfig, RobotConfig, SensorConfig, TableConfig
from wristscan.daemon.config.ros2 import Ros2Config
from wristscan.daemon.config.service import (
    CalibrationConfig,
    PipelineConfig,
    SyncConfig,
    ZenohConfig,
)
from wristscan.daemon.config.sim import SIM_KINDS_FOR_DRIVER, SimConfig
from wristscan.daemon.config.startup import ServiceConfig
from wristscan.daemon.config.values import CELL_NAME, StrictModel, cross_field, render_value

__all__ = [
    "DEFAULT_CONFIG_RESOURCE",
    "SCHEMA_VERSION",
    "Config",
    "load_config",
    "load_default",
    "parse_config",
]

SCHEMA_VERSION = 1
DEFAULT_CONFIG_RESOURCE = "default_sim.toml"
"""The embedded default inside ``wristscan.daemon`` (a copy of ``config/sim.toml``)."""


class Config(StrictModel):
    schema_version: Literal[1]
    cell: CellConfig
    robot: RobotConfig
    sensor: SensorConfig
    table: TableConfig | None = None
    sync: SyncConfig = Field(default_factory=SyncConfig)
    pipeline: PipelineConfig = Field(default_factory=PipelineConfig)
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig)
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    ros2: Ros2Config = Field(default_factory=Ros2Config)
    service: ServiceConfig = Field(default_factory=ServiceConfig)
    archive: ArchiveConfig = Field(default_factory=ArchiveConfig)
    sim: SimConfig | None = None

    _source: str = PrivateAttr(default="<config>")

    @property
    def source(self) -> str:
        """Where the config came from (a path, or ``<default>`` for the embedded one)."""
        return self._source

    @property
    def table_enabled(self) -> bool:
        return self.table is not None and self.table.enabled

    @model_validator(mode="before")
    @classmethod
    def _default_prefix(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        zenoh = data.get("zenoh", {})
        cell = data.get("cell")
        if (
            isinstance(zenoh, dict)
            and "prefix" not in zenoh
            and isinstance(cell, dict)
            and isinstance(cell.get("name"), str)
            and CELL_NAME.match(cell["name"])
        ):
            data = {**data, "zenoh": {**zenoh, "prefix": f"wristscan/{cell['name']}"}}
        return data

    @model_validator(mode="after")
    def _frame_needs_table(self) -> Config:
        if self.pipeline.frame != "base" and not self.table_enabled:
            raise cross_field(
                "pipeline.frame",
                f'frame = "{self.pipeline.frame}" needs an enabled [table] section',
            )
        if self.sync.pairing == "encoder" and self.sync.encoder_bits is None:
            raise cross_field("sync.encoder_bits", 'required with pairing = "encoder"')
        return self

    @model_validator(mode="after")
    def _sim_speaks_the_driver(self) -> Config:
        # A simulated cell whose sensor speaks another protocol than the daemon reads would start
        # and then deliver nothing (or fail deep inside the simulator).
        if self.sim is None:
            return self
        driver, kind = self.sensor.driver, self.sim.sensor.kind
        kinds = SIM_KINDS_FOR_DRIVER.get(driver)
        if kinds is not None and kind not in kinds:
            raise cross_field(
                "sim.sensor.kind",
                f'"{kind}" is not what [sensor] driver = "{driver}" reads: use '
                + " or ".join(f'"{k}"' for k in kinds),
            )
        url = str(getattr(self.sensor.options, "url", ""))
        if kind == "scip-tcp" and not url.startswith("socket://"):
            raise cross_field(
                "sensor.options.url", 'the simulated "scip-tcp" scanner needs a socket:// url'
            )
        if kind == "scip-serial" and url.startswith("socket://"):
            raise cross_field(
                "sensor.options.url", 'the simulated "scip-serial" scanner needs a serial device'
            )
        if kind == "gocator":
            o = self.sensor.options
            base = int(getattr(o, "control_port", 3190))
            for name, step in (("data_port", 6), ("health_port", 4)):
                if int(getattr(o, name, base + step)) != base + step:
                    raise cross_field(
                        f"sensor.options.{name}",
                        f"the simulated Gocator serves it at control_port + {step} ({base + step})",
                    )
        return self

    def summary(self) -> list[str]:
        """A few human-readable lines: what this config connects to."""
        r, s, t, z, p = self.robot, self.sensor, self.table, self.zenoh, self.pipeline
        motion = "motion enabled" if r.motion_enabled else "receive only"
        rows = [
            ("cell", self.cell.name),
            ("robot", f"{r.driver} {r.model} at {r.host} ({motion})"),
            ("sensor", f"{s.driver} {_options_text(s.options)}"),
        ]
        if t is None or not t.enabled:
            rows.append(("table", "none"))
        else:
            where = f"{t.host}:{t.port}" if t.transport == "tcp" else t.serial_port
            rows.append(("table", f"{t.driver} {t.transport} {where} device {t.device_id}"))
        eps = ", ".join([*(f"listen {e}" for e in z.listen), *(f"connect {e}" for e in z.connect)])
        rows.append(("zenoh", f"{z.mode} prefix {z.prefix}" + (f" ({eps})" if eps else "")))
        rows.append(("frame", f"{p.frame}, batches of {p.batch_s:g} s"))
        calib = self.calibration.file
        rows.append(("calibration", str(calib) if calib is not None else "none"))
        ros = self.ros2
        if ros.enabled:
            where = f"{ros.topic_for(self.cell.name)} ({ros.mode}, domain {ros.domain_id})"
            rows.append(("ros2", where + (", /tf_static" if ros.tf_static else "")))
        if self.sim is not None:
            c, ss = self.sim.controller, self.sim.sensor
            rows.append(
                (
                    "sim",
                    f"{c.model} at {c.host}, {ss.kind} {ss.n_points} points at {ss.rate_hz:g} Hz",
                )
            )
        return [f"{label:<12}{text}" for label, text in rows]


def _options_text(options: BaseModel | Mapping[str, Any]) -> str:
    items = options.model_dump() if isinstance(options, BaseModel) else dict(options)
    shown = [f"{k}={v}" for k, v in items.items() if v is not None]
    return " ".join(shown)


def _toml_error(source: str, exc: tomllib.TOMLDecodeError) -> ConfigError:
    text = str(exc)
    m = re.search(r"\s*\(at line (\d+), column (\d+)\)$", text)
    if m is not None:
        reason = text[: m.start()]
        where = f"line {m.group(1)}, column {m.group(2)}"
    else:
        m_end = re.search(r"\s*\(at end of document\)$", text)
        reason = text[: m_end.start()] if m_end else text
        where = "end of file"
    return ConfigError(source, [f"{source}: {where}: invalid TOML: {reason}"])


def _check_version(source: str, data: Mapping[str, Any]) -> None:
    if "schema_version" not in data:
        raise ConfigError(
            source,
            [
                f"{source}: schema_version: missing; the file must start with "
                f"'schema_version = {SCHEMA_VERSION}'"
            ],
        )
    v = data["schema_version"]
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(
            source, [f"{source}: schema_version: must be an integer (got {render_value(v)})"]
        )
    if v != SCHEMA_VERSION:
        raise ConfigError(
            source,
            [
                f"{source}: schema_version: version {v} is not supported; this wristscan "
                f"reads schema_version = {SCHEMA_VERSION}"
            ],
        )


def parse_config(text: str, source: str = "<config>", base_dir: Path | None = None) -> Config:
    """Validate TOML ``text``; ``source`` names it in messages and ``base_dir`` anchors its
    relative paths (default: the current directory). Raises :class:`ConfigError`."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _toml_error(source, exc) from None
    _check_version(source, data)
    context = {"base_dir": base_dir if base_dir is not None else Path.cwd()}
    try:
        config = Config.model_validate(data, context=context)
    except ValidationError as exc:
        raise ConfigError(source, format_validation_error(exc, source, Config)) from None
    config._source = source
    return config


def load_config(path: str | os.PathLike[str]) -> Config:
    """Read and validate a config file. Raises :class:`ConfigError` (a ``ValueError``) naming the
    file, the field and what is expected, also when the file cannot be read."""
    p = Path(path)
    source = str(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(source, [f"{source}: cannot read: {exc.strerror or exc}"]) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            source, [f"{source}: not UTF-8 text (byte {exc.start} is invalid)"]
        ) from None
    return parse_config(text, source, p.resolve().parent)


def load_default() -> Config:
    """The embedded default config (the simulated cell, a copy of ``config/sim.toml``)."""
    resource = resources.files("wristscan.daemon") / DEFAULT_CONFIG_RESOURCE
    text = resource.read_text(encoding="utf-8")
    try:
        base = Path(str(resource)).parent
    except (TypeError, ValueError):
        base = None
    return parse_config(text, "<default>", base)
