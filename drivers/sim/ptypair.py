"""A linked pair of pseudo-terminals: two device paths that pyserial opens like real ports.

A single pty has one path (the slave) and one file descriptor (the master), and a library such as
pymodbus' serial server insists on opening a port by path. Two ptys whose masters are relayed to
each other give two paths, like a null-modem cable (what ``socat pty,raw pty,raw`` does).
"""

from __future__ import annotations

import logging
import os
import selectors
import threading
import tty

__all__ = ["PtyPair"]

log = logging.getLogger(__name__)


class PtyPair:
    """Two pty slave paths connected back to back; bytes written to one come out of the other."""

    def __init__(self) -> None:
        self._masters: list[int] = []
        self._slaves: list[int] = []
        self.paths: tuple[str, str]
        paths = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no newline translation: a binary link
            self._masters.append(master)
            self._slaves.append(slave)  # held open so the master never sees EOF between clients
            paths.append(os.ttyname(slave))
        self.paths = (paths[0], paths[1])
        self._stop_r, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=self._relay, name="sim-ptypair", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        sel = selectors.DefaultSelector()
        for i, fd in enumerate(self._masters):
            os.set_blocking(fd, False)
            sel.register(fd, selectors.EVENT_READ, i)
        sel.register(self._stop_r, selectors.EVENT_READ, -1)
        try:
            while True:
                for key, _ in sel.select():
                    if key.data == -1:
                        return
                    src = self._masters[key.data]
                    dst = self._masters[1 - key.data]
                    try:
                        data = os.read(src, 65536)
                    except (BlockingIOError, OSError):
                        continue
                    view = memoryview(data)
                    while view:
                        try:
                            n = os.write(dst, view)
                        except BlockingIOError:
                            continue  # the other side's buffer is full: retry until drained
                        view = view[n:]
        finally:
            sel.close()

    def close(self) -> None:
        if self._thread.is_alive():
            os.write(self._stop_w, b"x")
            self._thread.join(timeout=2)
        for fd in (*self._masters, *self._slaves, self._stop_r, self._stop_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._masters, self._slaves = [], []

    def __enter__(self) -> PtyPair:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
