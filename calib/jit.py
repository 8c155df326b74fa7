"""Compiled loops for the daemon's hot path (extra ``fast``: numba), with numpy as the fallback.

numpy needs several passes over a profile's points for what one loop does in one: the float32
alignment of :func:`wristscan.calib.align.align_rows` with its WSC1 frame costs 8-20 us per
2048-point profile in numpy (cast, matmul, three strided copies into the interleaved output, the
compaction of invalid points, the finiteness check) and 4-8 us compiled (benchmarks/calib_align.py
``--hot``, all valid to 30 % invalid scattered). The kernels are compiled when first
asked for (:func:`warm`; ~0.3-0.6 s, then loaded from numba's on-disk cache) so that a process
that never aligns never imports numba.

Without numba, or with the environment variable ``WRISTSCAN_JIT=0``, every caller takes its
numpy path; the two agree to float32 rounding (tests/calib/test_align_rows.py runs both).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

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

    out = np.empty((2, 3), np.float32)
    ks["align_rows"](
        np.zeros((1, 2)), np.zeros((1, 2)), np.ones((1, 2), np.bool_), True,
        np.zeros((1, 3, 3), np.float32), out,
    )  # fmt: skip


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
    import numpy as np

    # 'contract' lets a multiply and an add fuse (FMA); no other fast-math licence, so the
    # finiteness test below is kept.
    jit = _njit(numba, nogil=True, boundscheck=False, fastmath={"contract"})

    @jit
    def align_rows(y, z, valid, has_mask, A, out):  # type: ignore[no-untyped-def]
        """Eq. (1) for P profiles into ``out`` (M, 3) float32: ``y`` (1 or P, N) float64,
        ``z`` (P, N) float64, ``valid`` (P, N) (read when ``has_mask``), ``A`` (P, 3, 3)
        float32 rows of ``[R[:, 1] | R[:, 2] | t]``. Returns the output rows written, or
        -1 - row of the first valid point whose result is not finite."""
        p, n = z.shape
        shared = y.shape[0] == 1
        k = 0
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
            # x - x is 0 for a finite x and NaN otherwise: one sum tells (no branch per point)
            bad = np.float32(0.0)
            if nv == n:  # the usual profile, every point valid: no compaction
                o = out[k : k + n]
                for j in range(n):
                    yy, zz = np.float32(yi[j]), np.float32(zi[j])
                    x0 = a00 * yy + a01 * zz + a02
                    x1 = a10 * yy + a11 * zz + a12
                    x2 = a20 * yy + a21 * zz + a22
                    o[j, 0], o[j, 1], o[j, 2] = x0, x1, x2
                    bad += (x0 - x0) + (x1 - x1) + (x2 - x2)
                k += n
            elif nv:
                for j in range(n):
                    if vi[j]:
                        yy, zz = np.float32(yi[j]), np.float32(zi[j])
                        x0 = a00 * yy + a01 * zz + a02
                        x1 = a10 * yy + a11 * zz + a12
                        x2 = a20 * yy + a21 * zz + a22
                        out[k, 0], out[k, 1], out[k, 2] = x0, x1, x2
                        bad += (x0 - x0) + (x1 - x1) + (x2 - x2)
                        k += 1
            if bad != 0.0:
                for r in range(start, k):
                    if not (np.isfinite(out[r, 0]) and np.isfinite(out[r, 1])
                            and np.isfinite(out[r, 2])):  # fmt: skip
                        return -1 - r
        return k

    return {"align_rows": align_rows}
