"""Publishing aligned batches from a thread of their own.

A zenoh put of a 10 kHz tick's batch (100 profiles, 2.6 MB) costs the calling thread 0.5-0.8 ms
of CPU (zenoh serialises and queues it; measured 2026-11-26), 5-8 us per profile: as much as
aligning it. zenoh's put runs without the GIL (a Python thread spinning beside a thread that
puts without pause keeps 96 % of its speed), so from a thread of its own it runs on another core
while the worker reads, pairs and aligns the next tick. Batches are handed over in order through
a bounded queue; a full queue makes the worker wait (back-pressure: the overload shedder then
sees the longer ticks and sheds, ``overload.py``).

Counters stay exact: a batch handed over counts as *publishing* (pending) until its put returns,
then as published, both changed under the pipeline's counter lock.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.daemon.service.instruments import StepCpu
from wristscan.daemon.service.readers import name_os_thread

__all__ = ["Outgoing", "Publisher"]

log = logging.getLogger(__name__)


@dataclass
class Outgoing:
    """One aligned batch on its way out: the WSC1 payload and what the pose stream and the
    latency figures need."""

    cloud: Any
    """A ``wsc1.Wsc1Frame`` (or what the publish callable accepts)."""
    t_first_ns: int
    t_last_ns: int
    n_profiles: int
    n_points: int
    frame: str
    exposure_ns: NDArray[np.int64]
    flange2base: NDArray[np.float64]
    sensor2frame: NDArray[np.float64]
    arrival_ns: NDArray[np.int64] | None
    tick_ns: int


class Publisher:
    """A thread that publishes :class:`Outgoing` batches in order (see the module docstring).

    ``put(item) -> None`` does the publishing (the cloud, then its poses); ``done(item)`` is
    called after it, ``fail(exc)`` if it raises. Not started, :meth:`submit` publishes inline.
    """

    def __init__(
        self,
        put: Callable[[Outgoing], None],
        done: Callable[[Outgoing], None],
        fail: Callable[[BaseException], None],
        depth: int = 8,
    ) -> None:
        self._put = put
        self._done = done
        self._fail = fail
        self.depth = max(1, int(depth))
        self._q: deque[Outgoing] = deque()
        self._cv = threading.Condition()
        self._closing = False
        self._thread: threading.Thread | None = None
        self.cpu = StepCpu()
        """The publishing thread's CPU time (ns)."""
        self.waited_s = 0.0
        """Time the worker waited for room in the queue."""

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="publisher", daemon=True)
        self._thread.start()

    def submit(self, item: Outgoing) -> None:
        """Queue ``item`` (waiting while the queue is full), or publish it now if not started."""
        if self._thread is None:
            with self.cpu:
                self._put(item)
            self._done(item)
            return
        with self._cv:
            if len(self._q) >= self.depth:
                t0 = time.monotonic()
                while len(self._q) >= self.depth and self._thread.is_alive():
                    self._cv.wait(0.1)
                self.waited_s += time.monotonic() - t0
            self._q.append(item)
            self._cv.notify_all()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Publish what is queued, then end the thread."""
        if self._thread is None:
            return
        with self._cv:
            self._closing = True
            self._cv.notify_all()
        self._thread.join(timeout_s)
        self._thread = None
        self._closing = False

    def _run(self) -> None:
        name_os_thread("publisher")
        try:
            while True:
                with self._cv:
                    while not self._q and not self._closing:
                        self._cv.wait()
                    if not self._q:
                        return
                    item = self._q[0]
                with self.cpu:
                    self._put(item)
                with self._cv:
                    self._q.popleft()
                    self._cv.notify_all()
                self._done(item)
        except BaseException as exc:
            log.exception("publishing failed")
            self._fail(exc)
