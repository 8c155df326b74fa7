"""The transports of a simulated sensor, as the device sees them: UDP, a TCP server, a pty.

A link queues the wire units the sensor sends (counting them in the sensor's statistics) and
pushes them out when the sensor loop flushes it; stream links (TCP, pty) buffer, a serial one
throttled to its baud rate. :meth:`Link.go_down` and :meth:`Link.come_back` make the device
vanish and return (:meth:`~.sensors.SimulatedSensor.disconnect`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import selectors
import socket
import time
import tty
from collections.abc import Callable
from typing import Any

__all__ = ["Link", "PtyLink", "StreamLink", "TcpLink", "UdpLink"]

log = logging.getLogger(__name__)


class Link:
    """A transport as the device sees it. ``send`` queues bytes; ``flush`` pushes them out."""

    connected = True

    def __init__(self, stats: dict[str, int]) -> None:
        self.stats = stats
        self.down_until_ns = 0

    def register(self, sel: selectors.BaseSelector) -> None:
        """Register readable file objects with ``data`` = a callable handling the event."""

    def send(self, unit: bytes) -> None:
        raise NotImplementedError

    def flush(self, now_ns: int) -> None:
        """Push queued bytes out (stream transports)."""

    def wants_write(self) -> bool:
        return False

    def go_down(self, sel: selectors.BaseSelector) -> None:
        """Disconnect (until :meth:`come_back`)."""

    def come_back(self, sel: selectors.BaseSelector) -> None:
        """Reconnect after :meth:`go_down`."""

    def endpoint(self) -> dict[str, Any]:
        return {}

    def close(self) -> None:
        pass


class UdpLink(Link):
    def __init__(self, stats: dict[str, int], host: str, target: tuple[str, int]) -> None:
        super().__init__(stats)
        self.target = target
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
        self.sock.bind((host, 0))
        self.sock.setblocking(False)
        self.up = True

    def send(self, unit: bytes) -> None:
        if not self.up:
            self.stats["unsent"] += 1
            return
        try:
            self.sock.sendto(unit, self.target)
            self.stats["units_sent"] += 1
        except (BlockingIOError, ConnectionRefusedError):
            # Nobody listening (ICMP port unreachable) or the socket buffer is full: like a
            # real sensor, the datagram is simply gone.
            self.stats["unsent"] += 1
        except OSError as exc:
            log.debug("UDP send failed: %s", exc)
            self.stats["unsent"] += 1

    def go_down(self, sel: selectors.BaseSelector) -> None:
        self.up = False

    def come_back(self, sel: selectors.BaseSelector) -> None:
        self.up = True

    def endpoint(self) -> dict[str, Any]:
        host, port = self.sock.getsockname()[:2]
        return {"host": host, "port": port, "target": self.target}

    def close(self) -> None:
        self.sock.close()


class StreamLink(Link):
    """Shared output buffering of TCP and pty links."""

    max_pending = 8 << 20

    def __init__(self, stats: dict[str, int]) -> None:
        super().__init__(stats)
        self.pending = bytearray()
        self.on_data: Callable[[bytes], None] = lambda data: None
        self.on_connect: Callable[[], None] = lambda: None

    @property
    def connected(self) -> bool:  # type: ignore[override]
        return self._out_fd() is not None

    def _out_fd(self) -> int | None:
        raise NotImplementedError

    def _budget(self, now_ns: int) -> int:
        return 1 << 30

    def _spend(self, n: int) -> None:
        pass

    def send(self, unit: bytes) -> None:
        if not self.connected:
            self.stats["unsent"] += 1
            return
        if len(self.pending) > self.max_pending:
            self.stats["tx_overflow"] += 1
            return
        self.pending += unit
        self.stats["units_sent"] += 1

    def send_now(self, data: bytes) -> None:
        """Command replies: queued ahead of nothing, never subject to faults."""
        if self.connected:
            self.pending += data

    def wants_write(self) -> bool:
        return bool(self.pending)

    def flush(self, now_ns: int) -> None:
        fd = self._out_fd()
        if fd is None:
            self.pending.clear()
            return
        while self.pending:
            budget = self._budget(now_ns)
            if budget <= 0:
                return
            try:
                with memoryview(self.pending) as view, view[: min(budget, 1 << 20)] as part:
                    n = self._write(part)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.debug("stream write failed: %s", exc)
                self._lost()
                return
            self._spend(n)
            del self.pending[:n]

    def _write(self, data: memoryview) -> int:
        raise NotImplementedError

    def _lost(self) -> None:
        self.pending.clear()


class TcpLink(StreamLink):
    def __init__(self, stats: dict[str, int], host: str, port: int) -> None:
        super().__init__(stats)
        self.host = host
        self.listener: socket.socket | None = None
        self.client: socket.socket | None = None
        self.sel: selectors.BaseSelector | None = None
        self._listen(port)

    def _listen(self, port: int) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.host, port))
        s.listen(2)
        s.setblocking(False)
        self.listener = s
        self.port = s.getsockname()[1]

    def register(self, sel: selectors.BaseSelector) -> None:
        self.sel = sel
        if self.listener is not None:
            sel.register(self.listener, selectors.EVENT_READ, self._accept)

    def _accept(self) -> None:
        assert self.listener is not None
        try:
            conn, _ = self.listener.accept()
        except BlockingIOError:
            return
        # One client at a time, as on the devices: a new connection replaces the old one.
        self._drop_client()
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.client = conn
        self.stats["clients"] += 1
        assert self.sel is not None
        self.sel.register(conn, selectors.EVENT_READ, self._read)
        self.on_connect()

    def _read(self) -> None:
        if self.client is None:
            return
        try:
            data = self.client.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop_client()
            return
        self.on_data(data)

    def _drop_client(self) -> None:
        if self.client is not None:
            if self.sel is not None:
                with contextlib.suppress(KeyError, ValueError):
                    self.sel.unregister(self.client)
            self.client.close()
            self.client = None
        self.pending.clear()

    def _lost(self) -> None:
        self._drop_client()

    def _out_fd(self) -> int | None:
        return None if self.client is None else self.client.fileno()

    def _write(self, data: memoryview) -> int:
        assert self.client is not None
        return self.client.send(data)

    def go_down(self, sel: selectors.BaseSelector) -> None:
        self._drop_client()
        if self.listener is not None:
            with contextlib.suppress(KeyError, ValueError):
                sel.unregister(self.listener)
            self.listener.close()
            self.listener = None

    def come_back(self, sel: selectors.BaseSelector) -> None:
        self._listen(self.port)
        self.register(sel)

    def endpoint(self) -> dict[str, Any]:
        return {"host": self.host, "port": self.port}

    def close(self) -> None:
        self._drop_client()
        if self.listener is not None:
            self.listener.close()
            self.listener = None


class PtyLink(StreamLink):
    max_pending = 1 << 20

    def __init__(self, stats: dict[str, int], baud: int | None) -> None:
        super().__init__(stats)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # binary link: no echo, no newline translation
        self.path = os.ttyname(self.slave)
        os.set_blocking(self.master, False)
        self.bytes_per_s = None if baud is None else baud / 10.0
        self._credit = 0.0
        self._credit_t = time.monotonic_ns()
        self.up = True

    def register(self, sel: selectors.BaseSelector) -> None:
        sel.register(self.master, selectors.EVENT_READ, self._read)

    def _read(self) -> None:
        try:
            data = os.read(self.master, 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return
        if data and self.up:
            self.on_data(data)

    def _out_fd(self) -> int | None:
        return self.master if self.up else None

    def _budget(self, now_ns: int) -> int:
        if self.bytes_per_s is None:
            return 1 << 30
        self._credit = min(
            self._credit + (now_ns - self._credit_t) * 1e-9 * self.bytes_per_s,
            max(4096.0, 0.01 * self.bytes_per_s),
        )
        self._credit_t = now_ns
        return int(self._credit)

    def _spend(self, n: int) -> None:
        if self.bytes_per_s is not None:
            self._credit -= n

    def _write(self, data: memoryview) -> int:
        return os.write(self.master, data)

    def go_down(self, sel: selectors.BaseSelector) -> None:
        self.up = False
        self.pending.clear()

    def come_back(self, sel: selectors.BaseSelector) -> None:
        self.up = True

    def endpoint(self) -> dict[str, Any]:
        return {"port_path": self.path}

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)
