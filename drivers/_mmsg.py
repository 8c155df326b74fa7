"""``recvmmsg(2)`` for the UDP drivers: every waiting datagram in one system call.

Python's socket module receives one datagram per call (``recvmsg_into``: about 2 µs of
interpreter and system-call overhead each, as much as the kernel's own work on a 4 kB
datagram). Linux's ``recvmmsg`` fills many at once; it is reached through :mod:`ctypes` (the C
library's own function, no compiled code of ours), with the message headers, the source
addresses and the ancillary data (``SO_TIMESTAMPNS`` stamps) laid out as numpy arrays, so that
lengths, sources and stamps of a whole pass are read as arrays.

Each datagram gets a row of :data:`ROW_BYTES` (64 kB: the largest UDP payload fits, nothing is
ever truncated). :func:`available` is False off Linux, on other than 64-bit C layouts, or when
the C library lacks the call: the drivers then receive with ``recvmsg_into``.
"""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
import select
import socket
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import jit

__all__ = ["ROW_BYTES", "MmsgReceiver", "available"]

ROW_BYTES = 65536
_MSG_DONTWAIT = 0x40
_SCM_TIMESTAMPNS = 35  # Linux asm-generic (SO_TIMESTAMPNS)
_NAME_BYTES = 16  # struct sockaddr_in
_CMSG_BYTES = socket.CMSG_SPACE(16)  # one struct timespec

_MMSGHDR = np.dtype(
    [
        ("name", "<u8"),
        ("namelen", "<u4"),
        ("pad0", "<u4"),
        ("iov", "<u8"),
        ("iovlen", "<u8"),
        ("control", "<u8"),
        ("controllen", "<u8"),
        ("flags", "<i4"),
        ("pad1", "<u4"),
        ("len", "<u4"),
        ("pad2", "<u4"),
    ]
)
"""``struct mmsghdr`` (a ``struct msghdr`` and the received length) on 64-bit Linux."""
_CMSG = np.dtype(
    [("len", "<u8"), ("level", "<i4"), ("type", "<i4"), ("sec", "<i8"), ("nsec", "<i8")]
)
"""A ``struct cmsghdr`` holding one ``struct timespec``."""
_LEVEL_AT = 8
"""Offset of ``level`` (then ``type``) in :data:`_CMSG`."""
_LEVEL_TYPE = np.array([socket.SOL_SOCKET, _SCM_TIMESTAMPNS], "<i4").view("<i8")[0]
"""``level`` and ``type`` of a receipt stamp's control message, read as one int64."""


def _load() -> Callable[..., int] | None:
    little = sys.byteorder == "little"
    if not sys.platform.startswith("linux") or ctypes.sizeof(ctypes.c_void_p) != 8 or not little:
        return None
    try:
        fn: Any = ctypes.CDLL(None, use_errno=True).recvmmsg
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_void_p]
    fn.restype = ctypes.c_int
    f: Callable[..., int] = fn
    return f


_recvmmsg = _load()


_checked: list[bool] = []


def available() -> bool:
    """``recvmmsg`` can be used here: the call exists and, tried once on a loopback socket,
    hands back the datagrams, lengths, source and stamp as this module lays them out."""
    if not _checked:
        ok = _recvmmsg is not None and _MMSGHDR.itemsize == 64 and _CMSG.itemsize == _CMSG_BYTES
        _checked.append(ok and _self_test())
    return _checked[0]


def _self_test() -> bool:
    """Two datagrams to a loopback socket of our own, received in one call and read back."""
    sent = [b"wristscan", b"recvmmsg!!"]
    try:
        with (
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx,
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx,
        ):
            rx.bind(("127.0.0.1", 0))
            rx.setsockopt(socket.SOL_SOCKET, _SCM_TIMESTAMPNS, 1)
            for payload in sent:
                tx.sendto(payload, rx.getsockname())
            select.select([rx], [], [], 1.0)
            time.sleep(0.005)  # loopback queues both at once; a loaded machine may lag
            r = MmsgReceiver(4)
            n = r.receive(rx.fileno(), 4)
            if n != len(sent):
                return False
            lengths = r.lengths(n).tolist()
            got = [bytes(r.buf[k * ROW_BYTES : k * ROW_BYTES + lengths[k]]) for k in range(n)]
            sources = {socket.inet_ntoa(a.tobytes()) for a in r.sources(n)}
            stamps = r.realtime_stamps(n)
    except OSError:
        return False
    return (
        got == sent
        and sources == {"127.0.0.1"}
        and stamps is not None
        and bool(np.all(np.abs(stamps - time.time_ns()) < 60_000_000_000))
    )


class MmsgReceiver:
    """Receives up to ``rows`` datagrams per call into :attr:`buf`, datagram ``i`` at byte
    ``i * ROW_BYTES``; its length, source address and kernel stamp read back as arrays."""

    def __init__(self, rows: int) -> None:
        if _recvmmsg is None:
            raise OSError("recvmmsg is not available here")
        self.rows = int(rows)
        # Anonymous memory: pages are only allocated where datagrams land (a few kB per row),
        # not the rows' full 64 kB.
        self.buf = mmap.mmap(-1, self.rows * ROW_BYTES)
        self._data = np.frombuffer(self.buf, np.uint8)  # pins the buffer (never resized)
        self._names = np.zeros((self.rows, _NAME_BYTES), np.uint8)
        self._ctrl = np.zeros(self.rows, _CMSG)
        self._iov = np.zeros((self.rows, 2), np.uint64)
        k = np.arange(self.rows, dtype=np.uint64)
        self._iov[:, 0] = self._data.ctypes.data + k * np.uint64(ROW_BYTES)
        self._iov[:, 1] = ROW_BYTES
        hdr = np.zeros(self.rows, _MMSGHDR)
        hdr["name"] = self._names.ctypes.data + k * np.uint64(_NAME_BYTES)
        hdr["iov"] = self._iov.ctypes.data + k * np.uint64(16)
        hdr["iovlen"] = 1
        hdr["control"] = self._ctrl.ctypes.data + k * np.uint64(_CMSG_BYTES)
        self._hdr = hdr
        self.row_numbers = np.arange(self.rows, dtype=np.int64)
        """0 .. rows - 1, for the passes' row arrays (views: not to be written)."""
        self._hdr_ptr = ctypes.c_void_p(hdr.ctypes.data)
        # The fields read or reset at every call, as views made once (a structured array's
        # field lookup costs more than the rows' values).
        self._namelen, self._controllen, self._len = hdr["namelen"], hdr["controllen"], hdr["len"]
        ctrl = self._ctrl
        self._sec, self._nsec = ctrl["sec"], ctrl["nsec"]
        self._ctrl_lt = np.ndarray((self.rows,), "<i8", ctrl, _LEVEL_AT, (_CMSG.itemsize,))

    def receive(self, fd: int, limit: int) -> int:
        """Datagrams received now, without waiting (0: none waiting); ``OSError`` otherwise."""
        k = max(1, min(int(limit), self.rows))
        self._namelen[:k] = _NAME_BYTES
        self._controllen[:k] = _CMSG_BYTES
        assert _recvmmsg is not None
        n = _recvmmsg(fd, self._hdr_ptr, k, _MSG_DONTWAIT, None)
        if n < 0:
            err = ctypes.get_errno()
            if err in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR):
                return 0
            raise OSError(err, os.strerror(err))
        return n

    def read_back(
        self, n: int, now_ns: int, offset_ns: int | None
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
        """The first ``n`` datagrams' lengths, receipt times and total bytes: the kernel's
        stamps on the monotonic clock (``realtime - offset_ns``, never after ``now_ns``) when
        ``offset_ns`` is given and every datagram has one, else ``now_ns``. One compiled call
        (:mod:`wristscan.calib.jit`) where numpy takes a dozen."""
        kern = jit.kernel("mmsg_read_back")
        if kern is None:
            lengths = self.lengths(n)
            real = None if offset_ns is None else self.realtime_stamps(n)
            if real is None or offset_ns is None:
                return lengths, np.full(n, now_ns, np.int64), int(lengths.sum())
            return lengths, np.minimum(real - offset_ns, now_ns), int(lengths.sum())
        lengths = np.empty(n, np.int64)
        stamps = np.empty(n, np.int64)
        stamped = offset_ns is not None
        total = kern(self._len, self._ctrl_lt, self._controllen, self._sec, self._nsec,
                     _LEVEL_TYPE, _CMSG_BYTES, stamped, offset_ns or 0, now_ns, lengths,
                     stamps)  # fmt: skip
        return lengths, stamps, int(total)

    def lengths(self, n: int) -> NDArray[np.int64]:
        return self._len[:n].astype(np.int64)

    def sources(self, n: int) -> NDArray[np.uint32]:
        """The IPv4 source addresses (network byte order, as ``socket.inet_aton`` gives)."""
        return self._names[:n, 4:8].copy().view(np.uint32)[:, 0]

    def realtime_stamps(self, n: int) -> NDArray[np.int64] | None:
        """The kernel's CLOCK_REALTIME receipt stamps (ns); None unless every datagram has one."""
        # The control block is whole, at the socket level and a timestamp in every row: three
        # comparisons as one (level and type side by side as one int64).
        lt = self._ctrl_lt[:n]
        if not (lt == _LEVEL_TYPE).all() or not (self._controllen[:n] >= _CMSG_BYTES).all():
            return None
        out = self._sec[:n] * 1_000_000_000
        out += self._nsec[:n]
        return out
