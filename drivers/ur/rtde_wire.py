"""RTDE wire format, shared by the receive client (:mod:`wristscan.drivers.ur.receive`) and the
simulated controller (:mod:`wristscan.drivers.sim.ur.rtde_server`): packet framing, the variable
type table, recipes.

Packet: ``uint16 size`` (including the 3-byte header), ``uint8 type``, payload; big-endian
(PROTOCOLS.md, "UR RTDE"). The name -> type table lists every variable a UR controller knows, as
documented in UR's RTDE guide and mirrored by Universal_Robots_Client_Library's test server; a name
missing from it is answered with ``NOT_FOUND``. Registers 0-23 are the general-purpose range and
24-47 the upper range that ur_rtde uses with ``FLAG_UPPER_RANGE_REGISTERS``.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

__all__ = [
    "DATA_PACKAGE",
    "GET_URCONTROL_VERSION",
    "HEADER",
    "INPUT_NAMES",
    "OUTPUT_NAMES",
    "PAUSE",
    "REQUEST_PROTOCOL_VERSION",
    "SETUP_INPUTS",
    "SETUP_OUTPUTS",
    "START",
    "TEXT_MESSAGE",
    "TYPE_DTYPE",
    "TYPE_FORMAT",
    "VARIABLE_TYPES",
    "PacketReader",
    "Recipe",
    "encode",
    "encode_text_message",
    "next_packet",
    "parse_text_message",
    "split_names",
    "zero_value",
]

HEADER = struct.Struct(">HB")

# Packet types (ASCII codes).
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

TYPE_FORMAT: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
"""struct format of each RTDE type (big-endian prefix added by :class:`Recipe`)."""

TYPE_DTYPE: dict[str, tuple[str, int]] = {
    "BOOL": ("?", 1),
    "UINT8": ("u1", 1),
    "UINT32": ("u4", 1),
    "UINT64": ("u8", 1),
    "INT32": ("i4", 1),
    "DOUBLE": ("f8", 1),
    "VECTOR3D": ("f8", 3),
    "VECTOR6D": ("f8", 6),
    "VECTOR6INT32": ("i4", 6),
    "VECTOR6UINT32": ("u4", 6),
}
"""NumPy scalar type (without byte order) and element count of each RTDE type."""

_TYPE_LENGTH = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


def _registers() -> tuple[dict[str, str], dict[str, str]]:
    """Register variables, which are inputs that outputs may also read back."""
    inputs: dict[str, str] = {
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
    }
    outputs: dict[str, str] = {
        "output_bit_registers0_to_31": "UINT32",
        "output_bit_registers32_to_63": "UINT32",
    }
    for i in range(64, 128):
        inputs[f"input_bit_register_{i}"] = "BOOL"
        outputs[f"output_bit_register_{i}"] = "BOOL"
    for i in range(48):
        inputs[f"input_int_register_{i}"] = "INT32"
        outputs[f"output_int_register_{i}"] = "INT32"
    for i in range(48):
        inputs[f"input_double_register_{i}"] = "DOUBLE"
        outputs[f"output_double_register_{i}"] = "DOUBLE"
    return inputs, outputs


_IN_REGS, _OUT_REGS = _registers()

_INPUT_ONLY: dict[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "external_force_torque": "VECTOR6D",
}

_OUTPUT_ONLY: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "actual_current_window": "VECTOR6D",
    "actual_current_as_torque": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "tcp_offset": "VECTOR6D",
    "actual_TCP_acceleration": "VECTOR6D",
    "target_TCP_acceleration": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "actual_configurable_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "target_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "actual_configurable_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    "tcp_force_scalar": "DOUBLE",
    "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE",
    "ft_raw_wrench": "VECTOR6D",
    "wrench_calc_from_currents": "VECTOR6D",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
    "time_scale_source": "INT32",
    "target_gravity": "VECTOR3D",
    "target_base_acceleration": "VECTOR6D",
    "control_step": "UINT64",
    "target_base_wrench": "VECTOR6D",
    "actual_robot_energy_consumed": "DOUBLE",
    "actual_robot_braking_energy_dissipated": "DOUBLE",
    "encoder0_raw": "INT32",
    "encoder1_raw": "INT32",
}

INPUT_NAMES: frozenset[str] = frozenset(_INPUT_ONLY) | frozenset(_IN_REGS)
"""Names a client may write through an input recipe."""

VARIABLE_TYPES: dict[str, str] = {**_INPUT_ONLY, **_IN_REGS, **_OUTPUT_ONLY, **_OUT_REGS}
"""Every variable the controller knows, name -> RTDE type name."""

OUTPUT_NAMES: frozenset[str] = frozenset(VARIABLE_TYPES) - frozenset(_INPUT_ONLY)
"""Names an output recipe may read: outputs plus the input registers (read back)."""


def zero_value(type_name: str) -> Any:
    """The neutral value of a type: 0, 0.0, False or a tuple of those."""
    n = _TYPE_LENGTH.get(type_name)
    if type_name in ("VECTOR3D", "VECTOR6D"):
        return (0.0,) * (n or 0)
    if n is not None:
        return (0,) * n
    if type_name == "DOUBLE":
        return 0.0
    if type_name == "BOOL":
        return False
    return 0


def encode(packet_type: int, payload: bytes = b"") -> bytes:
    """One packet: header plus payload."""
    return HEADER.pack(HEADER.size + len(payload), packet_type) + payload


def encode_text_message(text: str, source: str = "", level: int = 3) -> bytes:
    """Payload of a protocol-2 text message ('M'): ``uint8`` length, message, ``uint8`` length,
    source, ``uint8`` level (0 exception, 1 error, 2 warning, 3 info)."""
    t = text.encode("utf-8")[:255]
    s = source.encode("utf-8")[:255]
    return bytes((len(t),)) + t + bytes((len(s),)) + s + bytes((level & 0xFF,))


def parse_text_message(payload: bytes) -> tuple[str, str, int]:
    """``(text, source, level)`` of a protocol-2 text message; a malformed one yields its bytes
    as text, level 3 (a message is informative: never worth dropping the link over)."""
    try:
        n = payload[0]
        text = payload[1 : 1 + n]
        m = payload[1 + n]
        source = payload[2 + n : 2 + n + m]
        level = payload[2 + n + m]
        if len(text) != n or len(source) != m:
            raise IndexError
    except IndexError:
        return payload.decode("utf-8", errors="replace"), "", 3
    return text.decode("utf-8", errors="replace"), source.decode("utf-8", errors="replace"), level


def split_names(text: bytes) -> list[str]:
    """Comma-separated names as ur_rtde sends them (with a trailing comma); empty items dropped."""
    return [n.strip() for n in text.decode("ascii", errors="replace").split(",") if n.strip()]


class Recipe:
    """An ordered list of variables with their packed layout (big-endian)."""

    def __init__(self, recipe_id: int, names: Sequence[str], types: Sequence[str]) -> None:
        self.recipe_id = recipe_id
        self.names = list(names)
        self.types = list(types)
        self.vector = [t in _TYPE_LENGTH for t in self.types]
        self.counts = [_TYPE_LENGTH.get(t, 1) for t in self.types]
        self.struct = struct.Struct(">" + "".join(TYPE_FORMAT[t] for t in self.types))
        self.field_structs = [struct.Struct(">" + TYPE_FORMAT[t]) for t in self.types]

    @functools.cached_property
    def dtype(self) -> np.dtype[np.void]:
        """Packed structured dtype of the fields as sent (big-endian), ``struct.size`` bytes
        (names must be unique)."""
        return self.numpy_dtype(">")

    def numpy_dtype(self, byte_order: str = "=") -> np.dtype[np.void]:
        """Packed structured dtype of the fields (``">"`` as on the wire, ``"="`` native);
        vector types are sub-arrays, e.g. ``actual_q`` has shape ``(6,)``."""
        fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
        for name, t in zip(self.names, self.types, strict=True):
            scalar, n = TYPE_DTYPE[t]
            code = scalar if scalar in ("?", "u1") else byte_order + scalar
            fields.append((name, code, (n,)) if t in _TYPE_LENGTH else (name, code))
        return np.dtype(fields)

    def pack(self, values: dict[str, Any], defaults: dict[str, Any]) -> bytes:
        """Payload of a data package: recipe id then the fields, read from ``values`` (falling
        back to ``defaults``) by name."""
        flat: list[Any] = []
        for name, is_vec in zip(self.names, self.vector, strict=True):
            v = values.get(name)
            if v is None:
                v = defaults[name]
            if is_vec:
                flat.extend(v)
            else:
                flat.append(v)
        return bytes((self.recipe_id,)) + self.struct.pack(*flat)

    def unpack(self, data: bytes) -> dict[str, Any]:
        """Field values of a data package payload (after the recipe id byte).

        A short payload yields the fields it holds completely (clients that pack fewer fields
        than their recipe names are tolerated rather than dropped)."""
        if len(data) == self.struct.size:
            raw = self.struct.unpack(data)
            out: dict[str, Any] = {}
            i = 0
            for name, n, is_vec in zip(self.names, self.counts, self.vector, strict=True):
                out[name] = tuple(raw[i : i + n]) if is_vec else raw[i]
                i += n
            return out
        out = {}
        offset = 0
        for name, fs, is_vec in zip(self.names, self.field_structs, self.vector, strict=True):
            if offset + fs.size > len(data):
                break
            vals = fs.unpack_from(data, offset)
            out[name] = tuple(vals) if is_vec else vals[0]
            offset += fs.size
        return out


def next_packet(buf: bytes | bytearray, pos: int = 0) -> tuple[int, bytes, int] | None:
    """The packet that starts at ``pos`` in ``buf``: ``(type, payload, end)``, or None while it is
    incomplete. Raises ``ValueError`` for a size shorter than the header (a stream out of step)."""
    if len(buf) - pos < HEADER.size:
        return None
    size, ptype = HEADER.unpack_from(buf, pos)
    if size < HEADER.size:
        raise ValueError(f"RTDE packet size {size} is shorter than its header")
    if len(buf) - pos < size:
        return None
    return ptype, bytes(buf[pos + HEADER.size : pos + size]), pos + size


class PacketReader:
    """Splits a byte stream into ``(type, payload)`` packets."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> Iterator[tuple[int, bytes]]:
        self._buf += data
        while (packet := next_packet(self._buf)) is not None:
            ptype, payload, end = packet
            del self._buf[:end]
            yield ptype, payload
