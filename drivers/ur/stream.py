"""The UR driver's state stream, seen from the caller's process: the receive child's supervisor.

:class:`URStateStream` starts the receive child (:mod:`.receive_child`), takes in what it sends
(rows, state changes, heartbeats, log lines) whenever the caller reads or asks for health, restarts
it when it ends or falls silent, and turns rows into :class:`~wristscan.drivers.records.RobotState`
records in order, counting duplicates, reordered and lost samples (see :mod:`.robot`, "Receiving").
It is the lowest layer of :class:`~.robot.URRobot`, which sets the settings declared below.
"""

from __future__ import annotations

import contextlib
import logging
import pickle
import select
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

import numpy as np

from wristscan.drivers.base import Backoff, DriverInitError, DriverTimeout, LinkState, Robot
from wristscan.drivers.records import RobotState
from wristscan.drivers.ur.process import (
    CHILD_LOG,
    CMD_STOP,
    TAG_OBJ,
    TAG_ROWS,
    spawn_child,
    stop_child,
)
from wristscan.drivers.ur.receive_child import (
    FLAG_PROGRAM_RUNNING,
    FLAG_PROTECTIVE_STOP,
    ROW_DTYPE,
    RxSpec,
    receive_main,
)

__all__ = ["E_SERIES_PERIOD_S", "URStateStream"]

log = logging.getLogger(__name__)

E_SERIES_PERIOD_S = 0.002
"""Sample period of an e-Series controller at its maximum rate, 500 Hz (s)."""
_CB3_PERIOD_S = 0.008
_RESTART_DROP_S = 1.0


def _missing(step_s: float, period_s: float) -> int:
    """Samples missing in a timestamp step (a step over 1.5 periods)."""
    return max(0, round(step_s / period_s) - 1) if step_s > 1.5 * period_s else 0


@dataclass
class _Rx:
    """The receive child as seen from the caller's process."""

    proc: BaseProcess
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


class URStateStream(Robot):
    """The receive side of :class:`~.robot.URRobot` (an abstract layer: the motion commands and
    the life cycle come from the layers above)."""

    # Settings, set by URRobot.__init__.
    host: str
    frequency_hz: float | None
    variables: tuple[str, ...]
    receive_backend: str
    poll_interval_s: float
    connect_timeout_s: float
    stall_timeout_s: float
    backoff_initial_s: float
    backoff_max_s: float
    queue_size: int

    def _init_stream(self) -> None:
        """The receive side's state (once the settings are set)."""
        self._rx: _Rx | None = None
        self._rx_lock = threading.Lock()
        self._next_supervise = 0.0
        self._rx_backoff = Backoff(self.backoff_initial_s, self.backoff_max_s)
        self._rx_restart_at: float | None = None
        self._rx_ever_up = False
        self._rx_restarts = 0
        self._rx_stats: dict[str, int] = {}
        self._queue: deque[RobotState] = deque()
        self._latest: RobotState | None = None
        self._last_t: float | None = None
        self._period_s: float | None = 1.0 / self.frequency_hz if self.frequency_hz else None
        self._lost_if_cb3 = 0
        self._lost_if_e_series = 0
        self._overflow = 0

    def _open_stream(self) -> None:
        """Start the receive child and wait until it streams (``connect_timeout_s``)."""
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

    def _reset_stream(self) -> None:
        self._queue.clear()
        self._last_t = None
        self._latest = None
        self._period_s = 1.0 / self.frequency_hz if self.frequency_hz else None
        self._lost_if_cb3 = 0
        self._lost_if_e_series = 0

    def _start_rx(self) -> None:
        spec = RxSpec(
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
        proc, conn = spawn_child(
            receive_main, (spec,), f"ur-receive-{self.receive_backend}-{self.host}"
        )
        self._rx = _Rx(proc, conn)
        self._rx_restart_at = None

    def _stop_rx(self) -> None:
        with self._rx_lock:
            rx, self._rx = self._rx, None
        if rx is not None:
            stop_child(rx.proc, rx.conn, CMD_STOP, wait_s=5.0)

    def _rx_died(self, reason: str, kill: bool = False) -> None:
        rx, self._rx = self._rx, None
        if rx is None:
            return
        if rx.state == "failed":  # cannot work here (ur_rtde missing): restarting will not help
            stop_child(rx.proc, rx.conn, None, wait_s=2.0)
            if self._open_flag:
                self._set_state(LinkState.FAILED, rx.error)
            return
        self._rx_restarts += 1
        log.warning("robot %s: receive process %s; restarting it", self.host, reason)
        if kill:
            rx.proc.kill()
        stop_child(rx.proc, rx.conn, None, wait_s=2.0)
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
            self._on_receive_drop()

    def _on_receive_drop(self) -> None:
        """The receive link dropped (the child reconnects); a layer above may react."""

    def _on_rows(self, data: memoryview | bytes) -> None:
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
        if self._period_s == E_SERIES_PERIOD_S:
            self.counters.lost += _missing(dt, E_SERIES_PERIOD_S)
            return
        if dt < 0.75 * _CB3_PERIOD_S:
            self._period_s = E_SERIES_PERIOD_S
            self.counters.lost += self._lost_if_e_series - self._lost_if_cb3
            self.counters.lost += _missing(dt, E_SERIES_PERIOD_S)
            return
        self._period_s = _CB3_PERIOD_S
        self._lost_if_cb3 += _missing(dt, _CB3_PERIOD_S)
        self._lost_if_e_series += _missing(dt, E_SERIES_PERIOD_S)
        self.counters.lost += _missing(dt, _CB3_PERIOD_S)

    def _take_rows(self, rows: list[memoryview]) -> None:
        """The rows gathered so far made into records in one call; ``rows`` emptied."""
        if rows:
            self._on_rows(rows[0] if len(rows) == 1 else b"".join(rows))
            rows.clear()

    def _handle_rx_message(self, rx: _Rx, msg: bytes, rows: list[memoryview]) -> None:
        """One message of the child; its rows are appended to ``rows`` (turned into records
        by the caller, all of a pump at once: per call, not per row, costs most there)."""
        rx.last_msg = time.monotonic()
        self.counters.bytes += len(msg)
        tag, body = msg[:1], memoryview(msg)[1:]
        if tag == TAG_ROWS:
            if len(body) % ROW_DTYPE.itemsize:
                self.counters.malformed += 1
                self.raw_log.add(msg)
                return
            rows.append(body)
            return
        self._take_rows(rows)  # what came before a state change is taken first, in order
        if tag != TAG_OBJ:
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
            CHILD_LOG.log(obj[1], "%s (receive): %s", self.host, obj[2])

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
                    rows: list[memoryview] = []
                    try:
                        for _ in range(4096):
                            self._handle_rx_message(rx, rx.conn.recv_bytes(), rows)
                            if not rx.readable(0.0):
                                break
                    finally:
                        self._take_rows(rows)
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
