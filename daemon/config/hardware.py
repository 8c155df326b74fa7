"""The sections about what the daemon connects to: ``[cell]``, ``[robot]``, ``[sensor]`` (with
its driver-specific ``[sensor.options]``) and ``[table]``.

Built-in sensor drivers have their options checked here; a plug-in driver (an entry point) gets
its options unchecked. Driver names are checked against the registry.
"""

from __future__ import annotations

import difflib
import math
import os
from typing import Annotated, Any, Literal, Union

from pydantic import (
    BaseModel,
    Discriminator,
    Field,
    Tag,
    ValidationInfo,
    field_validator,
    model_validator,
)

from wristscan.daemon.config.values import (
    CELL_NAME,
    Baudrate,
    Bool,
    Float,
    Host,
    Int,
    OptionalHost,
    Port,
    RegisterAddress,
    Str,
    StrictModel,
    URModelName,
    Vec3,
    cross_field,
)
from wristscan.drivers import registry

__all__ = [
    "TAGGED_SENSOR_MODELS",
    "CellConfig",
    "Lpf1SerialOptions",
    "Lpf1SerialSensorConfig",
    "Lpf1TcpOptions",
    "Lpf1TcpSensorConfig",
    "Lpf1UdpOptions",
    "Lpf1UdpSensorConfig",
    "PluginSensorConfig",
    "Rf627Options",
    "Rf627SensorConfig",
    "RobotConfig",
    "ScipOptions",
    "ScipSensorConfig",
    "SensorConfig",
    "TableConfig",
]

# --------------------------------------------------------------------------------------------
# [cell]


class CellConfig(StrictModel):
    name: Str
    """Names the cell in the zenoh key prefix and the status: letters, digits, ``_ . -``."""
    description: Str = ""

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not CELL_NAME.match(v):
            raise ValueError(
                "must start with a letter or digit and hold only letters, digits, '_', '.', '-' "
                "(at most 64 characters)"
            )
        return v


# --------------------------------------------------------------------------------------------
# [robot]


class RobotConfig(StrictModel):
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
    kinematics_file: Annotated[Str, Field(min_length=1)] | None = None
    """The arm's kinematics identified with the probe (``wristscan calibrate kinematics``, JSON);
    when set, flange poses are computed with it (before the factory calibration). Relative paths
    are resolved against the config file's folder."""
    options: dict[str, Any] = Field(default_factory=dict)
    """Extra settings for a plug-in driver (not checked here)."""

    @field_validator("driver")
    @classmethod
    def _driver(cls, v: str) -> str:
        return _check_driver("robots", v)

    @field_validator("kinematics_file")
    @classmethod
    def _kinematics_file(cls, v: str | None, info: ValidationInfo) -> str | None:
        base = (info.context or {}).get("base_dir")
        if v is None or base is None or os.path.isabs(os.path.expanduser(v)):
            return None if v is None else os.path.expanduser(v)
        return os.path.normpath(os.path.join(base, os.path.expanduser(v)))

    @model_validator(mode="after")
    def _workspace(self) -> RobotConfig:
        lo, hi = self.workspace_min_m, self.workspace_max_m
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise cross_field(
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


class _UdpReceiverOptions(StrictModel):
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


class Lpf1TcpOptions(StrictModel):
    host: Host
    """The sensor (or bridge) to connect to."""
    port: Port
    connect_timeout_s: Annotated[Float, Field(gt=0, le=60)] = 2.0


class Lpf1SerialOptions(StrictModel):
    url: Annotated[Str, Field(min_length=1)]
    """A device path (``/dev/ttyUSB0``) or a pyserial URL (``socket://host:port``, ``loop://``)."""
    baudrate: Baudrate = 921600


class Rf627Options(_UdpReceiverOptions):
    port: Port = 50001
    """The host port the sensor streams profiles to."""
    sensor_host: OptionalHost = None
    """The sensor's address: datagrams from others are ignored (None: any)."""
    recv_buffer_bytes: RecvBufferBytes = 8 << 20


class ScipOptions(StrictModel):
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
                raise cross_field("end_step", "must be >= start_step")
        return self


class GocatorOptions(StrictModel):
    host: Host
    """The sensor's address (docs/gocator.md)."""
    control_port: Port = 3190
    data_port: Port = 3196
    health_port: Port = 3194
    connect_timeout_s: Annotated[Float, Field(gt=0, le=60)] = 2.0


class _SensorCommon(StrictModel):
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


class GocatorSensorConfig(_SensorCommon):
    driver: Literal["gocator"]
    options: GocatorOptions


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
    "gocator": GocatorSensorConfig,
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
        Annotated[GocatorSensorConfig, Tag("<gocator>")],
        Annotated[PluginSensorConfig, Tag(_PLUGIN_TAG)],
    ],
    Discriminator(_sensor_tag),
]
TAGGED_SENSOR_MODELS: dict[str, type[BaseModel]] = {
    **{f"<{k}>": v for k, v in _SENSOR_VARIANTS.items()},
    _PLUGIN_TAG: PluginSensorConfig,
}
"""The model behind each union tag of :data:`SensorConfig` (the error formatter follows error
locations through them)."""


# --------------------------------------------------------------------------------------------
# [table]


class TableConfig(StrictModel):
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
            raise cross_field("host", 'required with transport = "tcp"')
        if self.transport == "rtu" and not self.serial_port:
            raise cross_field("serial_port", 'required with transport = "rtu"')
        if (self.counts_per_rev is None) == (self.scale_rad_per_count is None):
            raise cross_field(
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
