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

The hot path reads with :meth:`UdpProfileSensor.read_blocks`: every datagram available now is
received into one buffer at fixed-stride offsets (a :class:`Datagrams` set: the buffer, each
datagram's first row, length and stamp) and the whole set goes to the driver's
``_on_datagrams``, which decodes what it can in one vectorised step and returns
:class:`~wristscan.drivers.records.ProfileBlock` s in arrival order. On Linux one ``recvmmsg``
system call receives up to ``mmsg_rows`` datagrams into 64 kB rows (:mod:`._mmsg`); elsewhere
``recvmsg_into`` receives one per call into rows of the longest datagram seen (a longer one
spans several rows, and the stride grows for the next pass). With ``recvmmsg`` the only Python
work left per datagram is the decoder's CRC: lengths, sources and kernel stamps are arrays.
"""

from __future__ import annotations

import logging
import mmap
import select
import socket
import struct
import sys
import time
from abc import abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers import _bpf, _mmsg
from wristscan.drivers._sensor import SensorCore
from wristscan.drivers.base import DriverInitError, DriverIOError
from wristscan.drivers.records import Profile, ProfileBlock

__all__ = ["SO_TIMESTAMPNS", "Datagrams", "UdpProfileSensor", "kernel_stamp"]

log = logging.getLogger(__name__)

MAX_DATAGRAM = 65536

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform.startswith("linux") else None)
"""Linux asm-generic value; Python 3.11's socket module does not name it. The kernel then
stamps each datagram on arrival (CLOCK_REALTIME), see :func:`kernel_stamp`."""
_TIMESPEC = struct.Struct("@qq")
_ANC_SPACE = socket.CMSG_SPACE(_TIMESPEC.size)
_STRIDE_ALIGN = 64
"""Rows start on 64-byte boundaries (aligned arrays for the decoders)."""
_FIRST_STRIDE = 8192
_BUFFER_BYTES = 4 << 20
"""Rows per receive pass: as many as fit in this many bytes (at least one)."""
_RAW_LOG_KEEP = 8
"""Frames the raw log holds (:class:`~wristscan.drivers.base.RawFrameLog`'s default)."""


@dataclass(slots=True)
class Datagrams:
    """The datagrams of one receive pass, in arrival order, in one buffer.

    Datagram ``i`` starts at byte ``rows[i] * stride`` of ``buf`` and is ``lengths[i]`` bytes
    long; ``stamps[i]`` is its receipt time (host monotonic ns). The buffer is reused by the
    next pass: decoders copy what they keep.
    """

    buf: bytearray | mmap.mmap
    view: memoryview
    stride: int
    rows: NDArray[np.int64]
    lengths: NDArray[np.int64]
    stamps: NDArray[np.int64]
    logged: int = 0
    """Datagrams already added to the driver's raw frame log."""

    def __len__(self) -> int:
        return int(self.rows.shape[0])

    def frame(self, i: int) -> memoryview:
        start = int(self.rows[i]) * self.stride
        return self.view[start : start + int(self.lengths[i])]


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


def _fits_int64(p: Profile) -> Profile:
    """``p`` with a frame counter or device time of 2**63 or more (64-bit unsigned on the wire;
    only a faulty sender gets there) wrapped to the negative int64 a block's arrays hold,
    as numpy's conversion of the vectorised path does."""
    if p.frame_counter >= 1 << 63 or p.sensor_time_ns >= 1 << 63:
        p.frame_counter = (p.frame_counter + (1 << 63)) % (1 << 64) - (1 << 63)
        p.sensor_time_ns = (p.sensor_time_ns + (1 << 63)) % (1 << 64) - (1 << 63)
    return p


class UdpProfileSensor(SensorCore):
    """A sensor that streams profiles as UDP datagrams to a local port.

    ``port=0`` binds any free port (tests): :attr:`local_address` tells which after ``open``.
    ``source_host`` keeps only datagrams from that address (others are counted in
    ``detail["foreign_source"]``).
    """

    stale_after_s = 1.0
    batch_receive = "auto"
    """How :meth:`read_blocks` receives: ``"recvmmsg"`` (many datagrams per system call,
    :mod:`wristscan.drivers._mmsg`), ``"recvmsg"`` (one per call) or ``"auto"`` (the first
    where Linux offers it)."""
    mmsg_rows = 256
    """Datagrams per ``recvmmsg`` call (64 kB of address space each, pages used only as far as
    datagrams reach): a 10 ms tick at 10 kHz is one call and one decoding pass, not two."""
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
        self._stride = _FIRST_STRIDE
        self._block_buf = bytearray()
        self._row_views: list[list[memoryview]] = []
        self._views_stride = 0
        self._mmsg: _mmsg.MmsgReceiver | None = None
        self._sock: socket.socket | None = None
        self._poll: select.poll | None = None
        self._source_ip: str | None = None
        self._last_rx_ns: int | None = None
        self.kernel_stamps = False
        """Receipt stamps come from the kernel (``SO_TIMESTAMPNS``), not the reading thread."""
        self.admission = None

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
        self.admission, self._gaps_shed = None, False
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

    def read_blocks(self, max_profiles: int = 4096) -> list[ProfileBlock]:
        """Every datagram available now (at most ``max_profiles``), decoded as blocks in
        arrival order (:meth:`_on_datagrams`); never waits."""
        if not self._open_flag:
            raise DriverIOError(f"{self.kind}: read on a closed device")
        out: list[ProfileBlock] = []
        budget = int(max_profiles)
        held: list[Profile] = []
        while self._ready and len(held) < budget:
            held.append(_fits_int64(self._ready.popleft()))
        if held:
            out += ProfileBlock.from_profiles(held)
            budget -= len(held)
        more = True
        while budget > 0:
            grams, got, more = self._receive(budget)
            if grams is not None:
                out += self._on_datagrams(grams)
            budget -= got
            if not more:
                break
        if not more and self.admission is None:
            self._gaps_shed = False  # what was queued under a filter has been read
        self.counters.received += sum(b.n_profiles for b in out)
        return out

    def set_admission(self, fraction: float | None) -> bool:
        """Let the kernel pass only ``fraction`` of the profile frames (a socket filter,
        :mod:`._bpf`: evenly spread by frame counter, decided before the datagrams are queued,
        so the reading thread never pays for the shed ones); None or >= 1 removes it. False
        when the driver has no filter for its frames, or the system none at all. Gaps are
        counted as ``shed`` from now until the socket has been drained after the removal (the
        datagrams queued before the filter was set count so too, though they were not
        filtered: under overload their losses are overload's)."""
        sock = self._sock
        want = None if fraction is None or fraction >= 1.0 else max(float(fraction), 1e-6)
        if not _bpf.available():
            return False
        if sock is None:  # closed or reopening: a new socket starts without a filter
            return want is None or self._admission_program(want) is not None
        if want is None:
            if self.admission is not None:
                _bpf.detach(sock)
                self.admission = None
            return True
        program = self._admission_program(want)
        if program is None:
            return False
        try:
            _bpf.attach(sock, program)
        except OSError as exc:
            log.warning("%s: the kernel refused the admission filter: %s", self.kind, exc)
            return False
        self.admission, self._gaps_shed = want, True
        return True

    def _rows_for(self, limit: int) -> int:
        """Rows of this pass (the buffer and its row views made again when the stride grew)."""
        stride = self._stride
        if self._views_stride != stride:
            rows = max(1, _BUFFER_BYTES // stride)
            self._block_buf = bytearray(rows * stride + MAX_DATAGRAM)
            view = memoryview(self._block_buf)
            self._row_views = [[view[r * stride :]] for r in range(rows)]
            self._views_stride = stride
        return min(limit, len(self._row_views))

    def _receive(self, limit: int) -> tuple[Datagrams | None, int, bool]:
        """Up to ``limit`` datagrams into the block buffer (None: none kept), how many were
        received (with those of a foreign source) and whether more may be waiting (the pass
        ended on the limit or the buffer, not on an empty socket)."""
        sock = self._sock
        if sock is None:
            return None, 0, False
        mode = self.batch_receive
        if mode == "recvmmsg" or (mode == "auto" and _mmsg.available()):
            return self._receive_mmsg(sock, limit)
        slots = self._rows_for(limit)
        stride, views, kernel = self._stride, self._row_views, self.kernel_stamps
        source = self._source_ip
        rows: list[int] = []
        lengths: list[int] = []
        ancs: list[list[tuple[int, int, bytes]]] = []
        own_stamps: list[int] = []
        row, nbytes, got, more = 0, 0, 0, True
        while row < slots and got < limit:
            try:
                if kernel:
                    n, anc, _flags, addr = sock.recvmsg_into(views[row], _ANC_SPACE)
                else:
                    n, addr = sock.recvfrom_into(views[row][0])
                    anc = []
                    own = time.monotonic_ns()
            except BlockingIOError:
                more = False
                break
            except OSError as exc:
                more = False
                if self._sock is not None:  # not closed by another thread
                    self.stats["socket_errors"] += 1
                    self._last_error = str(exc)
                break
            nbytes += n
            got += 1
            if source is not None and addr[0] != source:
                self.stats["foreign_source"] += 1
                continue
            rows.append(row)
            lengths.append(n)
            if kernel:
                ancs.append(anc)
            else:
                own_stamps.append(own)
            row += max(1, -(-n // stride))
        self.counters.bytes += nbytes
        if not rows:
            if got:
                self._last_rx_ns = time.monotonic_ns()
            return None, got, more
        stamps = self._stamps(ancs) if kernel else np.array(own_stamps, np.int64)
        self._last_rx_ns = int(stamps[-1])
        longest = max(lengths)
        if longest > stride:
            self._stride = -(-longest // _STRIDE_ALIGN) * _STRIDE_ALIGN
        grams = Datagrams(
            self._block_buf,
            memoryview(self._block_buf),
            stride,
            np.array(rows, np.int64),
            np.array(lengths, np.int64),
            stamps,
        )
        return grams, got, more

    def _receive_mmsg(self, sock: socket.socket, limit: int) -> tuple[Datagrams | None, int, bool]:
        """:meth:`_receive` with one ``recvmmsg`` system call."""
        rx = self._mmsg
        if rx is None:
            rx = self._mmsg = _mmsg.MmsgReceiver(self.mmsg_rows)
        want = min(limit, rx.rows)
        try:
            n = rx.receive(sock.fileno(), want)
        except (OSError, ValueError) as exc:  # ValueError: closed by another thread
            if self._sock is not None:
                self.stats["socket_errors"] += 1
                self._last_error = str(exc)
            return None, 0, False
        if n == 0:
            return None, 0, False
        now = time.monotonic_ns()
        offset = _offset_at(now) if self.kernel_stamps else None
        lengths, stamps, nbytes = rx.read_back(n, now, offset)
        self.counters.bytes += nbytes
        self._last_rx_ns = int(stamps[-1])
        rows = rx.row_numbers[:n]
        if self._source_ip is not None:
            mine = rx.sources(n) == np.frombuffer(socket.inet_aton(self._source_ip), np.uint32)[0]
            if not mine.all():
                self.stats["foreign_source"] += int(n - mine.sum())
                rows, lengths, stamps = rows[mine], lengths[mine], stamps[mine]
        if rows.shape[0] == 0:
            return None, n, n == want
        grams = Datagrams(rx.buf, memoryview(rx.buf), _mmsg.ROW_BYTES, rows, lengths, stamps)
        return grams, n, n == want

    @staticmethod
    def _stamps(ancs: list[list[tuple[int, int, bytes]]]) -> NDArray[np.int64]:
        """The kernel's receipt times on the monotonic clock, all at once (as
        :func:`kernel_stamp` does one by one)."""
        now = time.monotonic_ns()
        try:
            raw = b"".join(
                [
                    a[0][2]
                    for a in ancs
                    if a[0][0] == socket.SOL_SOCKET and a[0][1] == SO_TIMESTAMPNS
                ]
            )
        except IndexError:
            raw = b""
        if len(raw) != len(ancs) * _TIMESPEC.size:
            return np.array([kernel_stamp(a, now) for a in ancs], np.int64)
        ts = np.frombuffer(raw, np.int64).reshape(-1, 2)
        stamps = ts[:, 0] * 1_000_000_000 + ts[:, 1] - _offset_at(now)
        return np.minimum(stamps, now)

    def _datagram_slow(self, grams: Datagrams, i: int, records: list[Profile]) -> None:
        """Datagram ``i`` through the per-datagram path (``_on_datagram``), the raw frame log
        brought up to it first (a rejection dumps the frames that came before); the profiles
        it completes are appended to ``records``."""
        self._log_raw(grams, i + 1)
        self._on_datagram(grams.frame(i), int(grams.stamps[i]))
        ready = self._ready
        while ready:
            records.append(_fits_int64(ready.popleft()))

    def _log_raw(self, grams: Datagrams, upto: int) -> None:
        """The raw frame log as if datagrams ``0 .. upto - 1`` had been added one by one."""
        for j in range(max(grams.logged, upto - _RAW_LOG_KEEP), upto):
            self.raw_log.add(grams.frame(j))
        grams.logged = max(grams.logged, upto)

    def _on_datagrams(self, grams: Datagrams) -> list[ProfileBlock]:
        """Decode a pass's datagrams into blocks, in arrival order. This default sends each
        through ``_on_datagram``; drivers that decode many at once override it."""
        records: list[Profile] = []
        for i in range(len(grams)):
            self._datagram_slow(grams, i, records)
        self._log_raw(grams, len(grams))
        return ProfileBlock.from_profiles(records)

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
            "admission": self.admission,
            "last_rx_age_s": None if last is None else (time.monotonic_ns() - last) * 1e-9,
        }

    # --- for subclasses ---------------------------------------------------------------------
    def _reset_decoder(self) -> None:
        """Forget partial state (fragments) when the socket is (re)opened."""

    def _admission_program(self, fraction: float) -> list[_bpf.Instruction] | None:
        """The socket filter keeping ``fraction`` of this driver's profile frames (None: the
        driver has none)."""
        return None

    @abstractmethod
    def _on_datagram(self, frame: memoryview, host_time_ns: int) -> None:
        """Decode one datagram; queue profiles with ``_deliver``, reject with ``_reject``."""
