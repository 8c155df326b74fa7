"""Reader threads: one per device, moving records from its driver into a bounded queue that the
pipeline's worker drains at each tick.
"""

from __future__ import annotations

import ctypes
import logging
import sys
import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

from wristscan.drivers.base import Device, DriverError

__all__ = ["InlineReader", "Reader", "name_os_thread"]

log = logging.getLogger(__name__)

T = TypeVar("T")


def name_os_thread(name: str) -> None:
    """Give the calling thread its name at the OS level too (Linux, 15 bytes), so that
    ``top -H``, ``ps -L`` and ``/proc/<pid>/task/*/comm`` tell the pipeline's threads apart."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(15, name.encode("ascii", "replace")[:15], 0, 0, 0)  # PR_SET_NAME
    except (OSError, AttributeError):  # no prctl: a cosmetic loss only
        pass


class InlineReader(Generic[T]):
    """A device read by the worker itself at each tick, for drivers whose records are stamped
    on receipt by a process of their own (``stamped_on_receipt``, the UR driver's receive
    child): reading them late changes no time, and a thread woken for every record (500 a
    second from a UR controller, each costing a wake-up, two polls and the GIL) is saved.
    :class:`Reader`'s interface (``start``, ``stop``, ``join`` do nothing here) plus
    :meth:`pump`."""

    def __init__(
        self,
        name: str,
        device: Device[T],
        sink: deque[T],
        maxsize: int,
        on_drop: Callable[[], None],
    ) -> None:
        self.name = name
        self.device = device
        self.sink = sink
        self.maxsize = maxsize
        self._on_drop = on_drop
        self.errors = 0
        self._failing = 0
        """Errors since the last record: the first is a warning, the rest debug."""

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def join(self, timeout: float) -> None:
        pass

    def _read_failed(self, exc: DriverError) -> None:
        # The driver reconnects by itself: logged, counted, and the reading goes on.
        self.errors += 1
        self._failing += 1
        level = logging.WARNING if self._failing == 1 else logging.DEBUG
        log.log(level, "%s: %s", self.device.kind, exc)

    def _put(self, rec: T) -> bool:
        """``rec`` into the sink (True), or dropped and counted when the sink is full."""
        if self._failing:
            log.info("%s: records again after %d read errors", self.device.kind, self._failing)
            self._failing = 0
        if len(self.sink) < self.maxsize:
            self.sink.append(rec)
            return True
        self._on_drop()
        return False

    def pump(self, timeout_s: float = 0.0) -> int:
        """Move every record the device holds into the sink, waiting up to ``timeout_s`` for
        the first; how many arrived. A driver error ends the pump (the next one tries again)."""
        read = self.device.read
        n = 0
        wait = max(0.0, timeout_s)
        while True:
            try:
                rec = read(timeout=wait)
            except DriverError as exc:
                self._read_failed(exc)
                return n
            if rec is None:
                return n
            wait = 0.0
            n += 1
            self._put(rec)


class Reader(InlineReader[T]):
    """A thread that moves records from a driver into a bounded queue.

    The queue is a ``deque`` with one producer (this thread) and one consumer (the worker):
    ``append`` and ``popleft`` are atomic, so no lock or condition is needed per record (a
    ``queue.Queue`` costs both on each side, thousands of times a second). The bound is checked
    before appending; the consumer only ever shortens the deque, so it is never exceeded.
    """

    def __init__(
        self,
        name: str,
        device: Device[T],
        sink: deque[T],
        maxsize: int,
        on_drop: Callable[[], None],
        on_fail: Callable[[BaseException], None],
        signal: threading.Event | None = None,
    ) -> None:
        super().__init__(name, device, sink, maxsize, on_drop)
        self.signal = signal
        self._on_fail = on_fail
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"reader-{name}", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float) -> None:
        self.thread.join(timeout)

    def _run(self) -> None:
        name_os_thread(self.thread.name)
        read, signal = self.device.read, self.signal
        try:
            while not self._stop.is_set():
                try:
                    rec = read(timeout=0.05)
                except DriverError as exc:
                    self._read_failed(exc)
                    self._stop.wait(0.1)  # back off a little
                    continue
                if rec is not None and self._put(rec) and signal is not None:
                    if not signal.is_set():
                        signal.set()  # (set() takes a lock and notifies even when set)
        except BaseException as exc:
            log.exception("%s reader failed", self.device.kind)
            self._on_fail(exc)
