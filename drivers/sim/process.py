"""A simulated device running in a spawned process of its own, driven over a pipe.

The child calls its target with the child end of the pipe and answers ``("ready", endpoint)``
once it listens (or ``("error", text)``); ``("stop",)`` ends it. ``stop`` is idempotent and
kills a child that does not end in time, so tests never leave processes behind.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any, Self

__all__ = ["SimProcess"]


class SimProcess:
    """Base of the simulated devices' parent-side handles (a context manager)."""

    process_name = "sim-device"

    def __init__(self) -> None:
        self.endpoint: dict[str, Any] = {}
        self._proc: Any = None
        self._conn: Connection | None = None

    def _target(self) -> tuple[Callable[..., None], tuple[Any, ...]]:
        """The child's function and its arguments before the pipe end."""
        raise NotImplementedError

    def start(self, timeout_s: float = 30.0) -> Self:
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        fn, args = self._target()
        self._proc = ctx.Process(
            target=fn, args=(*args, child), name=self.process_name, daemon=True
        )
        self._proc.start()
        child.close()
        self._conn = parent
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
        return self

    def stop(self) -> None:
        if self._proc is None:
            return
        try:
            if self._conn is not None:
                self._conn.send(("stop",))
        except (BrokenPipeError, OSError):
            pass
        self._proc.join(timeout=5)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=5)
        if self._conn is not None:
            self._conn.close()
        self._proc = None
        self._conn = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
