"""Universal Robots arm over RTDE: a state stream (own client or ``ur_rtde``), and guarded motion
(``ur_rtde``).

Why child processes
-------------------
``ur_rtde``'s Python constructors (and ``reconnect``) hold the GIL while they block on the network,
so in the caller's process they would freeze every other thread, the sensor path included, for as
long as a connection takes (PROTOCOLS.md). Both ``ur_rtde`` interfaces therefore live in child
processes of their own (``multiprocessing`` spawn); the native receive client does too, which
keeps its decoding off the caller's GIL and the two backends interchangeable. The caller's
process only ever waits on pipes, which releases the GIL. A child that hangs or crashes is
killed and restarted; the caller sees a state change, never an exception from the link.

Receiving
---------
The receive child subscribes to a small recipe (:data:`REQUIRED_VARIABLES`) with one of two
clients (``receive_backend``) and sends each controller sample to the caller's process as one
fixed-size binary row (:data:`ROW_DTYPE`, 168 bytes) over a socket pair, stamped with the host's
``time.monotonic_ns()`` when the child got it.

* ``"native"`` (default): :class:`~wristscan.drivers.ur.receive.RtdeReceiver`, this package's
  own RTDE client, reads the TCP stream itself. It sleeps in ``poll()`` until packets arrive
  and ships every data package, in order; each is stamped right after the ``recv()`` that
  completed it. Nothing is lost while the child is not scheduled: the kernel holds the
  packets (a controller drops a client only after ~10 s of not reading), and they come out
  together, with the stamp of the call that took them in, when the child runs again. No data
  for ``stall_timeout_s`` counts as a lost link.
* ``"ur_rtde"``: ``RTDEReceiveInterface``, polled faster than the controller rate, since ur_rtde
  keeps only the newest packet and offers no wait for a new one. Its getters read the latest
  packet one call at a time, so two calls can see two packets; the child reads ``timestamp``
  before and after the other getters and retries when it changed (``torn_reads`` in the health
  detail). Each new sample (deduplicated by timestamp) is stamped when the poll saw it (up to
  one poll interval, ~0.4 ms, plus ur_rtde's own hand-over after its arrival).

Why native is the default: the polling costs about a fifth of a core at 500 Hz and still loses
the samples that arrive while the child waits for a CPU (5-14 % on a busy 2-core machine),
which leaves gaps in the robot track (``docs/drivers.md``, "UR robot receive path"). ``ur_rtde``
stays as the reference client.

The child never blocks on the pipe to the caller: rows wait in the child while the pipe is full
and the oldest are dropped past ``queue_size`` (they then count as lost).

The caller's process turns rows into :class:`~wristscan.drivers.records.RobotState` records in
order. Counters: ``duplicates`` (a timestamp delivered twice), ``reordered`` (older than the last
delivered, dropped), ``lost`` (controller samples never delivered: a timestamp step larger than 1.5
nominal periods counts ``round(step / period) - 1``; samples dropped from a full queue). The
nominal period is ``1 / frequency_hz``; without ``frequency_hz`` the client asks for the
controller's maximum, 500 Hz (e-Series) or 125 Hz (CB3), told apart by the steps seen (the count
is corrected once a step under 6 ms proves a 500 Hz stream). A controller restart (the timestamp
falls by more than a second) starts a new sequence.

Link loss: the native client raises (end of stream, reset, silence); with ur_rtde the child
sees ``isConnected()`` false (or a getter failing). Either way the child lets the link go and
connects again with exponential :class:`~wristscan.drivers.base.Backoff`; unknown variable
names (``NOT_FOUND``, native client) fail for good instead. For ur_rtde, ``reconnect()`` is not
used: in ur_rtde's source (1.5) it resets the frequency to the controller's maximum and waits
without a timeout for the first packet. Dead ur_rtde interfaces are not destroyed either:
ur_rtde's ``disconnect()`` (and so its destructor) sleeps 500 ms (measured with 1.6.5), which
would stop the loop; a child exits without running them. The health state is ``RECONNECTING``
until data flows again; every recovery counts one ``reconnects``. The child sends a heartbeat
every 0.25 s; a child silent for ``stall_timeout_s`` (or ``connect_timeout_s`` while
connecting) is killed and restarted. All of this is driven from :meth:`read` / :meth:`health`
calls: the caller's process runs no thread of the driver's.

Motion
------
Only with ``motion_enabled``: every command first passes :meth:`Robot.check_motion` (speed and
acceleration caps, the TCP target inside the workspace box); :meth:`move_j` also checks the TCP
along the joint-space path (16 samples from the latest state to the target) with the kinematic
model (factory calibration when read, else ``model``, else the controller's own forward
kinematics). Refusals raise :class:`MotionNotEnabled` / :class:`WorkspaceViolation` before
anything reaches the controller.

The control child (``RTDEControlInterface`` and a dashboard client) starts at the first command,
not at :meth:`open`: uploading the control script takes over the robot's program, which a
receive-only run must never do. It always issues ur_rtde's asynchronous moves and tracks them
itself, so :meth:`stop` works while a blocking :meth:`move_l` / :meth:`move_j` waits in another
thread. Outcome of a move (:class:`MoveStatus`): ``DONE`` (the controller reports it finished
and the state stream shows the arm at the target: TCP within 1 mm and 0.01 rad, or every joint
within 0.01 rad; without a fresh state it stays unconfirmed, with a warning); ``STOPPED`` by
:meth:`stop`;
``PROTECTIVE_STOP`` (the control program stopped and the dashboard reports a safety stop:
protective, safeguard or emergency); ``FAILED`` (refused by the controller, program stopped
otherwise, link lost). A blocking move raises :class:`ProtectiveStop` or :class:`MotionFailed`
(both :class:`~wristscan.drivers.base.DriverIOError`, with ``.status``) for anything but
``DONE``; an asynchronous one returns at once and :meth:`wait_until_idle` returns its final
status. After a protective stop is cleared on the robot, the next command re-uploads the control
script.

Control link loss: ur_rtde's control interface reconnects from inside its own receive thread and
then keeps two threads on one socket (its 1.5 source; with 1.6.5 it reconnects over and over). So
the control child watches ur_rtde's console messages and ``isConnected()``, and exits at the first
sign of a lost link; a fresh child starts at the next command, which is sent once more when the
old child reports the loss instead of an answer (moves are absolute: repeating one is harmless,
and the fresh ur_rtde first stops a script the old one left running). A new command after the
receive link dropped also starts a fresh child first. A move in progress when the link drops
ends ``FAILED`` ("link lost"); the arm may still finish it, so check the stream.

Factory kinematics: with ``read_kinematics``, :meth:`open` reads the primary interface's
KinematicsInfo (:mod:`.ur_primary`); :meth:`kinematic_model` then returns the calibrated model.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import multiprocessing as mp
import operator
import os
import pickle
import re
import select
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.drivers.base import (
    Backoff,
    DriverError,
    DriverInitError,
    DriverIOError,
    DriverTimeout,
    Health,
    LinkState,
    Robot,
    WorkspaceViolation,
)
from wristscan.drivers.records import RobotState
from wristscan.drivers.ur.receive import RtdeError, RtdeNotFound, RtdeReceiver

if TYPE_CHECKING:
    from wristscan.calib.kinematics import DHParams
    from wristscan.drivers.ur.primary import KinematicsInfo
__all__ = [
    "RECEIVE_BACKENDS",
    "REQUIRED_VARIABLES",
    "ROW_DTYPE",
    "MotionFailed",
    "MoveStatus",
    "ProtectiveStop",
    "URRobot",
]

log = logging.getLogger(__name__)
_native_log = logging.getLogger(__name__ + ".ur_rtde")

REQUIRED_VARIABLES: tuple[str, ...] = (
    "timestamp",
    "actual_q",
    "actual_qd",
    "actual_TCP_pose",
    "safety_status_bits",
    "runtime_state",
)
"""RTDE outputs the receive child always subscribes to."""

RECEIVE_BACKENDS: tuple[str, ...] = ("native", "ur_rtde")
"""Clients the receive child can read the stream with (see the module doc, "Receiving")."""

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

_TAG_ROWS = b"D"
_TAG_OBJ = b"P"
_CMD_STOP = b"stop"

_E_SERIES_PERIOD_S = 0.002
_CB3_PERIOD_S = 0.008
_RESTART_DROP_S = 1.0
_HEARTBEAT_S = 0.25
_NATIVE_WAIT_S = 0.05  # longest wait for data before the native loop looks at the parent's pipe
_WAIT_SLICE_S = 0.05
_PATH_SAMPLES = 16
_GRAVEYARD_MAX = 32
_FK_REFERENCE_TCP = (0.0, 0.0, 0.1, 0.0, 0.0, 0.0)
_LOSS_GRACE_S = 0.1
# A move reported done counts only once the stream shows the arm at the target.
_ARRIVAL_TOL_M = 1e-3
_ARRIVAL_TOL_RAD = 1e-2
_VERIFY_WAIT_S = 0.5
_STALE_NS = 1_000_000_000
_RETRY_ON_LOSS = frozenset({"move", "stop", "fk", "set_tcp"})

# ur_rtde's messages when its link breaks; the control child exits on them (see module doc).
_TROUBLE = re.compile(
    r"Could not receive data|Robot closed the connection|Reconnecting|Could not recover", re.I
)
_WARN_WORDS = re.compile(r"exception|error|fail|could not|lost|disconnect", re.I)


class MoveStatus(enum.Enum):
    """Outcome of the last motion command."""

    IDLE = "idle"
    """No command issued since the control link started."""
    MOVING = "moving"
    DONE = "done"
    """Reached the target (confirmed by the state stream)."""
    STOPPED = "stopped"
    """Decelerated by :meth:`URRobot.stop` before reaching the target."""
    PROTECTIVE_STOP = "protective_stop"
    """Ended by a safety stop (protective, safeguard or emergency)."""
    FAILED = "failed"
    """Refused by the controller, program stopped, or control link lost."""


class MotionFailed(DriverIOError):
    """A motion command did not complete; ``status`` says how it ended."""

    def __init__(self, message: str, status: MoveStatus = MoveStatus.FAILED) -> None:
        super().__init__(message)
        self.status = status


class ProtectiveStop(MotionFailed):
    """The robot is, or went, into a safety stop (protective, safeguard or emergency)."""

    def __init__(self, message: str) -> None:
        super().__init__(message, MoveStatus.PROTECTIVE_STOP)


# ============================================================================ child processes


class _ChildLink:
    """The child's end of the pipe: thread-safe sends, optionally without blocking."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.lock = threading.Lock()
        self.broken = False

    def send_bytes(self, data: bytes) -> None:
        with self.lock:
            try:
                self.conn.send_bytes(data)
            except OSError:
                self.broken = True

    def send_obj(self, obj: object) -> None:
        self.send_bytes(_TAG_OBJ + pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))

    def writable(self) -> bool:
        try:
            _, w, _ = select.select([], [self.conn.fileno()], [], 0)
        except (OSError, ValueError):
            self.broken = True
            return False
        return bool(w)


class _ForwardHandler(logging.Handler):
    def __init__(self, link: _ChildLink) -> None:
        super().__init__()
        self.link = link

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self.link.send_obj(("log", record.levelno, self.format(record)))


class _OutputPump:
    """ur_rtde's console output (C++ ``std::cout``/``std::cerr``, fds 1 and 2) redirected into a
    pipe and forwarded line by line to the parent as log messages; link-failure messages set
    ``trouble``. A thread keeps the pipe from filling up (ur_rtde would block on it);
    :meth:`drain` processes what is pending right now, for decisions that must not race with
    ur_rtde's reports."""

    def __init__(self, link: _ChildLink, trouble: threading.Event | None) -> None:
        self.link = link
        self.trouble = trouble
        sys.stdout.flush()
        sys.stderr.flush()
        r, w = os.pipe()
        os.dup2(w, 1)
        os.dup2(w, 2)
        os.close(w)
        os.set_blocking(r, False)
        self.fd = r
        self.buf = b""
        self.lock = threading.Lock()
        threading.Thread(target=self._run, name="ur-rtde-output", daemon=True).start()

    def _run(self) -> None:
        while True:
            select.select([self.fd], [], [])
            self.drain()

    def drain(self) -> None:
        with self.lock:
            while True:
                try:
                    data = os.read(self.fd, 65536)
                except BlockingIOError:
                    break
                if not data:
                    break
                self.buf += data
            *lines, self.buf = self.buf.split(b"\n")
            # Inside the lock: when drain() returns, every complete line written before the
            # call has been acted on, whichever thread read it.
            for raw in lines:
                text = raw.decode("utf-8", errors="replace").strip()
                if not text:
                    continue
                if self.trouble is not None and _TROUBLE.search(text):
                    self.trouble.set()
                level = logging.WARNING if _WARN_WORDS.search(text) else logging.INFO
                self.link.send_obj(("log", level, text))


def _child_setup(
    link: _ChildLink, log_level: int, trouble: threading.Event | None = None
) -> _OutputPump:
    """Forward the child's logging and ur_rtde's console output to the parent."""
    root = logging.getLogger()
    root.handlers[:] = [_ForwardHandler(link)]
    root.setLevel(log_level)
    return _OutputPump(link, trouble)


def _stop_requested(conn: Connection) -> bool:
    """True once the parent asked to stop or went away."""
    try:
        if not conn.poll(0):
            return False
        return conn.recv_bytes() == _CMD_STOP
    except (EOFError, OSError):
        return True


def _wait_or_stop(conn: Connection, seconds: float) -> bool:
    """Sleep up to ``seconds``; True when a stop request (or EOF) arrived meanwhile."""
    try:
        if conn.poll(seconds):
            return conn.recv_bytes() == _CMD_STOP
    except (EOFError, OSError):
        return True
    return False


@dataclass(frozen=True)
class _RxSpec:
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
    pass


class _ControlLost(Exception):
    """The control child lost its link (or ended); a fresh one is needed."""


def _receive_main(spec: _RxSpec, conn: Connection) -> None:
    """Body of the receive child."""
    link = _ChildLink(conn)
    _child_setup(link, spec.log_level)
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

    def __init__(self, spec: _RxSpec, conn: Connection, link: _ChildLink) -> None:
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
        return _stop_requested(self.conn)

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
            self.link.send_bytes(_TAG_ROWS + chunk)
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
                        if _wait_or_stop(self.conn, self.backoff.next_delay()):
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
                    if _wait_or_stop(self.conn, self.backoff.next_delay()):
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

    def __init__(self, spec: _RxSpec, conn: Connection, link: _ChildLink) -> None:
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
        return _stop_requested(self.conn)

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

    def __init__(self, spec: _RxSpec, conn: Connection, link: _ChildLink, module: Any) -> None:
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


@dataclass(frozen=True)
class _CtlSpec:
    host: str
    log_level: int
    script_start_timeout_s: float = 5.0


def _control_main(spec: _CtlSpec, conn: Connection) -> None:
    """Body of the control child."""
    link = _ChildLink(conn)
    trouble = threading.Event()
    output = _child_setup(link, spec.log_level, trouble)
    try:
        import dashboard_client
        import rtde_control
    except ImportError as exc:
        link.send_obj(("state", "failed", f"ur_rtde is not installed ({exc}): pip install ur-rtde"))
        return
    session = _ControlSession(spec, conn, link, output, rtde_control, dashboard_client)
    session.run()
    # Leave without ur_rtde's destructors (``session`` holds the interface until here): after a
    # broken link ur_rtde may have two threads on one socket, and its disconnect() sleeps 500 ms
    # by design; the OS closes the sockets.
    os._exit(0)


@dataclass
class _Move:
    kind: str
    before: int
    op_id: int | None = None
    """Async operation id of this move, when it was seen running right after the command."""
    seen_running: bool = False
    stop_requested: bool = False
    status: str = "moving"
    detail: str = ""


class _ControlSession:
    def __init__(
        self,
        spec: _CtlSpec,
        conn: Connection,
        link: _ChildLink,
        output: _OutputPump,
        rtde_control: Any,
        dashboard_client: Any,
    ) -> None:
        self.spec = spec
        self.conn = conn
        self.link = link
        self.output = output
        assert output.trouble is not None
        self.trouble = output.trouble
        self.rc = rtde_control
        self.dc = dashboard_client
        self.ctrl: Any = None
        self.dash: Any = None
        self.move: _Move | None = None

    # --- helpers --------------------------------------------------------------------------
    def safety_status(self) -> str | None:
        """Dashboard safety status word (``NORMAL``, ``PROTECTIVE_STOP`` ...), None if unknown."""
        for _ in range(2):
            try:
                if self.dash is None or not self.dash.isConnected():
                    self.dash = self.dc.DashboardClient(self.spec.host)
                    self.dash.connect(2000)
                text = str(self.dash.safetystatus())
                return text.split(":")[-1].strip().upper()
            except Exception as exc:
                log.warning("dashboard query failed: %s", exc)
                self.dash = None
        return None

    def classify_program_stop(self) -> tuple[str, str]:
        status = self.safety_status()
        if status is None:
            return "failed", "the control program stopped (safety status unknown)"
        if status in ("NORMAL", "REDUCED"):
            return "failed", "the control program stopped"
        return "pstop", status

    def ensure_program(self) -> tuple[str, str] | None:
        """Make the control script run; an error tuple when it cannot."""
        if self.ctrl.isProgramRunning():
            return None
        status, detail = self.classify_program_stop()
        if status == "pstop":
            return status, f"the robot is in a safety stop ({detail})"
        if not self.ctrl.reuploadScript():
            return "failed", "cannot upload the control script"
        deadline = time.monotonic() + self.spec.script_start_timeout_s
        while time.monotonic() < deadline:
            if self.ctrl.isProgramRunning():
                return None
            time.sleep(0.01)
        return "failed", "the control script did not start"

    def update_move(self) -> None:
        m = self.move
        if m is None or m.status != "moving":
            return
        if not self.ctrl.isProgramRunning():
            m.status, m.detail = self.classify_program_stop()
            return
        st = self.ctrl.getAsyncOperationProgressEx()
        if st.isAsyncOperationRunning():
            m.seen_running = True
            return
        if m.op_id is not None and int(st.operationId()) != m.op_id:
            # Another control script replaced ours (a late upload from a previous session).
            m.status, m.detail = "failed", "the control program was replaced"
            return
        if m.seen_running or st.value() != m.before:
            m.status = "stopped" if m.stop_requested else "done"

    def move_state(self) -> tuple[str, str]:
        if self.move is None:
            return "idle", ""
        return self.move.status, self.move.detail

    # --- operations -----------------------------------------------------------------------
    def op_move(self, kind: str, target: list[float], speed: float, accel: float) -> Any:
        if self.move is not None and self.move.status == "moving":
            self.move.status, self.move.detail = "stopped", "superseded by a new command"
        err = self.ensure_program()
        if err is not None:
            return err
        before = int(self.ctrl.getAsyncOperationProgressEx().value())
        if kind == "l":
            ok = self.ctrl.moveL(target, speed, accel, True)
        else:
            ok = self.ctrl.moveJ(target, speed, accel, True)
        if not ok:
            if not self.ctrl.isProgramRunning():
                return self.classify_program_stop()
            return "failed", f"the controller refused move{kind.upper()}"
        self.move = _Move(kind, before)
        st = self.ctrl.getAsyncOperationProgressEx()
        if st.isAsyncOperationRunning():
            self.move.op_id = int(st.operationId())
            self.move.seen_running = True
        return "ok", None

    def op_wait(self, slice_s: float) -> Any:
        deadline = time.monotonic() + slice_s
        while True:
            self.update_move()
            state = self.move_state()
            if state[0] != "moving" or time.monotonic() >= deadline or self.link_lost():
                return "ok", state
            time.sleep(0.002)

    def op_stop(self, decel_l: float, decel_j: float) -> Any:
        m = self.move
        self.update_move()
        if m is None or m.status != "moving":
            return "ok", self.move_state()
        m.stop_requested = True
        if m.kind == "l":
            self.ctrl.stopL(decel_l, False)
        else:
            self.ctrl.stopJ(decel_j, False)
        self.update_move()
        if m.status == "moving":
            m.status = "stopped"
        return "ok", self.move_state()

    def op_fk(self, qs: list[list[float]], tcp: list[float]) -> Any:
        err = self.ensure_program()
        if err is not None:
            return err
        poses = [list(self.ctrl.getForwardKinematics(q, tcp)) for q in qs]
        if any(len(p) != 6 for p in poses):
            return "failed", "the controller did not return forward kinematics"
        return "ok", poses

    def op_set_tcp(self, pose: list[float]) -> Any:
        err = self.ensure_program()
        if err is not None:
            return err
        if not self.ctrl.setTcp(pose):
            return "failed", "the controller refused setTcp"
        return "ok", list(self.ctrl.getTCPOffset())

    def handle(self, op: str, args: tuple[Any, ...]) -> Any:
        if op == "move":
            return self.op_move(*args)
        if op == "wait":
            return self.op_wait(*args)
        if op == "status":
            self.update_move()
            return "ok", self.move_state()
        if op == "stop":
            return self.op_stop(*args)
        if op == "fk":
            return self.op_fk(*args)
        if op == "set_tcp":
            return self.op_set_tcp(*args)
        return "failed", f"unknown control operation {op!r}"

    # --- main loop ------------------------------------------------------------------------
    def run(self) -> bool:
        """Serve requests; True after an orderly close, False when the link broke."""
        try:
            self.ctrl = self.rc.RTDEControlInterface(
                self.spec.host, flags=self.rc.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
            )
        except Exception as exc:
            self.link.send_obj(("state", "failed", f"{type(exc).__name__}: {exc}"))
            return False
        tcp = list(self.ctrl.getTCPOffset())
        self.link.send_obj(("state", "ready", {"tcp": tcp}))
        while True:
            if self.link_lost():
                if self.move is not None and self.move.status == "moving":
                    self.move.status, self.move.detail = "failed", "the control link was lost"
                self.link.send_obj(("state", "lost", "the control link was lost"))
                return False
            active = self.move is not None and self.move.status == "moving"
            try:
                if not self.conn.poll(0.005 if active else 0.05):
                    if active:
                        self.update_move()
                    continue
                msg = self.conn.recv()
            except (EOFError, OSError):
                self.close()
                return True
            _, rid, op, args = msg
            if op == "close":
                self.close()
                self.link.send_obj(("reply", rid, "ok", None))
                return True
            if self.link_lost():
                self.link.send_obj(("reply", rid, "lost", "the control link was lost"))
                continue  # the check at the top of the loop reports it and ends the session
            try:
                status, payload = self.handle(op, args)
            except Exception as exc:  # a ur_rtde error must reach the caller, not kill us
                status, payload = "failed", f"{op}: {type(exc).__name__}: {exc}"
            if status != "ok":
                # A command that fails just as the link breaks fails because of it: give
                # ur_rtde's messages a moment to arrive before blaming the command.
                time.sleep(_LOSS_GRACE_S)
                if self.link_lost():
                    status, payload = "lost", "the control link was lost"
            self.link.send_obj(("reply", rid, status, payload))

    def link_lost(self) -> bool:
        self.output.drain()  # take in ur_rtde's messages written so far
        return self.trouble.is_set() or not self.ctrl.isConnected()

    def close(self) -> None:
        ctrl = self.ctrl
        if ctrl is None:
            return
        with contextlib.suppress(Exception):
            if ctrl.isConnected() and ctrl.isProgramRunning():
                ctrl.stopScript()  # ends the control program, and with it any motion


# ============================================================================ caller's process


def _missing(step_s: float, period_s: float) -> int:
    """Samples missing in a timestamp step (a step over 1.5 periods)."""
    return max(0, round(step_s / period_s) - 1) if step_s > 1.5 * period_s else 0


def _vec6(values: ArrayLike, name: str) -> NDArray[np.float64]:
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} needs 6 finite numbers, got {np.asarray(values).tolist()!r}")
    return v


def _recv_obj(conn: Connection) -> tuple[Any, ...]:
    """One message from a child (tag byte, then a pickle)."""
    data = conn.recv_bytes()
    if data[:1] != _TAG_OBJ:
        raise OSError(f"unexpected message from the control process: {data[:16]!r}")
    obj = pickle.loads(memoryview(data)[1:])
    assert isinstance(obj, tuple)
    return obj


def _stop_process(proc: Any, conn: Connection | None, message: bytes | None, wait_s: float) -> None:
    """End a child: send ``message``, close the pipe (the child ends on end-of-file too), wait
    ``wait_s`` seconds, then terminate it, then kill it."""
    if conn is not None:
        if message is not None:
            with contextlib.suppress(OSError, ValueError):
                conn.send_bytes(message)
        conn.close()
    if proc is not None:
        proc.join(timeout=wait_s)
        if proc.is_alive():
            proc.terminate()
            proc.join(timeout=2.0)
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=2.0)


@dataclass
class _Rx:
    """The receive child as seen from the caller's process."""

    proc: Any
    conn: Connection
    state: str = "starting"
    error: str | None = None
    last_msg: float = field(default_factory=time.monotonic)
    poller: Any = None
    """A ``select.poll`` on ``conn``, made once: ``Connection.poll`` builds a selector on every
    call, which at 500 rows/s cost several percent of a core."""

    def readable(self, timeout_s: float) -> bool:
        if self.poller is None:
            self.poller = select.poll()
            self.poller.register(self.conn.fileno(), select.POLLIN)
        return bool(self.poller.poll(max(0.0, timeout_s) * 1e3))


class URRobot(Robot):
    """A UR arm through ``ur_rtde`` (RTDE 30004, dashboard 29999, script 30003; optionally the
    primary interface 30001 for the factory kinematics).

    ``frequency_hz``: RTDE output rate; None asks for the controller's maximum (500 Hz e-Series,
    125 Hz CB3). ``variables``: extra RTDE outputs to subscribe (the receive child always reads
    :data:`REQUIRED_VARIABLES`; extra ones only widen the recipe). ``model``: UR model name or
    DH parameters for the ``move_j`` workspace check (the factory calibration wins when
    ``read_kinematics`` is set). ``receive_backend``: the client of the receive child,
    ``"native"`` (default: lossless, nearly no CPU) or ``"ur_rtde"`` (the reference client;
    see the module doc, "Receiving"). ``poll_interval_s`` applies to ``"ur_rtde"`` only.
    Caps and the workspace box: see :class:`Robot`.
    """

    def __init__(
        self,
        host: str,
        frequency_hz: float | None = None,
        motion_enabled: bool = False,
        max_speed_m_s: float = 0.25,
        max_accel_m_s2: float = 1.2,
        max_joint_speed_rad_s: float = 1.0,
        max_joint_accel_rad_s2: float = 1.4,
        workspace_min_m: ArrayLike | None = None,
        workspace_max_m: ArrayLike | None = None,
        *,
        model: str | DHParams | None = None,
        variables: Sequence[str] | None = None,
        read_kinematics: bool = False,
        kinematics_port: int = 30001,
        connect_timeout_s: float = 10.0,
        command_timeout_s: float = 10.0,
        stall_timeout_s: float = 3.0,
        backoff_initial_s: float = 0.05,
        backoff_max_s: float = 2.0,
        poll_interval_s: float | None = None,
        queue_size: int = 8192,
        receive_backend: str = "native",
    ) -> None:
        super().__init__(
            motion_enabled=motion_enabled,
            max_speed_m_s=max_speed_m_s,
            max_accel_m_s2=max_accel_m_s2,
            max_joint_speed_rad_s=max_joint_speed_rad_s,
            max_joint_accel_rad_s2=max_joint_accel_rad_s2,
            workspace_min_m=workspace_min_m,
            workspace_max_m=workspace_max_m,
        )
        if not isinstance(host, str) or not host:
            raise DriverInitError("robot: host must be a non-empty address string")
        if frequency_hz is not None and not 0 < frequency_hz <= 500:
            raise DriverInitError(f"robot: frequency_hz must be in (0, 500], got {frequency_hz}")
        if (self.workspace_min_m is None) != (self.workspace_max_m is None):
            raise DriverInitError("robot: give both workspace_min_m and workspace_max_m, or none")
        if self.workspace_min_m is not None:
            assert self.workspace_max_m is not None
            if self.workspace_min_m.shape != (3,) or self.workspace_max_m.shape != (3,):
                raise DriverInitError("robot: the workspace box corners need 3 values each")
            if not np.all(self.workspace_min_m < self.workspace_max_m):
                raise DriverInitError("robot: workspace_max_m must exceed workspace_min_m")
        if receive_backend not in RECEIVE_BACKENDS:
            raise DriverInitError(
                f"robot: receive_backend must be one of {', '.join(RECEIVE_BACKENDS)}, "
                f"got {receive_backend!r}"
            )
        extra = [v for v in (variables or ()) if v not in REQUIRED_VARIABLES]
        if not all(isinstance(v, str) and v for v in extra):
            raise DriverInitError("robot: variables must be RTDE output names")
        self.host = host
        self.frequency_hz = frequency_hz
        self.receive_backend = receive_backend
        self.model = model
        self.variables: tuple[str, ...] = (*REQUIRED_VARIABLES, *dict.fromkeys(extra))
        self.read_kinematics = read_kinematics
        self.kinematics_port = kinematics_port
        self.connect_timeout_s = connect_timeout_s
        self.command_timeout_s = command_timeout_s
        self.stall_timeout_s = stall_timeout_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        nominal = 1.0 / frequency_hz if frequency_hz else _E_SERIES_PERIOD_S
        self.poll_interval_s = poll_interval_s or min(0.0004, nominal / 5)
        self.queue_size = queue_size
        self.kinematics_info: KinematicsInfo | None = None
        """The factory calibration, when ``read_kinematics`` read it at :meth:`open`."""

        self._ctx = mp.get_context("spawn")
        # receive side
        self._rx: _Rx | None = None
        self._rx_lock = threading.Lock()
        self._next_supervise = 0.0
        self._rx_backoff = Backoff(backoff_initial_s, backoff_max_s)
        self._rx_restart_at: float | None = None
        self._rx_ever_up = False
        self._rx_restarts = 0
        self._rx_stats: dict[str, int] = {}
        self._queue: deque[RobotState] = deque()
        self._latest: RobotState | None = None
        self._last_t: float | None = None
        self._period_s: float | None = 1.0 / frequency_hz if frequency_hz else None
        self._lost_if_cb3 = 0
        self._lost_if_e_series = 0
        self._overflow = 0
        # control side
        self._ctl_proc: Any = None
        self._ctl_conn: Connection | None = None
        self._ctl_lock = threading.RLock()
        self._ctl_seq = 0
        self._ctl_state = "idle"
        self._ctl_error: str | None = None
        self._ctl_backoff = Backoff(backoff_initial_s, backoff_max_s)
        self._ctl_retry_at = 0.0
        self._ctl_starts = 0
        self._ctl_suspect = False
        self._tcp_offset: NDArray[np.float64] | None = None
        self._move_status = MoveStatus.IDLE
        self._move_detail = ""
        self._move_target: tuple[str, NDArray[np.float64]] = ("l", np.zeros(6))

    # ------------------------------------------------------------------ life cycle

    def _open(self) -> None:
        if self.read_kinematics:
            from wristscan.drivers.ur.primary import read_kinematics_info

            try:
                self.kinematics_info = read_kinematics_info(
                    self.host, self.kinematics_port, self.connect_timeout_s
                )
            except (DriverError, OSError) as exc:
                raise DriverInitError(
                    f"robot: cannot read the factory kinematics from {self.host}:"
                    f"{self.kinematics_port} ({exc}); set read_kinematics = false to use the "
                    "nominal model"
                ) from exc
        self._reset_stream()
        self._rx_ever_up = False
        self._rx_restarts = 0
        self._start_rx()
        deadline = time.monotonic() + self.connect_timeout_s
        while True:
            rx = self._rx
            if rx is None:
                break
            if rx.state == "up":
                return
            if rx.state in ("down", "failed"):
                break
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._stop_rx()
                raise DriverTimeout(
                    f"robot: no RTDE connection to {self.host} within {self.connect_timeout_s:g} s"
                )
            self._pump(min(remaining, 0.1), supervise=False)
        error = self._rx.error if self._rx is not None else "the receive process ended"
        self._stop_rx()
        raise DriverInitError(f"robot: cannot connect to RTDE at {self.host}:30004: {error}")

    def _close(self) -> None:
        try:
            self._stop_ctl()
        finally:
            self._stop_rx()
            self._rx_restart_at = None

    def _reset_stream(self) -> None:
        self._queue.clear()
        self._last_t = None
        self._latest = None
        self._period_s = 1.0 / self.frequency_hz if self.frequency_hz else None
        self._lost_if_cb3 = 0
        self._lost_if_e_series = 0

    # ------------------------------------------------------------------ receive side

    def _start_rx(self) -> None:
        spec = _RxSpec(
            host=self.host,
            frequency_hz=self.frequency_hz,
            variables=self.variables,
            backend=self.receive_backend,
            poll_s=self.poll_interval_s,
            # The child reports a failed attempt itself, before the parent's patience ends.
            connect_timeout_s=min(5.0, self.connect_timeout_s / 2),
            data_timeout_s=self.stall_timeout_s,
            backoff_initial_s=self.backoff_initial_s,
            backoff_max_s=self.backoff_max_s,
            pending_max=self.queue_size,
            log_level=log.getEffectiveLevel(),
        )
        parent_conn, child_conn = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(
            target=_receive_main,
            args=(spec, child_conn),
            name=f"ur-receive-{self.receive_backend}-{self.host}",
            daemon=True,
        )
        proc.start()
        child_conn.close()
        self._rx = _Rx(proc, parent_conn)
        self._rx_restart_at = None

    def _stop_rx(self) -> None:
        with self._rx_lock:
            rx, self._rx = self._rx, None
        if rx is not None:
            _stop_process(rx.proc, rx.conn, _CMD_STOP, wait_s=5.0)

    def _rx_died(self, reason: str, kill: bool = False) -> None:
        rx, self._rx = self._rx, None
        if rx is None:
            return
        if rx.state == "failed":  # cannot work here (ur_rtde missing): restarting will not help
            _stop_process(rx.proc, rx.conn, None, wait_s=2.0)
            if self._open_flag:
                self._set_state(LinkState.FAILED, rx.error)
            return
        self._rx_restarts += 1
        log.warning("robot %s: receive process %s; restarting it", self.host, reason)
        if kill:
            rx.proc.kill()
        _stop_process(rx.proc, rx.conn, None, wait_s=2.0)
        delay = self._rx_backoff.next_delay()
        self._rx_restart_at = time.monotonic() + delay
        if self._open_flag:
            self._set_state(LinkState.RECONNECTING, f"receive process {reason}")

    def _on_rx_state(self, rx: _Rx, name: str, error: str | None) -> None:
        rx.state, rx.error = name, error
        if name == "up":
            if self._rx_ever_up:
                self.counters.reconnects += 1
            self._rx_ever_up = True
            self._rx_backoff.reset()
            if self._open_flag:
                self._set_state(LinkState.OPEN)
        elif name == "failed":
            if self._open_flag:
                self._set_state(LinkState.FAILED, error)
        elif self._open_flag and name in ("reconnecting", "down"):
            self._set_state(LinkState.RECONNECTING, error)
            # The control link most likely broke too; its child may not have noticed yet.
            self._ctl_suspect = self._ctl_proc is not None

    def _on_rows(self, data: memoryview) -> None:
        rows = np.frombuffer(data, dtype=ROW_DTYPE)
        # Columns once per chunk: indexing a structured row field by field costs more than the
        # rest of the record's handling.
        ts, hosts, flag_list = rows["t"].tolist(), rows["host_ns"].tolist(), rows["flags"].tolist()
        qs, tcps, qds = rows["q"].copy(), rows["tcp"].copy(), rows["qd"].copy()
        for i, t in enumerate(ts):
            last = self._last_t
            if last is not None:
                dt = t - last
                if dt == 0.0:
                    self.counters.duplicates += 1
                    continue
                if dt < 0.0:
                    if dt > -_RESTART_DROP_S:
                        self.counters.reordered += 1
                        continue
                    log.warning(
                        "robot %s: controller clock went back %.3f s (controller restarted?)",
                        self.host,
                        -dt,
                    )
                else:
                    self._account_step(dt)
            self._last_t = t
            flags = flag_list[i]
            state = RobotState(
                controller_time_s=t,
                host_time_ns=hosts[i],
                q=qs[i],
                tcp_pose=tcps[i],
                protective_stop=bool(flags & FLAG_PROTECTIVE_STOP),
                program_running=bool(flags & FLAG_PROGRAM_RUNNING),
                qd=qds[i],
            )
            if len(self._queue) >= self.queue_size:
                self._queue.popleft()
                self.counters.lost += 1
                self._overflow += 1
            self._queue.append(state)
            self._latest = state

    def _account_step(self, dt: float) -> None:
        if self.frequency_hz is not None:
            assert self._period_s is not None
            self.counters.lost += _missing(dt, self._period_s)
            return
        # ur_rtde asked for the controller's maximum rate: 2 ms (e-Series) or 8 ms (CB3). Until a
        # step under 6 ms proves e-Series, count as CB3 and keep the e-Series count aside, to
        # correct the total when the proof comes.
        if self._period_s == _E_SERIES_PERIOD_S:
            self.counters.lost += _missing(dt, _E_SERIES_PERIOD_S)
            return
        if dt < 0.75 * _CB3_PERIOD_S:
            self._period_s = _E_SERIES_PERIOD_S
            self.counters.lost += self._lost_if_e_series - self._lost_if_cb3
            self.counters.lost += _missing(dt, _E_SERIES_PERIOD_S)
            return
        self._period_s = _CB3_PERIOD_S
        self._lost_if_cb3 += _missing(dt, _CB3_PERIOD_S)
        self._lost_if_e_series += _missing(dt, _E_SERIES_PERIOD_S)
        self.counters.lost += _missing(dt, _CB3_PERIOD_S)

    def _handle_rx_message(self, rx: _Rx, msg: bytes) -> None:
        rx.last_msg = time.monotonic()
        self.counters.bytes += len(msg)
        tag, body = msg[:1], memoryview(msg)[1:]
        if tag == _TAG_ROWS:
            if len(body) % ROW_DTYPE.itemsize:
                self.counters.malformed += 1
                self.raw_log.add(msg)
                return
            self._on_rows(body)
            return
        if tag != _TAG_OBJ:
            self.counters.malformed += 1
            self.raw_log.add(msg)
            return
        obj = pickle.loads(body)
        kind = obj[0]
        if kind == "state":
            self._on_rx_state(rx, obj[1], obj[2])
        elif kind == "beat":
            self._rx_stats = dict(obj[1])
        elif kind == "log":
            _native_log.log(obj[1], "%s (receive): %s", self.host, obj[2])

    def _pump(self, timeout: float, supervise: bool = True, wait_lock: bool = True) -> None:
        """Take whatever the receive child sent (waiting up to ``timeout`` s for the first
        message), then look after the child."""
        if not self._rx_lock.acquire(timeout=timeout if wait_lock else 0):
            return
        try:
            rx = self._rx
            if rx is None:
                if supervise and self._rx_restart_at is not None:
                    if time.monotonic() >= self._rx_restart_at:
                        self._start_rx()
                    elif timeout > 0:
                        time.sleep(min(timeout, self._rx_restart_at - time.monotonic()))
                return
            try:
                if rx.readable(timeout):
                    for _ in range(4096):
                        self._handle_rx_message(rx, rx.conn.recv_bytes())
                        if not rx.readable(0.0):
                            break
            except (EOFError, OSError):
                if supervise or rx.state not in ("down", "failed"):
                    self._rx_died("ended")
                return
            now = time.monotonic()
            if supervise and now >= self._next_supervise:
                # A child's death shows within 50 ms; not a wait() system call per sample.
                self._next_supervise = now + 0.05
                self._supervise_rx(rx)
        finally:
            self._rx_lock.release()

    def _supervise_rx(self, rx: _Rx) -> None:
        if not rx.proc.is_alive():
            self._rx_died(f"exited with code {rx.proc.exitcode}")
            return
        silent = time.monotonic() - rx.last_msg
        limit = self.stall_timeout_s if rx.state == "up" else self.connect_timeout_s
        if silent > limit:
            self._rx_died(f"silent for {silent:.1f} s", kill=True)

    def _read_internal(self, timeout: float | None) -> RobotState | None:
        with contextlib.suppress(IndexError):
            return self._queue.popleft()
        self._pump(0.1 if timeout is None else timeout)
        with contextlib.suppress(IndexError):
            return self._queue.popleft()
        return None

    @property
    def stamped_on_receipt(self) -> bool:
        """The receive child stamps each sample as it takes it (either backend)."""
        return True

    def latest_state(self) -> RobotState | None:
        """The newest sample received so far (it stays in the read queue too)."""
        self._pump(0.0, wait_lock=False)
        return self._latest

    def health(self) -> Health:
        """State, counters and detail, after taking in what the children reported."""
        if self._open_flag:
            self._pump(0.0, wait_lock=False)
        self._drain_ctl()
        return super().health()

    def _health_detail(self) -> dict[str, Any]:
        rx = self._rx
        return {
            "host": self.host,
            "receive": rx.state if rx is not None else "stopped",
            "receive_backend": self.receive_backend,
            "period_s": self._period_s,
            "queued": len(self._queue),
            "queue_overflow": self._overflow,
            "receive_restarts": self._rx_restarts,
            **self._rx_stats,
            "control": self._ctl_state,
            "control_starts": self._ctl_starts,
            "control_error": self._ctl_error,
            "move_status": self._move_status.value,
            "kinematics": (
                "factory"
                if self.kinematics_info is not None
                else "nominal"
                if self.model is not None
                else "controller"
            ),
        }

    # ------------------------------------------------------------------ control side

    def _ctl_alive(self) -> bool:
        return self._ctl_proc is not None and self._ctl_proc.is_alive()

    def _drain_ctl(self) -> None:
        """Take the control child's notices (state, log lines) without waiting."""
        if not self._ctl_lock.acquire(blocking=False):
            return
        try:
            conn = self._ctl_conn
            while conn is not None and conn.poll(0):
                msg = _recv_obj(conn)
                if msg[0] != "reply":
                    self._on_ctl_message(msg)
        except (EOFError, OSError):
            self._ctl_state = "lost"
        finally:
            self._ctl_lock.release()

    def _drop_ctl(self, reason: str) -> None:
        proc, conn = self._ctl_proc, self._ctl_conn
        self._ctl_proc = self._ctl_conn = None
        self._ctl_state = "down"
        self._ctl_error = reason
        if self._move_status is MoveStatus.MOVING:
            self._set_move(MoveStatus.FAILED, reason)
        _stop_process(proc, conn, None, wait_s=2.0)

    def _stop_ctl(self) -> None:
        with self._ctl_lock:
            proc, conn = self._ctl_proc, self._ctl_conn
            if proc is None:
                return
            if conn is not None and proc.is_alive():
                try:
                    self._ctl_seq += 1
                    conn.send(("req", self._ctl_seq, "close", ()))
                    # The child stops the control script (and the arm) before it replies.
                    end = time.monotonic() + 5.0
                    while time.monotonic() < end and conn.poll(end - time.monotonic()):
                        msg = _recv_obj(conn)
                        if msg[0] == "reply" and msg[1] == self._ctl_seq:
                            break
                except (EOFError, OSError):
                    pass
            self._ctl_proc = self._ctl_conn = None
            self._ctl_state = "idle"
            _stop_process(proc, conn, None, wait_s=5.0)

    def _on_ctl_message(self, msg: tuple[Any, ...]) -> None:
        kind = msg[0]
        if kind == "log":
            _native_log.log(msg[1], "%s (control): %s", self.host, msg[2])
        elif kind == "state":
            name, info = msg[1], msg[2]
            self._ctl_state = name
            if name == "ready":
                self._ctl_error = None
                self._ctl_backoff.reset()
                self._tcp_offset = np.asarray(info["tcp"], dtype=np.float64)
            else:
                self._ctl_error = str(info)
                if name == "lost":
                    log.warning("robot %s: control link lost", self.host)

    def _ctl_connect(self, deadline: float, command: bool = False) -> Connection:
        """The control child's pipe, starting the child (and waiting for it) if needed. For a
        new ``command``, a child that may have lost its link (the receive link dropped since)
        is replaced first, so the command does not race with the child finding out."""
        if not self._open_flag:
            raise DriverIOError(f"robot {self.host}: not open")
        if command and self._ctl_suspect and self._ctl_proc is not None:
            self._drop_ctl("the receive link dropped meanwhile")
        if self._ctl_alive() and self._ctl_state == "ready":
            conn = self._ctl_conn
            assert conn is not None
            try:  # take a "lost" notice the child may have sent since the last request
                while conn.poll(0):
                    self._on_ctl_message(_recv_obj(conn))
            except (EOFError, OSError):
                self._ctl_state = "lost"
            if self._ctl_state == "ready":
                return conn
        if self._ctl_proc is not None:
            self._drop_ctl(self._ctl_error or "the control process ended")
        wait = self._ctl_retry_at - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, max(0.0, deadline - time.monotonic())))
        parent_conn, child_conn = self._ctx.Pipe(duplex=True)
        spec = _CtlSpec(host=self.host, log_level=log.getEffectiveLevel())
        proc = self._ctx.Process(
            target=_control_main,
            args=(spec, child_conn),
            name=f"ur-rtde-control-{self.host}",
            daemon=True,
        )
        proc.start()
        child_conn.close()
        self._ctl_proc, self._ctl_conn = proc, parent_conn
        self._ctl_suspect = False
        self._ctl_state = "connecting"
        self._ctl_starts += 1
        try:
            while self._ctl_state == "connecting":
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not parent_conn.poll(remaining):
                    raise DriverTimeout(
                        f"robot: the control interface of {self.host} did not connect in time"
                    )
                self._on_ctl_message(_recv_obj(parent_conn))
        except (EOFError, OSError) as exc:
            self._ctl_state = "failed"
            self._ctl_error = f"the control process ended while connecting ({exc})"
        except DriverTimeout:
            self._ctl_retry_at = time.monotonic() + self._ctl_backoff.next_delay()
            self._drop_ctl("connect timeout")
            raise
        if self._ctl_state != "ready":
            error = self._ctl_error
            self._ctl_retry_at = time.monotonic() + self._ctl_backoff.next_delay()
            self._drop_ctl(error or "failed")
            raise DriverIOError(
                f"robot: cannot connect the control interface of {self.host}: {error}"
            )
        return parent_conn

    def _ctl_call(self, op: str, *args: Any, timeout_s: float | None = None) -> tuple[str, Any]:
        """One request to the control child; returns ``(status, payload)``. When the control
        link turns out to be lost, commands (not waits) are sent once more through a fresh
        control process: moves are absolute, so repeating one is harmless, and the fresh
        process's ur_rtde first stops the script the old one left running."""
        with self._ctl_lock:
            try:
                return self._ctl_call_once(op, args, timeout_s)
            except _ControlLost:
                if op not in _RETRY_ON_LOSS:
                    raise MotionFailed(f"robot: the control link to {self.host} was lost") from None
                log.warning("robot %s: control link lost; %r again on a new link", self.host, op)
            try:
                return self._ctl_call_once(op, args, timeout_s)
            except _ControlLost:
                raise MotionFailed(f"robot: the control link to {self.host} was lost") from None

    def _ctl_call_once(
        self, op: str, args: tuple[Any, ...], timeout_s: float | None
    ) -> tuple[str, Any]:
        with self._ctl_lock:
            conn = self._ctl_connect(
                time.monotonic() + self.connect_timeout_s, command=op in _RETRY_ON_LOSS
            )
            deadline = time.monotonic() + (timeout_s or self.command_timeout_s)
            self._ctl_seq += 1
            rid = self._ctl_seq
            try:
                conn.send(("req", rid, op, args))
                while True:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        self._drop_ctl(f"no answer to {op!r}")
                        raise DriverTimeout(
                            f"robot: the control process gave no answer to {op!r} in time"
                        )
                    if not conn.poll(min(remaining, 0.5)):
                        if not self._ctl_alive():
                            raise EOFError("the control process ended")
                        continue
                    msg = _recv_obj(conn)
                    if msg[0] == "reply":
                        if msg[1] != rid:
                            continue  # the late answer to a request that timed out
                        if msg[2] == "lost":
                            raise _ControlLost(msg[3])
                        return msg[2], msg[3]
                    self._on_ctl_message(msg)
                    if msg[0] == "state" and msg[1] == "lost":
                        raise _ControlLost(str(msg[2]))
            except _ControlLost as exc:
                self._drop_ctl(f"the control link was lost ({exc})")
                raise
            except (EOFError, OSError) as exc:
                self._drop_ctl(f"the control process ended ({exc})")
                raise _ControlLost(str(exc)) from exc

    def _set_move(self, status: MoveStatus, detail: str = "") -> None:
        self._move_status, self._move_detail = status, detail

    def _arrived(self) -> tuple[bool, str]:
        """Whether the stream shows the arm at the last move's target (end-to-end check of a
        move the controller reports done); waits up to ``_VERIFY_WAIT_S`` for the stream."""
        kind, target = self._move_target
        t_done = time.monotonic_ns()
        deadline = time.monotonic() + _VERIFY_WAIT_S
        miss = ""
        while True:
            self._pump(0.02)
            s = self._latest
            if s is None or s.host_time_ns < t_done - _STALE_NS:
                if time.monotonic() >= deadline:
                    log.warning("robot %s: no fresh state to confirm the move", self.host)
                    return True, "not confirmed: no fresh robot state"
                continue
            if kind == "j":
                err = float(np.max(np.abs(s.q - target)))
                if err < _ARRIVAL_TOL_RAD:
                    return True, ""
                miss = f"a joint is {err:.4f} rad from the target"
            else:
                from wristscan.calib import se3

                T, G = se3.pose_to_matrix(s.tcp_pose), se3.pose_to_matrix(target)
                dp = float(np.linalg.norm(T[:3, 3] - G[:3, 3]))
                dr = float(se3.rotation_angle(T[:3, :3].T @ G[:3, :3]))
                if dp < _ARRIVAL_TOL_M and dr < _ARRIVAL_TOL_RAD:
                    return True, ""
                miss = f"the TCP is {dp * 1e3:.1f} mm / {dr:.4f} rad from the target"
            if time.monotonic() >= deadline:
                return False, f"reported done, but {miss}"

    def _apply_move_state(self, state: tuple[str, str]) -> MoveStatus:
        name, detail = state
        status = {
            "idle": MoveStatus.IDLE,
            "moving": MoveStatus.MOVING,
            "done": MoveStatus.DONE,
            "stopped": MoveStatus.STOPPED,
            "pstop": MoveStatus.PROTECTIVE_STOP,
            "failed": MoveStatus.FAILED,
        }.get(name, MoveStatus.FAILED)
        if status is MoveStatus.IDLE:
            # A fresh control child knows nothing of earlier moves.
            if self._move_status is MoveStatus.MOVING:
                self._set_move(MoveStatus.FAILED, "the control process lost track of the move")
            return self._move_status
        if status is MoveStatus.DONE and self._move_status is MoveStatus.MOVING:
            ok, why = self._arrived()
            if not ok:
                status, detail = MoveStatus.FAILED, why
            elif why:
                detail = why
        self._set_move(status, detail)
        return status

    def _raise_for(self, status: MoveStatus, what: str) -> None:
        detail = self._move_detail
        if status is MoveStatus.PROTECTIVE_STOP:
            raise ProtectiveStop(f"robot: {what} ended by a safety stop ({detail})")
        if status is MoveStatus.STOPPED:
            raise MotionFailed(f"robot: {what} was stopped before its target", status)
        if status is not MoveStatus.DONE:
            raise MotionFailed(f"robot: {what} failed: {detail or status.value}", status)

    def _move(
        self, kind: str, target: NDArray[np.float64], speed: float, accel: float, wait: bool
    ) -> None:
        what = f"move{kind.upper()}"
        status, payload = self._ctl_call("move", kind, target.tolist(), float(speed), float(accel))
        if status != "ok":
            if status == "pstop":
                self._set_move(MoveStatus.PROTECTIVE_STOP, str(payload))
                raise ProtectiveStop(f"robot: {what} refused: {payload}")
            self._set_move(MoveStatus.FAILED, str(payload))
            raise MotionFailed(f"robot: {what} refused: {payload}")
        self._move_target = (kind, target.copy())
        self._set_move(MoveStatus.MOVING)
        if wait:
            self._raise_for(self.wait_until_idle(None), what)

    def move_l(
        self, pose: ArrayLike, speed: float, accel: float, asynchronous: bool = False
    ) -> None:
        """Linear move of the TCP to UR pose ``[x, y, z, rx, ry, rz]`` (m, rad) at ``speed`` m/s
        and ``accel`` m/s^2. Blocking unless ``asynchronous``; see the module doc for the
        outcome and its exceptions."""
        p = _vec6(pose, "move_l pose")
        self.check_motion(p[:3], speed, accel, joint=False)
        self._move("l", p, speed, accel, not asynchronous)

    def move_j(self, q: ArrayLike, speed: float, accel: float, asynchronous: bool = False) -> None:
        """Joint move to ``q`` (rad) at ``speed`` rad/s and ``accel`` rad/s^2 (of the leading
        joint). With a workspace box, the TCP along the path must stay inside it."""
        qv = _vec6(q, "move_j q")
        self.check_motion(None, speed, accel, joint=True)
        if self.workspace_min_m is not None:
            self._check_joint_path(qv)
        self._move("j", qv, speed, accel, not asynchronous)

    def _check_joint_path(self, q_target: NDArray[np.float64]) -> None:
        latest = self.latest_state()
        if latest is None:
            qs = q_target[None, :]
        else:
            s = np.linspace(0.0, 1.0, _PATH_SAMPLES + 1)[1:, None]
            qs = latest.q[None, :] + s * (q_target - latest.q)[None, :]
        from wristscan.calib import kinematics, se3

        tcp2flange = se3.pose_to_matrix(self.tcp_offset())
        model = self.kinematic_model()
        if model is not None:
            xyz = np.asarray((kinematics.forward(model, qs) @ tcp2flange)[:, :3, 3])
        else:
            # Ask with a non-zero reference TCP, taken off again below: ur_rtde sends a request
            # without TCP (and, seen with 1.6.5, one with an all-zero TCP) in a recipe that
            # leaves the TCP registers alone, while the control script reads the TCP from them,
            # so the previous command's leftovers would be used.
            status, poses = self._ctl_call("fk", qs.tolist(), list(_FK_REFERENCE_TCP))
            if status != "ok":
                raise WorkspaceViolation(
                    f"robot: cannot check the joint path against the workspace box ({poses})"
                )
            ref2base = se3.pose_to_matrix(np.asarray(poses, dtype=np.float64))
            ref2flange = se3.pose_to_matrix(np.asarray(_FK_REFERENCE_TCP))
            tcp2base = ref2base @ se3.invert(ref2flange) @ tcp2flange
            xyz = np.asarray(tcp2base[:, :3, 3])
        lo, hi = self.workspace_min_m, self.workspace_max_m
        assert lo is not None and hi is not None
        outside = np.any((xyz < lo) | (xyz > hi), axis=1)
        if np.any(outside):
            i = int(np.argmax(outside))
            where = "target" if i == len(xyz) - 1 else f"path sample {i + 1}/{len(xyz)}"
            raise WorkspaceViolation(
                f"joint move: TCP at {np.round(xyz[i], 4).tolist()} m ({where}) outside the "
                f"workspace box {lo.tolist()} .. {hi.tolist()} m"
            )

    def stop(self, decel_m_s2: float | None = None, decel_rad_s2: float | None = None) -> None:
        """Decelerate the current move to a standstill (``decel_*`` default: the acceleration
        caps) and wait until the arm has stopped. Without a control link nothing this driver
        commanded can be moving, so it does nothing then."""
        with self._ctl_lock:
            if not self._ctl_alive() and self._move_status is not MoveStatus.MOVING:
                return
            status, payload = self._ctl_call(
                "stop",
                float(decel_m_s2 or self.max_accel_m_s2),
                float(decel_rad_s2 or self.max_joint_accel_rad_s2),
            )
            if status == "ok":
                self._apply_move_state(tuple(payload))
            else:
                raise MotionFailed(f"robot: stop failed: {payload}")

    def wait_until_idle(self, timeout: float | None = None) -> MoveStatus:
        """Wait for the current move to end; returns its final status, or
        :attr:`MoveStatus.MOVING` if it still moves after ``timeout`` seconds. Raises nothing
        for a failed move (a blocking move does)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._move_status is not MoveStatus.MOVING:
                return self._move_status
            if not self._ctl_alive():
                self._set_move(MoveStatus.FAILED, self._ctl_error or "control process ended")
                return self._move_status
            remaining = _WAIT_SLICE_S if deadline is None else deadline - time.monotonic()
            if remaining <= 0:
                return MoveStatus.MOVING
            slice_s = min(_WAIT_SLICE_S, remaining)
            try:
                status, payload = self._ctl_call(
                    "wait", slice_s, timeout_s=slice_s + self.command_timeout_s
                )
            except MotionFailed as exc:
                self._set_move(MoveStatus.FAILED, str(exc))
                return MoveStatus.FAILED
            if status == "ok":
                self._apply_move_state(tuple(payload))

    def move_status(self) -> MoveStatus:
        """Status of the last motion command (asks the control child while one runs)."""
        with self._ctl_lock:
            if self._move_status is MoveStatus.MOVING and self._ctl_alive():
                try:
                    status, payload = self._ctl_call("status")
                except MotionFailed:
                    return self._move_status
                if status == "ok":
                    self._apply_move_state(tuple(payload))
            elif self._move_status is MoveStatus.MOVING:
                self._set_move(MoveStatus.FAILED, self._ctl_error or "control process ended")
            return self._move_status

    def is_moving(self) -> bool:
        """True while a commanded move runs."""
        return self.move_status() is MoveStatus.MOVING

    def connect_control(self) -> None:
        """Start the control link now instead of at the first command (uploads the control
        script, which takes over the robot's program). Needs ``motion_enabled``."""
        self._require_motion()
        with self._ctl_lock:
            self._ctl_connect(time.monotonic() + self.connect_timeout_s)

    def _require_motion(self) -> None:
        """Raise MotionNotEnabled unless motion is enabled (the caps trivially pass)."""
        self.check_motion(None, self.max_speed_m_s, self.max_accel_m_s2)

    def set_tcp(self, pose: ArrayLike) -> None:
        """Set the controller's active TCP (UR pose in the flange frame, m and rad); the
        reported ``tcp_pose`` follows it. Needs ``motion_enabled`` (it uses the control link)."""
        p = _vec6(pose, "set_tcp pose")
        self._require_motion()
        status, payload = self._ctl_call("set_tcp", p.tolist())
        if status != "ok":
            raise DriverIOError(f"robot: set_tcp failed: {payload}")
        self._tcp_offset = np.asarray(payload, dtype=np.float64)

    def tcp_offset(self) -> NDArray[np.float64]:
        """The controller's active TCP offset (UR pose in the flange frame); asks the control
        link, so it needs ``motion_enabled``."""
        if self._tcp_offset is None or not self._ctl_alive():
            self._require_motion()
            with self._ctl_lock:
                self._ctl_connect(time.monotonic() + self.connect_timeout_s)
        assert self._tcp_offset is not None
        return self._tcp_offset.copy()

    def kinematic_model(self) -> DHParams | None:
        """The factory-calibrated model when read, else the nominal ``model``, else None."""
        if self.kinematics_info is not None:
            return self.kinematics_info.model(f"{self.host} factory calibration")
        if self.model is None:
            return None
        from wristscan.calib import kinematics

        return kinematics.get_model(self.model)
