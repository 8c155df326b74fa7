"""Reading a Gocator Data Protocol stream: message groups out of a TCP byte stream.

The layouts and the per-message checks are :mod:`wristscan.drivers.gocator`; this module keeps
the state from one read to the next (partial messages, the group being read, the receipt time
of each chunk) and resynchronises after damage.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from wristscan.drivers.gocator import (
    GDP_HEADER,
    MAX_MESSAGE,
    FrameError,
    Msg,
    check_message,
)

__all__ = ["LOOKAHEAD", "MAX_TYPE", "GdpReader"]

MAX_TYPE = 255
"""The manual's message types are small numbers: a larger one is damage."""
LOOKAHEAD = 16
"""Bytes of the next group needed to release one (its size, type and counts)."""

Message = tuple[int, bool, bytes, int]
"""``(type, last, bytes, host_ns)``."""


class GdpReader:
    """Splits a GDP byte stream into complete messages ``(type, last, bytes, host_ns)``.

    A group starts with a Stamp (a health message is a group of its own); inside a group,
    messages of unknown types (up to ``MAX_TYPE``) are skipped by their size, up to
    ``max_unknown`` bytes. A message
    that breaks these rules or whose structure does not hold together (see
    :func:`check_message`) is counted in ``bad`` and the reader resynchronises on the next
    well-formed Stamp or health message. Candidates are found vectorised (size and type fields
    of every offset at once), then checked one by one.

    Messages are released a whole group at a time, and with ``lookahead`` only once the header
    of the next group has arrived right after the last message and holds together: a TCP stream
    has no checksum, and a message cut short would otherwise swallow the start of what follows
    unnoticed. A damaged group is dropped whole. ``host_ns`` is the receipt time of the chunk
    that completed each message (not of the later one that released it).
    """

    starters = (Msg.STAMP, Msg.HEALTH)
    known = (Msg.HEALTH, Msg.STAMP, Msg.PROFILE_POINT_CLOUD, Msg.UNIFORM_PROFILE,
             Msg.PROFILE_INTENSITY)  # fmt: skip

    def __init__(
        self, lookahead: bool = True, max_message: int = MAX_MESSAGE, max_unknown: int = 1 << 20
    ) -> None:
        self.lookahead = lookahead
        self.max_message = max_message
        self.max_unknown = max_unknown
        self.bad = 0
        """Damaged spots skipped (each once, however many bytes it took to resynchronise)."""
        self._buf = bytearray()
        self._base = 0
        """Stream offset of ``_buf[0]``."""
        self._chunks: deque[tuple[int, int]] = deque()
        """(stream offset after the chunk, its receipt time) of the chunks still in ``_buf``."""
        self._in_group = self._hunting = False
        self._group: list[Message] = []
        """The messages of the group being read (released together at its end)."""

    def reset(self) -> None:
        self._base += len(self._buf)
        self._buf.clear()
        self._chunks.clear()
        self._group.clear()
        self._in_group = self._hunting = False

    def _check(self, buf: bytearray, pos: int, in_group: bool) -> tuple[int, int, bool]:
        size, kind, last = check_message(buf, pos)
        if size > self.max_message:
            raise FrameError(f"Gocator message of {size} bytes")
        if not in_group and kind not in self.starters:
            raise FrameError(f"Gocator group starting with a type {kind} message")
        if kind not in self.known and (size > self.max_unknown or kind > MAX_TYPE):
            raise FrameError(f"Gocator message of unknown type {kind} and {size} bytes")
        return size, kind, last

    def _received(self, end: int) -> int:
        """Receipt time of the chunk holding stream offset ``end - 1``."""
        for chunk_end, host_ns in self._chunks:
            if chunk_end >= end:
                return host_ns
        return self._chunks[-1][1]

    def feed(self, data: bytes | bytearray | memoryview, host_ns: int = 0) -> list[Message]:
        buf, group = self._buf, self._group
        buf += data
        self._chunks.append((self._base + len(buf), host_ns))
        out: list[Message] = []
        pos, n = 0, len(buf)
        while n - pos >= GDP_HEADER.size:
            try:
                size, kind, last = self._check(buf, pos, self._in_group)
                end = pos + size
                if n < end or (self.lookahead and last and n - end < LOOKAHEAD):
                    break
                if self.lookahead and last:
                    self._check(buf, end, False)  # the next group must start right here
            except FrameError:
                if not self._hunting:  # one damaged spot counts once, however long the hunt
                    self.bad += 1
                    self._hunting = True
                self._in_group = False
                group.clear()
                pos = self._resync(buf, pos + 1)
                continue
            group.append((kind, last, bytes(buf[pos:end]), self._received(self._base + end)))
            if last:
                out += group
                group.clear()
            self._in_group = not last
            self._hunting = False
            pos = end
        del buf[:pos]
        self._base += pos
        while self._chunks and self._chunks[0][0] <= self._base:
            self._chunks.popleft()
        return out

    @property
    def holding(self) -> bool:
        """Bytes are waiting: a group for the next one's header, or a message being received."""
        return bool(self._buf)

    def release(self) -> list[Message]:
        """The group waiting for the next group's header when nothing has arrived after it (the
        stream paused or ended: no later bytes can have completed a message cut short)."""
        buf = self._buf
        if len(buf) < GDP_HEADER.size:
            return []
        try:
            size, kind, last = self._check(buf, 0, self._in_group)
        except FrameError:
            return []
        if not last or size != len(buf):
            return []
        out = [*self._group, (kind, last, bytes(buf), self._received(self._base + size))]
        self.reset()
        return out

    def _resync(self, buf: bytearray, start: int) -> int:
        """The next offset from ``start`` where a well-formed group starts (or where its header
        could still be completed by more bytes)."""
        n = len(buf)
        if n - start < GDP_HEADER.size:
            return start
        a = np.frombuffer(buf, np.uint8, n - start, start).astype(np.uint32)
        m = a.size - GDP_HEADER.size + 1
        size = a[:m] | a[1 : m + 1] << 8 | a[2 : m + 2] << 16 | a[3 : m + 3] << 24
        kind = (a[4 : m + 4] | a[5 : m + 5] << 8) & 0x7FFF
        ok = (size >= GDP_HEADER.size) & (size <= self.max_message) & np.isin(kind, self.starters)
        for i in np.flatnonzero(ok):
            try:
                check_message(buf, start + int(i))
            except FrameError:
                continue
            return start + int(i)
        return start + m
