"""Byte-stream links shared by the TCP and serial sensor drivers (LPF1-TCP, LPF1-serial, SCIP).

A :class:`Transport` is one open connection: a TCP socket (``recv_into`` a preallocated buffer)
or a pyserial port (``serial_for_url``: device paths, ``loop://``, ``rfc2217://`` ...; a
``socket://host:port`` URL is served by the TCP transport, which reads in large chunks where
pyserial's socket handler returns one byte per call).

:class:`StreamProfileSensor` keeps the link up: a read error, an end of stream or silence for
longer than the silence limit (no valid message) drops the link; the driver then reports
RECONNECTING, ``read`` returns ``None``, and reconnect attempts follow with exponential backoff
(:class:`~wristscan.drivers.base.Backoff`). The link counts as restored, and ``reconnects`` is
incremented, when the first valid message arrives after the drop.
"""

from __future__ import annotations

import contextlib
import io
import logging
import select
import socket
import time
from abc import abstractmethod
from typing import Any
from urllib.parse import urlsplit

import serial

from wristscan.drivers._sensor import SensorCore
from wristscan.drivers.base import Backoff, DriverError, DriverInitError, LinkState
from wristscan.drivers.records import Profile

__all__ = [
    "LinkDown",
    "SerialTransport",
    "StreamProfileSensor",
    "TcpTransport",
    "Transport",
    "open_url",
]

log = logging.getLogger(__name__)

Chunk = bytes | bytearray | memoryview


class LinkDown(Exception):
    """The connection ended or failed (internal: drivers turn it into a reconnect)."""


class Transport:
    """One open byte-stream connection."""

    description = ""

    def read(self, timeout: float) -> Chunk:
        """Bytes that arrived within ``timeout`` seconds (empty on timeout). A returned
        memoryview is valid until the next call. Raises :class:`LinkDown`."""
        raise NotImplementedError

    def write(self, data: bytes) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class TcpTransport(Transport):
    def __init__(self, host: str, port: int, connect_timeout_s: float = 2.0) -> None:
        self.description = f"tcp {host}:{port}"
        self._sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buf = bytearray(1 << 18)
        self._view = memoryview(self._buf)
        self._timeout: float | None = None

    def read(self, timeout: float) -> Chunk:
        sock = self._sock
        try:
            if timeout != self._timeout:
                sock.settimeout(timeout)
                self._timeout = timeout
            n = sock.recv_into(self._buf)
        except TimeoutError:
            return b""
        except OSError as exc:
            raise LinkDown(f"{self.description}: {exc}") from exc
        if n == 0:
            raise LinkDown(f"{self.description}: connection closed by the device")
        return self._view[:n]

    def write(self, data: bytes) -> None:
        try:
            self._sock.settimeout(2.0)
            self._timeout = 2.0
            self._sock.sendall(data)
        except OSError as exc:
            raise LinkDown(f"{self.description}: write failed: {exc}") from exc

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.close()


class SerialTransport(Transport):
    """A pyserial port. POSIX ports are waited on with ``poll`` (changing pyserial's timeout
    reconfigures the tty each time); other URL handlers read with a fixed short timeout."""

    _fallback_timeout_s = 0.05

    def __init__(self, url: str, baudrate: int) -> None:
        self.description = f"serial {url}"
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=2.0)
        except (ValueError, serial.SerialException) as exc:
            raise DriverInitError(f"cannot open serial port {url!r}: {exc}") from exc
        self._poll: select.poll | None = None
        try:
            fd = self._port.fileno()
        except (AttributeError, io.UnsupportedOperation, serial.SerialException):
            fd = None
        if isinstance(fd, int) and fd >= 0:
            self._poll = select.poll()
            self._poll.register(fd, select.POLLIN)
        else:
            self._port.timeout = self._fallback_timeout_s

    def read(self, timeout: float) -> Chunk:
        port = self._port
        try:
            n = port.in_waiting
            if n:
                return bytes(port.read(n))
            if self._poll is not None:
                if not self._poll.poll(timeout * 1000.0):
                    return b""
                # Readable but nothing waiting: pyserial raises for a hang-up (unplugged).
                return bytes(port.read(max(1, port.in_waiting)))
            first = port.read(1)
            if not first:
                return b""
            n = port.in_waiting
            return bytes(first + port.read(n)) if n else bytes(first)
        except (OSError, serial.SerialException, ValueError, TypeError) as exc:
            # ValueError/TypeError: pyserial touching a port closed by another thread.
            raise LinkDown(f"{self.description}: {exc}") from exc

    def write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except (OSError, serial.SerialException) as exc:
            raise LinkDown(f"{self.description}: write failed: {exc}") from exc

    def close(self) -> None:
        with contextlib.suppress(OSError, serial.SerialException):
            self._port.close()


def open_url(url: str, baudrate: int, connect_timeout_s: float = 2.0) -> Transport:
    """``socket://host:port`` (TCP), otherwise a pyserial port or URL."""
    if url.startswith("socket://"):
        parts = urlsplit(url)
        if parts.hostname and parts.port and not parts.query:
            return TcpTransport(parts.hostname, parts.port, connect_timeout_s)
    return SerialTransport(url, baudrate)


class StreamProfileSensor(SensorCore):
    """A sensor on a byte stream that reconnects by itself (see the module docstring)."""

    silence_timeout_s = 2.5
    """No valid message for this long drops the link (LPF1 sends a heartbeat every second)."""
    max_wait_s = 0.1
    """Longest single wait inside ``read``, so a ``close`` from another thread is seen soon."""

    def __init__(self, sensor_id: int | None) -> None:
        super().__init__(sensor_id)
        self._transport: Transport | None = None
        self._backoff = Backoff()
        self._next_attempt = 0.0
        self._recovering = False
        self._last_valid = 0.0

    # --- for subclasses ---------------------------------------------------------------------
    @abstractmethod
    def _connect(self) -> Transport:
        """Open the connection (raise OSError or DriverError when it cannot be)."""

    def _start(self, transport: Transport) -> None:
        """Handshake after connecting (raise LinkDown or DriverError on failure)."""

    def _stop(self, transport: Transport) -> None:
        """Say goodbye before closing (best effort)."""

    @abstractmethod
    def _reset_decoder(self) -> None:
        """Forget partial input: a new connection starts a new stream."""

    @abstractmethod
    def _consume(self, data: Chunk, host_time_ns: int) -> None:
        """Decode received bytes; call ``_valid`` per good message, ``_deliver``/``_reject``."""

    def _silence_limit_s(self) -> float:
        return self.silence_timeout_s

    def _where(self) -> str:
        t = self._transport
        return t.description if t is not None else self.kind

    def _valid(self) -> None:
        """A well-formed message arrived: the link is alive (and restored after a drop)."""
        self._last_valid = time.monotonic()
        if self._recovering:
            self._recovering = False
            self.counters.reconnects += 1
            self._backoff.reset()
            self._set_state(LinkState.OPEN)

    # --- life cycle -------------------------------------------------------------------------
    def _establish(self) -> Transport:
        transport = self._connect()
        try:
            self._reset_decoder()
            self._start(transport)
        except BaseException:
            transport.close()
            raise
        return transport

    def _open(self) -> None:
        self._ready.clear()
        self._recovering = False
        try:
            transport = self._establish()
        except LinkDown as exc:
            raise DriverInitError(f"{self.kind}: {exc}") from exc
        self._transport = transport
        self._last_valid = time.monotonic()
        self._backoff.reset()

    def _close(self) -> None:
        transport, self._transport = self._transport, None
        if transport is None:
            return
        try:
            self._stop(transport)
        except (LinkDown, OSError) as exc:
            log.debug("%s: goodbye failed: %s", self.kind, exc)
        finally:
            transport.close()

    def _drop(self, reason: str) -> None:
        transport, self._transport = self._transport, None
        if transport is not None:
            transport.close()
        self._recovering = True
        self._set_state(LinkState.RECONNECTING, reason)
        self._next_attempt = time.monotonic() + self._backoff.next_delay()

    def _attempt(self) -> None:
        with self._lock:  # close() waits for an attempt in progress instead of racing it
            if not self._open_flag or self._transport is not None:
                return
            self.stats["reconnect_attempts"] += 1
            try:
                transport = self._establish()
            except (LinkDown, OSError, DriverError) as exc:
                self._set_state(LinkState.RECONNECTING, str(exc))
                self._next_attempt = time.monotonic() + self._backoff.next_delay()
                return
            self._transport = transport
            # The silence limit runs from the new connection.
            self._last_valid = max(self._last_valid, time.monotonic())

    # --- reading ----------------------------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> Profile | None:
        ready = self._pop()
        if ready is not None:
            return ready
        wait = self.max_wait_s if timeout is None else min(timeout, self.max_wait_s)
        transport = self._transport
        if transport is None:
            now = time.monotonic()
            if now < self._next_attempt:
                time.sleep(min(wait, self._next_attempt - now))
                return None
            self._attempt()
            return self._pop()
        try:
            data = transport.read(wait)
        except LinkDown as exc:
            if self._transport is transport and self._open_flag:
                self._drop(str(exc))
            return None
        if data:
            self.counters.bytes += len(data)
            self.raw_log.add(data)
            self._consume(data, time.monotonic_ns())
        if (
            self._transport is transport
            and time.monotonic() - self._last_valid > self._silence_limit_s()
        ):
            self._drop(f"no valid data for {self._silence_limit_s():g} s")
        return self._pop()

    def _health_detail(self) -> dict[str, Any]:
        t = self._transport
        return {
            **super()._health_detail(),
            "link": None if t is None else t.description,
            "last_valid_age_s": time.monotonic() - self._last_valid,
        }
