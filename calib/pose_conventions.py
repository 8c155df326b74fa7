"""Robot pose notations of the controllers a stop-and-go data set may come from.

A flange pose is written as a position ``x, y, z`` and an orientation whose columns depend on the
controller:

==================  ========================  ==================================================
convention          orientation columns       rotation
==================  ========================  ==================================================
``ur-rotvec``       ``rx, ry, rz``            rotation vector (axis times angle, radians)
``fanuc-xyzwpr``    ``w, p, r`` (degrees)     ``R = Rz(r) Ry(p) Rx(w)`` (fixed axes X, Y, Z)
``kuka-abc``        ``a, b, c`` (degrees)     ``R = Rz(a) Ry(b) Rx(c)``
``abb-quaternion``  ``q1, q2, q3, q4``        unit quaternion, ``q1`` the scalar part
``matrix``          ``r11 .. r33`` (row-major) the rotation matrix itself
==================  ========================  ==================================================

:func:`to_matrix` turns rows of these numbers (positions in metres) into ``flange2base``
transforms ``(N, 4, 4)``; :func:`from_matrix` writes transforms in a notation. Quaternions and
matrices are checked (a quaternion's norm within :data:`UNIT_TOL` of 1, a matrix orthonormal
within :data:`ORTHO_TOL`, determinant +1) and then normalised, so that numbers printed to six or
so digits are accepted. A bad row raises :class:`PoseRowError` naming the row (0-based).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from wristscan.calib import se3

__all__ = [
    "CONVENTIONS",
    "ORTHO_TOL",
    "UNIT_TOL",
    "PoseRowError",
    "columns",
    "from_matrix",
    "to_matrix",
]

FloatArray = NDArray[np.float64]

CONVENTIONS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        "ur-rotvec": ("rx", "ry", "rz"),
        "fanuc-xyzwpr": ("w", "p", "r"),
        "kuka-abc": ("a", "b", "c"),
        "abb-quaternion": ("q1", "q2", "q3", "q4"),
        "matrix": tuple(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)),
    }
)
"""The orientation columns of each convention, in file order."""

UNIT_TOL = 1e-3
"""Largest accepted deviation of a quaternion's norm from 1."""
ORTHO_TOL = 1e-3
"""Largest accepted entry of ``R^T R - I`` of a rotation matrix."""


class PoseRowError(ValueError):
    """A pose that is not a valid rigid transform; ``row`` is its 0-based row."""

    def __init__(self, row: int, message: str) -> None:
        super().__init__(message)
        self.row = row


def columns(convention: str) -> tuple[str, ...]:
    """All columns of a pose in ``convention``: ``x, y, z`` and the orientation's."""
    return ("x", "y", "z", *_orientation_columns(convention))


def _orientation_columns(convention: str) -> tuple[str, ...]:
    try:
        return CONVENTIONS[convention]
    except KeyError:
        raise ValueError(
            f"unknown pose convention {convention!r}; one of {', '.join(CONVENTIONS)}"
        ) from None


def to_matrix(convention: str, values: ArrayLike) -> FloatArray:
    """``flange2base`` ``(N, 4, 4)`` from rows ``(N, 3 + k)``: ``x, y, z`` (metres) and the
    ``k`` orientation numbers of ``convention`` (see the module doc)."""
    ori = _orientation_columns(convention)
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 + len(ori):
        raise ValueError(f"{convention}: expected rows of {3 + len(ori)} numbers, got {v.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
    if bad.size:
        raise PoseRowError(int(bad[0]), "holds a value that is not a finite number")
    o = v[:, 3:]
    if convention == "ur-rotvec":
        R = se3.rotvec_to_matrix(o)
    elif convention == "fanuc-xyzwpr":
        R = Rotation.from_euler("ZYX", o[:, ::-1], degrees=True).as_matrix()
    elif convention == "kuka-abc":
        R = Rotation.from_euler("ZYX", o, degrees=True).as_matrix()
    elif convention == "abb-quaternion":
        R = _quaternions(o)
    else:
        R = _matrices(o.reshape(-1, 3, 3))
    T = np.broadcast_to(np.eye(4), (v.shape[0], 4, 4)).copy()
    T[:, :3, :3] = R
    T[:, :3, 3] = v[:, :3]
    return T


def _quaternions(q: FloatArray) -> FloatArray:
    n = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(n - 1.0) > UNIT_TOL)
    if bad.size:
        k = int(bad[0])
        raise PoseRowError(k, f"quaternion norm {n[k]:.6g}, not 1 (a unit quaternion is needed)")
    qn = q / n[:, None]
    return se3.quat_wxyz_to_matrix(qn)


def _matrices(M: FloatArray) -> FloatArray:
    E = np.abs(np.swapaxes(M, -1, -2) @ M - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(M)
    bad = np.flatnonzero((E > ORTHO_TOL) | (det <= 0.0))
    if bad.size:
        k = int(bad[0])
        what = "a reflection (determinant < 0)" if det[k] <= 0 else f"not orthonormal ({E[k]:.3g})"
        raise PoseRowError(k, f"rotation matrix is {what}")
    U, _, Vt = np.linalg.svd(M)
    return np.asarray(U @ Vt, dtype=np.float64)


def from_matrix(convention: str, flange2base: ArrayLike) -> FloatArray:
    """Rows ``(N, 3 + k)`` in ``convention`` (positions in metres) from transforms
    ``(N, 4, 4)``: the inverse of :func:`to_matrix`."""
    _orientation_columns(convention)
    T = np.asarray(flange2base, dtype=np.float64).reshape(-1, 4, 4)
    R = T[:, :3, :3]
    if convention == "ur-rotvec":
        o = se3.matrix_to_rotvec(R)
    elif convention == "fanuc-xyzwpr":
        o = Rotation.from_matrix(R).as_euler("ZYX", degrees=True)[:, ::-1]
    elif convention == "kuka-abc":
        o = Rotation.from_matrix(R).as_euler("ZYX", degrees=True)
    elif convention == "abb-quaternion":
        o = se3.matrix_to_quat_wxyz(R)
    else:
        o = R.reshape(-1, 9)
    return np.concatenate([T[:, :3, 3], o], axis=1)
