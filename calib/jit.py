"""Compiled loops for the daemon's hot path (extra ``fast``: numba), with numpy as the fallback.

numpy needs several passes over a profile's points for what one loop does in one: the float32
alignment of :func:`wristscan.calib.align.align_rows` costs ~7-8 us per 2048-point profile in
numpy (cast, matmul, three strided copies into the interleaved output, the finiteness check) and
~2.2 us compiled (benchmarks/calib_align.py ``--hot``). The kernels are compiled when first
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
    """The compiled kernel ``name`` (compiled or loaded on the first call), or None when
    numba is missing or the kernels are switched off."""
    if not enabled:
        return None
    ks = _kernels if _tried else _build()
    return None if ks is None else ks[name]


def available() -> bool:
    """The kernels are in use (numba importable and not switched off)."""
    return kernel("align_rows") is not None


def warm() -> float:
    """Compile (or load) every kernel now, not on the first profile; returns the seconds it
    took (0 when they are not in use)."""
    t0 = time.perf_counter()
    if not available():
        return 0.0
    import numpy as np

    ks = _kernels
    assert ks is not None
    out = np.empty((2, 3), np.float32)
    ks["align_rows"](
        np.zeros((1, 2)), np.zeros((1, 2)), np.ones((1, 2), np.bool_), True,
        np.zeros((1, 3, 3), np.float32), out,
    )  # fmt: skip
    return time.perf_counter() - t0


def _build() -> dict[str, Callable[..., Any]] | None:
    global _kernels, _tried
    with _lock:
        if _tried:
            return _kernels
        try:
            import numba
        except ImportError:
            log.info(
                "numba is not installed: the hot path runs on numpy (pip install 'wristscan[fast]')"
            )
            _tried = True
            return None
        t0 = time.perf_counter()
        _kernels = _compile(numba)
        _tried = True
        log.debug("hot-path kernels ready in %.2f s (numba %s)", time.perf_counter() - t0,
                  numba.__version__)  # fmt: skip
        return _kernels


def _compile(numba: Any) -> dict[str, Callable[..., Any]]:
    """The kernels, jitted lazily (compiled at their first call, cached on disk)."""
    import numpy as np

    # 'contract' lets a multiply and an add fuse (FMA); no other fast-math licence, so the
    # finiteness test below is kept.
    jit = numba.njit(cache=True, nogil=True, boundscheck=False, fastmath={"contract"})

    @jit
    def align_rows(y, z, valid, has_mask, A, out):  # type: ignore[no-untyped-def]
        """Eq. (1) for P profiles into ``out`` (M, 3) float32: ``y`` (1 or P, N) float64,
        ``z`` (P, N) float64, ``valid`` (P, N) (read when ``has_mask``), ``A`` (P, 3, 3)
        float32 rows of ``[R[:, 1] | R[:, 2] | t]``. Returns the output rows written, or
        -1 - row of the first valid point whose result is not finite."""
        p, n = z.shape
        shared = y.shape[0] == 1
        tmp = np.empty((3, n), np.float32)
        k = 0
        for i in range(p):
            yi = y[0] if shared else y[i]
            zi = z[i]
            a00, a01, a02 = A[i, 0, 0], A[i, 0, 1], A[i, 0, 2]
            a10, a11, a12 = A[i, 1, 0], A[i, 1, 1], A[i, 1, 2]
            a20, a21, a22 = A[i, 2, 0], A[i, 2, 1], A[i, 2, 2]
            for j in range(n):
                yy = np.float32(yi[j])
                zz = np.float32(zi[j])
                tmp[0, j] = a00 * yy + a01 * zz + a02
                tmp[1, j] = a10 * yy + a11 * zz + a12
                tmp[2, j] = a20 * yy + a21 * zz + a22
            start = k
            # x - x is 0 for a finite x and NaN otherwise: one sum tells (no branch per point)
            bad = np.float32(0.0)
            if has_mask:
                vi = valid[i]
                for j in range(n):
                    if vi[j]:
                        x0, x1, x2 = tmp[0, j], tmp[1, j], tmp[2, j]
                        out[k, 0] = x0
                        out[k, 1] = x1
                        out[k, 2] = x2
                        bad += (x0 - x0) + (x1 - x1) + (x2 - x2)
                        k += 1
            else:
                for j in range(n):
                    x0, x1, x2 = tmp[0, j], tmp[1, j], tmp[2, j]
                    out[k + j, 0] = x0
                    out[k + j, 1] = x1
                    out[k + j, 2] = x2
                    bad += (x0 - x0) + (x1 - x1) + (x2 - x2)
                k += n
            if bad != 0.0:
                for r in range(start, k):
                    if not (np.isfinite(out[r, 0]) and np.isfinite(out[r, 1])
                            and np.isfinite(out[r, 2])):  # fmt: skip
                        return -1 - r
        return k

    return {"align_rows": align_rows}
