"""sd_notify over real AF_UNIX datagram sockets (a path and an abstract name), and the watchdog."""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from wristscan.daemon.service.notify import Notifier, Watchdog, watchdog_interval_s


class Listener:
    """What systemd does: a bound datagram socket collecting the messages with arrival times."""

    def __init__(self, address: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)

    def recv(self, timeout_s: float = 2.0) -> str:
        self.sock.settimeout(timeout_s)
        return self.sock.recv(4096).decode()

    def drain(self, duration_s: float) -> list[tuple[float, str]]:
        """Messages arriving within ``duration_s`` (monotonic arrival time, text)."""
        out: list[tuple[float, str]] = []
        end = time.monotonic() + duration_s
        while (left := end - time.monotonic()) > 0:
            self.sock.settimeout(left)
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                break
            out.append((time.monotonic(), data.decode()))
        return out

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    for name in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


@pytest.fixture
def path_listener(tmp_path: Path, clean_env: pytest.MonkeyPatch) -> Iterator[Listener]:
    address = str(tmp_path / "notify.sock")
    listener = Listener(address)
    clean_env.setenv("NOTIFY_SOCKET", address)
    yield listener
    listener.close()


@pytest.fixture
def abstract_listener(clean_env: pytest.MonkeyPatch) -> Iterator[Listener]:
    name = f"wristscan-test-{uuid.uuid4().hex}"
    listener = Listener("\0" + name)
    clean_env.setenv("NOTIFY_SOCKET", "@" + name)
    yield listener
    listener.close()


def _exchange(listener: Listener) -> None:
    with Notifier() as n:
        assert n.enabled
        assert "NOTIFY_SOCKET" not in os.environ
        assert n.ready("devices open")
        assert listener.recv() == "READY=1\nSTATUS=devices open"
        assert n.status("12 profiles/s\npaired 99 %")
        assert listener.recv() == "STATUS=12 profiles/s paired 99 %"
        assert n.watchdog()
        assert listener.recv() == "WATCHDOG=1"
        before = time.monotonic_ns() // 1000
        assert n.reloading()
        after = time.monotonic_ns() // 1000
        first, second = listener.recv().split("\n")
        assert first == "RELOADING=1"
        key, value = second.split("=")
        assert key == "MONOTONIC_USEC" and before <= int(value) <= after
        assert n.stopping("shutting down")
        assert listener.recv() == "STOPPING=1\nSTATUS=shutting down"
        assert n.extend_timeout(2.5)
        assert listener.recv() == "EXTEND_TIMEOUT_USEC=2500000"
        assert n.n_sent == 6 and n.n_failed == 0
    assert not n.enabled and n.ready() is False  # closed: a no-op


def test_messages_reach_a_path_socket(path_listener: Listener) -> None:
    _exchange(path_listener)


def test_messages_reach_an_abstract_socket(abstract_listener: Listener) -> None:
    _exchange(abstract_listener)


def test_no_op_without_notify_socket(clean_env: pytest.MonkeyPatch) -> None:
    n = Notifier()
    assert not n.enabled
    assert n.ready() is False and n.watchdog() is False and n.status("x") is False
    assert n.watchdog_interval_s() is None
    n.close()


def test_unsupported_address_is_reported(
    clean_env: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    clean_env.setenv("NOTIFY_SOCKET", "vsock:2:1234")
    with caplog.at_level(logging.WARNING, logger="wristscan.daemon.service.notify"):
        n = Notifier()
    assert not n.enabled
    assert "unsupported NOTIFY_SOCKET" in caplog.text


def test_children_do_not_inherit_the_notify_variables(path_listener: Listener) -> None:
    os.environ["WATCHDOG_USEC"] = "4000000"
    os.environ["WATCHDOG_PID"] = str(os.getpid())
    with Notifier() as n:
        assert n.watchdog_interval_s() == 4.0
        child = subprocess.run(
            [
                sys.executable,
                "-c",
                "import os; print([k for k in os.environ if k in "
                "('NOTIFY_SOCKET', 'WATCHDOG_USEC', 'WATCHDOG_PID')])",
            ],
            capture_output=True,
            text=True,
            timeout=30,
            check=True,
        )
        assert child.stdout.strip() == "[]"


def test_watchdog_interval_from_environment() -> None:
    pid = str(os.getpid())
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000"}) == 10.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": pid}) == 10.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "0"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "ten"}) is None
    assert watchdog_interval_s({}) is None


def test_send_failure_is_logged_once_not_raised(
    tmp_path: Path, clean_env: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    address = str(tmp_path / "gone.sock")
    clean_env.setenv("NOTIFY_SOCKET", address)  # nobody listens there (yet)
    with Notifier() as n, caplog.at_level(logging.DEBUG, logger="wristscan.daemon.service.notify"):
        assert n.ready() is False
        assert n.watchdog() is False
        assert n.status("still trying") is False
        assert n.n_failed == 3
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1
        assert "cannot notify systemd (READY)" in warnings[0].getMessage()
        listener = Listener(address)  # systemd is back
        try:
            assert n.watchdog() is True
            assert listener.recv() == "WATCHDOG=1"
        finally:
            listener.close()
        assert any("go through again" in r.getMessage() for r in caplog.records)


def _wait(predicate: Callable[[], bool], what: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(0.005)


def test_watchdog_pings_at_half_the_interval_only_while_healthy(
    path_listener: Listener, clean_env: pytest.MonkeyPatch
) -> None:
    """Asserted on what happened, not on arrival times a loaded machine stretches: the ticks
    (health checks) keep a fixed schedule and are never early, a ping per healthy tick, none
    while unhealthy (at most the one already decided), pings again from the next tick, none
    after the stop."""
    clean_env.setenv("WATCHDOG_USEC", "200000")  # 0.2 s: pings every 0.1 s
    healthy = threading.Event()
    healthy.set()
    ticks: list[float] = []

    def is_healthy() -> bool:
        ticks.append(time.monotonic())
        return healthy.is_set()

    # Read as they come (a datagram socket queues only 10): the arrivals are counted, not timed.
    got: list[str] = []
    stop = threading.Event()

    def read() -> None:
        path_listener.sock.settimeout(0.05)
        while not stop.is_set():
            try:
                got.append(path_listener.sock.recv(4096).decode())
            except TimeoutError:
                pass

    reader = threading.Thread(target=read, name="test-notify-reader")
    reader.start()
    try:
        _watch(ticks, healthy, is_healthy, got)
    finally:
        stop.set()
        reader.join()
    assert path_listener.drain(0.25) == []  # none after the stop


def _watch(
    ticks: list[float],
    healthy: threading.Event,
    is_healthy: Callable[[], bool],
    got: list[str],
) -> None:
    with Notifier() as n:
        dog = Watchdog(n, is_healthy)
        assert dog.period_s == pytest.approx(0.1)
        t_start = time.monotonic()
        with dog:
            assert dog.running
            _wait(lambda: dog.n_pings >= 6, "fewer than 6 pings while healthy")
            # The fixed schedule: tick k comes at t_start + k * period or later (never early,
            # whatever the load), and late only by what the machine delays a waking thread: a
            # period of 2 x 0.1 s would be 0.1 s late at the first tick and more at each next.
            lateness = [t - (t_start + k * 0.1) for k, t in enumerate(ticks[:6], start=1)]
            assert min(lateness) >= -0.002, lateness
            assert float(np.median(lateness)) < 0.1, lateness

            healthy.clear()
            pinged = dog.n_pings
            _wait(lambda: dog.n_withheld >= 3, "pings not withheld")
            # At most one ping that was decided when the flag flipped.
            assert dog.n_pings <= pinged + 1

            withheld = dog.n_withheld
            healthy.set()
            pinged = dog.n_pings
            _wait(lambda: dog.n_pings >= pinged + 2, "pings did not resume")
            # Resumed at the next tick: at most one more withheld (decided before the flip).
            assert dog.n_withheld <= withheld + 1
        assert not dog.running  # stopped and joined: nothing more can be sent
        # Every ping sent arrived, once, each a WATCHDOG=1.
        _wait(lambda: len(got) >= dog.n_pings, f"{len(got)} of {dog.n_pings} pings arrived")
        assert got == ["WATCHDOG=1"] * dog.n_pings


def test_watchdog_health_check_exception_withholds_the_ping(
    path_listener: Listener, clean_env: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def broken() -> bool:
        raise RuntimeError("pipeline state unavailable")

    with Notifier() as n, caplog.at_level(logging.ERROR, logger="wristscan.daemon.service.notify"):
        with Watchdog(n, broken, interval_s=0.1) as dog:
            _wait(lambda: dog.n_withheld >= 3, "the health check did not run")
        assert dog.n_pings == 0
        assert path_listener.drain(0.3) == []
    assert "pipeline state unavailable" in caplog.text


def test_watchdog_without_interval_does_nothing(clean_env: pytest.MonkeyPatch) -> None:
    with Notifier() as n:
        dog = Watchdog(n, lambda: True)
        dog.start()
        assert dog.period_s is None and not dog.running
        dog.stop()
    with pytest.raises(ValueError, match="interval_s"):
        Watchdog(n, lambda: True, interval_s=0.0)
