"""systemd service notifications (``sd_notify``) and a watchdog that pings only while healthy.

The protocol: newline-separated ``KEY=VALUE`` assignments in one datagram sent over an
``AF_UNIX``/``SOCK_DGRAM`` socket to the address in ``$NOTIFY_SOCKET`` (a path, or an abstract
socket name written with a leading ``@``). Outside systemd (``NOTIFY_SOCKET`` unset) every call is
a no-op. ``WATCHDOG_USEC`` (with ``WATCHDOG_PID``, when set, naming this process) gives the
watchdog timeout: a service must send ``WATCHDOG=1`` more often than that.

The environment variables are removed once read so that child processes (simulated devices,
helpers) do not inherit them and talk to systemd in the service's name.

A notification that cannot be sent never raises into the caller (the daemon must not die because
systemd is slow), but it is logged: the first failure of a run of failures as a warning, the
recovery at info level.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping
from types import TracebackType

__all__ = ["Notifier", "Watchdog", "watchdog_interval_s"]

log = logging.getLogger(__name__)

_SEND_TIMEOUT_S = 0.2


def watchdog_interval_s(environ: Mapping[str, str] | None = None) -> float | None:
    """The watchdog timeout from ``WATCHDOG_USEC`` in seconds, or None when the watchdog is off,
    the value is invalid, or ``WATCHDOG_PID`` names another process."""
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("ignoring invalid WATCHDOG_USEC=%r", usec)
        return None
    if value <= 0:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            log.warning("ignoring invalid WATCHDOG_PID=%r", pid)
            return None
    return value / 1e6


def _address(raw: str) -> str | None:
    if raw.startswith("@"):
        return "\0" + raw[1:]  # Linux abstract namespace
    if raw.startswith("/"):
        return raw
    return None


class Notifier:
    """Sends service state to systemd; a no-op when not started by systemd.

    ``socket_path`` overrides ``$NOTIFY_SOCKET`` (tests). With ``unset_environment`` (default)
    ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` are removed from ``os.environ``
    after reading. Thread-safe; use as a context manager or call :meth:`close`.
    """

    def __init__(self, socket_path: str | None = None, *, unset_environment: bool = True) -> None:
        raw = os.environ.get("NOTIFY_SOCKET") if socket_path is None else socket_path
        self._watchdog_s = watchdog_interval_s()
        if unset_environment:
            for name in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
                os.environ.pop(name, None)
        self._lock = threading.Lock()
        self._failing = False
        self.n_sent = 0
        self.n_failed = 0
        self._addr: str | None = None
        self._sock: socket.socket | None = None
        if raw:
            self._addr = _address(raw)
            if self._addr is None:
                log.warning("unsupported NOTIFY_SOCKET %r: systemd notifications are off", raw)
            else:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                # Bounded: a full receive queue must not hang the caller (counts as a failure).
                self._sock.settimeout(_SEND_TIMEOUT_S)

    @property
    def enabled(self) -> bool:
        """True when notifications go somewhere."""
        return self._sock is not None

    def watchdog_interval_s(self) -> float | None:
        """The watchdog timeout systemd expects pings within (seconds), None when off."""
        return self._watchdog_s

    def notify(self, *assignments: str) -> bool:
        """Send ``KEY=VALUE`` assignments in one datagram; True when sent, False when
        notifications are off or the send failed (logged, never raised)."""
        if self._sock is None or self._addr is None:
            return False
        data = "\n".join(assignments).encode("utf-8", "replace")
        with self._lock:
            if self._sock is None:  # closed meanwhile
                return False
            try:
                self._sock.sendto(data, self._addr)
            except OSError as exc:
                self.n_failed += 1
                if not self._failing:
                    log.warning(
                        "cannot notify systemd (%s): %s; further failures are logged at debug "
                        "level until a notification goes through",
                        ", ".join(a.split("=", 1)[0] for a in assignments),
                        exc,
                    )
                    self._failing = True
                else:
                    log.debug("cannot notify systemd: %s", exc)
                return False
            self.n_sent += 1
            if self._failing:
                log.info("systemd notifications go through again")
                self._failing = False
            return True

    @staticmethod
    def _status(text: str) -> str:
        # A newline would start a new assignment.
        return "STATUS=" + " ".join(text.splitlines())

    def ready(self, status: str | None = None) -> bool:
        """``READY=1``: start-up is complete (devices open, pipeline running)."""
        fields = ["READY=1"] + ([self._status(status)] if status else [])
        return self.notify(*fields)

    def status(self, text: str) -> bool:
        """``STATUS=...``: one line shown by ``systemctl status``."""
        return self.notify(self._status(text))

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: the service is alive and progressing."""
        return self.notify("WATCHDOG=1")

    def reloading(self, status: str | None = None) -> bool:
        """``RELOADING=1`` with ``MONOTONIC_USEC`` (CLOCK_MONOTONIC microseconds); send
        :meth:`ready` when the reload is complete."""
        fields = ["RELOADING=1", f"MONOTONIC_USEC={time.monotonic_ns() // 1000}"]
        return self.notify(*fields, *([self._status(status)] if status else []))

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: shutdown has begun."""
        return self.notify("STOPPING=1", *([self._status(status)] if status else []))

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC``: ask for more time to start or stop (e.g. a slow device)."""
        return self.notify(f"EXTEND_TIMEOUT_USEC={max(0, round(seconds * 1e6))}")

    def close(self) -> None:
        """Close the socket (idempotent); later notifications are no-ops."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class Watchdog:
    """Pings the systemd watchdog at half its timeout while ``is_healthy()`` says the pipeline
    progresses; withholds the ping otherwise, so that systemd restarts a stuck daemon.

    ``interval_s`` overrides the notifier's watchdog timeout (the ping period is half of it).
    Without a timeout, :meth:`start` does nothing. ``is_healthy`` runs in the watchdog thread;
    an exception from it counts as unhealthy (and is logged).
    """

    def __init__(
        self,
        notifier: Notifier,
        is_healthy: Callable[[], bool],
        interval_s: float | None = None,
    ) -> None:
        timeout = notifier.watchdog_interval_s() if interval_s is None else interval_s
        if timeout is not None and not timeout > 0:
            raise ValueError("Watchdog: interval_s must be > 0")
        self.notifier = notifier
        self.is_healthy = is_healthy
        self.period_s: float | None = None if timeout is None else timeout / 2.0
        self.n_pings = 0
        self.n_withheld = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        if self.period_s is None:
            log.debug("no systemd watchdog configured: not pinging")
            return
        if self._thread is not None:
            raise RuntimeError("Watchdog already started")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="wristscan-watchdog", daemon=True)
        self._thread.start()

    def _healthy(self) -> bool:
        try:
            return bool(self.is_healthy())
        except Exception:
            log.exception("watchdog health check raised; counting it as unhealthy")
            return False

    def _run(self) -> None:
        assert self.period_s is not None
        period = self.period_s
        next_t = time.monotonic() + period
        withheld = False
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            # Fixed schedule: a slow health check does not stretch the period.
            next_t += period
            now = time.monotonic()
            if next_t < now:
                next_t = now + period
            if self._healthy():
                self.notifier.watchdog()
                self.n_pings += 1
                if withheld:
                    log.warning("pipeline progresses again: watchdog pings resumed")
                    withheld = False
            else:
                self.n_withheld += 1
                if not withheld:
                    log.error("pipeline not progressing: withholding watchdog pings")
                    withheld = True

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop pinging and join the thread (idempotent)."""
        self._stop.set()
        t = self._thread
        if t is not None:
            t.join(timeout_s)
            if t.is_alive():
                log.error("watchdog thread did not stop within %.1f s", timeout_s)
            else:
                self._thread = None

    def __enter__(self) -> Watchdog:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
