"""Rigid transforms in SE(3), named by frames.

Conventions (see DESIGN.md):

* A transform ``a2b`` is a ``(..., 4, 4)`` float array that maps coordinates in frame ``a`` into
  frame ``b``: ``p_b = a2b @ p_a``.  Composition reads right to left:
  ``sensor2base = flange2base @ sensor2flange``.
* Rotation vectors are UR style (axis times angle, radians).
* Quaternions are always named by their component order: ``wxyz`` (scalar first) or ``xyzw``
  (scalar last, as scipy uses).
* A UR pose ``p[x, y, z, rx, ry, rz]`` holds metres and a rotation vector.

Every function takes batched inputs: leading dimensions broadcast where it makes sense.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]

__all__ = [
    "FloatArray",
    "apply",
    "check_transform",
    "compose",
    "identity",
    "interpolate",
    "invert",
    "make",
    "matrix_to_pose",
    "matrix_to_quat_wxyz",
    "matrix_to_quat_xyzw",
    "matrix_to_rotvec",
    "pose_to_matrix",
    "quat_wxyz_to_matrix",
    "quat_xyzw_to_matrix",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_angle",
    "rotvec_to_matrix",
    "translation",
]


def _as_float(a: ArrayLike) -> FloatArray:
    return np.asarray(a, dtype=np.float64)


def _rotations(fn_input: FloatArray, last: tuple[int, ...]) -> tuple[tuple[int, ...], FloatArray]:
    """Split leading batch shape off and flatten for scipy (which wants (N, ...))."""
    lead = fn_input.shape[: fn_input.ndim - len(last)]
    if fn_input.shape[fn_input.ndim - len(last) :] != last:
        raise ValueError(f"expected trailing shape {last}, got {fn_input.shape}")
    return lead, fn_input.reshape((-1, *last))


def rotvec_to_matrix(rotvec: ArrayLike) -> FloatArray:
    """Rotation vectors ``(..., 3)`` (radians) to rotation matrices ``(..., 3, 3)``."""
    lead, flat = _rotations(_as_float(rotvec), (3,))
    return Rotation.from_rotvec(flat).as_matrix().reshape((*lead, 3, 3))


def matrix_to_rotvec(R: ArrayLike) -> FloatArray:
    """Rotation matrices ``(..., 3, 3)`` to rotation vectors ``(..., 3)``; angle in [0, pi]."""
    lead, flat = _rotations(_as_float(R), (3, 3))
    return Rotation.from_matrix(flat).as_rotvec().reshape((*lead, 3))


def quat_xyzw_to_matrix(q: ArrayLike) -> FloatArray:
    """Quaternions in ``x, y, z, w`` order (scalar last) to rotation matrices."""
    lead, flat = _rotations(_as_float(q), (4,))
    return Rotation.from_quat(flat).as_matrix().reshape((*lead, 3, 3))


def quat_wxyz_to_matrix(q: ArrayLike) -> FloatArray:
    """Quaternions in ``w, x, y, z`` order (scalar first) to rotation matrices."""
    q = _as_float(q)
    return quat_xyzw_to_matrix(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def matrix_to_quat_xyzw(R: ArrayLike) -> FloatArray:
    """Rotation matrices to unit quaternions ``x, y, z, w`` (scalar last, w >= 0)."""
    lead, flat = _rotations(_as_float(R), (3, 3))
    q = Rotation.from_matrix(flat).as_quat(canonical=True)
    return q.reshape((*lead, 4))


def matrix_to_quat_wxyz(R: ArrayLike) -> FloatArray:
    """Rotation matrices to unit quaternions ``w, x, y, z`` (scalar first, w >= 0)."""
    q = matrix_to_quat_xyzw(R)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def rot_x(angle_rad: ArrayLike) -> FloatArray:
    """Rotation matrix about X by ``angle_rad`` (batched)."""
    a = _as_float(angle_rad)
    return rotvec_to_matrix(np.stack([a, np.zeros_like(a), np.zeros_like(a)], axis=-1))


def rot_y(angle_rad: ArrayLike) -> FloatArray:
    """Rotation matrix about Y by ``angle_rad`` (batched)."""
    a = _as_float(angle_rad)
    return rotvec_to_matrix(np.stack([np.zeros_like(a), a, np.zeros_like(a)], axis=-1))


def rot_z(angle_rad: ArrayLike) -> FloatArray:
    """Rotation matrix about Z by ``angle_rad`` (batched)."""
    a = _as_float(angle_rad)
    return rotvec_to_matrix(np.stack([np.zeros_like(a), np.zeros_like(a), a], axis=-1))


def identity(shape: tuple[int, ...] = ()) -> FloatArray:
    """Identity transforms of batch shape ``shape``."""
    return np.broadcast_to(np.eye(4), (*shape, 4, 4)).copy()


def make(R: ArrayLike | None = None, t: ArrayLike | None = None) -> FloatArray:
    """Build ``(..., 4, 4)`` transforms from rotations ``(..., 3, 3)`` and translations ``(..., 3)``
    (metres). Either may be omitted (identity rotation, zero translation)."""
    Ra = np.eye(3) if R is None else _as_float(R)
    ta = np.zeros(3) if t is None else _as_float(t)
    lead = np.broadcast_shapes(Ra.shape[:-2], ta.shape[:-1])
    T = identity(lead)
    T[..., :3, :3] = Ra
    T[..., :3, 3] = ta
    return T


def translation(T: ArrayLike) -> FloatArray:
    """Translation part ``(..., 3)`` of transforms."""
    return _as_float(T)[..., :3, 3].copy()


def invert(T: ArrayLike) -> FloatArray:
    """Inverse of rigid transforms (uses R^T, not a general matrix inverse): ``a2b -> b2a``."""
    Ta = _as_float(T)
    R = Ta[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(Ta)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, Ta[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def compose(*transforms: ArrayLike) -> FloatArray:
    """Product left to right: ``compose(b2c, a2b) == b2c @ a2b == a2c`` (batched, broadcast)."""
    if not transforms:
        raise ValueError("compose needs at least one transform")
    out = _as_float(transforms[0])
    for T in transforms[1:]:
        out = out @ _as_float(T)
    return out


def apply(T: ArrayLike, points: ArrayLike) -> FloatArray:
    """Map points ``(..., N, 3)`` through transforms ``(..., 4, 4)``: returns ``(..., N, 3)``."""
    Ta = _as_float(T)
    p = _as_float(points)
    R = Ta[..., None, :3, :3]
    return np.einsum("...ij,...j->...i", R, p) + Ta[..., None, :3, 3]


def pose_to_matrix(pose: ArrayLike) -> FloatArray:
    """UR poses ``p[x, y, z, rx, ry, rz]`` ``(..., 6)`` (metres, rotation vector) to transforms."""
    p = _as_float(pose)
    if p.shape[-1] != 6:
        raise ValueError(f"a UR pose has 6 values, got shape {p.shape}")
    return make(rotvec_to_matrix(p[..., 3:]), p[..., :3])


def matrix_to_pose(T: ArrayLike) -> FloatArray:
    """Transforms to UR poses ``(..., 6)``: metres and a rotation vector (angle in [0, pi])."""
    Ta = _as_float(T)
    return np.concatenate([Ta[..., :3, 3], matrix_to_rotvec(Ta[..., :3, :3])], axis=-1)


def rotation_angle(R: ArrayLike) -> FloatArray:
    """Rotation angle (radians, [0, pi]) of rotation matrices ``(..., 3, 3)``, accurate near 0."""
    return np.linalg.norm(matrix_to_rotvec(R), axis=-1)


def interpolate(T0: ArrayLike, T1: ArrayLike, s: ArrayLike) -> FloatArray:
    """Geodesic interpolation between transforms: translation linear, rotation along the shortest
    arc (slerp). ``s`` in [0, 1] broadcasts against the batch shape; ``s=0`` gives ``T0``."""
    A = _as_float(T0)
    B = _as_float(T1)
    sa = _as_float(s)
    R0 = A[..., :3, :3]
    dR = np.swapaxes(R0, -1, -2) @ B[..., :3, :3]
    rv = matrix_to_rotvec(dR)
    R = R0 @ rotvec_to_matrix(rv * sa[..., None])
    t = A[..., :3, 3] + (B[..., :3, 3] - A[..., :3, 3]) * sa[..., None]
    return make(R, t)


def check_transform(T: ArrayLike, name: str = "transform", tol: float = 1e-6) -> FloatArray:
    """Validate rigid transforms at an API boundary; raises ``ValueError`` naming ``name``."""
    Ta = _as_float(T)
    if Ta.shape[-2:] != (4, 4):
        raise ValueError(f"{name}: expected (..., 4, 4), got shape {Ta.shape}")
    if not np.all(np.isfinite(Ta)):
        raise ValueError(f"{name}: contains NaN or infinity")
    R = Ta[..., :3, :3]
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(initial=0.0)
    if err > tol:
        raise ValueError(f"{name}: rotation part is not orthonormal (error {err:.2e})")
    if np.any(np.linalg.det(R) < 0):
        raise ValueError(f"{name}: rotation part is a reflection (det < 0)")
    if np.abs(Ta[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0) > tol:
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1]")
    return Ta
