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


class Reader(Generic[T]):
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
        self.device = device
        self.signal = signal
        self.sink = sink
        self.maxsize = maxsize
        self._on_drop = on_drop
        self._on_fail = on_fail
        self._stop = threading.Event()
        self.errors = 0
        self.thread = threading.Thread(target=self._run, name=f"reader-{name}", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float) -> None:
        self.thread.join(timeout)

    def _run(self) -> None:
        name_os_thread(self.thread.name)
        sink, maxsize, read, signal = self.sink, self.maxsize, self.device.read, self.signal
        failing = 0  # errors since the last record: the first is a warning, the rest debug
        try:
            while not self._stop.is_set():
                try:
                    rec = read(timeout=0.05)
                except DriverError as exc:
                    # The driver reconnects by itself; back off a little and keep going.
                    self.errors += 1
                    failing += 1
                    level = logging.WARNING if failing == 1 else logging.DEBUG
                    log.log(level, "%s: %s", self.device.kind, exc)
                    self._stop.wait(0.1)
                    continue
                if rec is None:
                    continue
                if failing:
                    log.info("%s: records again after %d read errors", self.device.kind, failing)
                    failing = 0
                if len(sink) < maxsize:
                    sink.append(rec)
                    if signal is not None and not signal.is_set():
                        signal.set()  # (set() takes a lock and notifies even when set)
                else:
                    self._on_drop()
        except BaseException as exc:
            log.exception("%s reader failed", self.device.kind)
            self._on_fail(exc)


class InlineReader(Generic[T]):
    """A device read by the worker itself at each tick, for drivers whose records are stamped
    on receipt by a process of their own (``stamped_on_receipt``, the UR driver's receive
    child): reading them late changes no time, and a thread woken for every record (500 a
    second from a UR controller, each costing a wake-up, two polls and the GIL) is saved.
    :class:`Reader`'s interface (``start``, ``stop``, ``join`` do nothing) plus :meth:`pump`."""

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

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def join(self, timeout: float) -> None:
        pass

    def pump(self, timeout_s: float = 0.0) -> int:
        """Move every record the device holds into the sink, waiting up to ``timeout_s`` for
        the first; how many arrived. A driver error is logged as the reader thread logs it
        (the driver reconnects by itself) and ends the pump."""
        sink, maxsize, read = self.sink, self.maxsize, self.device.read
        n = 0
        wait = max(0.0, timeout_s)
        while True:
            try:
                rec = read(timeout=wait)
            except DriverError as exc:
                self.errors += 1
                self._failing += 1
                level = logging.WARNING if self._failing == 1 else logging.DEBUG
                log.log(level, "%s: %s", self.device.kind, exc)
                return n
            if rec is None:
                break
            self._failing = 0
            wait = 0.0
            n += 1
            if len(sink) < maxsize:
                sink.append(rec)
            else:
                self._on_drop()
        return n
