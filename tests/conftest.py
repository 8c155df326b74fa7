"""Test-wide guards: a test that leaves a thread or a child process behind fails.

A thread or child process still running when a test returns is given a generous
``_LEAK_DEADLINE_S`` to end (a driver's reader thread, a simulator process that finishes its
shutdown, all of which end within a second on an idle machine and can take several on a loaded
one); one still running after that is a leak and fails the test. A fixed short window would fail
a sound test on a busy machine; no window at all would miss a thread that never ends. Child
processes already running when the test starts (a module-scoped fixture's simulated cell, which
the fixture stops after the module's last test) are not the test's.

Hypothesis: no per-example deadline and no "too slow" health check, suite-wide; both measure wall
time, which a loaded machine stretches (what a property test checks is its assertions).
"""

from __future__ import annotations

import multiprocessing
import threading
import time
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, settings

# Threads that libraries start once per process and keep by design (zenoh runtime, etc.).
_ALLOWED_THREAD_PREFIXES = ("pyo3", "zenoh", "tokio", "rx-", "tx-", "acc-", "net-", "app-")
_LEAK_DEADLINE_S = 30.0

settings.register_profile("wristscan", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("wristscan")


def _foreign_threads(before: set[int]) -> list[threading.Thread]:
    return [
        t
        for t in threading.enumerate()
        if t.ident not in before
        and t.is_alive()
        and not t.name.startswith(_ALLOWED_THREAD_PREFIXES)
    ]


def _new_children(kept: set[int | None]) -> list[multiprocessing.process.BaseProcess]:
    return [c for c in multiprocessing.active_children() if c.pid not in kept]


@pytest.fixture(autouse=True)
def no_leaked_threads_or_processes() -> Iterator[None]:
    before = {t.ident for t in threading.enumerate() if t.ident is not None}
    # Children already running (a module-scoped fixture's simulated cell, which it stops itself
    # after the module's last test) are not this test's.
    kept = {c.pid for c in multiprocessing.active_children()}
    yield
    # Wait for each to end (join, not a polling window), up to one shared deadline; again while
    # one that was ending started another.
    deadline = time.monotonic() + _LEAK_DEADLINE_S
    while time.monotonic() < deadline:
        pending = [*_foreign_threads(before), *_new_children(kept)]
        if not pending:
            break
        for x in pending:
            x.join(max(0.0, deadline - time.monotonic()))
    left = _foreign_threads(before)
    children = _new_children(kept)
    for c in children:
        c.kill()
    for c in children:
        c.join(5.0)
    names = [t.name for t in left] + [f"process {c.pid} ({c.name})" for c in children]
    if names:
        pytest.fail(
            f"test left running {_LEAK_DEADLINE_S:.0f} s after it ended: {', '.join(names)}"
        )
