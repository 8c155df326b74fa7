"""Eq. (1) for batches of profiles: sensor points into the base, table or part frame.

``sensor2part = table2part(theta_R) @ base2table @ flange2base(q) @ sensor2flange`` (DESIGN.md).
A profile point ``(y, z)`` (metres, laser plane = sensor Y-Z plane) is the sensor-frame point
``(0, y, z)``.

The P sensor poses of a batch are composed once; points then pick their pose through
``profile_index``. Since x = 0, only columns 1 and 2 of each rotation and the translation matter:
``xyz = R[:, 1] y + R[:, 2] z + t``. Two evaluation paths give the same numbers:

* whole profiles of equal length in profile order (what the pipeline builds; pass invalid points
  through ``mask`` rather than removing them, to stay on this path): one small matrix product per
  profile inside numpy's batched ``matmul``, in cache-sized blocks;
* any other ``profile_index``: per-coordinate gathers of the pose coefficients, in blocks.
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3, table
from wristscan.calib.se3 import FloatArray

__all__ = [
    "Frame",
    "align",
    "align_and_poses",
    "align_with_poses",
    "profile_points",
    "sensor_poses",
]

log = logging.getLogger(__name__)

Frame = Literal["base", "table", "part"]
_FRAMES = ("base", "table", "part")
_BLOCK_POINTS = 16384
"""Points per block: keeps the temporaries in the CPU cache (measured best 8k-64k)."""


def profile_points(y: ArrayLike, z: ArrayLike) -> FloatArray:
    """Sensor-frame points ``(N, 3)`` (metres) from profile coordinates ``y, z`` (N,): x = 0."""
    ya = np.asarray(y, dtype=np.float64)
    za = np.asarray(z, dtype=np.float64)
    if ya.ndim != 1 or ya.shape != za.shape:
        raise ValueError(f"y and z must be 1-D of equal length, got {ya.shape} and {za.shape}")
    out = np.zeros((ya.shape[0], 3))
    out[:, 1] = ya
    out[:, 2] = za
    return out


def sensor_poses(
    flange2base: ArrayLike,
    sensor2flange: ArrayLike,
    base2table: ArrayLike | None = None,
    table_angle_rad: ArrayLike | None = None,
    encoder_offset_rad: float = 0.0,
    frame: Frame = "base",
) -> FloatArray:
    """Sensor poses ``sensor2<frame>`` (P, 4, 4) of P profiles.

    ``flange2base`` (P, 4, 4) is the robot pose at each profile instant, ``sensor2flange`` (4, 4)
    the tool transformation. ``frame="table"`` needs ``base2table`` (4, 4); ``frame="part"`` also
    needs ``table_angle_rad`` (P,) or a scalar (rad, encoder reading) and uses
    ``encoder_offset_rad``. Arguments a frame does not need are ignored.
    """
    if frame not in _FRAMES:
        raise ValueError(f"frame must be one of {_FRAMES}, got {frame!r}")
    F = se3.check_transform(flange2base, "flange2base")
    if F.ndim != 3:
        raise ValueError(f"flange2base: expected (P, 4, 4), got shape {F.shape}")
    S = se3.check_transform(sensor2flange, "sensor2flange")
    if S.shape != (4, 4):
        raise ValueError(f"sensor2flange: expected (4, 4), got shape {S.shape}")
    poses: FloatArray = F @ S
    if frame == "base":
        return poses
    if base2table is None:
        raise ValueError(f"frame {frame!r} needs base2table (run the table calibration)")
    B = se3.check_transform(base2table, "base2table")
    if B.shape != (4, 4):
        raise ValueError(f"base2table: expected (4, 4), got shape {B.shape}")
    poses = B @ poses
    if frame == "table":
        return poses
    if table_angle_rad is None:
        raise ValueError("frame 'part' needs table_angle_rad (one angle per profile)")
    th = np.asarray(table_angle_rad, dtype=np.float64)
    if th.ndim == 0:
        th = np.full(F.shape[0], float(th))
    if th.shape != (F.shape[0],):
        raise ValueError(f"table_angle_rad: expected ({F.shape[0]},) or a scalar, got {th.shape}")
    return table.table2part(th, encoder_offset_rad) @ poses


def align(
    y: ArrayLike,
    z: ArrayLike,
    profile_index: ArrayLike,
    flange2base: ArrayLike,
    sensor2flange: ArrayLike,
    base2table: ArrayLike | None = None,
    table_angle_rad: ArrayLike | None = None,
    encoder_offset_rad: float = 0.0,
    frame: Frame = "base",
    mask: ArrayLike | None = None,
) -> FloatArray:
    """Points ``(y, z)`` (N,) of a batch of P profiles into ``frame``: returns ``xyz`` (M, 3)
    float64 metres, M = N or the number of ``mask``-true points (invalid points are dropped,
    order kept).

    ``profile_index`` (N,) integer, the profile of each point (0 <= index < P). Pose arguments as
    in :func:`sensor_poses`. Raises ``ValueError`` on bad shapes, indices or transforms, and on
    non-finite coordinates among the kept points (mark those invalid with ``mask``).
    """
    return align_and_poses(
        y,
        z,
        profile_index,
        flange2base,
        sensor2flange,
        base2table,
        table_angle_rad,
        encoder_offset_rad,
        frame,
        mask,
    )[0]


def align_and_poses(
    y: ArrayLike,
    z: ArrayLike,
    profile_index: ArrayLike,
    flange2base: ArrayLike,
    sensor2flange: ArrayLike,
    base2table: ArrayLike | None = None,
    table_angle_rad: ArrayLike | None = None,
    encoder_offset_rad: float = 0.0,
    frame: Frame = "base",
    mask: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray]:
    """:func:`align`, also returning the sensor poses ``sensor2<frame>`` (P, 4, 4) the points
    went through (the daemon publishes them beside the cloud), composed and checked once."""
    poses = sensor_poses(
        flange2base, sensor2flange, base2table, table_angle_rad, encoder_offset_rad, frame
    )
    return _align_points(y, z, profile_index, poses, mask), poses


def align_with_poses(
    y: ArrayLike,
    z: ArrayLike,
    profile_index: ArrayLike,
    sensor2frame: ArrayLike,
    mask: ArrayLike | None = None,
) -> FloatArray:
    """As :func:`align` with the sensor poses ``sensor2frame`` (P, 4, 4) already composed."""
    poses = se3.check_transform(sensor2frame, "sensor2frame")
    if poses.ndim != 3:
        raise ValueError(f"sensor2frame: expected (P, 4, 4), got {poses.shape}")
    return _align_points(y, z, profile_index, poses, mask)


def _align_points(
    y: ArrayLike,
    z: ArrayLike,
    profile_index: ArrayLike,
    poses: FloatArray,
    mask: ArrayLike | None,
) -> FloatArray:
    """Shared body of :func:`align` and :func:`align_with_poses`; ``poses`` are validated."""
    ya = np.asarray(y, dtype=np.float64)
    za = np.asarray(z, dtype=np.float64)
    idx = np.asarray(profile_index)
    if ya.ndim != 1 or ya.shape != za.shape or idx.shape != ya.shape:
        raise ValueError(
            f"y, z, profile_index must be 1-D of equal length, got {ya.shape}, {za.shape}, "
            f"{idx.shape}"
        )
    if idx.dtype.kind not in "iu":
        raise ValueError(f"profile_index must be an integer array, got dtype {idx.dtype}")
    n_prof = poses.shape[0]
    m: NDArray[np.bool_] | None = None
    if mask is not None:
        m = np.asarray(mask)
        if m.dtype != np.bool_ or m.shape != ya.shape:
            raise ValueError(f"mask: expected bool ({ya.shape[0]},), got {m.dtype} {m.shape}")
    n = ya.shape[0]
    if n == 0:
        return np.zeros((0, 3))
    lo, hi = int(idx.min()), int(idx.max())
    if lo < 0 or hi >= n_prof:
        raise ValueError(f"profile_index out of range [0, {n_prof}): min {lo}, max {hi}")

    # Per-profile coefficients A (P, 3, 3), rows = R[:, 1], R[:, 2], t, so xyz = [y z 1] @ A.
    A = np.ascontiguousarray(poses[:, :3, 1:4].transpose(0, 2, 1))
    run = _regular_run(idx)
    out, finite = _eval_regular(ya, za, idx, A, run) if run else _eval_general(ya, za, idx, A)
    if m is not None and not bool(m.all()):
        out = _keep_rows(out, m)
    # The poses are finite, so only non-finite inputs (checked per block, in cache) can give a
    # non-finite point; the full test on the kept rows runs only then.
    if not finite:
        bad = np.flatnonzero(~np.all(np.isfinite(out), axis=1))
        if bad.size:
            raise ValueError(
                f"{bad.size} kept points have non-finite coordinates (first at output row "
                f"{bad[0]}); mark invalid points with mask"
            )
    return out


def _keep_rows(out: FloatArray, m: NDArray[np.bool_]) -> FloatArray:
    """``out[m]`` for a C-contiguous (N, 3) float64 array, several times faster: each row is
    moved as one 24-byte item instead of going through numpy's row-wise boolean indexing."""
    rows = out.view(np.dtype((np.void, 24))).reshape(-1)
    kept: FloatArray = rows[m].view(np.float64).reshape(-1, 3)
    return kept


def _all_finite(a: FloatArray) -> bool:
    return bool(np.isfinite(a).all())


def _regular_run(idx: NDArray[np.integer]) -> int:
    """Length n of the runs if ``idx`` is sorted and splits into runs of n equal indices, else 0."""
    if idx.shape[0] > 1 and not bool(np.all(idx[1:] >= idx[:-1])):
        return 0
    n = int(np.searchsorted(idx, idx[0], side="right"))
    if idx.shape[0] % n:
        return 0
    rows = idx.reshape(-1, n)
    # Sorted, so a row is constant iff its ends agree.
    return n if bool(np.all(rows[:, 0] == rows[:, -1])) else 0


def _eval_regular(
    y: FloatArray, z: FloatArray, idx: NDArray[np.integer], A: FloatArray, n: int
) -> tuple[FloatArray, bool]:
    """Whole profiles of n points in order: returns (xyz (N, 3), all y and z finite)."""
    rows = idx[::n].astype(np.intp)
    q = rows.shape[0]
    Y = y.reshape(q, n)
    Z = z.reshape(q, n)
    out = np.empty((q, n, 3))
    block = max(1, _BLOCK_POINTS // n)
    S = np.empty((min(block, q), 3, n))
    S[:, 2] = 1.0
    finite = True
    for a in range(0, q, block):
        b = min(a + block, q)
        s = S[: b - a]
        s[:, 0] = Y[a:b]
        s[:, 1] = Z[a:b]
        finite = finite and _all_finite(s[:, :2])
        # (m, n, 3) @ (m, 3, 3): one small product per profile, done by numpy's matmul loop.
        np.matmul(s.transpose(0, 2, 1), A[rows[a:b]], out=out[a:b])
    return out.reshape(q * n, 3), finite


def _eval_general(
    y: FloatArray, z: FloatArray, idx: NDArray[np.integer], A: FloatArray
) -> tuple[FloatArray, bool]:
    """Any profile order: returns (xyz (N, 3), all y and z finite)."""
    n = y.shape[0]
    out = np.empty((n, 3))
    # coef[j][r] (P,): coefficient r (of y, z, 1) of output coordinate j, contiguous for take().
    coef = [[np.ascontiguousarray(A[:, r, j]) for r in range(3)] for j in range(3)]
    blk = min(_BLOCK_POINTS * 2, n)
    t1 = np.empty(blk)
    t2 = np.empty(blk)
    finite = True
    for a in range(0, n, blk):
        b = min(a + blk, n)
        i = idx[a:b].astype(np.intp)
        u, v, ya, za = t1[: b - a], t2[: b - a], y[a:b], z[a:b]
        finite = finite and _all_finite(ya) and _all_finite(za)
        for j in range(3):
            np.take(coef[j][0], i, out=u)
            u *= ya
            np.take(coef[j][1], i, out=v)
            v *= za
            u += v
            np.take(coef[j][2], i, out=v)
            u += v
            out[a:b, j] = u
    return out, finite
