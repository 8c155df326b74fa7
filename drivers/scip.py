"""Hokuyo SCIP 2.0 framing: commands, replies, checksums and the 2/3/4-character encodings.

Wire format (PROTOCOLS.md): ASCII, every line ends with LF. A reply is the echoed command line,
a status line (two characters and their checksum), data lines (each with its checksum) and an
empty line. Checksum of a line: ``(sum of its bytes & 0x3F) + 0x30``; for ``KEY:VALUE;`` info
lines (VV, PP, II) the sum covers ``KEY:VALUE`` and the checksum follows the semicolon. Values
are big-endian groups of 6 bits, each sent as ``value + 0x30``: 2 characters (MS/GS, up to 4095),
3 characters (MD/ME/GD/GE ranges and intensities, up to 262143) or 4 characters (the 24-bit
millisecond timestamp, which wraps every 4.66 h). Scan data is one character stream cut into
lines of 64 characters; a value may straddle two lines.

Encoders and decoders here are vectorised with numpy (one step per scan). Decoders raise
:class:`FrameError` on anything malformed and never return a partial scan.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "LINE_CHARS",
    "TIMESTAMP_MODULO_MS",
    "Command",
    "FrameError",
    "Reply",
    "ReplyDecoder",
    "Scan",
    "checksum",
    "decode_info",
    "decode_scan",
    "decode_values",
    "encode_data_block",
    "encode_values",
    "info_line",
    "make_reply",
    "parse_command",
    "parse_reply",
    "scan_reply",
    "with_checksum",
]

LINE_CHARS = 64
TIMESTAMP_MODULO_MS = 1 << 24
LF = 0x0A

SCAN_COMMANDS = {
    # code: (parameter characters, characters per value, with intensity)
    "MD": (13, 3, False),
    "ME": (13, 3, True),
    "MS": (13, 2, False),
    "GD": (10, 3, False),
    "GE": (10, 3, True),
    "GS": (10, 2, False),
}


class FrameError(ValueError):
    """Malformed SCIP input: bad checksum, bad characters, wrong length or structure."""


def checksum(data: bytes) -> int:
    """The SCIP checksum character code of ``data``."""
    return (sum(data) & 0x3F) + 0x30


def with_checksum(data: bytes) -> bytes:
    return data + bytes((checksum(data),))


def _verify(line: bytes) -> bytes:
    if len(line) < 2:
        raise FrameError(f"SCIP line {line!r} too short for a checksum")
    body = line[:-1]
    if checksum(body) != line[-1]:
        raise FrameError(f"SCIP checksum mismatch in {line!r}")
    return body


def encode_values(values: ArrayLike, n_chars: int) -> bytes:
    """Encode non-negative integers with ``n_chars`` characters each (values are clipped)."""
    v = np.asarray(values, dtype=np.int64).reshape(-1)
    v = np.clip(v, 0, (1 << (6 * n_chars)) - 1)
    shifts = 6 * np.arange(n_chars - 1, -1, -1)
    chars = ((v[:, None] >> shifts) & 0x3F) + 0x30
    return chars.astype(np.uint8).tobytes()


def decode_values(data: bytes | bytearray | memoryview, n_chars: int) -> NDArray[np.int64]:
    """Decode a character stream of ``n_chars``-character values."""
    raw = np.frombuffer(data, dtype=np.uint8)
    if raw.size % n_chars:
        raise FrameError(f"SCIP data of {raw.size} characters is not a multiple of {n_chars}")
    if raw.size and (raw.min() < 0x30 or raw.max() > 0x6F):
        raise FrameError("SCIP data holds characters outside the 6-bit encoding")
    digits = (raw.astype(np.int64) - 0x30).reshape(-1, n_chars)
    shifts = 6 * np.arange(n_chars - 1, -1, -1)
    return np.asarray((digits << shifts).sum(axis=1))


def encode_data_block(chars: bytes) -> bytes:
    """Cut a character stream into 64-character lines, each with its checksum and LF."""
    raw = np.frombuffer(chars, dtype=np.uint8)
    n_full = raw.size // LINE_CHARS
    full = raw[: n_full * LINE_CHARS].reshape(n_full, LINE_CHARS)
    block = np.empty((n_full, LINE_CHARS + 2), dtype=np.uint8)
    block[:, :LINE_CHARS] = full
    block[:, LINE_CHARS] = (full.sum(axis=1, dtype=np.int64) & 0x3F) + 0x30
    block[:, LINE_CHARS + 1] = LF
    out = block.tobytes()
    rest = bytes(raw[n_full * LINE_CHARS :])
    if rest:
        out += with_checksum(rest) + b"\n"
    return out


def _decode_data_lines(lines: Sequence[bytes]) -> bytes:
    """Verify data lines (each ``chars + checksum``) and join their characters."""
    if not lines:
        return b""
    body = lines[:-1]
    if body and all(len(ln) == LINE_CHARS + 1 for ln in body):
        arr = np.frombuffer(b"".join(body), dtype=np.uint8).reshape(-1, LINE_CHARS + 1)
        sums = (arr[:, :LINE_CHARS].sum(axis=1, dtype=np.int64) & 0x3F) + 0x30
        if np.any(sums != arr[:, LINE_CHARS]):
            raise FrameError("SCIP checksum mismatch in scan data")
        head = arr[:, :LINE_CHARS].tobytes()
    else:
        head = b"".join(_verify(ln) for ln in body)
    return head + _verify(lines[-1])


def info_line(key: str, value: object) -> bytes:
    """``KEY:VALUE;`` plus the checksum of ``KEY:VALUE`` (VV, PP, II replies)."""
    text = f"{key}:{value}".encode("ascii")
    return text + b";" + bytes((checksum(text),))


def make_reply(echo: bytes, status: bytes, lines: Sequence[bytes] = ()) -> bytes:
    """A complete reply: ``lines`` must already carry their checksums."""
    if len(status) != 2:
        raise ValueError("SCIP status is two characters")
    parts = [echo, with_checksum(status), *lines]
    return b"\n".join(parts) + b"\n\n"


def scan_reply(
    echo: bytes,
    status: bytes,
    timestamp_ms: int,
    ranges_mm: ArrayLike,
    intensity: ArrayLike | None = None,
    n_chars: int = 3,
) -> bytes:
    """A GD/GE/GS answer (status ``00``) or an MD/ME/MS scan (status ``99``)."""
    r = np.asarray(ranges_mm, dtype=np.int64).reshape(-1)
    if intensity is None:
        chars = encode_values(r, n_chars)
    else:
        inter = np.empty((r.size, 2), dtype=np.int64)
        inter[:, 0] = r
        inter[:, 1] = np.asarray(intensity, dtype=np.int64).reshape(-1)
        chars = encode_values(inter, n_chars)
    ts = with_checksum(encode_values([timestamp_ms % TIMESTAMP_MODULO_MS], 4))
    return (
        echo + b"\n" + with_checksum(status) + b"\n" + ts + b"\n" + encode_data_block(chars) + b"\n"
    )


# ----------------------------------------------------------------------------------------------
# Commands


@dataclass(frozen=True, slots=True)
class Command:
    """A parsed command line (without LF)."""

    code: str
    """``"MD"``, ``"VV"``, ``"%ST"`` ..."""
    params: str
    string: str
    """The optional ``;string`` tag the host adds (echoed back)."""
    raw: bytes

    def scan_params(self) -> tuple[int, int, int, int, int]:
        """``(start, end, cluster, interval, scans)`` of MD/ME/MS/GD/GE/GS (interval and scans
        are 0 for the single-scan commands)."""
        spec = SCAN_COMMANDS.get(self.code)
        if spec is None:
            raise FrameError(f"{self.code} is not a scan command")
        p = self.params
        if len(p) != spec[0] or not p.isdigit():
            raise FrameError(f"{self.code} needs {spec[0]} digits, got {p!r}")
        if spec[0] == 13:
            return int(p[0:4]), int(p[4:8]), int(p[8:10]), int(p[10:11]), int(p[11:13])
        return int(p[0:4]), int(p[4:8]), int(p[8:10]), 0, 0


def parse_command(line: bytes) -> Command:
    """Split a command line (LF removed) into code, parameters and the ``;string`` tag."""
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError as exc:
        raise FrameError("SCIP command is not ASCII") from exc
    head, _, tag = text.partition(";")
    if len(tag) > 16:
        raise FrameError("SCIP string tag longer than 16 characters")
    n = 3 if head.startswith("%") else 2
    if len(head) < n:
        raise FrameError(f"SCIP command {text!r} too short")
    return Command(head[:n], head[n:], tag, line)


# ----------------------------------------------------------------------------------------------
# Replies (host side)


@dataclass(frozen=True, slots=True)
class Reply:
    """One reply block: echo line, status (checksum verified) and raw data lines."""

    echo: bytes
    status: bytes
    lines: tuple[bytes, ...]


@dataclass(frozen=True, slots=True)
class Scan:
    timestamp_ms: int
    """The sensor's 24-bit millisecond counter."""
    ranges_mm: NDArray[np.int64]
    intensity: NDArray[np.int64] | None
    remaining: int | None
    """Scans still to come for MD/ME/MS with a scan count (from the echo), else None."""


def parse_reply(block: bytes) -> Reply:
    """One reply block without its final empty line."""
    lines = block.split(b"\n")
    if len(lines) < 2:
        raise FrameError(f"SCIP reply {block[:40]!r} lacks a status line")
    status_line = lines[1]
    if len(status_line) != 3:
        raise FrameError(f"SCIP status line {status_line!r} is not 3 characters")
    return Reply(lines[0], _verify(status_line), tuple(lines[2:]))


class ReplyDecoder:
    """Splits a byte stream from a sensor into replies (blocks ending with an empty line)."""

    def __init__(self, max_block: int = 1 << 20) -> None:
        self._buf = bytearray()
        self.max_block = max_block
        self.bad_replies = 0

    def feed(self, data: bytes | bytearray | memoryview) -> list[Reply]:
        self._buf += data
        parts = bytes(self._buf).split(b"\n\n")
        self._buf = bytearray(parts.pop())
        if len(self._buf) > self.max_block:
            self.bad_replies += 1
            self._buf.clear()
        out = []
        for block in parts:
            # A stray LF (line noise) makes an empty block: skip it rather than fail.
            if not block.strip(b"\n"):
                continue
            try:
                out.append(parse_reply(block.lstrip(b"\n")))
            except FrameError:
                self.bad_replies += 1
        return out


def decode_scan(reply: Reply, n_chars: int = 3, with_intensity: bool = False) -> Scan:
    """The timestamp and ranges (mm) of a GD/GE/GS or MD/ME/MS scan reply."""
    if reply.status not in (b"00", b"99"):
        raise FrameError(f"SCIP scan reply with status {reply.status!r}")
    if not reply.lines:
        raise FrameError("SCIP scan reply without a timestamp")
    ts_chars = _verify(reply.lines[0])
    if len(ts_chars) != 4:
        raise FrameError("SCIP timestamp is not 4 characters")
    ts = int(decode_values(ts_chars, 4)[0])
    values = decode_values(_decode_data_lines(reply.lines[1:]), n_chars)
    remaining = None
    echo = reply.echo.split(b";")[0]
    if len(echo) == 15 and echo[:2] in (b"MD", b"ME", b"MS") and echo[13:15].isdigit():
        remaining = int(echo[13:15])
    if with_intensity:
        if values.size % 2:
            raise FrameError("SCIP range/intensity data has an odd number of values")
        return Scan(ts, values[0::2].copy(), values[1::2].copy(), remaining)
    return Scan(ts, values, None, remaining)


def decode_info(reply: Reply) -> dict[str, str]:
    """``KEY:VALUE`` pairs of a VV, PP or II reply (checksums verified)."""
    if reply.status != b"00":
        raise FrameError(f"SCIP info reply with status {reply.status!r}")
    out = {}
    for line in reply.lines:
        if len(line) < 3 or line[-2:-1] != b";":
            raise FrameError(f"SCIP info line {line!r} lacks ';'")
        text = line[:-2]
        if checksum(text) != line[-1]:
            raise FrameError(f"SCIP checksum mismatch in {line!r}")
        key, sep, value = text.decode("ascii", "replace").partition(":")
        if not sep:
            raise FrameError(f"SCIP info line {line!r} lacks ':'")
        out[key] = value
    return out
