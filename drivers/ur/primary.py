"""Small clients for what a UR controller says about the arm itself: the factory kinematics
(primary interface, TCP 30001) and the serial number (dashboard server, TCP 29999).

Every UR arm is calibrated at the factory; the controller reports the resulting DH parameters in
the ``KinematicsInfo`` sub-package of its ROBOT_STATE messages (PROTOCOLS.md, "UR kinematics").
Without them, forward kinematics from the nominal table can be off by centimetres.

Wire format (big-endian): a message is ``int32 size`` (including the 5-byte header), ``uint8
type``, payload. ROBOT_STATE (type 16) carries sub-packages, each ``uint32 size`` (including its
own 5-byte header), ``uint8 type``, body. KinematicsInfo (sub-package type 5):
``uint32[6] checksum, double[6] theta, double[6] a, double[6] d, double[6] alpha, uint32
calibration_status``. Other messages (version, robot messages ...) and sub-packages are skipped.

The values are the complete calibrated parameters (nominal plus per-robot deltas), so
:meth:`KinematicsInfo.model` builds the model directly
(:func:`wristscan.calib.kinematics.from_kinematics_info`), and :meth:`KinematicsInfo.deltas`
expresses them as deltas on a nominal model for
:func:`wristscan.calib.kinematics.with_deltas`. The raw values can look odd (large ``d`` of
joints 2/3 that cancel): forward kinematics with them is still exact.

The serial number: the dashboard server (a line-based text protocol: a welcome line, then one
reply line per command line) answers ``get serial number`` with the controller's serial from
PolyScope 5.6 on; older software replies ``could not understand: ...``
(:func:`read_serial_number` then returns None).

Plain blocking sockets with timeouts: waiting releases the GIL, so it does not stall other
threads of the caller.
"""

from __future__ import annotations

import logging
import re
import socket
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import kinematics
from wristscan.drivers.base import DriverIOError, DriverTimeout

__all__ = [
    "DASHBOARD_PORT",
    "MSG_ROBOT_STATE",
    "PRIMARY_PORT",
    "SUB_KINEMATICS_INFO",
    "KinematicsInfo",
    "PrimaryInterfaceError",
    "iter_messages",
    "iter_subpackages",
    "parse_kinematics_info",
    "read_kinematics_info",
    "read_serial_number",
]

log = logging.getLogger(__name__)

PRIMARY_PORT = 30001
DASHBOARD_PORT = 29999
MSG_ROBOT_STATE = 16
SUB_KINEMATICS_INFO = 5

_MSG_HEADER = struct.Struct(">iB")
_SUB_HEADER = struct.Struct(">IB")
_KIN_BODY = struct.Struct(">6I24dI")  # checksum, theta, a, d, alpha, calibration_status
_MAX_MESSAGE = 1 << 20  # a primary message is a few kB; anything larger means lost framing
_SERIAL = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


class PrimaryInterfaceError(DriverIOError):
    """The primary interface answered with something that is not its wire format, or closed."""


@dataclass(frozen=True)
class KinematicsInfo:
    """The factory calibration a controller reports (radians and metres, joint 1 first)."""

    checksum: tuple[int, ...]
    theta: tuple[float, ...]
    """DH joint-angle offsets (rad)."""
    a: tuple[float, ...]
    """DH link lengths (m)."""
    d: tuple[float, ...]
    """DH link offsets (m)."""
    alpha: tuple[float, ...]
    """DH link twists (rad)."""
    calibration_status: int

    def model(self, name: str = "calibrated") -> kinematics.DHParams:
        """The calibrated kinematic model."""
        return kinematics.from_kinematics_info(self.theta, self.a, self.d, self.alpha, name=name)

    def deltas(
        self, nominal: str | kinematics.DHParams
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``(delta_theta, delta_a, delta_d, delta_alpha)`` relative to ``nominal``, so that
        ``kinematics.with_deltas(nominal, *info.deltas(nominal))`` equals :meth:`model`."""
        d, a, alpha, theta = kinematics.get_model(nominal).arrays()
        return (
            np.asarray(self.theta) - theta,
            np.asarray(self.a) - a,
            np.asarray(self.d) - d,
            np.asarray(self.alpha) - alpha,
        )


def parse_kinematics_info(body: bytes | memoryview) -> KinematicsInfo:
    """Decode a KinematicsInfo sub-package body (after its 5-byte header)."""
    if len(body) < _KIN_BODY.size:
        raise PrimaryInterfaceError(
            f"KinematicsInfo sub-package too short: {len(body)} < {_KIN_BODY.size} bytes"
        )
    v = _KIN_BODY.unpack_from(body)
    info = KinematicsInfo(
        checksum=tuple(int(x) for x in v[0:6]),
        theta=tuple(v[6:12]),
        a=tuple(v[12:18]),
        d=tuple(v[18:24]),
        alpha=tuple(v[24:30]),
        calibration_status=int(v[30]),
    )
    if not np.all(np.isfinite(np.r_[info.theta, info.a, info.d, info.alpha])):
        raise PrimaryInterfaceError("KinematicsInfo holds NaN or infinite parameters")
    return info


def iter_subpackages(payload: bytes | memoryview) -> Iterator[tuple[int, memoryview]]:
    """``(type, body)`` of each sub-package of a ROBOT_STATE payload (after the message
    header)."""
    view = memoryview(payload)
    pos = 0
    while pos < len(view):
        if len(view) - pos < _SUB_HEADER.size:
            raise PrimaryInterfaceError(f"truncated sub-package header at byte {pos}")
        size, kind = _SUB_HEADER.unpack_from(view, pos)
        if size < _SUB_HEADER.size or pos + size > len(view):
            raise PrimaryInterfaceError(
                f"sub-package of type {kind} claims {size} bytes, {len(view) - pos} left"
            )
        yield kind, view[pos + _SUB_HEADER.size : pos + size]
        pos += size


class _MessageReader:
    """Reassembles primary-interface messages from a byte stream."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> Iterator[tuple[int, bytes]]:
        self._buf += data
        while len(self._buf) >= _MSG_HEADER.size:
            size, kind = _MSG_HEADER.unpack_from(self._buf)
            if size < _MSG_HEADER.size or size > _MAX_MESSAGE:
                raise PrimaryInterfaceError(
                    f"message of type {kind} claims {size} bytes: not the primary interface?"
                )
            if len(self._buf) < size:
                return
            payload = bytes(self._buf[_MSG_HEADER.size : size])
            del self._buf[:size]
            yield kind, payload


def iter_messages(data: bytes) -> Iterator[tuple[int, bytes]]:
    """``(type, payload)`` of each complete message in ``data`` (a helper for tests and
    captures)."""
    yield from _MessageReader().feed(data)


def read_kinematics_info(
    host: str, port: int = PRIMARY_PORT, timeout_s: float = 5.0
) -> KinematicsInfo:
    """Connect to the primary interface and return the first KinematicsInfo it reports.

    Raises :class:`DriverTimeout` when none arrives within ``timeout_s`` seconds,
    :class:`PrimaryInterfaceError` for a closed or garbled stream, ``OSError`` when the
    connection is refused.
    """
    deadline = time.monotonic() + timeout_s
    reader = _MessageReader()
    seen: dict[int, int] = {}
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            sock.settimeout(remaining)
            try:
                data = sock.recv(65536)
            except TimeoutError:
                break
            if not data:
                raise PrimaryInterfaceError(f"{host}:{port} closed the primary interface")
            for kind, payload in reader.feed(data):
                seen[kind] = seen.get(kind, 0) + 1
                if kind != MSG_ROBOT_STATE:
                    continue
                for sub, body in iter_subpackages(payload):
                    if sub == SUB_KINEMATICS_INFO:
                        info = parse_kinematics_info(body)
                        log.info(
                            "%s: factory kinematics read (calibration status %d)",
                            host,
                            info.calibration_status,
                        )
                        return info
    raise DriverTimeout(
        f"no KinematicsInfo from {host}:{port} within {timeout_s:g} s "
        f"(messages seen by type: {seen or 'none'})"
    )


def _read_line(sock: socket.socket, buf: bytearray, deadline: float, where: str) -> str:
    """The next line of a text protocol (without its end), reading into ``buf``."""
    while b"\n" not in buf:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise DriverTimeout(f"{where}: no reply line in time")
        sock.settimeout(remaining)
        try:
            data = sock.recv(4096)
        except TimeoutError:
            raise DriverTimeout(f"{where}: no reply line in time") from None
        if not data:
            raise PrimaryInterfaceError(f"{where} closed the connection")
        buf += data
        if len(buf) > 65536:
            raise PrimaryInterfaceError(f"{where}: a reply line over 64 kB: not a dashboard?")
    line, _, rest = bytes(buf).partition(b"\n")
    buf[:] = rest
    return line.decode("utf-8", "replace").strip()


def read_serial_number(host: str, port: int = DASHBOARD_PORT, timeout_s: float = 5.0) -> str | None:
    """The controller's serial number from its dashboard server (``get serial number``), or
    None when the controller's software does not know the command (before PolyScope 5.6).

    Raises :class:`DriverTimeout` when no reply comes within ``timeout_s`` seconds,
    :class:`PrimaryInterfaceError` for a closed connection, ``OSError`` when the connection is
    refused.
    """
    where = f"dashboard {host}:{port}"
    deadline = time.monotonic() + timeout_s
    buf = bytearray()
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        _read_line(sock, buf, deadline, where)  # the welcome line
        sock.sendall(b"get serial number\n")
        reply = _read_line(sock, buf, deadline, where)
        try:
            sock.sendall(b"quit\n")
        except OSError:
            pass  # the answer is in; a server that closed first is no error
    if _SERIAL.fullmatch(reply) is None:
        log.info("%s: no serial number (reply %r)", where, reply[:80])
        return None
    return reply
