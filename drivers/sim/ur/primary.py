"""A tiny simulated UR primary interface (TCP 30001): version message and ROBOT_STATE with the
KinematicsInfo sub-package, in the real wire format (big-endian).

Message: ``int32 size`` (including the 5-byte header), ``uint8 type``, payload. On connection the
server sends a version message (ROBOT_MESSAGE, type 20), then every ``period_s`` a ROBOT_STATE
(type 16) holding a robot-mode sub-package (type 0) and KinematicsInfo (type 5: ``uint32[6]
checksum, double[6] theta, a, d, alpha, uint32 calibration_status``). The first ROBOT_STATE after
connecting has no KinematicsInfo, so clients must skip messages and sub-packages they do not need.
Whatever clients send is ignored (a real controller would run it as URScript).

Two ways to run it:

* inside an asyncio event loop (the simulated controller's): ``server = await
  PrimaryServer.start(host, values)``, later ``server.close()`` and ``await server.wait_closed()``;
* standalone, for tests: ``with PrimaryInterfaceServer(host, values): ...`` runs the same server
  in an event loop on a thread of its own (the client is plain sockets, so no GIL trouble).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

from wristscan.calib import kinematics

__all__ = [
    "PRIMARY_PORT",
    "KinematicsValues",
    "PrimaryInterfaceServer",
    "PrimaryServer",
    "encode_robot_state",
    "encode_version_message",
]

log = logging.getLogger(__name__)

PRIMARY_PORT = 30001
MSG_ROBOT_MESSAGE = 20
MSG_ROBOT_STATE = 16
SUB_ROBOT_MODE = 0
SUB_KINEMATICS_INFO = 5
ROBOT_MESSAGE_VERSION = 3


@dataclass(frozen=True)
class KinematicsValues:
    """What the simulated controller reports as its factory calibration (rad, m)."""

    theta: tuple[float, ...]
    a: tuple[float, ...]
    d: tuple[float, ...]
    alpha: tuple[float, ...]
    checksum: tuple[int, ...] = (0,) * 6
    calibration_status: int = 2

    def __post_init__(self) -> None:
        for name in ("theta", "a", "d", "alpha", "checksum"):
            if len(getattr(self, name)) != 6:
                raise ValueError(f"KinematicsValues.{name} needs 6 values")

    @classmethod
    def from_model(
        cls,
        model: str | kinematics.DHParams,
        checksum: Sequence[int] = (0,) * 6,
        calibration_status: int = 2,
    ) -> KinematicsValues:
        """Report ``model`` (its ``theta_offset`` as theta) as the calibration."""
        m = kinematics.get_model(model)
        return cls(
            theta=tuple(m.theta_offset),
            a=tuple(m.a),
            d=tuple(m.d),
            alpha=tuple(m.alpha),
            checksum=tuple(int(c) for c in checksum),
            calibration_status=calibration_status,
        )


def _message(kind: int, payload: bytes) -> bytes:
    return struct.pack(">iB", 5 + len(payload), kind) + payload


def _sub(kind: int, body: bytes) -> bytes:
    return struct.pack(">IB", 5 + len(body), kind) + body


def encode_version_message(version: Sequence[int] = (5, 15, 0, 0)) -> bytes:
    """ROBOT_MESSAGE / VERSION: ``uint64 timestamp, int8 source, uint8 message type (3), int8
    name length, name, uint8 major, uint8 minor, int32 bugfix, int32 build, build date``."""
    name = b"URControl"
    major, minor, bugfix, build = (int(v) for v in version)
    body = struct.pack(">QbBb", 0, -2, ROBOT_MESSAGE_VERSION, len(name)) + name
    body += struct.pack(">BBii", major, minor, bugfix, build) + b"01-01-2024, 00:00:00"
    return _message(MSG_ROBOT_MESSAGE, body)


def encode_robot_state(
    values: KinematicsValues | None, timestamp_us: int = 0, robot_mode: int = 7
) -> bytes:
    """ROBOT_STATE with a robot-mode sub-package and, when ``values`` is given, KinematicsInfo."""
    mode = struct.pack(
        ">Q7?BBdddB",
        timestamp_us,
        True,  # real robot connected
        True,  # real robot enabled
        robot_mode >= 4,  # power on
        False,  # emergency stopped
        False,  # protective stopped
        False,  # program running
        False,  # program paused
        robot_mode,
        0,  # control mode: position
        1.0,  # target speed fraction
        1.0,  # speed scaling
        1.0,  # target speed fraction limit
        0,  # reserved
    )
    payload = _sub(SUB_ROBOT_MODE, mode)
    if values is not None:
        kin = struct.pack(
            ">6I24dI",
            *values.checksum,
            *values.theta,
            *values.a,
            *values.d,
            *values.alpha,
            values.calibration_status,
        )
        payload += _sub(SUB_KINEMATICS_INFO, kin)
    return _message(MSG_ROBOT_STATE, payload)


class _Protocol(asyncio.Protocol):
    def __init__(self, server: PrimaryServer) -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self._timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.server._conns.add(self)
        transport.write(encode_version_message(self.server.version))
        transport.write(encode_robot_state(None, self._stamp()))
        self._send_state()

    def _stamp(self) -> int:
        return (time.monotonic_ns() - self.server.start_ns) // 1000

    def _send_state(self) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        self.transport.write(encode_robot_state(self.server.values, self._stamp()))
        loop = asyncio.get_running_loop()
        self._timer = loop.call_later(self.server.period_s, self._send_state)

    def data_received(self, data: bytes) -> None:
        log.debug("primary interface: %d bytes from the client ignored", len(data))

    def connection_lost(self, exc: Exception | None) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self.transport = None
        self.server._conns.discard(self)

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        if self.transport is not None:
            self.transport.close()


class PrimaryServer:
    """The primary interface on ``host:port`` in the running event loop."""

    def __init__(self, values: KinematicsValues, period_s: float, version: Sequence[int]) -> None:
        self.values = values
        self.period_s = period_s
        self.version = tuple(version)
        self.start_ns = time.monotonic_ns()
        self._server: asyncio.Server | None = None
        self._conns: set[_Protocol] = set()

    @classmethod
    async def start(
        cls,
        host: str,
        values: KinematicsValues,
        port: int = PRIMARY_PORT,
        period_s: float = 0.1,
        version: Sequence[int] = (5, 15, 0, 0),
    ) -> PrimaryServer:
        """Listen on ``host:port``; ROBOT_STATE every ``period_s`` seconds to each client."""
        self = cls(values, period_s, version)
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            lambda: _Protocol(self), host, port, reuse_address=True
        )
        return self

    @property
    def clients(self) -> int:
        return len(self._conns)

    def close(self) -> None:
        """Stop listening and close every client connection."""
        if self._server is not None:
            self._server.close()
        for c in list(self._conns):
            c.close()

    async def wait_closed(self) -> None:
        if self._server is not None:
            await self._server.wait_closed()


class PrimaryInterfaceServer:
    """:class:`PrimaryServer` in an event loop on its own thread; a context manager."""

    def __init__(
        self,
        host: str,
        values: KinematicsValues,
        port: int = PRIMARY_PORT,
        period_s: float = 0.1,
    ) -> None:
        self.host, self.port = host, port
        self.values = values
        self.period_s = period_s
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: PrimaryServer | None = None
        self._stop: asyncio.Event | None = None
        self._error: BaseException | None = None

    def start(self, timeout_s: float = 10.0) -> PrimaryInterfaceServer:
        ready = threading.Event()

        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            try:
                self._server = await PrimaryServer.start(
                    self.host, self.values, self.port, self.period_s
                )
            except OSError as e:
                self._error = e
                ready.set()
                return
            ready.set()
            try:
                await self._stop.wait()
            finally:
                self._server.close()
                await self._server.wait_closed()

        self._thread = threading.Thread(
            target=asyncio.run, args=(main(),), name=f"sim-primary-{self.host}", daemon=True
        )
        self._thread.start()
        if not ready.wait(timeout_s):
            self.stop()
            raise RuntimeError(f"primary interface server on {self.host} did not start")
        if self._error is not None:
            self.stop()
            raise OSError(
                f"primary interface cannot listen on {self.host}:{self.port}: {self._error}"
            )
        return self

    def stop(self) -> None:
        loop, stop, thread = self._loop, self._stop, self._thread
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(stop.set)
        if thread is not None:
            thread.join(timeout=10)
        self._thread = None
        self._loop = None

    def __enter__(self) -> PrimaryInterfaceServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
