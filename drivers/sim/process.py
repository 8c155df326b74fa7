"""A simulated device running in a spawned process of its own, driven over a pipe.

The child calls its target with the child end of the pipe and answers ``("ready", endpoint)``
once it listens (or ``("error", text)``); ``("stop",)`` ends it. ``stop`` is idempotent and
ends a child that does not stop in time (terminate, then kill), so tests never leave processes
behind. Starting and stopping are the UR driver's
(:func:`~wristscan.drivers.ur.process.spawn_child`,
:func:`~wristscan.drivers.ur.process.stop_child`): one way to run a child, real or simulated.
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, Self

from wristscan.drivers.ur.process import spawn_child, stop_child

__all__ = ["SimProcess"]


class SimProcess:
    """Base of the simulated devices' parent-side handles (a context manager)."""

    process_name = "sim-device"

    def __init__(self) -> None:
        self.endpoint: dict[str, Any] = {}
        self._proc: BaseProcess | None = None
        self._conn: Connection | None = None

    def _target(self) -> tuple[Callable[..., None], tuple[Any, ...]]:
        """The child's function and its arguments before the pipe end."""
        raise NotImplementedError

    def start(self, timeout_s: float = 30.0) -> Self:
        """Spawn the process and wait until it listens (``RuntimeError`` if it does not)."""
        return self.spawn().wait_ready(timeout_s)

    def spawn(self) -> Self:
        """Start the process without waiting for it (several start side by side: most of a
        start is the child's imports); then :meth:`wait_ready`."""
        fn, args = self._target()
        self._proc, self._conn = spawn_child(fn, args, self.process_name)
        return self

    def wait_ready(self, timeout_s: float = 30.0) -> Self:
        """Wait until the spawned process listens; stopped and ``RuntimeError`` if it does not."""
        parent = self._conn
        if parent is None:
            raise RuntimeError(f"{self.process_name} was not spawned")
        if not parent.poll(timeout_s):
            self.stop()
            raise RuntimeError(f"{self.process_name} did not start within {timeout_s:g} s")
        try:
            kind, payload = parent.recv()
        except EOFError:
            kind, payload = "error", "the process exited during start-up"
        if kind != "ready":
            self.stop()
            raise RuntimeError(f"{self.process_name} failed: {payload}")
        self.endpoint = payload
        self._on_ready()
        return self

    def _on_ready(self) -> None:
        """What a device takes from its ``ready`` answer beyond the endpoint."""

    def stop(self) -> None:
        if self._proc is None:
            return
        proc, conn = self._proc, self._conn
        self._proc = None
        self._conn = None
        # The child reads with recv(): the stop message goes as a pickle.
        stop_child(proc, conn, pickle.dumps(("stop",)), wait_s=5.0)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
