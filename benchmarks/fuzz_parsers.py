"""Mutation fuzzing of every frame parser: valid frames from the encoders, damaged at random.

Mutations (in turn): byte substitutions (1-4 bytes changed to other values), one bit flipped,
truncation, insertion (1-8 random bytes), deletion (1-8 bytes) and a corrupted length field
(LPF1 ``header_len``/``payload_len``/``point_count``/fragment fields, RF627 ``payload_size``/
``data_offset``/``hardware_params_offset``, SCIP: a line feed added or removed). For each parser:

* no exception other than the codec's ``FrameError`` may escape (target: 0);
* a frame that is accepted must decode to exactly what the undamaged frame decodes to, or it is
  *bogus*. LPF1 (CRC-32) must give 0 bogus frames; SCIP (6-bit checksum per line, plus the
  driver's check of the value count) must give 0 for single-byte damage and truncation, and its
  rate for multi-byte damage is reported; RF627 carries no checksum: the undetected rate is
  reported, for the codec alone and for the driver's stream checks (header lock, counter/clock
  agreement), and truncation/insertion/deletion/length damage must always be caught. The same
  holds for the Gocator (a TCP stream without checksum): a damaged message group between intact
  ones goes through the stream reader and the driver's checks (``_consume``: resynchronisation,
  the lookahead on the next header, the stream lock, frame index/timestamp agreement); Gocator
  length fields are the message sizes, stamp count and size, ``attributeSize``, count, width.

Run: ``.venv/bin/python benchmarks/fuzz_parsers.py [--n 100000] [--seed 1] [--json out.json]``
"""

from __future__ import annotations

import argparse
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
from _report import Figure, report
from support import same_profile

from wristscan.drivers import gocator, lpf1, lpf1_reader, rf627, scip
from wristscan.drivers.records import Profile
from wristscan.drivers.sensor_gocator import GocatorSensor
from wristscan.drivers.sensor_rf627 import Rf627Sensor

MUTATIONS = ("byte", "bit", "truncate", "insert", "delete", "length")
RF627_MUTATIONS = ("byte", "bit", "hbyte", "hbit", "truncate", "insert", "delete", "length")
"""``hbyte``/``hbit``: the damage falls in the 64-byte header (the rest is mostly point data)."""
SINGLE = ("bit", "truncate")
"""Damage every checksum must catch (a single byte changed is in ``byte`` when 1 byte)."""


# ----------------------------------------------------------------------------------------------
# Mutations


def mutate(frame: bytes, kind: str, rng: np.random.Generator, length_fields: list[tuple[int, int]],
           head: int = rf627.HEADER_LEN) -> bytes:  # fmt: skip
    """A damaged copy of ``frame`` (always different from it); ``hbyte``/``hbit`` damage the
    first ``head`` bytes."""
    if kind in ("hbyte", "hbit"):
        return mutate(frame[:head], kind[1:], rng, length_fields) + frame[head:]
    b = bytearray(frame)
    n = len(b)
    if kind == "byte":
        k = int(rng.integers(1, 5))
        for pos in rng.choice(n, size=min(k, n), replace=False):
            b[pos] = (b[pos] + int(rng.integers(1, 256))) & 0xFF
    elif kind == "bit":
        pos = int(rng.integers(0, n))
        b[pos] ^= 1 << int(rng.integers(0, 8))
    elif kind == "truncate":
        del b[int(rng.integers(0, n)) :]
    elif kind == "insert":
        pos = int(rng.integers(0, n + 1))
        b[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
    elif kind == "delete":
        pos = int(rng.integers(0, n))
        del b[pos : pos + int(rng.integers(1, 9))]
    elif kind == "length":
        off, size = length_fields[int(rng.integers(0, len(length_fields)))]
        if size == 0:  # SCIP: a line feed added or removed
            lfs = [i for i, c in enumerate(b) if c == 0x0A]
            if lfs and rng.random() < 0.5:
                del b[lfs[int(rng.integers(0, len(lfs)))]]
            else:
                b.insert(int(rng.integers(0, n)), 0x0A)
        else:
            old = int.from_bytes(b[off : off + size], "little")
            choices = [old + 1, old - 1, old * 2, old // 2, int(rng.integers(0, 1 << (8 * size)))]
            new = choices[int(rng.integers(0, len(choices)))] % (1 << (8 * size))
            if new == old:
                new = (old + 1) % (1 << (8 * size))
            b[off : off + size] = new.to_bytes(size, "little")
    else:
        raise ValueError(kind)
    if bytes(b) == frame:  # a no-op mutation (e.g. a truncation at the end): damage it anyway
        b.append(0)
    return bytes(b)


# ----------------------------------------------------------------------------------------------
# Bookkeeping


@dataclass
class Outcome:
    name: str
    n: int = 0
    rejected: int = 0
    identical: int = 0
    bogus: Counter[str] = field(default_factory=Counter)
    escaped: Counter[str] = field(default_factory=Counter)
    by_kind: Counter[str] = field(default_factory=Counter)
    examples: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def escape(self, kind: str, exc: BaseException) -> None:
        self.escaped[type(exc).__name__] += 1
        if len(self.examples) < 3:
            self.examples.append(f"{kind}: {''.join(traceback.format_exception(exc))}")

    @property
    def n_bogus(self) -> int:
        return sum(self.bogus.values())

    @property
    def n_escaped(self) -> int:
        return sum(self.escaped.values())


def run_parser(
    name: str,
    frames: list[tuple[bytes, Any]],
    decode: Callable[[bytes], Any | None],
    same: Callable[[Any, Any], bool],
    errors: tuple[type[BaseException], ...],
    length_fields: list[tuple[int, int]],
    n: int,
    rng: np.random.Generator,
    mutations: tuple[str, ...] = MUTATIONS,
) -> Outcome:
    """``decode`` returns the decoded value (None: nothing accepted) or raises ``errors``."""
    out = Outcome(name)
    t0 = time.perf_counter()
    for i in range(n):
        frame, expect = frames[i % len(frames)]
        kind = mutations[i % len(mutations)]
        bad = mutate(frame, kind, rng, length_fields)
        out.n += 1
        out.by_kind[kind] += 1
        try:
            got = decode(bad)
        except errors:
            out.rejected += 1
            continue
        except Exception as exc:  # what the fuzzing is looking for
            out.escape(kind, exc)
            continue
        if got is None:
            out.rejected += 1
        elif same(got, expect):
            out.identical += 1
        else:
            out.bogus[kind] += 1
    out.seconds = time.perf_counter() - t0
    return out


# ----------------------------------------------------------------------------------------------
# Parsers


def lpf1_frames(rng: np.random.Generator, n_points: int = 256) -> list[bytes]:
    """Valid LPF1 messages of every shape: formats, explicit x, intensity, encoder, control."""
    out: list[bytes] = []
    z = rng.uniform(0.06, 0.14, (4, n_points))
    valid = rng.random((4, n_points)) > 0.1
    x = np.linspace(-0.02, 0.02, n_points)
    inten = rng.integers(0, 256, (4, n_points))
    for fmt in lpf1.PointFormat:
        for explicit in (False, True):
            enc = lpf1.ProfileEncoder(
                3, fmt, x_uniform=None if explicit else (-0.02, 0.04 / (n_points - 1)),
                intensity=explicit, max_message_bytes=None,
            )  # fmt: skip
            msgs = enc.encode(
                np.arange(4) + 10, np.arange(4) * 1000 + 5, z, valid,
                x=x if explicit else None, intensity=inten if explicit else None,
                encoder=np.arange(4) - 2 if explicit else None,
            )  # fmt: skip
            out += [m[0] for m in msgs]
    out.append(lpf1.encode_control(lpf1.MsgType.HELLO, 3, 9, 100, {"model": "fuzz", "n": 256}))
    out.append(lpf1.encode_control(lpf1.MsgType.HEARTBEAT, 3, 9, 100))
    return out


LPF1_LENGTHS = [(5, 1), (8, 4), (40, 4), (64, 2), (66, 2), (68, 4)]


def lpf1_decode(data: bytes) -> Any:
    msg = lpf1.parse_message(data)
    if msg.header.msg_type == lpf1.MsgType.PROFILE:
        return lpf1.decode_profile(msg)
    return msg


def lpf1_same(a: Any, b: Any) -> bool:
    if isinstance(a, Profile) and isinstance(b, Profile):
        return same_profile(a, b)
    return bool(a == b)


def fuzz_lpf1(n: int, rng: np.random.Generator) -> Outcome:
    frames = [(f, lpf1_decode(f)) for f in lpf1_frames(rng)]
    return run_parser("lpf1 datagram", frames, lpf1_decode, lpf1_same, (lpf1.FrameError,),
                      LPF1_LENGTHS, n, rng)  # fmt: skip


def fuzz_lpf1_fragments(n: int, rng: np.random.Generator) -> Outcome:
    """One fragment of a 3-fragment frame damaged; the frame must come out whole or not."""
    enc = lpf1.ProfileEncoder(4, x_uniform=(-0.02, 1e-4), max_message_bytes=76 + 200)
    z = rng.uniform(0.06, 0.14, (8, 256))
    frames = enc.encode(np.arange(8), np.arange(8), z, np.ones((8, 256), bool))
    whole = [lpf1.decode_profile(lpf1.parse_message(lpf1.ProfileEncoder(
        4, x_uniform=(-0.02, 1e-4), max_message_bytes=None).encode(i, i, z[i], True)[0][0]))
        for i in range(8)]  # fmt: skip
    cases = []
    for i, frags in enumerate(frames):
        for j in range(len(frags)):
            cases.append(((i, j), frags))

    def run_case(i: int, j: int, bad: bytes) -> Profile | None:
        frags = frames[i]
        ra = lpf1_reader.Reassembler()
        got = None
        order = [bad if k == j else f for k, f in enumerate(frags)]
        for part in order[::-1] if i % 2 else order:
            try:
                msg = lpf1.parse_message(part)
            except lpf1.FrameError:
                continue
            m = ra.push(msg)
            if m is not None:
                got = lpf1.decode_profile(m)
        return got

    out = Outcome("lpf1 fragments")
    t0 = time.perf_counter()
    for k in range(n):
        (i, j), frags = cases[k % len(cases)]
        kind = MUTATIONS[k % len(MUTATIONS)]
        bad = mutate(frags[j], kind, rng, LPF1_LENGTHS)
        out.n += 1
        out.by_kind[kind] += 1
        try:
            got = run_case(i, j, bad)
        except lpf1.FrameError:
            out.rejected += 1
            continue
        except Exception as exc:
            out.escape(kind, exc)
            continue
        if got is None:
            out.rejected += 1
        elif same_profile(got, whole[i]):
            out.identical += 1
        else:
            out.bogus[kind] += 1
    out.seconds = time.perf_counter() - t0
    return out


def _stream_fuzz(
    name: str,
    msgs: list[bytes],
    framed: list[bytes],
    new_decoder: Callable[[], Any],
    n: int,
    rng: np.random.Generator,
    lengths: list[tuple[int, int]],
) -> Outcome:
    """A run of three framed messages, the middle one damaged, fed in two random pieces: every
    message that comes out must be one of the originals, in order."""
    originals = [lpf1.parse_message(m) for m in msgs]
    out = Outcome(name)
    t0 = time.perf_counter()
    k = len(framed)
    for i in range(n):
        a = i % (k - 2)
        kind = MUTATIONS[i % len(MUTATIONS)]
        bad = mutate(framed[a + 1], kind, rng, lengths)
        stream = framed[a] + bad + framed[a + 2]
        cut = int(rng.integers(0, len(stream) + 1))
        out.n += 1
        out.by_kind[kind] += 1
        dec = new_decoder()
        try:
            got = dec.feed(stream[:cut]) + dec.feed(stream[cut:])
        except Exception as exc:
            out.escape(kind, exc)
            continue
        expected = [originals[a], originals[a + 1], originals[a + 2]]
        pos = 0
        ok = True
        for m in got:
            while pos < 3 and expected[pos] != m:
                pos += 1
            if pos == 3:
                ok = False
                break
            pos += 1
        if not ok:
            out.bogus[kind] += 1
        elif any(m == originals[a + 1] for m in got):
            out.identical += 1
        else:
            out.rejected += 1
    out.seconds = time.perf_counter() - t0
    return out


def fuzz_lpf1_stream(n: int, rng: np.random.Generator) -> Outcome:
    msgs = [f for f in lpf1_frames(rng, 64)]
    return _stream_fuzz(
        "lpf1 tcp stream", msgs, msgs, lpf1_reader.StreamDecoder, n, rng, LPF1_LENGTHS
    )


def fuzz_lpf1_serial(n: int, rng: np.random.Generator) -> Outcome:
    msgs = [f for f in lpf1_frames(rng, 64)]
    framed = [lpf1.cobs_frame(m) for m in msgs]
    # Length damage on a COBS frame: a code byte (they say how far the next zero is).
    return _stream_fuzz(
        "lpf1 serial (cobs)", msgs, framed, lpf1_reader.SerialDecoder, n, rng, [(0, 1)]
    )


RF627_LENGTHS = [(61, 2), (19, 1), (18, 1), (63, 1)]


def rf627_frames(rng: np.random.Generator, n_points: int = 648, count: int = 8) -> list[bytes]:
    enc = rf627.RF627Encoder(serial=5, intensity=False)
    x = np.linspace(-0.02, 0.02, n_points)
    z = rng.uniform(0.02, 0.09, (count, n_points))
    valid = rng.random((count, n_points)) > 0.1
    grams = enc.encode(np.arange(count) + 100, np.arange(count) * 1_000_000, x, z, valid)
    enc_i = rf627.RF627Encoder(serial=5, intensity=True, interpolated=True)
    grams += enc_i.encode(np.arange(count) + 100, np.arange(count) * 1_000_000, x, z, valid,
                          intensity=rng.integers(0, 256, (count, n_points)),
                          step_count=np.arange(count))  # fmt: skip
    return grams


def rf627_decode(data: bytes) -> Profile:
    p = rf627.decode(data).profile
    # What the codec promises for any accepted packet: consistent shapes, finite coordinates
    # (NaN only where invalid), values within the 16-bit scaled ranges.
    assert p.y.shape == p.z.shape == p.valid.shape and p.y.ndim == 1
    assert np.all(np.isfinite(p.y)) and np.all(np.isfinite(p.z[p.valid]))
    assert np.all(np.isnan(p.z[~p.valid])) and np.all(p.z[p.valid] > 0)
    return p


def fuzz_rf627(n: int, rng: np.random.Generator) -> Outcome:
    frames = [(g, rf627_decode(g)) for g in rf627_frames(rng)]
    return run_parser("rf627 codec", frames, rf627_decode, same_profile, (rf627.FrameError,),
                      RF627_LENGTHS, n, rng, RF627_MUTATIONS)  # fmt: skip


def fuzz_rf627_driver(n: int, rng: np.random.Generator) -> Outcome:
    """The driver's stream checks: clean packets alternating with damaged ones; a delivered
    profile must be one of the clean ones or the intact version of the damaged one."""
    period = 1_000_000
    batch = 500
    enc = rf627.RF627Encoder(serial=5)
    x = np.linspace(-0.02, 0.02, 648)
    zs = rng.uniform(0.02, 0.09, (2 * batch, 648))
    drv = Rf627Sensor()
    out = Outcome("rf627 driver checks")
    t0 = time.perf_counter()
    count = 0
    grams: list[bytes] = []
    expect: list[Profile] = []
    for i in range(n):
        if i % batch == 0:
            counters = np.arange(count, count + 2 * batch)
            grams = enc.encode(counters, counters * period, x, zs, True)
            expect = [rf627.decode(g).profile for g in grams]
            count += 2 * batch
        j = 2 * (i % batch)
        kind = RF627_MUTATIONS[i % len(RF627_MUTATIONS)]
        bad = mutate(grams[j + 1], kind, rng, RF627_LENGTHS)
        out.n += 1
        out.by_kind[kind] += 1
        try:
            for g in (grams[j], bad):
                drv._on_datagram(memoryview(g), 0)
        except Exception as exc:
            out.escape(kind, exc)
            continue
        got = list(drv._ready)
        drv._ready.clear()
        pair = expect[j : j + 2]
        if any(not any(same_profile(p, e) for e in pair) for p in got):
            out.bogus[kind] += 1
        elif any(same_profile(p, pair[1]) for p in got):
            out.identical += 1
        else:
            out.rejected += 1
    out.seconds = time.perf_counter() - t0
    return out


GOCATOR_LENGTHS = [(0, 4), (6, 4), (10, 2), (70, 4), (76, 2), (78, 4), (82, 4)]
GOCATOR_HEAD = 70 + 48
"""A stamp message and the profile message's header."""


def fuzz_gocator_driver(n: int, rng: np.random.Generator) -> Outcome:
    """Intact message groups alternating with damaged ones through the driver's stream path;
    a delivered profile must be the intact profile of its frame index."""
    period_us, batch, width = 1000, 500, 512
    encoders = [gocator.GocatorEncoder(5, width, intensity=True),
                gocator.GocatorEncoder(5, width, uniform=False)]  # fmt: skip
    x = np.linspace(-0.025, 0.025, width)
    zs = rng.uniform(0.06, 0.14, (2 * batch, width))
    inten = rng.integers(1, 256, (2 * batch, width))
    out = Outcome("gocator driver checks")
    t0 = time.perf_counter()
    count = 0
    for e, enc in enumerate(encoders):
        drv = GocatorSensor("127.0.0.1")
        expect: dict[int, Profile] = {}
        kind_of: dict[int, str] = {}
        groups: list[bytes] = []
        for i in range(n // 2 if e == 0 else n - n // 2):
            if i % batch == 0:
                counters = np.arange(count, count + 2 * batch)
                groups = enc.encode(counters, counters * period_us, x, zs, True, inten)
                ref = GocatorSensor("127.0.0.1")
                ref._consume(b"".join(groups) + groups[0][:16], 0)
                expect.update({p.frame_counter: p for p in ref._ready})
                count += 2 * batch
            j = 2 * (i % batch)
            kind = RF627_MUTATIONS[i % len(RF627_MUTATIONS)]
            bad = mutate(groups[j + 1], kind, rng, GOCATOR_LENGTHS, GOCATOR_HEAD)
            # Its last message is released by the next group's header: judged next time.
            kind_of[count - 2 * batch + j + 1] = kind
            out.n += 1
            out.by_kind[kind] += 1
            try:
                drv._consume(groups[j] + bad, 0)
            except Exception as exc:
                out.escape(kind, exc)
                continue
            for p in drv._ready:  # the damaged frames have the odd indices
                intact = expect.get(p.frame_counter)
                if intact is None or not same_profile(p, intact):
                    out.bogus[kind_of.get(p.frame_counter, kind)] += 1
                elif p.frame_counter % 2:
                    out.identical += 1
            drv._ready.clear()
    out.rejected = out.n - out.identical - out.n_bogus
    out.seconds = time.perf_counter() - t0
    return out


def scip_frames(rng: np.random.Generator, n_values: int = 181) -> list[tuple[bytes, bool]]:
    out = []
    for k in range(6):
        ranges = rng.integers(0, 30000, n_values)
        inten = rng.integers(0, 10000, n_values) if k % 2 else None
        echo = (b"ME" if inten is not None else b"MD") + b"0000018001000"
        out.append((scip.scan_reply(echo, b"99", 1000 + 25 * k, ranges, inten), inten is not None))
    return out


def fuzz_scip(n: int, rng: np.random.Generator) -> Outcome:
    """ReplyDecoder + decode_scan + the driver's value-count check."""
    n_values = 181
    frames = scip_frames(rng, n_values)
    flags = {f: w for f, w in frames}

    def decode_with(with_int: bool) -> Callable[[bytes], Any]:
        def decode(data: bytes) -> Any:
            dec = scip.ReplyDecoder()
            replies = dec.feed(data)
            if not replies:
                return None
            if len(replies) > 1:
                raise scip.FrameError("two blocks")
            s = scip.decode_scan(replies[0], 3, with_int)
            if s.ranges_mm.size != n_values:
                raise scip.FrameError("value count")
            return s

        return decode

    def same(a: scip.Scan, b: scip.Scan) -> bool:
        return (
            a.timestamp_ms == b.timestamp_ms
            and np.array_equal(a.ranges_mm, b.ranges_mm)
            and np.array_equal(
                np.asarray(a.intensity if a.intensity is not None else []),
                np.asarray(b.intensity if b.intensity is not None else []),
            )
        )

    out = Outcome("scip scan")
    t0 = time.perf_counter()
    expect = {f: decode_with(flags[f])(f) for f, _ in frames}
    for i in range(n):
        frame, with_int = frames[i % len(frames)]
        kind = MUTATIONS[i % len(MUTATIONS)]
        bad = mutate(frame, kind, rng, [(0, 0)])
        out.n += 1
        out.by_kind[kind] += 1
        try:
            got = decode_with(with_int)(bad)
        except scip.FrameError:
            out.rejected += 1
            continue
        except Exception as exc:
            out.escape(kind, exc)
            continue
        if got is None:
            out.rejected += 1
        elif same(got, expect[frame]):
            out.identical += 1
        else:
            out.bogus[kind] += 1
    out.seconds = time.perf_counter() - t0
    return out


def fuzz_scip_info(n: int, rng: np.random.Generator) -> Outcome:
    reply = scip.make_reply(b"PP", b"00", [
        scip.info_line("MODL", "UTM-30LX"), scip.info_line("DMIN", 23),
        scip.info_line("DMAX", 60000), scip.info_line("ARES", 1440),
        scip.info_line("AMIN", 0), scip.info_line("AMAX", 1080),
        scip.info_line("AFRT", 540), scip.info_line("SCAN", 2400)])  # fmt: skip

    def decode(data: bytes) -> Any:
        replies = scip.ReplyDecoder().feed(data)
        if len(replies) != 1:
            return None
        return scip.decode_info(replies[0])

    return run_parser("scip info", [(reply, decode(reply))], decode, lambda a, b: a == b,
                      (scip.FrameError,), [(0, 0)], n, rng)  # fmt: skip


# ----------------------------------------------------------------------------------------------


def run(n: int = 100_000, seed: int = 1, json_out: str | None = None) -> int:
    rng = np.random.default_rng(seed)
    results = [
        fuzz_lpf1(n, rng),
        fuzz_lpf1_fragments(n, rng),
        fuzz_lpf1_stream(n, rng),
        fuzz_lpf1_serial(n, rng),
        fuzz_rf627(n, rng),
        fuzz_rf627_driver(n, rng),
        fuzz_gocator_driver(n, rng),
        fuzz_scip(n, rng),
        fuzz_scip_info(max(1, n // 4), rng),
    ]
    figures: list[Figure] = []
    for r in results:
        print(
            f"-- {r.name}: {r.n} mutated frames in {r.seconds:.1f} s; rejected {r.rejected}, "
            f"accepted unchanged {r.identical}, bogus {dict(r.bogus)}, escaped {dict(r.escaped)}"
        )
        for ex in r.examples:
            print("   " + ex.replace("\n", "\n   "))
        want = n if "info" not in r.name else max(1, n // 4)
        figures.append(Figure(f"{r.name}: mutated frames", r.n, "frames", f">= {want}",
                              r.n >= want))  # fmt: skip
        figures.append(Figure(f"{r.name}: escaped exceptions", r.n_escaped, "", "0",
                              r.n_escaped == 0))  # fmt: skip
        if r.name.startswith("lpf1"):
            figures.append(Figure(f"{r.name}: bogus frames", r.n_bogus, "", "0", r.n_bogus == 0))
        elif r.name == "scip scan":
            single = sum(r.bogus[k] for k in SINGLE)
            figures.append(Figure(f"{r.name}: bogus, 1 bit / truncated", single, "", "0",
                                  single == 0))  # fmt: skip
            figures.append(Figure(f"{r.name}: bogus, other damage", r.n_bogus - single,
                                  "", "report", None))  # fmt: skip
        elif r.name == "scip info":
            # Info lines have no character-range check: a flip of bit 6 or 7 keeps the 6-bit
            # checksum. The driver's handshake rejects values that do not parse.
            figures.append(Figure(f"{r.name}: undetected damage", 100.0 * r.n_bogus / r.n,
                                  "%", "report", None))  # fmt: skip
        else:
            framing = sum(r.bogus[k] for k in ("truncate", "insert", "delete", "length"))
            figures.append(Figure(f"{r.name}: bogus, framing damage", framing, "", "0",
                                  framing == 0))  # fmt: skip
            for where, kinds in (
                ("anywhere", ("byte", "bit")),
                ("in the header", ("hbyte", "hbit")),
            ):
                bad = sum(r.bogus[k] for k in kinds)
                tried = sum(r.by_kind[k] for k in kinds)
                pct = 100.0 * bad / max(1, tried)
                figures.append(Figure(f"{r.name}: undetected byte/bit damage {where}", pct, "%",
                                      "report", None))  # fmt: skip
    return report("frame parser fuzzing", figures, json_out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000, help="mutated frames per parser")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    return run(a.n, a.seed, a.json)


if __name__ == "__main__":
    sys.exit(main())
