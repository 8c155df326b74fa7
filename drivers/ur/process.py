"""Child processes of the UR driver, and the pipe between them and the caller's process.

Why a module of its own: the receive child (:mod:`.receive_child`), the control child
(:mod:`.control`) and the caller's side (:mod:`.robot`) share one way of starting a child, of
stopping it, and of talking over its pipe; the simulated devices (``drivers/sim``) start and stop
their processes the same way (:func:`spawn_child`, :func:`stop_child`).

Messages from a child start with a tag byte: :data:`TAG_ROWS` (packed state rows) or
:data:`TAG_OBJ` (a pickled tuple: ``("state", name, info)``, ``("beat", stats)``,
``("log", level, text)``, ``("reply", id, status, payload)``). The caller asks a receive child to
end with :data:`CMD_STOP`; every child also ends when its pipe reaches end-of-file.

Inside a child, :func:`child_setup` forwards the child's logging, and ur_rtde's console output
(:class:`OutputPump`), to the caller's process as ``"log"`` messages.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import pickle
import re
import select
import sys
import threading
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

__all__ = [
    "CHILD_LOG",
    "CMD_STOP",
    "TAG_OBJ",
    "TAG_ROWS",
    "ChildLink",
    "ForwardHandler",
    "OutputPump",
    "child_setup",
    "recv_obj",
    "spawn_child",
    "stop_child",
    "stop_received",
    "wait_or_stop",
]

CHILD_LOG = logging.getLogger("wristscan.drivers.ur.robot.ur_rtde")
"""Where the caller's process logs what its children (and ur_rtde in them) reported."""

TAG_ROWS = b"D"
TAG_OBJ = b"P"
CMD_STOP = b"stop"

# ur_rtde's messages when its link breaks; the control child exits on them (see .robot's doc).
_TROUBLE = re.compile(
    r"Could not receive data|Robot closed the connection|Reconnecting|Could not recover", re.I
)
_WARN_WORDS = re.compile(r"exception|error|fail|could not|lost|disconnect", re.I)


# ============================================================================ start and stop


def spawn_child(
    target: Callable[..., object], args: tuple[Any, ...], name: str
) -> tuple[BaseProcess, Connection]:
    """Start ``target(*args, conn)`` in a daemonic process of the ``"spawn"`` context (a fresh
    interpreter: no threads, locks or sockets inherited from the caller), ``conn`` being the
    child's end of a duplex pipe. Returns the process and the caller's end of the pipe."""
    ctx = mp.get_context("spawn")
    parent_conn, child_conn = ctx.Pipe(duplex=True)
    proc = ctx.Process(target=target, args=(*args, child_conn), name=name, daemon=True)
    try:
        proc.start()
    except BaseException:
        # Nothing started: the caller has no handle to stop, so nothing may be left open.
        parent_conn.close()
        raise
    finally:
        child_conn.close()
    return proc, parent_conn


def stop_child(
    proc: BaseProcess | None,
    conn: Connection | None,
    message: bytes | None = None,
    wait_s: float = 5.0,
) -> None:
    """End a child: send ``message`` as is (``Connection.send_bytes``; for a child that reads
    with ``recv()``, pass a pickle), close the pipe (the child ends on end-of-file too), wait
    ``wait_s`` seconds, then terminate it, then kill it. Either argument may be None."""
    if conn is not None:
        if message is not None:
            with contextlib.suppress(OSError, ValueError):
                conn.send_bytes(message)
        conn.close()
    if proc is not None:
        proc.join(timeout=wait_s)
        if proc.is_alive():
            proc.terminate()
            proc.join(timeout=2.0)
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=2.0)


def recv_obj(conn: Connection) -> tuple[Any, ...]:
    """One message from a child (tag byte, then a pickle)."""
    data = conn.recv_bytes()
    if data[:1] != TAG_OBJ:
        raise OSError(f"unexpected message from the control process: {data[:16]!r}")
    obj = pickle.loads(memoryview(data)[1:])
    assert isinstance(obj, tuple)
    return obj


# ============================================================================ inside a child


class ChildLink:
    """The child's end of the pipe: thread-safe sends, optionally without blocking."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.lock = threading.Lock()
        self.broken = False

    def send_bytes(self, data: bytes) -> None:
        with self.lock:
            try:
                self.conn.send_bytes(data)
            except OSError:
                self.broken = True

    def send_obj(self, obj: object) -> None:
        self.send_bytes(TAG_OBJ + pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))

    def writable(self) -> bool:
        try:
            _, w, _ = select.select([], [self.conn.fileno()], [], 0)
        except (OSError, ValueError):
            self.broken = True
            return False
        return bool(w)


class ForwardHandler(logging.Handler):
    def __init__(self, link: ChildLink) -> None:
        super().__init__()
        self.link = link

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self.link.send_obj(("log", record.levelno, self.format(record)))


class OutputPump:
    """ur_rtde's console output (C++ ``std::cout``/``std::cerr``, fds 1 and 2) redirected into a
    pipe and forwarded line by line to the parent as log messages; link-failure messages set
    ``trouble``. A thread keeps the pipe from filling up (ur_rtde would block on it);
    :meth:`drain` processes what is pending right now, for decisions that must not race with
    ur_rtde's reports."""

    def __init__(self, link: ChildLink, trouble: threading.Event | None) -> None:
        self.link = link
        self.trouble = trouble
        sys.stdout.flush()
        sys.stderr.flush()
        r, w = os.pipe()
        os.dup2(w, 1)
        os.dup2(w, 2)
        os.close(w)
        os.set_blocking(r, False)
        self.fd = r
        self.buf = b""
        self.lock = threading.Lock()
        threading.Thread(target=self._run, name="ur-rtde-output", daemon=True).start()

    def _run(self) -> None:
        while True:
            select.select([self.fd], [], [])
            self.drain()

    def drain(self) -> None:
        with self.lock:
            while True:
                try:
                    data = os.read(self.fd, 65536)
                except BlockingIOError:
                    break
                if not data:
                    break
                self.buf += data
            *lines, self.buf = self.buf.split(b"\n")
            # Inside the lock: when drain() returns, every complete line written before the
            # call has been acted on, whichever thread read it.
            for raw in lines:
                text = raw.decode("utf-8", errors="replace").strip()
                if not text:
                    continue
                if self.trouble is not None and _TROUBLE.search(text):
                    self.trouble.set()
                level = logging.WARNING if _WARN_WORDS.search(text) else logging.INFO
                self.link.send_obj(("log", level, text))


def child_setup(
    link: ChildLink, log_level: int, trouble: threading.Event | None = None
) -> OutputPump:
    """Forward the child's logging and ur_rtde's console output to the parent."""
    root = logging.getLogger()
    root.handlers[:] = [ForwardHandler(link)]
    root.setLevel(log_level)
    return OutputPump(link, trouble)


def stop_received(conn: Connection) -> bool:
    """True once the parent asked to stop or went away."""
    try:
        if not conn.poll(0):
            return False
        return conn.recv_bytes() == CMD_STOP
    except (EOFError, OSError):
        return True


def wait_or_stop(conn: Connection, seconds: float) -> bool:
    """Sleep up to ``seconds``; True when a stop request (or EOF) arrived meanwhile."""
    try:
        if conn.poll(seconds):
            return conn.recv_bytes() == CMD_STOP
    except (EOFError, OSError):
        return True
    return False
