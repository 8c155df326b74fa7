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
from collections.abc import Callable
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import jit, se3, table
from wristscan.calib.se3 import FloatArray

__all__ = [
    "Frame",
    "align",
    "align_and_poses",
    "align_rows",
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
    checked: bool = True,
) -> FloatArray:
    """Sensor poses ``sensor2<frame>`` (P, 4, 4) of P profiles.

    ``flange2base`` (P, 4, 4) is the robot pose at each profile instant, ``sensor2flange`` (4, 4)
    the tool transformation. ``frame="table"`` needs ``base2table`` (4, 4); ``frame="part"`` also
    needs ``table_angle_rad`` (P,) or a scalar (rad, encoder reading) and uses
    ``encoder_offset_rad``. Arguments a frame does not need are ignored. ``checked=False`` skips
    validating the transforms (for trusted ones: kinematics, a loaded calibration).
    """
    if frame not in _FRAMES:
        raise ValueError(f"frame must be one of {_FRAMES}, got {frame!r}")
    # The hot path passes transforms made by forward kinematics and a calibration checked when
    # it was loaded (``checked=False``): checking 50 poses a batch cost ~2 us per profile.
    check = se3.check_transform if checked else (lambda t, _: np.asarray(t, dtype=np.float64))
    F = check(flange2base, "flange2base")
    if F.ndim != 3:
        raise ValueError(f"flange2base: expected (P, 4, 4), got shape {F.shape}")
    S = check(sensor2flange, "sensor2flange")
    if S.shape != (4, 4):
        raise ValueError(f"sensor2flange: expected (4, 4), got shape {S.shape}")
    poses: FloatArray = F @ S
    if frame == "base":
        return poses
    if base2table is None:
        raise ValueError(f"frame {frame!r} needs base2table (run the table calibration)")
    B = check(base2table, "base2table")
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


_ROW_BLOCK_POINTS = 8192
"""Points per block of :func:`align_rows`: its float32 scratch stays in the core's cache
(4 profiles of 2048 measured best of 1-50)."""
_VOID12 = np.dtype((np.void, 12))


def align_rows(
    y: ArrayLike,
    z: ArrayLike,
    valid: ArrayLike | None,
    sensor2frame: NDArray[np.floating],
    out: NDArray[np.float32] | None = None,
    check_finite: bool = True,
    z_scale: tuple[float, float] | None = None,
) -> NDArray[np.float32]:
    """Eq. (1) for whole profiles in float32, straight into ``out``: the hot path's alignment.

    ``y`` (N,) lateral grid shared by every profile, or (P, N); ``z`` (P, N) metres; ``valid``
    (P, N) bool or None (all valid); ``sensor2frame`` (P, 4, 4) composed and checked
    (:func:`sensor_poses`). Returns ``xyz`` (M, 3) float32 metres, the valid points of profile 0,
    then 1, ..., in grid order (M = valid points). ``out``, when given, is a C-contiguous (M, 3)
    float32 array the points are written into (in the daemon a WSC1 payload's view,
    ``Wsc1Frame.xyz``) and is returned. Each profile's transform is cast to float32 once and
    every point computed in float32 (error against the float64 :func:`align` 0.12 um for points
    within 2 m of the frame's origin: benchmarks/calib_align.py).
    Invalid points may hold anything (NaN); a non-finite valid point raises ``ValueError``
    unless ``check_finite`` is False (the check costs ~1 us per 2048-point profile: a caller
    whose decoder makes every valid point finite may skip it).
    ``z_scale`` ``(scale, offset)``: ``z`` holds a sensor's integer codes, ``z = codes * scale +
    offset`` metres (float64, multiply then add), decoded in the compiled pass as it reads them
    (a quarter of float64 z's bytes to read).
    """
    if z_scale is not None and jit.kernel("align_rows") is None:  # numpy: decoded first
        z = np.asarray(z).astype(np.float64) * z_scale[0] + z_scale[1]
        z_scale = None
    ya, za, m = _rows_inputs(y, z, valid, z_scale is None)
    poses = np.asarray(sensor2frame)
    p, n = za.shape
    if poses.shape != (p, 4, 4):
        raise ValueError(f"sensor2frame: expected ({p}, 4, 4) for {p} profiles, got {poses.shape}")
    n_out = p * n if m is None else int(np.count_nonzero(m))
    if out is None:
        out = np.empty((n_out, 3), np.float32)
    elif (
        out.dtype != np.float32 or out.shape != (n_out, 3) or not out.flags.c_contiguous
    ) or not out.flags.writeable:
        raise ValueError(
            f"out: expected a writable C-contiguous float32 ({n_out}, 3) array, got "
            f"{out.dtype} {out.shape}"
        )
    if n_out == 0:
        return out
    kern = jit.kernel("align_rows")
    if kern is not None:
        _rows_jit(kern, ya, za, m, poses, out, check_finite, z_scale or (1.0, 0.0))
        return out
    # inf * 0 in the products of invalid points is no error: they are dropped
    with np.errstate(invalid="ignore", over="ignore"):
        _rows_into(ya, za, m, poses, out, check_finite)
    return out


_NO_MASK = np.ones((1, 1), np.bool_)


def _rows_jit(
    kern: Callable[..., int],
    ya: FloatArray,
    za: FloatArray,
    m: NDArray[np.bool_] | None,
    poses: NDArray[np.floating],
    out: NDArray[np.float32],
    check_finite: bool,
    z_scale: tuple[float, float],
) -> None:
    """:func:`align_rows`' work in one compiled pass (:mod:`.jit`): the same float32 transform
    per profile, the same points to float32 rounding."""
    A = np.ascontiguousarray(poses[:, :3, 1:4], dtype=np.float32)
    # The grid copied (N values): a read-only shared grid would be a second compiled variant.
    y2 = np.array(ya.reshape(1, -1) if ya.ndim == 1 else ya, np.float64, order="C")
    z2 = za if za.flags.c_contiguous and za.flags.writeable else np.array(za, order="C")
    mask = _NO_MASK if m is None else np.ascontiguousarray(m)
    got = int(kern(y2, z2, mask, m is not None, A, out.reshape(-1), *z_scale))
    if got >= 0 or not check_finite:
        return
    if m is None:  # as the numpy path: the inputs name what is wrong
        _check_finite(ya, "y")
        _check_finite(za, "z")
    raise ValueError(
        f"valid points with non-finite coordinates (first at output row {-1 - got}); "
        "mark them invalid"
    )


def _rows_into(
    ya: FloatArray,
    za: FloatArray,
    m: NDArray[np.bool_] | None,
    poses: NDArray[np.floating],
    out: NDArray[np.float32],
    check_finite: bool,
) -> None:
    """:func:`align_rows`' work, block by block of whole profiles."""
    p, n = za.shape
    # A (P, 3, 3): rows R[:, 1], R[:, 2], t of each pose, cast to float32 once; a point of
    # profile i is A[i] @ [y, z, 1].
    A = poses[:, :3, 1:4].astype(np.float32)
    rows = max(1, min(p, _ROW_BLOCK_POINTS // n))
    # The rows y, z, 1 of a block's profiles, coordinate-major so that each is contiguous; a
    # shared grid and the ones are written once.
    S = np.empty((3, rows, n), np.float32)
    S[2] = 1.0
    if ya.ndim == 1:
        S[0] = ya
    if check_finite and m is None:  # every point valid: the inputs tell, one pass each
        _check_finite(ya, "y")
        _check_finite(za, "z")
    planar = np.empty((rows, 3, n), np.float32)
    inter = None if m is None else np.empty((rows, n, 3), np.float32)
    dst = out.view(_VOID12).reshape(-1)
    start = 0
    for a in range(0, p, rows):
        b = min(a + rows, p)
        k = b - a
        s, res = S[:, :k], planar[:k]
        if ya.ndim == 2:
            s[0] = ya[a:b]
        s[1] = za[a:b]
        # (k, 3, 3) @ (k, 3, n): planar, what numpy's matmul does fast (the interleaved
        # (k, n, 3) @ (k, 3, 3) takes ~1.6x as long).
        np.matmul(A[a:b], s.transpose(1, 0, 2), out=res)
        if inter is None or m is None:
            end = b * n
            _interleave(res, out[start:end].reshape(k, n, 3))
        else:
            _interleave(res, inter[:k])
            # The kept 12-byte rows moved as one item each: a boolean index of the rows as
            # np.void items is faster than np.take, np.compress or per-coordinate compaction
            # (2x on runs of invalid points, 1.3x scattered), and than (M, 3) row indexing.
            kept = inter[:k].reshape(-1).view(_VOID12)[m[a:b].reshape(-1)]
            end = start + kept.shape[0]
            dst[start:end] = kept
        start = end
    if check_finite and m is not None:
        # The poses are finite: only a non-finite valid input makes a non-finite point.
        _check_finite(out, "point")


def _check_finite(a: NDArray[np.floating], what: str) -> None:
    """Raise ``ValueError`` if ``a`` holds a non-finite value; rows of ``a`` are profiles (y, z)
    or output rows (point). ``np.isfinite(a).all()``, not a dot product of ``a`` with itself:
    that is faster alone, but OpenBLAS runs it on several threads from 10 000 elements, whose
    spinning took the hot path from 7 to 30-45 us per profile on a 2-core machine."""
    if bool(np.isfinite(a).all()):
        return
    bad = np.flatnonzero(~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1))
    if what == "point":
        raise ValueError(
            f"valid points with non-finite coordinates (first at output row {bad[0]}); "
            "mark them invalid"
        )
    where = "the lateral grid" if a.ndim == 1 else f"profile {bad[0]}"
    raise ValueError(f"non-finite {what} in {where}: mark such points invalid")


def _interleave(planar: NDArray[np.float32], dst: NDArray[np.float32]) -> None:
    """(k, 3, n) into (k, n, 3), one coordinate at a time (a single transposing copy walks the
    3-long axis innermost and is ~5x slower)."""
    for j in range(3):
        dst[:, :, j] = planar[:, j]


def _rows_inputs(
    y: ArrayLike, z: ArrayLike, valid: ArrayLike | None, z_float: bool = True
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_] | None]:
    """:func:`align_rows`' arrays checked: y (N,) or (P, N), z (P, N), valid (P, N) bool or None
    (also when every point is valid: the output is then written without compaction)."""
    ya = np.asarray(y, dtype=np.float64)
    za = np.asarray(z, dtype=np.float64) if z_float else np.asarray(z)  # codes: as they are
    if za.ndim != 2:
        raise ValueError(f"z: expected (P, N) profiles x points, got shape {za.shape}")
    if ya.shape not in ((za.shape[1],), za.shape):
        raise ValueError(
            f"y: expected ({za.shape[1]},) or {za.shape} for z {za.shape}, got {ya.shape}"
        )
    if valid is None:
        return ya, za, None
    m = np.asarray(valid)
    if m.dtype != np.bool_ or m.shape != za.shape:
        raise ValueError(f"valid: expected bool {za.shape}, got {m.dtype} {m.shape}")
    return ya, za, None if bool(m.all()) else m
