"""The daemon's configuration: one TOML file, validated once at start-up into typed objects.

A file starts with ``schema_version = 1`` and holds the sections ``[cell]``, ``[robot]``,
``[sensor]`` (with a driver-specific ``[sensor.options]`` table), optionally ``[table]``, then
``[sync]``, ``[pipeline]``, ``[zenoh]``, ``[calibration]`` and, for the simulated cell, ``[sim]``.
``config/sim.toml`` is the commented reference; it ships inside the package as
``default_sim.toml`` so that :func:`load_default` needs no file on disk.

Every value is checked here, with ranges, so that the rest of the daemon can trust it: unknown
keys are errors (typos must not be silently ignored), numbers must be finite, units are SI and
part of the field names (``_m``, ``_s``, ``_hz``, ``_rad``, ``_deg``). A bad file raises one
:class:`ConfigError` that lists every problem as one readable line::

    config/sim.toml: robot.max_speed_m_s: must be > 0 (got -1)

Relative paths (calibration files, an extra zenoh config) are resolved against the folder of the
config file.
"""

from __future__ import annotations

import difflib
import ipaddress
import json
import math
import os
import re
import tomllib
import types
from collections.abc import Callable, Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    PrivateAttr,
    Strict,
    Tag,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from wristscan.calib import kinematics, se3
from wristscan.drivers import registry

__all__ = [
    "DEFAULT_CONFIG_RESOURCE",
    "SCHEMA_VERSION",
    "CalibrationConfig",
    "CellConfig",
    "Config",
    "ConfigError",
    "Lpf1SerialOptions",
    "Lpf1SerialSensorConfig",
    "Lpf1TcpOptions",
    "Lpf1TcpSensorConfig",
    "Lpf1UdpOptions",
    "Lpf1UdpSensorConfig",
    "PipelineConfig",
    "PluginSensorConfig",
    "Rf627Options",
    "Rf627SensorConfig",
    "RobotConfig",
    "ScipOptions",
    "ScipSensorConfig",
    "SensorConfig",
    "SimConfig",
    "SimControllerConfig",
    "SimSceneConfig",
    "SimSensorConfig",
    "SimTableConfig",
    "SimTruthConfig",
    "SyncConfig",
    "TableConfig",
    "ZenohConfig",
    "format_validation_error",
    "load_config",
    "load_default",
    "parse_config",
]

SCHEMA_VERSION = 1
DEFAULT_CONFIG_RESOURCE = "default_sim.toml"
"""The embedded default inside ``wristscan.daemon`` (a copy of ``config/sim.toml``)."""

FloatArray = NDArray[np.float64]

# --------------------------------------------------------------------------------------------
# Value types. Strict scalars: TOML is typed, so "5" for a number or 1 for a boolean is a mistake
# worth reporting rather than coercing (ints are still accepted where a float is expected).

Float = Annotated[float, Strict()]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]

NonNegFloat = Annotated[Float, Field(ge=0)]
Probability = Annotated[Float, Field(ge=0, le=1)]
Port = Annotated[Int, Field(ge=1, le=65535)]
Baudrate = Annotated[Int, Field(ge=50, le=12_000_000)]
RegisterAddress = Annotated[Int, Field(ge=0, le=65535)]


def _fixed_length(n: int, what: str) -> Callable[[Any], Any]:
    def check(value: Any) -> Any:
        if isinstance(value, list | tuple) and len(value) != n:
            raise ValueError(f"expected {n} numbers {what}")
        return value

    return check


Vec3 = Annotated[tuple[Float, Float, Float], BeforeValidator(_fixed_length(3, "[x, y, z]"))]
Pose6 = Annotated[
    tuple[Float, Float, Float, Float, Float, Float],
    BeforeValidator(_fixed_length(6, "[x, y, z, rx, ry, rz] (m, rad)")),
]
Joints6 = Annotated[
    tuple[Float, Float, Float, Float, Float, Float],
    BeforeValidator(_fixed_length(6, "(one per joint)")),
]

_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"^(?=.{{1,253}}$){_LABEL}(\.{_LABEL})*$")
_CELL_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_ENDPOINT_NET = re.compile(
    r"^(tcp|udp|tls|quic|ws)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+):(\d{1,5})(#\S*)?$"
)
_ENDPOINT_OTHER = re.compile(r"^(unixsock-stream|serial)/\S+$")


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


def _cross(field: str, message: str) -> PydanticCustomError:
    """An error about a field found by a check across fields; ``field`` is relative to the model
    that raises it (the formatter appends it to the error location)."""
    return PydanticCustomError("cross_field", message, {"field": field})


def _resolve_path(value: str | None, info: ValidationInfo) -> Path | None:
    if value is None:
        return None
    path = Path(os.path.expanduser(value))
    base = (info.context or {}).get("base_dir")
    if not path.is_absolute() and base is not None:
        path = Path(base) / path
    return Path(os.path.normpath(path))


class _Model(BaseModel):
    model_config = ConfigDict(
        extra="forbid", frozen=True, allow_inf_nan=False, validate_default=False
    )


# --------------------------------------------------------------------------------------------
# [cell]


class CellConfig(_Model):
    name: Str
    """Names the cell in the zenoh key prefix and the status: letters, digits, ``_ . -``."""
    description: Str = ""

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not _CELL_NAME.match(v):
            raise ValueError(
                "must start with a letter or digit and hold only letters, digits, '_', '.', '-' "
                "(at most 64 characters)"
            )
        return v


# --------------------------------------------------------------------------------------------
# [robot]


class RobotConfig(_Model):
    driver: Str = "ur-rtde"
    """Robot driver name from the registry (built-in or a ``wristscan.robots`` entry point)."""
    host: Host
    """Controller address."""
    model: URModelName
    """UR model name for the nominal kinematics (``UR5e``, ``UR10e``, ...)."""
    frequency_hz: Annotated[Float, Field(gt=0, le=500)] | None = None
    """RTDE output rate; None: the controller's maximum (500 Hz e-Series, 125 Hz CB3)."""
    receive_backend: Literal["native", "ur_rtde"] = "native"
    """How the state stream is read: ``native`` (our RTDE client: every packet, a blocking read)
    or ``ur_rtde`` (its RTDEReceiveInterface, polled; it keeps only the newest packet)."""
    motion_enabled: Bool = False
    """Allow the daemon to move the robot (calibration sweeps). Off: receive only."""
    max_speed_m_s: Annotated[Float, Field(gt=0, le=3.0)] = 0.25
    max_accel_m_s2: Annotated[Float, Field(gt=0, le=15.0)] = 0.5
    max_joint_speed_rad_s: Annotated[Float, Field(gt=0, le=math.pi)] = 1.0
    max_joint_accel_rad_s2: Annotated[Float, Field(gt=0, le=40.0)] = 1.5
    workspace_min_m: Vec3 = (-0.9, -0.9, 0.0)
    """Box (base frame) the TCP must stay in during motions the daemon commands."""
    workspace_max_m: Vec3 = (0.9, 0.9, 1.2)
    use_factory_kinematics: Bool = True
    """Read the arm's own DH calibration (primary interface) instead of the nominal table."""
    options: dict[str, Any] = Field(default_factory=dict)
    """Extra settings for a plug-in driver (not checked here)."""

    @field_validator("driver")
    @classmethod
    def _driver(cls, v: str) -> str:
        return _check_driver("robots", v)

    @model_validator(mode="after")
    def _workspace(self) -> RobotConfig:
        lo, hi = self.workspace_min_m, self.workspace_max_m
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise _cross(
                "workspace_max_m",
                f"must be above workspace_min_m on every axis (min {list(lo)}, max {list(hi)})",
            )
        return self


def _check_driver(kind: registry.Kind, name: str) -> str:
    known = registry.names(kind)
    if name not in known:
        close = difflib.get_close_matches(name, known, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown {kind[:-1]} driver {name!r}{hint}; known: {', '.join(known)}")
    return name


# --------------------------------------------------------------------------------------------
# [sensor] and [sensor.options]


RecvBufferBytes = Annotated[Int, Field(ge=65536, le=1 << 30)]


class _UdpReceiverOptions(_Model):
    """What the sensors streaming to the host over UDP share. Each names, after ``port``, the
    only sender it accepts (an ``OptionalHost``), then ``recv_buffer_bytes`` (the fields are
    declared there to keep the order of the driver's arguments and of the error messages)."""

    bind_host: Host = "0.0.0.0"
    """Local address to receive datagrams on."""
    port: Port


class Lpf1UdpOptions(_UdpReceiverOptions):
    port: Port = 50002
    source_host: OptionalHost = None
    """Accept datagrams from this address only (None: any)."""
    recv_buffer_bytes: RecvBufferBytes = 8 << 20


class Lpf1TcpOptions(_Model):
    host: Host
    """The sensor (or bridge) to connect to."""
    port: Port
    connect_timeout_s: Annotated[Float, Field(gt=0, le=60)] = 2.0


class Lpf1SerialOptions(_Model):
    url: Annotated[Str, Field(min_length=1)]
    """A device path (``/dev/ttyUSB0``) or a pyserial URL (``socket://host:port``, ``loop://``)."""
    baudrate: Baudrate = 921600


class Rf627Options(_UdpReceiverOptions):
    port: Port = 50001
    """The host port the sensor streams profiles to."""
    sensor_host: OptionalHost = None
    """The sensor's address: datagrams from others are ignored (None: any)."""
    recv_buffer_bytes: RecvBufferBytes = 8 << 20


class ScipOptions(_Model):
    url: Annotated[Str, Field(min_length=1)]
    """``/dev/ttyACM0`` or ``socket://192.168.0.10:10940`` (Ethernet models)."""
    baudrate: Baudrate = 115200
    intensity: Bool = False
    """Request ranges with intensities (ME instead of MD)."""
    start_step: Annotated[Int, Field(ge=0)] | None = None
    """First step of the scan (None: the sensor's AMIN)."""
    end_step: Annotated[Int, Field(ge=0)] | None = None
    cluster: Annotated[Int, Field(ge=1, le=99)] = 1

    @model_validator(mode="after")
    def _steps(self) -> ScipOptions:
        if self.start_step is not None and self.end_step is not None:
            if self.end_step < self.start_step:
                raise _cross("end_step", "must be >= start_step")
        return self


class _SensorCommon(_Model):
    sensor_id: Annotated[Int, Field(ge=0, le=2**32 - 1)] | None = None
    """Only profiles with this id are accepted (None: any)."""
    latency_s: Annotated[Float, Field(ge=0, le=1.0)] = 0.0
    """Constant delay from the exposure to the device timestamp (measure it with the latency
    calibration); subtracted from every profile time."""
    clock_bits: Annotated[Int, Field(ge=8, le=64)] = 64
    """Width of the device timestamp counter: it wraps at ``2**clock_bits`` ticks."""
    clock_tick_s: Annotated[Float, Field(ge=1e-9, le=1.0)] = 1e-9
    """Duration of one timestamp tick."""

    @property
    def time_modulus_ns(self) -> int | None:
        """Where device timestamps wrap, in ns; None when they never do in practice (64 bits)."""
        if self.clock_bits >= 64:
            return None
        return (1 << self.clock_bits) * max(1, round(self.clock_tick_s * 1e9))


class Lpf1UdpSensorConfig(_SensorCommon):
    driver: Literal["lpf1-udp"]
    options: Lpf1UdpOptions = Field(default_factory=Lpf1UdpOptions)


class Lpf1TcpSensorConfig(_SensorCommon):
    driver: Literal["lpf1-tcp"]
    options: Lpf1TcpOptions


class Lpf1SerialSensorConfig(_SensorCommon):
    driver: Literal["lpf1-serial"]
    options: Lpf1SerialOptions


class Rf627SensorConfig(_SensorCommon):
    driver: Literal["rf627-udp"]
    options: Rf627Options = Field(default_factory=Rf627Options)


class ScipSensorConfig(_SensorCommon):
    driver: Literal["scip"]
    options: ScipOptions
    clock_bits: Annotated[Int, Field(ge=8, le=64)] = 24
    clock_tick_s: Annotated[Float, Field(ge=1e-9, le=1.0)] = 1e-3
    """SCIP timestamps are 24-bit millisecond counters."""


class PluginSensorConfig(_SensorCommon):
    """A sensor driver from a ``wristscan.sensors`` entry point; its options are its own."""

    driver: Str
    options: dict[str, Any] = Field(default_factory=dict)

    @field_validator("driver")
    @classmethod
    def _driver(cls, v: str) -> str:
        return _check_driver("sensors", v)


# The built-in drivers have their options checked here; tags are written "<name>" so that the
# error formatter can drop them from error locations.
_SENSOR_VARIANTS: dict[str, type[_SensorCommon]] = {
    "lpf1-udp": Lpf1UdpSensorConfig,
    "lpf1-tcp": Lpf1TcpSensorConfig,
    "lpf1-serial": Lpf1SerialSensorConfig,
    "rf627-udp": Rf627SensorConfig,
    "scip": ScipSensorConfig,
}
_PLUGIN_TAG = "<plugin>"


def _sensor_tag(value: Any) -> str:
    driver = value.get("driver") if isinstance(value, dict) else getattr(value, "driver", None)
    return f"<{driver}>" if driver in _SENSOR_VARIANTS else _PLUGIN_TAG


SensorConfig = Annotated[
    Union[  # noqa: UP007 -- Tag annotations need the explicit Union form
        Annotated[Lpf1UdpSensorConfig, Tag("<lpf1-udp>")],
        Annotated[Lpf1TcpSensorConfig, Tag("<lpf1-tcp>")],
        Annotated[Lpf1SerialSensorConfig, Tag("<lpf1-serial>")],
        Annotated[Rf627SensorConfig, Tag("<rf627-udp>")],
        Annotated[ScipSensorConfig, Tag("<scip>")],
        Annotated[PluginSensorConfig, Tag(_PLUGIN_TAG)],
    ],
    Discriminator(_sensor_tag),
]
_TAGGED_MODELS: dict[str, type[BaseModel]] = {
    **{f"<{k}>": v for k, v in _SENSOR_VARIANTS.items()},
    _PLUGIN_TAG: PluginSensorConfig,
}


# --------------------------------------------------------------------------------------------
# [table]


class TableConfig(_Model):
    """A rotary table read (and optionally commanded) over Modbus.

    Register defaults follow the simulated table's map (``drivers/sim/table.py``): encoder count
    at 0-1, status 2, target 10-11, command 12, speed limit 13.
    """

    enabled: Bool = True
    driver: Str = "modbus"
    transport: Literal["tcp", "rtu"] = "tcp"
    host: OptionalHost = None
    """Modbus TCP server (``transport = "tcp"``)."""
    port: Port = 502
    serial_port: Str | None = None
    """Serial device or pyserial URL (``transport = "rtu"``)."""
    baudrate: Baudrate = 115200
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    device_id: Annotated[Int, Field(ge=0, le=247)] = 1
    register_type: Literal["holding", "input"] = "holding"
    encoder_register: RegisterAddress = 0
    encoder_bits: Literal[16, 32] = 32
    word_order: Literal["big", "little"] = "big"
    """``big``: the high word of a 32-bit value sits at the lower address."""
    counts_per_rev: Annotated[Int, Field(ge=1)] | None = None
    scale_rad_per_count: Annotated[Float, Field(gt=0)] | None = None
    """Give exactly one of ``counts_per_rev`` and ``scale_rad_per_count``."""
    offset_rad: Float = 0.0
    """Angle = count * scale + offset."""
    invert: Bool = False
    """The encoder counts clockwise (seen from above the platter)."""
    status_register: RegisterAddress | None = 2
    target_register: RegisterAddress | None = 10
    command_register: RegisterAddress | None = 12
    speed_register: RegisterAddress | None = 13
    """Set the command registers to None on a read-only table."""
    poll_hz: Annotated[Float, Field(gt=0, le=2000)] = 200.0
    timeout_s: Annotated[Float, Field(gt=0, le=30)] = 0.5
    options: dict[str, Any] = Field(default_factory=dict)
    """Extra settings for a plug-in driver (not checked here)."""

    @field_validator("driver")
    @classmethod
    def _driver(cls, v: str) -> str:
        return _check_driver("tables", v)

    @model_validator(mode="after")
    def _consistent(self) -> TableConfig:
        if self.transport == "tcp" and self.host is None:
            raise _cross("host", 'required with transport = "tcp"')
        if self.transport == "rtu" and not self.serial_port:
            raise _cross("serial_port", 'required with transport = "rtu"')
        if (self.counts_per_rev is None) == (self.scale_rad_per_count is None):
            raise _cross(
                "counts_per_rev", "give exactly one of counts_per_rev and scale_rad_per_count"
            )
        return self

    @property
    def rad_per_count(self) -> float:
        """Encoder scale in radians per count (sign included when ``invert``)."""
        if self.scale_rad_per_count is not None:
            scale = self.scale_rad_per_count
        else:
            assert self.counts_per_rev is not None  # ensured by the validator
            scale = 2.0 * math.pi / self.counts_per_rev
        return -scale if self.invert else scale


# --------------------------------------------------------------------------------------------
# [sync], [pipeline], [zenoh], [calibration]


class SyncConfig(_Model):
    interpolation: Literal["joint", "tcp"] = "joint"
    """``joint``: interpolate joint positions then forward kinematics; ``tcp``: the TCP pose."""
    pairing: Literal["clock", "encoder"] = "clock"
    """Pair profiles to robot states by time (clock) or by the sensor's encoder input."""
    max_gap_s: Annotated[Float, Field(gt=0, le=1.0)] = 0.020
    """Largest spacing of the two robot samples a profile is interpolated between."""
    table_max_gap_s: Annotated[Float, Field(gt=0, le=10.0)] = 0.200
    max_wait_s: Annotated[Float, Field(gt=0, le=10.0)] = 0.200
    """How long a profile may wait for the robot states after it before it is dropped."""
    clock_window_s: Annotated[Float, Field(gt=0, le=3600)] = 30.0
    """Sliding window of the device-to-host clock fit."""
    clock_max_uncertainty_s: Annotated[Float, Field(gt=0, le=0.1)] = 200e-6
    """A clock mapping is trusted while its uncertainty stays below this."""
    robot_latency_s: Annotated[Float, Field(ge=0, le=1.0)] = 0.0
    table_latency_s: Annotated[Float, Field(ge=0, le=1.0)] = 0.0
    encoder_bits: Annotated[Int, Field(ge=8, le=64)] | None = None
    """Width of the sensor's encoder counter (None: does not wrap)."""


class PipelineConfig(_Model):
    batch_s: Annotated[Float, Field(gt=0, le=1.0)] = 0.010
    """Profiles are aligned and published in batches of this length."""
    profile_queue: Annotated[Int, Field(ge=16, le=1_000_000)] = 4096
    """Profiles waiting for pairing at most (the oldest are dropped beyond)."""
    batch_queue: Annotated[Int, Field(ge=1, le=1024)] = 8
    """Aligned batches waiting for publication at most."""
    frame: Literal["base", "table", "part"] = "base"
    """Frame of the published points; ``table`` and ``part`` need a ``[table]``."""
    publish_raw_profiles: Bool = False
    publish_robot_state: Bool = False
    publish_intensity: Bool = False
    publish_profile_index: Bool = False


class ZenohConfig(_Model):
    mode: Literal["peer", "client"] = "peer"
    connect: list[Str] = Field(default_factory=list)
    """Endpoints to connect to, e.g. ``tcp/192.168.1.10:7447``."""
    listen: list[Str] = Field(default_factory=list)
    multicast_scouting: Bool = False
    """Off by default: on a cell network the endpoints are known and scouting crosses cells."""
    prefix: Str = ""
    """Key prefix (default ``wristscan/<cell.name>``)."""
    congestion_control: Literal["drop", "block"] = "drop"
    """``drop``: a slow network loses batches (seq gaps) rather than stalling acquisition."""
    status_period_s: Annotated[Float, Field(gt=0, le=3600)] = 1.0
    config_file: Str | None = None
    """An extra zenoh JSON5 config merged under these settings (TLS, authentication, ACL)."""

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for i, ep in enumerate(v):
            m = _ENDPOINT_NET.match(ep)
            if m is not None:
                if not 1 <= int(m.group(3)) <= 65535:
                    raise ValueError(f"item {i}: port out of range in {ep!r}")
            elif not _ENDPOINT_OTHER.match(ep):
                raise ValueError(
                    f"item {i}: not a zenoh endpoint {ep!r} (expected e.g. 'tcp/127.0.0.1:7447')"
                )
        return v

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, v: str) -> str:
        chunks = v.split("/")
        if not v or any(not c for c in chunks) or re.search(r"[*$?#\s]", v):
            raise ValueError(
                "not a plain zenoh key: non-empty chunks separated by '/', no wildcards "
                "('*', '$'), '?', '#' or spaces"
            )
        return v

    @field_validator("config_file")
    @classmethod
    def _config_file(cls, v: str | None, info: ValidationInfo) -> str | None:
        path = _resolve_path(v, info)
        return None if path is None else str(path)

    @model_validator(mode="after")
    def _client_needs_router(self) -> ZenohConfig:
        if self.mode == "client" and not self.connect:
            raise _cross("connect", 'mode = "client" needs at least one endpoint to connect to')
        return self


class CalibrationConfig(_Model):
    file: Path | None = None
    """The sensor2flange calibration (JSON, see :mod:`wristscan.daemon.io.calibfile`); relative
    paths are resolved against the config file's folder. None: no calibration yet."""
    table_file: Path | None = None
    """The rotary-table calibration (``kind = "table"``)."""
    check_identity: Bool = True
    """Refuse a calibration made for another robot or sensor."""

    @field_validator("file", "table_file", mode="before")
    @classmethod
    def _paths(cls, v: Any, info: ValidationInfo) -> Any:
        if isinstance(v, str):
            if not v:
                raise ValueError("must not be empty (leave the key out for none)")
            return _resolve_path(v, info)
        if v is None or isinstance(v, Path):
            return v
        raise ValueError(f"must be a path string (got {_render(v)})")


# --------------------------------------------------------------------------------------------
# [sim]: the simulated cell (``wristscan sim`` and the tests)


class SimControllerConfig(_Model):
    host: Host = "127.0.0.2"
    """Loopback address the simulated controller listens on (ports 29999, 30003, 30004)."""
    model: URModelName = "UR5e"
    version: Annotated[
        tuple[Int, Int, Int, Int],
        BeforeValidator(_fixed_length(4, "[major, minor, bugfix, build]")),
        Field(description="PolyScope version"),
    ] = (5, 15, 0, 0)
    serial_number: Str = "20235500001"
    repeatability_m: Annotated[Float, Field(ge=0, le=0.01)] = 0.0
    initial_q_rad: Joints6 | None = None
    initial_q_deg: Joints6 | None = None
    """Start joint positions: give them in radians or degrees (not both)."""

    @field_validator("version")
    @classmethod
    def _version(cls, v: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        if any(x < 0 for x in v):
            raise ValueError("version numbers must be >= 0")
        return v

    @model_validator(mode="after")
    def _one_q(self) -> SimControllerConfig:
        if self.initial_q_rad is not None and self.initial_q_deg is not None:
            raise _cross("initial_q_deg", "give initial_q_rad or initial_q_deg, not both")
        return self

    @property
    def q0_rad(self) -> tuple[float, ...] | None:
        """Start joint positions in radians (None: the simulator's default)."""
        if self.initial_q_deg is not None:
            return tuple(math.radians(a) for a in self.initial_q_deg)
        return self.initial_q_rad


SimSensorKind = Literal[
    "lpf1-udp", "lpf1-tcp", "lpf1-serial", "rf627-udp", "scip-tcp", "scip-serial"
]


class SimSensorConfig(_Model):
    kind: SimSensorKind = "lpf1-udp"
    sensor_id: Annotated[Int, Field(ge=0, le=2**32 - 1)] = 1
    rate_hz: Annotated[Float, Field(gt=0, le=100_000)] = 1000.0
    n_points: Annotated[Int, Field(ge=1, le=16383)] = 2048
    fov_lateral_m: Annotated[Float, Field(gt=0, le=2.0)] = 0.05
    """Full width of the laser line (the points span ``y`` in ``[-fov/2, fov/2]``)."""
    depth_min_m: Annotated[Float, Field(ge=0)] = 0.05
    depth_max_m: Annotated[Float, Field(gt=0, le=50.0)] = 0.15
    noise_m: NonNegFloat = 20e-6
    """Standard deviation of the range noise."""
    dropout_prob: Probability = 0.0
    outlier_prob: Probability = 0.0
    latency_s: Annotated[Float, Field(ge=0, le=1.0)] = 0.002
    """Exposure to send (and to the device timestamp)."""
    clock_offset_s: Float = 0.0
    clock_drift_ppm: Annotated[Float, Field(ge=-1000, le=1000)] = 0.0
    clock_jitter_s: Annotated[Float, Field(ge=0, le=0.1)] = 0.0
    encoder: Bool = False
    """The sensor reports the table's encoder count with every profile."""
    intensity: Bool = False
    seed: Int | None = None

    @model_validator(mode="after")
    def _depth(self) -> SimSensorConfig:
        if not self.depth_min_m < self.depth_max_m:
            raise _cross("depth_max_m", "must be greater than depth_min_m")
        return self


class SimTableConfig(_Model):
    enabled: Bool = True
    transport: Literal["tcp", "rtu"] = "tcp"
    host: Host = "127.0.0.1"
    port: Annotated[Int, Field(ge=0, le=65535)] = 5020
    """Modbus TCP port (0: any free port)."""
    device_id: Annotated[Int, Field(ge=0, le=247)] = 1
    counts_per_rev: Annotated[Int, Field(ge=1, le=2**31)] = 3_600_000
    word_order: Literal["big", "little"] = "big"
    max_speed_deg_s: Annotated[Float, Field(gt=0, le=3600)] = 90.0
    accel_deg_s2: Annotated[Float, Field(gt=0, le=36000)] = 180.0
    initial_angle_rad: Float = 0.0


class SimSceneConfig(_Model):
    preset: Literal["demo"] = "demo"
    """``demo``: table top, tooling ball on a post, rotary table with a part."""
    with_part: Bool = True
    ball_radius_m: Annotated[Float, Field(gt=0, le=0.2)] = 0.0127
    ball_centre_m: Vec3 = (0.45, -0.20, 0.16)
    """Tooling ball centre in the robot base frame."""


class SimTruthConfig(_Model):
    """Ground truth the calibrations are checked against."""

    sensor2flange_pose: Pose6 = (0.060, 0.010, 0.200, 0.020, -0.015, 0.010)
    """The true tool transformation as a UR pose (m, rotation vector in rad)."""
    table_axis_point_m: Vec3 = (0.45, 0.25, 0.0)
    """A point of the rotary table's axis (base frame): the platter centre at the table top."""
    table_axis_direction: Vec3 = (0.0, -0.003490651415223732, 0.9999939076577904)
    """Direction of the table axis (base frame; normalised here). The default leans 0.2 deg."""

    @field_validator("table_axis_direction")
    @classmethod
    def _unit(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        n = math.sqrt(sum(x * x for x in v))
        if n < 1e-9:
            raise ValueError("must not be the zero vector")
        return (v[0] / n, v[1] / n, v[2] / n)

    def sensor2flange(self) -> FloatArray:
        """The true tool transformation, 4x4."""
        return se3.pose_to_matrix(np.asarray(self.sensor2flange_pose, dtype=np.float64))

    def table_zero2base(self) -> FloatArray:
        """The table frame at angle zero in the base frame: origin on the axis point, +Z along
        the axis, reached from the base axes by the smallest rotation."""
        z = np.array([0.0, 0.0, 1.0])
        d = np.asarray(self.table_axis_direction, dtype=np.float64)
        axis = np.cross(z, d)
        s = float(np.linalg.norm(axis))
        angle = math.atan2(s, float(z @ d))
        if s < 1e-12:
            # Parallel or anti-parallel to +Z: no unique axis, turn about X when anti-parallel.
            rotvec = np.array([angle, 0.0, 0.0])
        else:
            rotvec = axis / s * angle
        return se3.make(se3.rotvec_to_matrix(rotvec), np.asarray(self.table_axis_point_m))


class SimConfig(_Model):
    controller: SimControllerConfig = Field(default_factory=SimControllerConfig)
    sensor: SimSensorConfig = Field(default_factory=SimSensorConfig)
    table: SimTableConfig = Field(default_factory=SimTableConfig)
    scene: SimSceneConfig = Field(default_factory=SimSceneConfig)
    truth: SimTruthConfig = Field(default_factory=SimTruthConfig)


# --------------------------------------------------------------------------------------------
# The whole file


class Config(_Model):
    schema_version: Literal[1]
    cell: CellConfig
    robot: RobotConfig
    sensor: SensorConfig
    table: TableConfig | None = None
    sync: SyncConfig = Field(default_factory=SyncConfig)
    pipeline: PipelineConfig = Field(default_factory=PipelineConfig)
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig)
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
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
            and _CELL_NAME.match(cell["name"])
        ):
            data = {**data, "zenoh": {**zenoh, "prefix": f"wristscan/{cell['name']}"}}
        return data

    @model_validator(mode="after")
    def _frame_needs_table(self) -> Config:
        if self.pipeline.frame != "base" and not self.table_enabled:
            raise _cross(
                "pipeline.frame",
                f'frame = "{self.pipeline.frame}" needs an enabled [table] section',
            )
        if self.sync.pairing == "encoder" and self.sync.encoder_bits is None:
            raise _cross("sync.encoder_bits", 'required with pairing = "encoder"')
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


# --------------------------------------------------------------------------------------------
# Loading and error reporting


class ConfigError(ValueError):
    """A config file that cannot be used; ``problems`` holds one readable line per error,
    each starting with the file name."""

    def __init__(self, source: str, problems: Sequence[str]) -> None:
        self.source = source
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


def _render(value: Any, limit: int = 60) -> str:
    """A value as it would be written in TOML (shortened)."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, str):
        text = json.dumps(value)
    elif isinstance(value, int | float):
        text = repr(value)
    elif isinstance(value, list | tuple):
        text = "[" + ", ".join(_render(v, limit) for v in value) + "]"
    elif isinstance(value, dict):
        text = "a table"
    else:
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


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
        if isinstance(part, str) and part in _TAGGED_MODELS:
            model = _TAGGED_MODELS[part]
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
        msg += f" (got {_render(err['input'])})"
    where = _path_text(loc)
    return f"{source}: {where}: {msg}" if where else f"{source}: {msg}"


def format_validation_error(
    exc: ValidationError, source: str, root: type[BaseModel] | None = None
) -> list[str]:
    """One readable line per error of ``exc``: ``"<source>: <dotted.field>: <what is expected>
    (got <value>)"``. ``root`` (the validated model) enables 'did you mean' hints."""
    model = root if root is not None else BaseModel
    return [_problem(source, e, model) for e in exc.errors(include_url=False)]


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
            source, [f"{source}: schema_version: must be an integer (got {_render(v)})"]
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
