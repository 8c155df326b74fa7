"""Forward kinematics of the small batches the pairer asks for every tick (up to
:data:`MATMUL_MAX` poses): compiled (:mod:`wristscan.calib.jit`, ``dh_forward``) when numba is
installed, else the six DH matrices multiplied as stacks (per-call cost, not arithmetic, rules
small batches). :func:`wristscan.calib.kinematics.forward` and ``forward_between`` call here."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import jit
from wristscan.calib.dh import DHParams

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

MATMUL_MAX = 256
"""Up to this many poses ``forward`` comes here; beyond, it accumulates the chain's columns."""


@functools.lru_cache(maxsize=64)
def _dh_constants(model: DHParams) -> tuple[FloatArray, ...]:
    """``theta_offset``, then ``cos alpha``, ``sin alpha``, ``a``, ``d`` as ``(6, 1)`` columns."""
    d, a, alpha, off = model.arrays()
    return off, np.cos(alpha)[:, None], np.sin(alpha)[:, None], a[:, None], d[:, None]


@functools.lru_cache(maxsize=64)
def dh_table(model: DHParams) -> FloatArray:
    """``theta_offset``, ``cos alpha``, ``sin alpha``, ``a``, ``d`` as the rows of one (5, 6)
    array: the constants the compiled kernels take (``dh_forward`` and those that call it)."""
    off, ca, sa, a, d = _dh_constants(model)
    return np.stack([off, ca[:, 0], sa[:, 0], a[:, 0], d[:, 0]])


@functools.lru_cache(maxsize=64)
def _dh_rows(model: DHParams) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``theta_offset`` and the DH matrices ``Rz Tz Tx Rx`` of the six joints as constants:
    their first two rows are ``cos theta * Kc + sin theta * Ks`` (``(6, 8, 1)``: the rows'
    eight entries, poses last), the last two ``K23`` (``(6, 1, 2, 4)``)."""
    off, ca, sa, a, d = _dh_constants(model)
    Kc = np.zeros((6, 2, 4))
    Ks = np.zeros((6, 2, 4))
    K23 = np.zeros((6, 1, 2, 4))
    Kc[:, 0, 0] = 1.0
    Kc[:, 0, 3] = a[:, 0]
    Kc[:, 1, 1] = ca[:, 0]
    Kc[:, 1, 2] = -sa[:, 0]
    Ks[:, 0, 1] = -ca[:, 0]
    Ks[:, 0, 2] = sa[:, 0]
    Ks[:, 1, 0] = 1.0
    Ks[:, 1, 3] = a[:, 0]
    K23[:, 0, 0, 1] = sa[:, 0]
    K23[:, 0, 0, 2] = ca[:, 0]
    K23[:, 0, 0, 3] = d[:, 0]
    K23[:, 0, 1, 3] = 1.0
    return off, Kc.reshape(6, 8, 1), Ks.reshape(6, 8, 1), K23


def _forward_matmul(model: DHParams, qa: FloatArray) -> FloatArray:
    """:func:`forward` as the product of the six DH matrices ``Rz Tz Tx Rx``, built for all
    joints at once (joint axis first, so each product takes contiguous stacks). Each entry of
    their first two rows is ``c * k + s * 0`` or ``c * 0 + s * k``: the same products as
    entry by entry, in a few whole-array steps (per-call cost dominates small batches)."""
    off, Kc, Ks, K23 = _dh_rows(model)
    th = (qa.reshape(-1, 6) + off).T
    P = th.shape[1]
    top = np.cos(th)[:, None, :] * Kc
    top += np.sin(th)[:, None, :] * Ks
    A = np.empty((6, P, 4, 4))
    A[:, :, 2:] = K23
    A[:, :, :2] = top.transpose(0, 2, 1).reshape(6, P, 2, 4)
    T = A[0] @ A[1]
    for i in range(2, 6):
        np.matmul(T, A[i], out=A[i - 2])
        T = A[i - 2]
    return T.reshape(*qa.shape[:-1], 4, 4)


def forward_small(m: DHParams, qa: FloatArray) -> FloatArray:
    """``flange2base`` (..., 4, 4) of ``qa`` (..., 6), at most :data:`MATMUL_MAX` poses."""
    kern = jit.kernel("dh_forward")
    if kern is None:
        return _forward_matmul(m, qa)
    out = np.empty((*qa.shape[:-1], 4, 4))
    # Compiled (the pairer's batch per tick): a quarter of the numpy steps' time per call.
    _forward_jit(kern, m, np.ascontiguousarray(qa).reshape(-1, 6), None, None, out)
    return out


def between_small(
    m: DHParams, samples: FloatArray, rows: IntArray, frac: FloatArray
) -> FloatArray | None:
    """``forward_between`` in one compiled call (the joints interpolated in the kernel, the same
    bits as numpy's); None when it does not apply (no numba, too many poses, not float64)."""
    kern = jit.kernel("dh_forward")
    M = rows.shape[0]
    if kern is None or M > MATMUL_MAX or samples.dtype != np.float64:
        return None
    out = np.empty((M, 4, 4))
    _forward_jit(kern, m, np.ascontiguousarray(samples), rows.astype(np.int64, copy=False),
                 frac.astype(np.float64, copy=False), out)  # fmt: skip
    return out


def _forward_jit(
    kern: Any, m: DHParams, Q: FloatArray, rows: IntArray | None, frac: FloatArray | None,
    out: FloatArray,
) -> None:  # fmt: skip
    off, ca, sa, a, d = _dh_constants(m)
    between = rows is not None and frac is not None
    if not between:
        rows, frac = _NO_ROWS, _NO_FRAC
    kern(Q, rows, frac, between, off, ca[:, 0], sa[:, 0], a[:, 0], d[:, 0], out.reshape(-1, 4, 4))


_NO_ROWS, _NO_FRAC = np.zeros(1, np.int64), np.zeros(1)
