"""Datagram reception shared by the UDP sensor drivers (LPF1-UDP, RF627).

One socket bound to the configured port with a large receive buffer; datagrams are received with
``recvmsg_into`` into one preallocated buffer and handed to the driver's ``_on_datagram`` as a
memoryview (valid only during the call: decoders copy what they keep).

Receipt stamps come from the kernel (Linux ``SO_TIMESTAMPNS``: the time the datagram reached the
socket) rather than from the reading thread: a reader that waits for the CPU or for Python's GIL
would otherwise stamp late, and the sensor clock fit would see that delay as link jitter. The
kernel stamps CLOCK_REALTIME; it is turned into the host monotonic clock with the offset between
the two read at that moment (both follow NTP's slewing; a step between the stamp and the read is
the only error, and the result is never later than the read). Without the option (other
systems) the thread stamps on return, as before; ``health().detail["kernel_stamps"]`` says which.

UDP has no link to lose: the state stays OPEN and ``health().detail["stale"]`` says when nothing
arrived for ``stale_after_s``.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import sys
import time
from abc import abstractmethod
from typing import Any

from wristscan.drivers._sensor import SensorCore
from wristscan.drivers.base import DriverInitError
from wristscan.drivers.records import Profile

__all__ = ["SO_TIMESTAMPNS", "UdpProfileSensor", "kernel_stamp"]

log = logging.getLogger(__name__)

MAX_DATAGRAM = 65536

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform.startswith("linux") else None)
"""Linux asm-generic value; Python 3.11's socket module does not name it. The kernel then
stamps each datagram on arrival (CLOCK_REALTIME), see :func:`kernel_stamp`."""
_TIMESPEC = struct.Struct("@qq")
_ANC_SPACE = socket.CMSG_SPACE(_TIMESPEC.size)


def _resolve_ipv4(host: str) -> str:
    try:
        infos = socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_DGRAM)
    except OSError as exc:
        raise DriverInitError(f"cannot resolve {host!r}: {exc}") from exc
    return str(infos[0][4][0])


def kernel_stamp(ancillary: list[tuple[int, int, bytes]], now_mono_ns: int) -> int:
    """The kernel's receipt time of a datagram on the monotonic clock (``now_mono_ns`` when
    the message carries none)."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return min(now_mono_ns, sec * 1_000_000_000 + nsec - _offset_at(now_mono_ns))
    return now_mono_ns


_OFFSET_REFRESH_NS = 10_000_000
_offset = [0, -(1 << 62)]  # realtime minus monotonic (ns), and when it was read (monotonic ns)


def _offset_at(now_mono_ns: int) -> int:
    """:func:`_real_minus_mono`, read again after 10 ms at most: reading it per datagram cost
    a tenth of the decoding, and it moves only by the clock's slewing (< 5 µs in 10 ms)."""
    if now_mono_ns - _offset[1] >= _OFFSET_REFRESH_NS:
        _offset[0] = _real_minus_mono()
        _offset[1] = now_mono_ns
    return _offset[0]


def _real_minus_mono() -> int:
    """CLOCK_REALTIME minus CLOCK_MONOTONIC (ns), read between two monotonic reads; a pair
    that a preemption split (half a millisecond would make every stamp that much early) is read
    again, and the tightest of three is kept."""
    best_gap, best = None, 0
    for _ in range(3):
        m0 = time.monotonic_ns()
        real = time.time_ns()
        m1 = time.monotonic_ns()
        gap = m1 - m0
        if best_gap is None or gap < best_gap:
            best_gap, best = gap, real - (m0 + m1) // 2
        if gap < 20_000:
            break
    return best


class UdpProfileSensor(SensorCore):
    """A sensor that streams profiles as UDP datagrams to a local port.

    ``port=0`` binds any free port (tests): :attr:`local_address` tells which after ``open``.
    ``source_host`` keeps only datagrams from that address (others are counted in
    ``detail["foreign_source"]``).
    """

    stale_after_s = 1.0
    max_wait_s = 0.1
    """Longest single wait inside ``read``, so a ``close`` from another thread is seen soon."""

    def __init__(
        self,
        sensor_id: int | None,
        bind_host: str,
        port: int,
        source_host: str | None,
        recv_buffer_bytes: int,
    ) -> None:
        super().__init__(sensor_id)
        if not 0 <= int(port) <= 65535:
            raise DriverInitError(f"{self.kind}: port {port} outside 0..65535")
        if recv_buffer_bytes <= 0:
            raise DriverInitError(f"{self.kind}: recv_buffer_bytes must be positive")
        self.bind_host = bind_host
        self.port = int(port)
        self.source_host = source_host
        self.recv_buffer_bytes = int(recv_buffer_bytes)
        self.local_address: tuple[str, int] | None = None
        """The bound ``(host, port)`` once open."""
        self.rcvbuf_bytes = 0
        """The socket receive buffer the kernel granted (bytes)."""
        self._buf = bytearray(MAX_DATAGRAM)
        self._view = memoryview(self._buf)
        self._sock: socket.socket | None = None
        self._poll: select.poll | None = None
        self._source_ip: str | None = None
        self._last_rx_ns: int | None = None
        self.kernel_stamps = False
        """Receipt stamps come from the kernel (``SO_TIMESTAMPNS``), not the reading thread."""

    # --- life cycle -------------------------------------------------------------------------
    @property
    def stamped_on_receipt(self) -> bool:
        return self.kernel_stamps

    def _open(self) -> None:
        self._source_ip = None if self.source_host is None else _resolve_ipv4(self.source_host)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.rcvbuf_bytes = self._grow_buffer(sock)
            sock.bind((self.bind_host, self.port))
            sock.setblocking(False)
            self.kernel_stamps = self._enable_kernel_stamps(sock)
        except OSError as exc:
            sock.close()
            raise DriverInitError(
                f"{self.kind}: cannot bind UDP {self.bind_host}:{self.port}: {exc}"
            ) from exc
        poll = select.poll()
        poll.register(sock, select.POLLIN)
        host, port = sock.getsockname()[:2]
        self.local_address = (str(host), int(port))
        self._sock, self._poll = sock, poll
        self._ready.clear()
        self._last_rx_ns = None
        self._reset_decoder()
        log.info(
            "%s: listening on %s:%d, receive buffer %d bytes",
            self.kind,
            host,
            port,
            self.rcvbuf_bytes,
        )

    @staticmethod
    def _enable_kernel_stamps(sock: socket.socket) -> bool:
        if SO_TIMESTAMPNS is None:
            return False
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        except OSError:
            return False
        return True

    def _grow_buffer(self, sock: socket.socket) -> int:
        want = self.recv_buffer_bytes
        # SO_RCVBUFFORCE passes net.core.rmem_max but needs CAP_NET_ADMIN; fall back quietly.
        force = getattr(socket, "SO_RCVBUFFORCE", None)
        try:
            if force is None:
                raise PermissionError
            sock.setsockopt(socket.SOL_SOCKET, force, want)
        except PermissionError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, want)
        got = int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
        # Linux reports twice the value it books against the limit.
        if got < want:
            log.warning(
                "%s: UDP receive buffer is %d bytes, %d requested: raise net.core.rmem_max "
                "(sysctl) or bursts will be dropped",
                self.kind,
                got,
                want,
            )
        return got

    def _close(self) -> None:
        sock, self._sock, self._poll = self._sock, None, None
        if sock is not None:
            sock.close()

    # --- reading ----------------------------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> Profile | None:
        ready = self._pop()
        if ready is not None:
            return ready
        sock, poll = self._sock, self._poll
        if sock is None or poll is None:
            return None
        wait = self.max_wait_s if timeout is None else min(timeout, self.max_wait_s)
        deadline = time.monotonic() + wait
        buf, view, kernel = self._buf, self._view, self.kernel_stamps
        bufs = [buf]
        while True:
            try:
                if kernel:
                    n, anc, _flags, addr = sock.recvmsg_into(bufs, _ANC_SPACE)
                else:
                    n, addr = sock.recvfrom_into(buf)
            except BlockingIOError:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                try:
                    if not poll.poll(remaining * 1000.0):
                        return None
                except (OSError, ValueError):  # closed by another thread
                    return None
                continue
            except OSError as exc:
                if self._sock is None:  # closed by another thread
                    return None
                self.stats["socket_errors"] += 1
                self._last_error = str(exc)
                return None
            host_ns = time.monotonic_ns()
            if kernel:
                host_ns = kernel_stamp(anc, host_ns)
            self._last_rx_ns = host_ns
            self.counters.bytes += n
            if self._source_ip is not None and addr[0] != self._source_ip:
                self.stats["foreign_source"] += 1
            else:
                frame = view[:n]
                self.raw_log.add(frame)
                self._on_datagram(frame, host_ns)
                ready = self._pop()
                if ready is not None:
                    return ready
            if time.monotonic() >= deadline:
                return None

    @property
    def stale(self) -> bool:
        """Nothing arrived for ``stale_after_s`` (or nothing at all yet)."""
        last = self._last_rx_ns
        return last is None or time.monotonic_ns() - last > self.stale_after_s * 1e9

    def _health_detail(self) -> dict[str, Any]:
        last = self._last_rx_ns
        return {
            **super()._health_detail(),
            "local_address": self.local_address,
            "rcvbuf_bytes": self.rcvbuf_bytes,
            "stale": self.stale,
            "kernel_stamps": self.kernel_stamps,
            "last_rx_age_s": None if last is None else (time.monotonic_ns() - last) * 1e-9,
        }

    # --- for subclasses ---------------------------------------------------------------------
    def _reset_decoder(self) -> None:
        """Forget partial state (fragments) when the socket is (re)opened."""

    @abstractmethod
    def _on_datagram(self, frame: memoryview, host_time_ns: int) -> None:
        """Decode one datagram; queue profiles with ``_deliver``, reject with ``_reject``."""
