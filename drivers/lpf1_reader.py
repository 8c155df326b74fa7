"""LPF1 readers: whole messages, and profiles, out of what each transport delivers.

:mod:`wristscan.drivers.lpf1` defines one message (its bytes, parsing and encoding); this module
holds the stateful side of reading a link, one reader per transport (``docs/lpf1.md``): UDP
fragments reassembled in any order (:class:`Reassembler`), a TCP byte stream split and
resynchronised after garbage (:class:`StreamDecoder`), serial COBS frames split at their zero
delimiters (:class:`SerialDecoder`), and the profiles a batch of messages completes
(:func:`iter_profiles`). Like the parser, a reader never returns a partial or guessed message.
"""

from __future__ import annotations

import struct
from collections import OrderedDict
from collections.abc import Iterable

from cobs import cobs

from wristscan.drivers.lpf1 import (
    CRC_LEN,
    HEADER_LEN,
    MAGIC,
    MAX_PAYLOAD,
    VERSION,
    Flags,
    FrameError,
    Header,
    Message,
    MsgType,
    decode_profile,
    parse_message,
)
from wristscan.drivers.records import Profile

__all__ = ["Reassembler", "SerialDecoder", "StreamDecoder", "iter_profiles"]


class Reassembler:
    """Collects the fragments of a frame; yields the complete message once all arrived.

    Fragments may arrive in any order; at most ``max_pending`` incomplete frames are held (the
    oldest is dropped and counted in ``dropped_frames``). Inconsistent fragments raise
    :class:`FrameError` and discard the frame.
    """

    def __init__(self, max_pending: int = 8) -> None:
        self.max_pending = max_pending
        self._pending: OrderedDict[tuple[int, int], dict[int, Message]] = OrderedDict()
        self.dropped_frames = 0

    def push(self, msg: Message) -> Message | None:
        h = msg.header
        if h.frag_count == 1:
            return msg
        key = (h.sensor_id, h.frame_counter)
        parts = self._pending.get(key)
        if parts is None:
            parts = self._pending[key] = {}
            while len(self._pending) > self.max_pending:
                self._pending.popitem(last=False)
                self.dropped_frames += 1
        first = next(iter(parts.values()), None)
        if first is not None and not _same_frame(first.header, h):
            del self._pending[key]
            raise FrameError("LPF1 fragments of one frame disagree")
        parts[h.frag_index] = msg
        if len(parts) < h.frag_count:
            return None
        del self._pending[key]
        ordered = [parts[i] for i in range(h.frag_count)]
        offset = 0
        for m in ordered:
            if m.header.frag_offset != offset:
                raise FrameError("LPF1 fragment offsets are not contiguous")
            offset += len(m.payload)
        if not ordered[-1].header.flags & Flags.LAST_FRAGMENT:
            raise FrameError("LPF1 last fragment lacks its flag")
        payload = b"".join(m.payload for m in ordered)
        merged = Header(
            **{
                **{k: getattr(h, k) for k in Header.__slots__},
                "payload_len": len(payload),
                "frag_index": 0,
                "frag_count": 1,
                "frag_offset": 0,
                "flags": h.flags | Flags.LAST_FRAGMENT,
            }
        )
        if len(payload) != merged.frame_payload_len():
            raise FrameError("LPF1 reassembled payload has the wrong size")
        return Message(merged, payload)

    def clear(self) -> None:
        self._pending.clear()


def _same_frame(a: Header, b: Header) -> bool:
    skip = {"payload_len", "frag_index", "frag_offset", "flags"}
    return all(getattr(a, k) == getattr(b, k) for k in Header.__slots__ if k not in skip) and (
        a.flags & ~Flags.LAST_FRAGMENT
    ) == (b.flags & ~Flags.LAST_FRAGMENT)


class StreamDecoder:
    """Splits a byte stream (TCP) into messages, resynchronising after garbage or corruption.

    A candidate starts at the magic; it is accepted when its length fields are sane and its CRC
    matches, otherwise the reader skips past that magic and searches again. ``skipped_bytes``
    and ``bad_messages`` count what was discarded.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.skipped_bytes = 0
        self.bad_messages = 0

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        self._buf += data
        out: list[Message] = []
        buf = self._buf
        pos = 0
        while True:
            start = buf.find(MAGIC, pos)
            if start < 0:
                # Keep a tail that may hold the start of a split magic.
                keep = max(pos, len(buf) - (len(MAGIC) - 1))
                self.skipped_bytes += keep - pos
                pos = keep
                break
            self.skipped_bytes += start - pos
            pos = start
            if len(buf) - pos < HEADER_LEN:
                break
            header_len = buf[pos + 5]
            (payload_len,) = struct.unpack_from("<I", buf, pos + 8)
            if buf[pos + 4] != VERSION or header_len < HEADER_LEN or payload_len > MAX_PAYLOAD:
                self.bad_messages += 1
                pos += 1
                continue
            total = header_len + payload_len + CRC_LEN
            if len(buf) - pos < total:
                # A corrupted length could stall the stream for megabytes: if a complete,
                # valid message starts further on, this candidate was not one.
                if self._valid_message_after(buf, pos + 1):
                    self.bad_messages += 1
                    pos += 1
                    continue
                break
            try:
                out.append(parse_message(memoryview(buf)[pos : pos + total]))
            except FrameError:
                self.bad_messages += 1
                pos += 1
                continue
            pos += total
        del buf[:pos]
        return out

    @staticmethod
    def _valid_message_after(buf: bytearray, start: int) -> bool:
        nxt = buf.find(MAGIC, start)
        while nxt >= 0 and len(buf) - nxt >= HEADER_LEN:
            header_len = buf[nxt + 5]
            (payload_len,) = struct.unpack_from("<I", buf, nxt + 8)
            total = header_len + payload_len + CRC_LEN
            if header_len >= HEADER_LEN and len(buf) - nxt >= total:
                try:
                    parse_message(memoryview(buf)[nxt : nxt + total])
                    return True
                except FrameError:
                    pass
            nxt = buf.find(MAGIC, nxt + 1)
        return False


class SerialDecoder:
    """Splits a serial byte stream of COBS-encoded, zero-terminated messages."""

    def __init__(self, max_frame: int = MAX_PAYLOAD) -> None:
        self._buf = bytearray()
        self.max_frame = max_frame
        self.bad_messages = 0
        self.skipped_bytes = 0

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        self._buf += data
        out: list[Message] = []
        *frames, rest = bytes(self._buf).split(b"\x00")
        self._buf = bytearray(rest)
        if len(self._buf) > self.max_frame:  # no delimiter for too long: line garbage
            self.skipped_bytes += len(self._buf)
            self._buf.clear()
        for enc in frames:
            if not enc:
                continue
            try:
                out.append(parse_message(cobs.decode(enc)))
            except (cobs.DecodeError, FrameError):
                self.bad_messages += 1
                self.skipped_bytes += len(enc) + 1
        return out


def iter_profiles(messages: Iterable[Message], reassembler: Reassembler,
                  host_time_ns: int = 0) -> list[Profile]:  # fmt: skip
    """Profiles completed by ``messages`` (control messages are skipped)."""
    out = []
    for m in messages:
        if m.header.msg_type != MsgType.PROFILE:
            continue
        whole = reassembler.push(m)
        if whole is not None:
            out.append(decode_profile(whole, host_time_ns))
    return out
