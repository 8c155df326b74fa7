"""Recorded sweeps as the solvers use them: a recording of the acquisition (profiles paired with
flange poses while the robot moved) reduced to a :class:`RecordedSweep` (a seeded subset of its
valid points, where and which way it went), how much of the ball it saw
(:func:`ball_coverage`), and a manual round trip split into its two passes
(:func:`split_round_trip`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye
from wristscan.daemon.procedure.acquisition import Sweep as RecordedData

__all__ = [
    "MIN_BALL_POINTS",
    "RecordedData",
    "RecordedSweep",
    "SweepStage",
    "ball_coverage",
    "base_label",
    "near_ball",
    "reduce_sweep",
    "relabel",
    "sample_indices",
    "split_round_trip",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

MIN_BALL_POINTS = 200
"""Fewest points near the ball for a sweep (or a pass's sphere fit) to count."""

SweepStage = Literal["find", "fov", "tilt", "check"]


@dataclass(frozen=True, eq=False)
class RecordedSweep:
    """One recorded pass, reduced to what the solvers use.

    ``sweep`` holds the kept points (at most ``max_points_per_sweep``, spread over all profiles)
    with the flange pose of every profile, in time order. ``group`` numbers the orientation (0:
    the start orientation of the FOV stage, 1...: tilts, -1: check scan); ``location`` numbers the
    place swept (a forward and a backward pass share it); ``direction`` is +1 along sensor +X,
    -1 back, 0 unknown (manual)."""

    stage: SweepStage
    group: int
    location: int
    direction: int
    label: str
    sweep: handeye.Sweep
    exposure_ns: IntArray
    n_points_recorded: int

    @property
    def n_profiles(self) -> int:
        return self.sweep.n_poses

    @property
    def travel_m(self) -> float:
        F = self.sweep.flange2base
        return float(np.linalg.norm(F[-1, :3, 3] - F[0, :3, 3]))

    def for_solver(self) -> handeye.Sweep:
        """The sweep as the paper's two-step method wants it: a backward pass reversed in time
        (the solver takes the first pose as the reference and the travel along sensor +X)."""
        if self.direction >= 0:
            return self.sweep
        s = self.sweep
        return handeye.Sweep(s.flange2base[::-1], s.points_sensor, s.n_poses - 1 - s.pose_index)


def relabel(w: RecordedSweep, label: str) -> RecordedSweep:
    """``w`` named ``label``, with " fwd" / " bwd" after it for a pass of a pair."""
    suffix = {1: " fwd", -1: " bwd"}.get(w.direction, "")
    return dataclasses.replace(w, label=label + suffix)


def base_label(label: str) -> str:
    """The name of a sweep's place: its label without " fwd" / " bwd"."""
    return label.removesuffix(" fwd").removesuffix(" bwd")


def ball_coverage(rs: RecordedSweep) -> tuple[float, float]:
    """How much of the travel saw the ball: the extent (m) of the flange positions of the
    profiles with kept points along the sweep's direction, and the longest gap (m) between
    consecutive ones. A gap comes from profiles the synchroniser could not pair."""
    s = rs.sweep
    if s.n_points == 0:
        return 0.0, 0.0
    prof = np.unique(s.pose_index)
    T = s.flange2base[:, :3, 3]
    d = T[-1] - T[0]
    n = float(np.linalg.norm(d))
    if n == 0.0:
        return 0.0, 0.0
    pos = np.sort((T[prof] - T[0]) @ (d / n))
    gap = float(np.max(np.diff(pos))) if pos.size > 1 else 0.0
    return float(pos[-1] - pos[0]), gap


def _slice_recording(data: RecordedData, lo: int, hi: int) -> RecordedData:
    """Profiles ``lo`` to ``hi - 1`` of a recording, with their points."""
    keep = (data.profile_index >= lo) & (data.profile_index < hi)
    return RecordedData(
        y=data.y[keep],
        z=data.z[keep],
        valid=data.valid[keep],
        profile_index=data.profile_index[keep] - lo,
        flange2base=data.flange2base[lo:hi],
        exposure_ns=data.exposure_ns[lo:hi],
        table_angle=None if data.table_angle is None else data.table_angle[lo:hi],
    )


def split_round_trip(data: RecordedData, min_travel_m: float = 5e-3) -> list[RecordedData]:
    """A recording that went across and came back (manual mode: "across the ball and back") as
    its two legs, split where the travel along its main direction turns; any other recording
    as is. The legs of a round trip are a forward/backward pair (see
    :func:`~.solve.apparent_latency`)."""
    P = data.n_profiles
    if P < 10:
        return [data]
    T = data.flange2base[:, :3, 3]
    d = T - T[0]
    _, _, Vt = np.linalg.svd(d - d.mean(axis=0), full_matrices=False)
    pos = d @ Vt[0]
    turn = int(np.argmax(np.abs(pos)))
    reach = abs(float(pos[turn]))
    if reach < min_travel_m or abs(float(pos[-1])) > 0.4 * reach or turn in (0, P - 1):
        return [data]
    return [_slice_recording(data, 0, turn + 1), _slice_recording(data, turn, P)]


def reduce_sweep(
    data: RecordedData,
    max_points: int,
    keep: Callable[[handeye.Sweep], BoolArray] | None = None,
) -> tuple[handeye.Sweep, int]:
    """The valid points of a recording as a :class:`handeye.Sweep` (at most ``max_points``, a
    seeded random subset) and how many valid points there were. ``keep`` may drop
    points first (e.g. those far from the predicted ball)."""
    ok = data.valid & np.isfinite(data.y) & np.isfinite(data.z)
    idx = np.flatnonzero(ok)
    n_valid = int(idx.size)
    full = handeye.Sweep.from_yz(
        data.flange2base, data.y[idx], data.z[idx], data.profile_index[idx]
    )
    if keep is not None and full.n_points:
        full = full.subset(keep(full))
    if full.n_points > max_points:
        pick = sample_indices(full.n_points, max_points)
        full = handeye.Sweep(full.flange2base, full.points_sensor[pick], full.pose_index[pick])
    return full, n_valid


def sample_indices(n: int, k: int, seed: int = 0) -> IntArray:
    """``k`` of ``n`` indices, sorted, drawn at random with a fixed seed. Not a stride: points
    come ordered by profile and ray, and a stride could keep the same rays of every profile."""
    if k >= n:
        return np.arange(n, dtype=np.int64)
    return np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False)).astype(np.int64)


def near_ball(
    X: FloatArray, centre: FloatArray, radius: float, band_m: float
) -> Callable[[handeye.Sweep], BoolArray]:
    """A ``keep`` for :func:`reduce_sweep`: the points within ``band_m`` of the ball surface
    predicted with sensor2flange ``X`` (drops clutter: the post, the table)."""

    def keep(s: handeye.Sweep) -> BoolArray:
        d = np.linalg.norm(s.points_base(X) - centre, axis=1)
        return np.asarray(np.abs(d - radius) <= band_m, dtype=bool)

    return keep
