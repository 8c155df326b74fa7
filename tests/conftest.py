"""Test-wide guards: a test that leaves a thread or a child process behind fails."""

from __future__ import annotations

import multiprocessing
import threading
import time
from collections.abc import Iterator

import pytest

# Threads that libraries start once per process and keep by design (zenoh runtime, etc.).
_ALLOWED_THREAD_PREFIXES = ("pyo3", "zenoh", "tokio", "rx-", "tx-", "acc-", "net-", "app-")


def _foreign_threads(before: set[int]) -> list[threading.Thread]:
    return [
        t
        for t in threading.enumerate()
        if t.ident not in before
        and t.is_alive()
        and not t.name.startswith(_ALLOWED_THREAD_PREFIXES)
    ]


@pytest.fixture(autouse=True)
def no_leaked_threads_or_processes() -> Iterator[None]:
    before = {t.ident for t in threading.enumerate() if t.ident is not None}
    yield
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        left = _foreign_threads(before)
        children = multiprocessing.active_children()
        if not left and not children:
            return
        time.sleep(0.05)
    left = _foreign_threads(before)
    children = multiprocessing.active_children()
    for c in children:
        c.kill()
    names = [t.name for t in left] + [f"process {c.pid}" for c in children]
    if names:
        pytest.fail(f"test left running: {', '.join(names)}")
