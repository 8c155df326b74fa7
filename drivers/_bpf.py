"""Kernel-side admission of a UDP sensor's frames: a classic BPF socket filter (Linux).

Under overload the daemon sheds whole profiles. Shedding after reading still costs the reading
thread the receive system call, the copy and the CRC of every shed datagram, which at twice the
worker's capacity leaves little for the profiles it keeps. A socket filter sheds them before
they are queued on the socket: the kernel runs it in the sender's or the network stack's
context, and the reading thread never sees them.

The filter keeps frame ``c`` when ``(c * F) mod 2**32 < F``, with ``F = fraction * 2**32``: a
Beatty sequence, i.e. exactly ``fraction`` of the frames, evenly spread (one kept every
``1 / fraction`` frames, never two in a row below one half), decided by the frame counter the
datagram carries, so every fragment of a frame shares its fate and the gaps are counted from
the counters as usual. Datagrams shorter than a header always pass, and so do messages other
than profiles (hello, heartbeats, status) in a stream that has them.

:func:`counter_filter` builds the program for a counter at a byte offset of the UDP payload
(little-endian, its low 32 bits), :func:`attach` / :func:`detach` set it on a socket
(``SO_ATTACH_FILTER`` replaces a previous program atomically).
"""

from __future__ import annotations

import ctypes
import socket
import struct
import sys

__all__ = ["attach", "available", "counter_filter", "detach", "kept"]

SO_ATTACH_FILTER = getattr(socket, "SO_ATTACH_FILTER", 26)
SO_DETACH_FILTER = getattr(socket, "SO_DETACH_FILTER", 27)
"""Linux values (asm-generic); Python's socket module does not name them."""

UDP_HEADER = 8
"""A UDP socket's filter sees the datagram from its UDP header: the payload starts here."""

# Classic BPF opcodes (linux/filter.h), the few this program needs.
_LD_LEN = 0x80  # A = packet length
_LDB_ABS = 0x30  # A = byte at k
_LSH_K, _OR_X, _MUL_K, _TAX = 0x64, 0x4C, 0x24, 0x07
_JEQ_K, _JGE_K, _RET_K = 0x15, 0x35, 0x06
_ACCEPT, _DROP = 0xFFFFFFFF, 0

Instruction = tuple[int, int, int, int]
"""(code, jump if true, jump if false, k)."""


def available() -> bool:
    """Socket filters exist here (Linux)."""
    return sys.platform.startswith("linux")


def _threshold(fraction: float) -> int:
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"admission fraction {fraction} outside (0, 1)")
    return min(max(1, round(fraction * 2.0**32)), 2**32 - 1)


def kept(counters: list[int], fraction: float) -> list[bool]:
    """Which frame counters the filter of ``fraction`` keeps: the kernel's rule in Python (what
    the tests check the kernel against)."""
    f = _threshold(fraction)
    return [((c & 0xFFFFFFFF) * f) & 0xFFFFFFFF < f for c in counters]


def counter_filter(
    fraction: float,
    counter_offset: int,
    min_length: int,
    type_offset: int | None = None,
    profile_type: int = 0,
) -> list[Instruction]:
    """The program keeping ``fraction`` of the profile frames by their counter (a little-endian
    integer at ``counter_offset`` of the payload, its low 32 bits used). Datagrams shorter than
    ``min_length`` payload bytes, or whose byte at ``type_offset`` is not ``profile_type``
    (when given: other messages share the stream), pass."""
    f = _threshold(fraction)
    c = UDP_HEADER + counter_offset
    typed: list[Instruction] = []
    if type_offset is not None:
        typed = [
            (_LDB_ABS, 0, 0, UDP_HEADER + type_offset),
            (_JEQ_K, 0, 0, profile_type),  # jf -> accept, patched below
        ]
    body: list[Instruction] = [
        (_LD_LEN, 0, 0, 0),
        (_JGE_K, 0, 0, UDP_HEADER + min_length),  # jf -> accept, patched below
        *typed,
        # cBPF loads are big-endian: the counter's bytes are put together from its top byte.
        (_LDB_ABS, 0, 0, c + 3),
        (_LSH_K, 0, 0, 8),
        (_TAX, 0, 0, 0),
        (_LDB_ABS, 0, 0, c + 2),
        (_OR_X, 0, 0, 0),
        (_LSH_K, 0, 0, 8),
        (_TAX, 0, 0, 0),
        (_LDB_ABS, 0, 0, c + 1),
        (_OR_X, 0, 0, 0),
        (_LSH_K, 0, 0, 8),
        (_TAX, 0, 0, 0),
        (_LDB_ABS, 0, 0, c),
        (_OR_X, 0, 0, 0),
        (_MUL_K, 0, 0, f),  # 32-bit: modulo 2**32
        (_JGE_K, 0, 1, f),  # A >= F: drop (the next), else accept (the one after)
        (_RET_K, 0, 0, _DROP),
        (_RET_K, 0, 0, _ACCEPT),
    ]
    accept = len(body) - 1
    for i in (1, 3) if typed else (1,):  # their "false" branch goes to accept
        code, jt, _, k = body[i]
        body[i] = (code, jt, accept - i - 1, k)
    return body


def attach(sock: socket.socket, program: list[Instruction]) -> None:
    """Set ``program`` as ``sock``'s filter (replacing any). Raises OSError if refused."""
    raw = b"".join(struct.pack("HBBI", *ins) for ins in program)
    buf = ctypes.create_string_buffer(raw, len(raw))
    # struct sock_fprog {unsigned short len; struct sock_filter *filter;}; the kernel copies it.
    fprog = struct.pack("HP", len(program), ctypes.addressof(buf))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)


def detach(sock: socket.socket) -> None:
    """Remove ``sock``'s filter (none attached: nothing to do)."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
    except OSError:  # ENOENT: no filter
        pass
