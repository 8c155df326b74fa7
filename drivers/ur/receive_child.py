"""The UR driver's receive child: reads the RTDE stream and ships it to the caller's process.

It runs in a process of its own (see :mod:`.robot`, "Why child processes" and "Receiving") and
reads the stream with one of two clients: this package's :class:`~.receive.RtdeReceiver`
(``"native"``) or ur_rtde's ``RTDEReceiveInterface`` (``"ur_rtde"``). Each controller sample
goes to the caller's process as one :data:`ROW_DTYPE` row (:data:`~.process.TAG_ROWS`
messages); state changes, heartbeats and log lines go as pickled tuples
(:data:`~.process.TAG_OBJ`). The caller's side is :class:`~.stream.URStateStream`.
"""

from __future__ import annotations

import operator
import os
import select
import struct
import time
from collections import deque
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from wristscan.drivers.base import Backoff
from wristscan.drivers.ur.process import (
    TAG_ROWS,
    ChildLink,
    child_setup,
    stop_received,
    wait_or_stop,
)
from wristscan.drivers.ur.receive import RtdeError, RtdeNotFound, RtdeReceiver

__all__ = [
    "FLAG_PROGRAM_RUNNING",
    "FLAG_PROTECTIVE_STOP",
    "ROW_DTYPE",
    "RxSpec",
    "receive_main",
]

ROW_DTYPE = np.dtype(
    [
        ("t", "<f8"),  # controller timestamp, s
        ("host_ns", "<i8"),  # host monotonic ns when the receive child got the sample
        ("q", "<f8", (6,)),
        ("tcp", "<f8", (6,)),
        ("qd", "<f8", (6,)),
        ("flags", "<u4"),
        ("pad", "<u4"),
    ]
)
"""One controller sample as the receive child ships it (168 bytes, little-endian)."""
_ROW = struct.Struct("<dq18dII")
assert _ROW.size == ROW_DTYPE.itemsize

FLAG_PROTECTIVE_STOP = 1
FLAG_PROGRAM_RUNNING = 2
_SAFETY_PROTECTIVE_BIT = 1 << 2  # safety_status_bits: protective stopped
_RUNTIME_PLAYING = 2

_HEARTBEAT_S = 0.25
_NATIVE_WAIT_S = 0.05  # longest wait for data before the native loop looks at the parent's pipe
_GRAVEYARD_MAX = 32


@dataclass(frozen=True)
class RxSpec:
    """What the receive child reads, and how (see :meth:`.stream.URStateStream._start_rx`)."""

    host: str
    frequency_hz: float | None
    variables: tuple[str, ...]
    backend: str
    poll_s: float
    connect_timeout_s: float
    data_timeout_s: float
    backoff_initial_s: float
    backoff_max_s: float
    pending_max: int
    log_level: int


class _LinkLost(Exception):
    """The client's link is gone (the loop lets it go and connects again)."""


def receive_main(spec: RxSpec, conn: Connection) -> None:
    """Body of the receive child."""
    link = ChildLink(conn)
    child_setup(link, spec.log_level)
    loop: _ReceiveLoopBase
    if spec.backend == "native":
        loop = _NativeReceiveLoop(spec, conn, link)
        loop.run()
        return
    try:
        import rtde_receive
    except ImportError as exc:
        link.send_obj(("state", "failed", f"ur_rtde is not installed ({exc}): pip install ur-rtde"))
        return
    loop = _UrRtdeReceiveLoop(spec, conn, link, rtde_receive)
    loop.run()
    # Skip ur_rtde's destructors (``loop`` holds the interfaces until here): each ends in
    # disconnect(), which sleeps 500 ms by design; the OS closes the sockets, which the
    # controller handles like any client going away.
    os._exit(0)


class _Fatal(Exception):
    """A connection error that retrying cannot fix (the child reports it and ends)."""


class _ReceiveLoopBase:
    """The receive child's loop, whichever client it reads: connection and backoff, rows
    queued for the parent without ever blocking on the pipe, heartbeats, state reports. A
    backend supplies :meth:`open_link`, :meth:`step` and :meth:`dispose`."""

    def __init__(self, spec: RxSpec, conn: Connection, link: ChildLink) -> None:
        self.spec = spec
        self.conn = conn
        self.link = link
        self.backoff = Backoff(spec.backoff_initial_s, spec.backoff_max_s)
        self.pending: deque[bytes] = deque()
        self.stats: dict[str, int] = {"child_overflow": 0, "samples": 0}
        self.next_beat = 0.0

    # --- backend ---------------------------------------------------------------------------
    def is_linked(self) -> bool:
        raise NotImplementedError

    def open_link(self) -> None:
        """Connect; raise on failure (:class:`_Fatal` when retrying cannot help)."""
        raise NotImplementedError

    def step(self) -> None:
        """Take in new samples (:meth:`push`), waiting briefly when there are none; raise when
        the link is lost."""
        raise NotImplementedError

    def dispose(self) -> None:
        """Let go of the link (after a loss, and at the end)."""
        raise NotImplementedError

    def give_up(self) -> bool:
        """True when the child should end after a loss (the parent then starts a new one)."""
        return False

    def stop_requested(self) -> bool:
        """True once the parent asked to stop or went away."""
        return stop_received(self.conn)

    # --- shared ----------------------------------------------------------------------------
    def state(self, name: str, error: str | None = None) -> None:
        self.link.send_obj(("state", name, error))

    def connect(self, first: bool) -> bool:
        self.state("connecting" if first else "reconnecting")
        try:
            self.open_link()
        except _Fatal as exc:
            self.state("failed", str(exc))
            raise
        except Exception as exc:  # ur_rtde raises RuntimeError subclasses of many kinds
            self.dispose()
            self.state("down", str(exc) if isinstance(exc, RtdeError) else f"{exc!r}")
            return False
        self.backoff.reset()
        self.state("up")
        return True

    def push(self, row: bytes) -> None:
        self.pending.append(row)
        self.stats["samples"] += 1

    def flush(self) -> None:
        if self.pending and self.link.writable():
            n = min(len(self.pending), 64)
            chunk = b"".join(self.pending.popleft() for _ in range(n))
            self.link.send_bytes(TAG_ROWS + chunk)
        excess = len(self.pending) - self.spec.pending_max
        for _ in range(max(0, excess)):
            self.pending.popleft()
            self.stats["child_overflow"] += 1

    def beat(self, now: float) -> None:
        if now >= self.next_beat:
            self.next_beat = now + _HEARTBEAT_S
            if self.link.writable():
                self.link.send_obj(("beat", dict(self.stats)))

    def run(self) -> None:
        first = True
        try:
            while not self.stop_requested() and not self.link.broken:
                if not self.is_linked():
                    ok = self.connect(first)
                    first = False
                    if not ok:
                        if wait_or_stop(self.conn, self.backoff.next_delay()):
                            return
                        continue
                try:
                    self.step()
                except Exception as exc:  # any failure of the client means the link is gone
                    self.dispose()
                    reason = str(exc) if isinstance(exc, _LinkLost | RtdeError) else f"{exc!r}"
                    self.state("reconnecting", reason)
                    if self.give_up():
                        return
                    if wait_or_stop(self.conn, self.backoff.next_delay()):
                        return
                    continue
                self.flush()
                self.beat(time.monotonic())
        except _Fatal:
            return
        finally:
            self.dispose()
            self.flush()


class _NativeReceiveLoop(_ReceiveLoopBase):
    """Reads the stream with :class:`~wristscan.drivers.ur.receive.RtdeReceiver`: sleeps in
    ``poll()`` on the RTDE socket and the parent's pipe together, and ships every data package.
    Each wake-up does little (one ``recv()``, a struct unpack and pack per package): at 500 Hz
    the per-wake-up cost is most of the child's CPU."""

    def __init__(self, spec: RxSpec, conn: Connection, link: ChildLink) -> None:
        super().__init__(spec, conn, link)
        self.client: RtdeReceiver | None = None
        self.poller: select.poll | None = None
        self.parent_pending = False
        self.stats["text_messages"] = 0
        self._text_before = 0
        self._time_index = 0
        self._pick: operator.itemgetter[Any] | None = None
        self._safety_index = 0
        self._runtime_index = 0

    def is_linked(self) -> bool:
        return self.client is not None

    def stop_requested(self) -> bool:
        # Read the pipe only when the poller saw something on it (or between connections).
        if self.client is not None and not self.parent_pending:
            return False
        self.parent_pending = False
        return stop_received(self.conn)

    def open_link(self) -> None:
        client = RtdeReceiver(
            self.spec.host,
            self.spec.variables,
            self.spec.frequency_hz,
            connect_timeout_s=self.spec.connect_timeout_s,
            data_timeout_s=self.spec.data_timeout_s,
        )
        try:
            client.open()
        except RtdeNotFound as exc:
            raise _Fatal(str(exc)) from exc
        recipe = client.recipe
        assert recipe is not None
        # Position of each variable's first value in a package's unpacked tuple.
        starts = dict(zip(recipe.names, np.cumsum([0, *recipe.counts[:-1]]).tolist(), strict=True))
        self._time_index = starts["timestamp"]
        vectors = ("actual_q", "actual_TCP_pose", "actual_qd")  # the row's order
        self._pick = operator.itemgetter(*(starts[n] + i for n in vectors for i in range(6)))
        self._safety_index = starts["safety_status_bits"]
        self._runtime_index = starts["runtime_state"]
        poller = select.poll()
        poller.register(client.fileno(), select.POLLIN)
        poller.register(self.conn.fileno(), select.POLLIN)
        self.client, self.poller = client, poller
        self._text_before = self.stats["text_messages"]

    def step(self) -> None:
        client, poller, pick = self.client, self.poller, self._pick
        assert client is not None and poller is not None and pick is not None
        for fd, _ in poller.poll(_NATIVE_WAIT_S * 1000):
            if fd != client.fileno():
                self.parent_pending = True
        stamps, payloads = client.read_payloads(timeout=0)
        self.stats["text_messages"] = self._text_before + client.counters["text_messages"]
        if not stamps:
            return
        assert client.recipe is not None
        ti, si, ri = self._time_index, self._safety_index, self._runtime_index
        for v, host_ns in zip(client.recipe.struct.iter_unpack(payloads), stamps, strict=True):
            flags = (FLAG_PROTECTIVE_STOP if v[si] & _SAFETY_PROTECTIVE_BIT else 0) | (
                FLAG_PROGRAM_RUNNING if v[ri] == _RUNTIME_PLAYING else 0
            )
            self.push(_ROW.pack(v[ti], host_ns, *pick(v), flags, 0))

    def dispose(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
            self.poller = None


class _UrRtdeReceiveLoop(_ReceiveLoopBase):
    """Polls ur_rtde's ``RTDEReceiveInterface`` (the reference client; see the module doc)."""

    def __init__(self, spec: RxSpec, conn: Connection, link: ChildLink, module: Any) -> None:
        super().__init__(spec, conn, link)
        self.module = module
        self.iface: Any = None
        self.graveyard: list[Any] = []
        self.last_t: float | None = None
        self.stats["torn_reads"] = 0

    def is_linked(self) -> bool:
        return self.iface is not None

    def open_link(self) -> None:
        freq = -1.0 if self.spec.frequency_hz is None else float(self.spec.frequency_hz)
        self.iface = self.module.RTDEReceiveInterface(
            self.spec.host, freq, list(self.spec.variables)
        )

    def dispose(self) -> None:
        """Forget the interface without destroying it: ur_rtde's disconnect() and destructor
        each sleep 500 ms, which would stop this loop; the dead ones are few and end with the
        process (past ``_GRAVEYARD_MAX`` the child exits and the parent starts a new one)."""
        if self.iface is not None:
            self.graveyard.append(self.iface)
            self.iface = None

    def give_up(self) -> bool:
        return len(self.graveyard) > _GRAVEYARD_MAX  # the parent restarts the process

    def step(self) -> None:
        got = self.sample(self.last_t)
        if got is None:
            time.sleep(self.spec.poll_s)
            return
        self.last_t, row = got
        self.push(row)

    def sample(self, last_t: float | None) -> tuple[float, bytes] | None:
        """The newest sample if it is new, read consistently; None when nothing new."""
        iface = self.iface
        for _ in range(8):
            if not iface.isConnected():
                raise _LinkLost("ur_rtde reports the RTDE connection lost")
            t1 = iface.getTimestamp()
            if t1 == last_t:
                return None
            host_ns = time.monotonic_ns()
            q = iface.getActualQ()
            tcp = iface.getActualTCPPose()
            qd = iface.getActualQd()
            safety = iface.getSafetyStatusBits()
            runtime = iface.getRuntimeState()
            if iface.getTimestamp() != t1:
                self.stats["torn_reads"] += 1
                continue
            if len(q) != 6 or len(tcp) != 6 or len(qd) != 6:
                raise _LinkLost("ur_rtde returned an empty state")
            flags = (FLAG_PROTECTIVE_STOP if safety & _SAFETY_PROTECTIVE_BIT else 0) | (
                FLAG_PROGRAM_RUNNING if runtime == _RUNTIME_PLAYING else 0
            )
            return t1, _ROW.pack(t1, host_ns, *q, *tcp, *qd, flags, 0)
        return None  # packets arrive faster than a consistent read: try again next poll
