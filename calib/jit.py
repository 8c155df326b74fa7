"""Compiled loops for the daemon's hot path (extra ``fast``: numba), with numpy as the fallback.

numpy needs several passes over a profile's points for what one loop does in one: the float32
alignment of :func:`wristscan.calib.align.align_rows` with its WSC1 frame costs 6-16 us per
2048-point profile in numpy (cast, matmul, three strided copies into the interleaved output, the
compaction of invalid points, the finiteness check) and 2.0-2.5 us compiled with every point
valid, 4.4-6.7 us with 26-30 % invalid (benchmarks/calib_align.py ``--hot``). The LPF1 reader's
usual pass (headers checked, fields and integer codes copied: :mod:`wristscan.drivers.lpf1_block`),
``recvmmsg``'s results, frame-counter steps and the pairer's forward kinematics are kernels too,
each one call where numpy takes many small ones (docs/pipeline.md, "Sixth session"), and so is
the synchroniser's arithmetic per tick (:mod:`wristscan.calib.jit_clock`: clock feed, fit and
mapping, bit for bit numpy's). The kernels are compiled when first asked for (:func:`warm`;
~5 s, then ~0.6 s loaded from numba's on-disk cache) so that a process that never aligns never
imports numba.

Without numba, or with the environment variable ``WRISTSCAN_JIT=0``, every caller takes its
numpy path; the alignments agree to float32 rounding (tests/calib/test_align_rows.py runs both),
the decodings bit for bit (tests/drivers/test_sensor_blocks.py).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from wristscan.calib import jit_clock

log = logging.getLogger(__name__)

_lock = threading.Lock()
_kernels: dict[str, Callable[..., Any]] | None = None
_tried = False
enabled = os.environ.get("WRISTSCAN_JIT", "1").strip().lower() not in ("0", "false", "no", "off")
"""False: the numpy paths everywhere (``WRISTSCAN_JIT=0``; tests switch it)."""


def kernel(name: str) -> Callable[..., Any] | None:
    """The compiled kernel ``name`` (compiled, or loaded from numba's cache, on the first
    call of any), or None when numba is missing, cannot run here or is switched off."""
    if not enabled:
        return None
    ks = _kernels if _tried else _build()
    return None if ks is None else ks[name]


def available() -> bool:
    """The kernels are in use (numba importable and working, not switched off)."""
    return kernel("align_rows") is not None


def warm() -> float:
    """Compile (or load) every kernel now, not on the first profile; returns the seconds it
    took (0 when they are not in use)."""
    t0 = time.perf_counter()
    if not available():
        return 0.0
    return time.perf_counter() - t0


def _build() -> dict[str, Callable[..., Any]] | None:
    global _kernels, _tried
    with _lock:
        if _tried:
            return _kernels
        _tried = True
        t0 = time.perf_counter()
        try:
            import numba

            ks = _compile(numba)
            _exercise(ks)  # compiled now: a failure falls back here, not in the hot path
        except ImportError:
            log.info(
                "numba is not installed: the hot path runs on numpy (pip install 'wristscan[fast]')"
            )
            return None
        except Exception as exc:
            # Any failure of the compiler means numpy, e.g. under systemd's
            # MemoryDenyWriteExecute=yes: no executable memory for a JIT.
            why = " ".join(str(exc).split()) or type(exc).__name__
            log.warning(
                "compiled hot-path kernels unavailable (%s): the hot path runs on numpy", why
            )
            return None
        _kernels = ks
        log.debug("hot-path kernels ready in %.2f s (numba %s)", time.perf_counter() - t0,
                  numba.__version__)  # fmt: skip
        return ks


def _exercise(ks: dict[str, Callable[..., Any]]) -> None:
    """Each kernel called once on tiny inputs of the types the callers pass."""
    import numpy as np

    out = np.empty(6, np.float32)
    for dt in (np.float64, np.int16, np.int32):  # decoded z, or a sensor's codes
        ks["align_rows"](
            np.zeros((1, 2)), np.zeros((1, 2), dt), np.ones((1, 2), np.bool_), True,
            np.zeros((1, 3, 3), np.float32), out, 1.0, 0.0,
        )  # fmt: skip
    one = np.zeros(1, np.int64)
    for dt in (np.int16, np.int32):
        ks["scale_codes"](
            np.zeros(4, dt), one, 4, 0, 1e-9, 0.0, -1, np.empty((1, 2)), np.empty((1, 2), np.bool_)
        )
        ks["take_codes"](np.zeros(4, dt), one, 4, 0, -1, np.empty((1, 2), dt),
                         np.empty((1, 2), np.bool_))  # fmt: skip
    ks["counter_gaps"](np.zeros(2, np.uint64), np.uint64(1), np.uint64(1))
    six, rows = np.zeros(6), np.zeros(1, np.int64)
    for between in (False, True):
        ks["dh_forward"](
            np.zeros((2, 6)), rows, np.zeros(1), between, six, six, six, six, six,
            np.empty((1, 4, 4)),
        )  # fmt: skip
    words = np.zeros(9, np.uint64)
    # recvmmsg's fields are strided views of its structured arrays (numba's layout "A").
    i64, u32, u64 = (np.zeros(4, t)[::2] for t in (np.int64, np.uint32, np.uint64))
    ks["mmsg_read_back"](
        u32, i64, u64, i64, i64, np.int64(0), 32, True, 0, 0, np.empty(2, np.int64),
        np.empty(2, np.int64),
    )  # fmt: skip
    ks["same_headers"](words, one, 9, words, one, np.uint64(1), np.empty((5, 1), np.uint64))
    jit_clock.exercise(ks)


def _njit(numba: Any, **options: Any) -> Callable[[Callable[..., Any]], Any]:
    """numba's ``njit`` with its on-disk cache (``__pycache__`` beside this file, else
    ``NUMBA_CACHE_DIR``, else a per-user folder), or compiled at every start when none of
    them can be written (a read-only install under systemd's ``ProtectSystem=strict``)."""

    def decorate(fn: Callable[..., Any]) -> Any:
        try:
            return numba.njit(cache=True, **options)(fn)
        except RuntimeError as exc:  # "cannot cache function ...: no locator available"
            log.info("numba cannot cache its compiled kernels here (%s): compiling them", exc)
            return numba.njit(cache=False, **options)(fn)

    return decorate


def _compile(numba: Any) -> dict[str, Callable[..., Any]]:
    """The kernels, jitted lazily (compiled at their first call, cached on disk)."""
    dh_forward = _kinematics_kernel(numba)
    return {
        **jit_clock.kernels(numba, _njit, dh_forward),
        "align_rows": _align_kernel(numba),
        "dh_forward": dh_forward,
        **_decode_kernels(numba),
        **_receive_kernels(numba),
    }


def _kinematics_kernel(numba: Any) -> Any:
    import math

    import numpy as np

    @_njit(numba, nogil=True, boundscheck=False)
    def dh_forward(Q, rows, frac, between, off, ca, sa, a, d, out):  # type: ignore[no-untyped-def]
        """Forward kinematics into ``out`` (P, 4, 4): of the joint vectors ``Q`` (P, 6), or,
        ``between``, of ``Q[rows] + (Q[rows + 1] - Q[rows]) * frac`` (``Q`` (n, >= 6) joint
        samples; numpy's interpolation, bit for bit). Each pose the product of the six DH
        matrices ``Rz(q + off) Tz(d) Tx(a) Rx(alpha)`` (``ca``, ``sa``: cos and sin alpha),
        the last row kept implicit until written."""
        q = np.empty(6)
        for p in range(out.shape[0]):
            if between:
                k, f = rows[p], frac[p]
                for j in range(6):
                    q[j] = Q[k, j] + (Q[k + 1, j] - Q[k, j]) * f
            else:
                for j in range(6):
                    q[j] = Q[p, j]
            T = out[p]
            for i in range(6):
                c, s = math.cos(q[i] + off[i]), math.sin(q[i] + off[i])
                # Rows 0-1 of the joint's matrix (rows 2-3: 0, sa, ca, d and 0, 0, 0, 1).
                r0 = (c, -s * ca[i], s * sa[i], a[i] * c)
                r1 = (s, c * ca[i], -c * sa[i], a[i] * s)
                if i == 0:
                    for col in range(4):
                        T[0, col], T[1, col] = r0[col], r1[col]
                    T[2, 0], T[2, 1], T[2, 2], T[2, 3] = 0.0, sa[i], ca[i], d[i]
                    continue
                for r in range(3):
                    t0, t1, t2 = T[r, 0], T[r, 1], T[r, 2]
                    T[r, 0] = t0 * r0[0] + t1 * r1[0]
                    T[r, 1] = t0 * r0[1] + t1 * r1[1] + t2 * sa[i]
                    T[r, 2] = t0 * r0[2] + t1 * r1[2] + t2 * ca[i]
                    T[r, 3] = t0 * r0[3] + t1 * r1[3] + t2 * d[i] + T[r, 3]
            T[3, 0], T[3, 1], T[3, 2], T[3, 3] = 0.0, 0.0, 0.0, 1.0

    return dh_forward


def _align_kernel(numba: Any) -> Any:
    import numpy as np

    # No fast-math licence: a sensor's codes decoded here (z = code * scale + offset) give the
    # bits numpy's decoding gives, so coded and decoded profiles align alike.
    jit = _njit(numba, nogil=True, boundscheck=False)

    @jit
    def align_rows(y, z, valid, has_mask, A, out, scale, offset):  # type: ignore[no-untyped-def]
        """Eq. (1) for P profiles into ``out``, the (M, 3) float32 output rows flat (3 M,):
        ``y`` (1 or P, N) float64, ``z`` (P, N) metres ``z * scale + offset`` (float64 with 1
        and 0, or a sensor's integer codes), ``valid`` (P, N) (read when ``has_mask``), ``A``
        (P, 3, 3) float32 rows of ``[R[:, 1] | R[:, 2] | t]``. Returns the output rows
        written, or -1 - row of the first valid point whose result is not finite."""
        p, n = z.shape
        shared = y.shape[0] == 1
        idx = np.empty(n, np.int64)
        k = 0  # output values written, three a point
        for i in range(p):
            yi = y[0] if shared else y[i]
            zi = z[i]
            a00, a01, a02 = A[i, 0, 0], A[i, 0, 1], A[i, 0, 2]
            a10, a11, a12 = A[i, 1, 0], A[i, 1, 1], A[i, 1, 2]
            a20, a21, a22 = A[i, 2, 0], A[i, 2, 1], A[i, 2, 2]
            nv = n
            if has_mask:
                vi = valid[i]
                nv = 0
                for j in range(n):
                    nv += vi[j]
            start = k
            if nv == n:  # the usual profile, every point valid: no compaction, vectorised
                o = out[k : k + 3 * n]
                for j in range(n):
                    yy, zz = np.float32(yi[j]), np.float32(np.float64(zi[j]) * scale + offset)
                    o[3 * j] = a00 * yy + a01 * zz + a02
                    o[3 * j + 1] = a10 * yy + a11 * zz + a12
                    o[3 * j + 2] = a20 * yy + a21 * zz + a22
                k += 3 * n
            elif nv:
                # The valid points' indices first (a store per point, no branch: a branch per
                # point mispredicts on scattered invalid ones), then those points computed.
                m = 0
                for j in range(n):
                    idx[m] = j
                    m += vi[j]
                o = out[k : k + 3 * m]
                for t in range(m):
                    j = idx[t]
                    yy, zz = np.float32(yi[j]), np.float32(np.float64(zi[j]) * scale + offset)
                    o[3 * t] = a00 * yy + a01 * zz + a02
                    o[3 * t + 1] = a10 * yy + a11 * zz + a12
                    o[3 * t + 2] = a20 * yy + a21 * zz + a22
                k += 3 * m
            # Not finite: the exponent's bits all set. An integer count vectorises where a
            # float sum (NaN-propagating) would keep the loop above scalar, 4x slower.
            bits = out[start:k].view(np.uint32)  # a slice's view: the count vectorises
            nbad = 0
            for r in range(k - start):
                nbad += (bits[r] & 0x7F800000) == 0x7F800000
            if nbad:
                for r in range(k - start):
                    if (bits[r] & 0x7F800000) == 0x7F800000:
                        return -1 - (start + r) // 3
        return k // 3

    return align_rows


def _decode_kernels(numba: Any) -> dict[str, Any]:
    import numpy as np

    # No fast-math licence at all: the values must be numpy's multiply-then-add, bit for bit.
    exact = _njit(numba, nogil=True, boundscheck=False)

    @exact
    def scale_codes(codes, rows, stride, at, scale, offset, sentinel, z, valid):  # type: ignore[no-untyped-def]
        """Integer point codes to metres for P profiles in one call: ``z[i, j] =
        float64(codes[rows[i] * stride + at + j]) * scale + offset`` (``codes`` 1-D
        int16/int32, e.g. a receive buffer seen as such, ``stride`` and ``at`` counted in
        codes; ``z`` (P, N) float64), NaN and ``valid`` False where the code is ``sentinel``.
        Returns the number of invalid points."""
        p, n = z.shape
        bad = 0
        for i in range(p):
            s = rows[i] * stride + at
            src = codes[s : s + n]  # a contiguous slice: the loops vectorise
            zi, vi = z[i], valid[i]
            for j in range(n):
                zi[j] = np.float64(src[j]) * scale + offset
            nv = 0
            for j in range(n):
                ok = src[j] != sentinel
                vi[j] = ok
                nv += ok
            if nv != n:  # a few invalid points: NaN there
                for j in range(n):
                    if not vi[j]:
                        zi[j] = np.nan
            bad += n - nv
        return bad

    @exact
    def same_headers(words, rows, stride, mask, lengths, limit, out):  # type: ignore[no-untyped-def]
        """Datagrams with one header: ``words`` the receive buffer as uint64, datagram i's
        header at word ``rows[i] * stride``. True when every header equals the first under
        ``mask`` (its W words), every length the first's and every word 2 is below ``limit``;
        the headers' first F words are copied into ``out`` (F, P) meanwhile. False at the
        first datagram that differs."""
        k = rows.shape[0]
        nw, nf = mask.shape[0], out.shape[0]
        s0 = rows[0] * stride
        for i in range(k):
            s = rows[i] * stride
            if lengths[i] != lengths[0] or words[s + 2] >= limit:
                return False
            for w in range(nw):
                if (words[s + w] ^ words[s0 + w]) & mask[w]:
                    return False
            for f in range(nf):
                out[f, i] = words[s + f]
        return True

    @exact
    def take_codes(buf, rows, stride, at, sentinel, codes, valid):  # type: ignore[no-untyped-def]
        """P profiles' integer codes copied out of ``buf`` (1-D int16/int32, profile i's
        at ``rows[i] * stride + at``, counted in codes) into ``codes`` (P, N), ``valid`` False
        where one is ``sentinel``. Returns the number of invalid points."""
        p, n = codes.shape
        bad = 0
        for i in range(p):
            s = rows[i] * stride + at
            src, ci, vi = buf[s : s + n], codes[i], valid[i]
            nv = 0
            for j in range(n):
                c = src[j]
                ci[j] = c
                ok = c != sentinel
                vi[j] = ok
                nv += ok
            bad += n - nv
        return bad

    return {"scale_codes": scale_codes, "same_headers": same_headers, "take_codes": take_codes}


def _receive_kernels(numba: Any) -> dict[str, Any]:
    import numpy as np

    exact = _njit(numba, nogil=True, boundscheck=False)

    @exact
    def mmsg_read_back(  # type: ignore[no-untyped-def]
        lens, lt, ctrl_len, sec, nsec, lt_want, ctrl_want, stamped, offset, now, lengths, stamps
    ):
        """``recvmmsg``'s results for the first P = ``lengths.shape[0]`` datagrams: their
        lengths and total bytes; their receipt times ``sec * 10**9 + nsec - offset``, never
        after ``now``, when ``stamped`` and every datagram's control message is a timestamp
        (``lt == lt_want``, ``ctrl_len >= ctrl_want``), else ``now``."""
        n = lengths.shape[0]
        total = 0
        for i in range(n):
            lengths[i] = lens[i]
            total += lens[i]
            if lt[i] != lt_want or ctrl_len[i] < ctrl_want:
                stamped = False
        for i in range(n):
            t = sec[i] * 1_000_000_000 + nsec[i] - offset if stamped else now
            stamps[i] = min(t, now)
        return total

    @exact
    def counter_gaps(c, mask, max_step):  # type: ignore[no-untyped-def]
        """Frame counters ``c`` (uint64) that simply continue: each 1 to ``max_step`` after the
        one before it (differences taken modulo ``mask + 1``). Returns the frames missing
        between them, or -1 when they do not continue."""
        one = np.uint64(1)
        missing = np.uint64(0)
        for i in range(1, c.shape[0]):
            step = (c[i] - c[i - 1]) & mask
            if step - one >= max_step:  # a step of 0 wraps to the top
                return np.int64(-1)
            missing += step - one
        return np.int64(missing)

    return {"mmsg_read_back": mmsg_read_back, "counter_gaps": counter_gaps}
