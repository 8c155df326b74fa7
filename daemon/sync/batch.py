"""The pairer's output: :class:`PairedBatch`, profiles paired with their robot (and table)
states, ready for vectorised alignment, and :func:`concat_batches` to join consecutive ones.

A batch's points are held as :class:`Segment` s, runs of consecutive profiles that are views of
the blocks they arrived in (no copy); the flat per-point arrays (``y``, ``z``, ``valid``,
``intensity``, ``profile_index``) are built from them when first read. An aligner that works
segment by segment (:meth:`PairedBatch.segments`) never copies the points.
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from wristscan.drivers.records import PointCodes

__all__ = ["PairedBatch", "Segment", "concat_batches"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class Segment:
    """Profiles ``start:start + n`` of a batch, all of ``N`` points, as ``(n, N)`` arrays
    (usually views of the block they arrived in: read-only by convention). A segment of coded
    points (``codes``: :class:`~wristscan.drivers.records.PointCodes`) decodes ``z`` when it
    is first read; the hot path aligns the codes themselves."""

    __slots__ = ("_z", "codes", "intensity", "start", "valid", "y")

    def __init__(
        self,
        start: int,
        y: FloatArray,
        z: FloatArray | None,
        valid: BoolArray,
        intensity: NDArray[np.uint8] | None,
        codes: PointCodes | None = None,
    ) -> None:
        self.start = start
        self.y = y
        """``(N,)`` when the profiles share one lateral grid, else ``(n, N)``."""
        self._z = z
        self.valid = valid
        self.intensity = intensity
        self.codes = codes

    @property
    def z(self) -> FloatArray:
        if self._z is None:
            assert self.codes is not None
            self._z = self.codes.decode()
        return self._z

    @property
    def points(self) -> FloatArray | PointCodes:
        """``z``, or the codes while they are not decoded (what the hot path aligns)."""
        if self._z is None and self.codes is not None:
            return self.codes
        return self.z

    @property
    def n_profiles(self) -> int:
        return int(self.valid.shape[0])

    def y_rows(self) -> FloatArray:
        """``y`` as ``(n, N)`` (a read-only broadcast view for a shared grid)."""
        return np.broadcast_to(self.y, self.valid.shape) if self.y.ndim == 1 else self.y

    def shifted(self, by: int) -> Segment:
        """The same profiles, ``by`` further into a batch."""
        return Segment(self.start + by, self.y, self._z, self.valid, self.intensity, self.codes)


def _flat_segments(
    offsets: IntArray,
    y: FloatArray | None,
    grid: FloatArray | None,
    z: FloatArray,
    valid: BoolArray,
    intensity: NDArray[np.uint8] | None,
) -> list[Segment]:
    """Segments of flat arrays: runs of consecutive profiles with equal point counts."""
    n = np.diff(offsets)
    cuts = [0, *(np.flatnonzero(n[1:] != n[:-1]) + 1).tolist(), int(n.shape[0])]
    out = []
    for a, b in itertools.pairwise(cuts):
        if a == b:
            continue
        o0, o1, N = int(offsets[a]), int(offsets[b]), int(n[a])

        def part(arr: Any, o0: int = o0, o1: int = o1, N: int = N) -> Any:
            return arr[o0:o1].reshape(-1, N)

        ys = grid if grid is not None and y is None else part(y)
        inten = None if intensity is None else part(intensity)
        out.append(Segment(a, ys, part(z), part(valid), inten))
    return out


class PairedBatch:
    """Profiles paired with their robot state, ready for vectorised alignment.

    Per profile ``(P,)``: ``sensor_id``, ``frame_counter``, ``exposure_ns`` and ``arrival_ns``
    (host monotonic: the estimated exposure and the driver's receipt), ``clock_uncertainty_ns``,
    ``flange2base (P, 4, 4)``, ``table_angle`` (rad) or None.
    Per point: ``y``, ``z`` (m, sensor frame), ``valid``, ``intensity`` (only when every
    profile has one), ``profile_index`` (uint32) into the profiles; profile ``k`` owns points
    ``offsets[k]:offsets[k + 1]``. These flat arrays are built when first read.

    The fast path, without looking at every point: :meth:`segments` (runs of profiles as
    ``(n, N)`` views of the arrived blocks: no copy), ``points_per_profile`` (N when every
    profile has N points, else None), :meth:`rows` (``y``, ``z``, ``valid`` as ``(P, N)``:
    views for one segment, one copy for several) and ``y_grid`` (the lateral grid ``(N,)`` when
    every profile shares it, else None).

    Build it from flat arrays (``y`` or ``y_grid``, ``z``, ``valid``, ``intensity``, and
    ``offsets`` or ``profile_index``) or from ``segments`` and ``offsets``.
    """

    def __init__(
        self,
        sensor_id: IntArray,
        frame_counter: IntArray,
        exposure_ns: IntArray,
        clock_uncertainty_ns: FloatArray,
        flange2base: FloatArray,
        table_angle: FloatArray | None,
        y: FloatArray | None = None,
        z: FloatArray | None = None,
        valid: BoolArray | None = None,
        intensity: NDArray[np.uint8] | None = None,
        profile_index: NDArray[np.integer[Any]] | None = None,
        offsets: IntArray | None = None,
        arrival_ns: IntArray | None = None,
        *,
        y_grid: FloatArray | None = None,
        segments: list[Segment] | None = None,
        points_per_profile: int | None = None,
    ) -> None:
        self.sensor_id = sensor_id
        self.frame_counter = frame_counter
        self.exposure_ns = exposure_ns
        self.clock_uncertainty_ns = clock_uncertainty_ns
        self.flange2base = flange2base
        self.table_angle = table_angle
        self.arrival_ns = arrival_ns
        p = int(exposure_ns.shape[0])
        if offsets is None:
            if profile_index is None:
                raise ValueError("PairedBatch: give offsets or profile_index")
            offsets = np.searchsorted(profile_index, np.arange(p + 1)).astype(np.int64)
        self.offsets = offsets
        self._profile_index = profile_index
        self.y_grid = y_grid
        """The lateral grid ``(N,)`` every profile shares, or None."""
        if segments is None:
            if z is None or valid is None or (y is None and y_grid is None):
                raise ValueError("PairedBatch: give y (or y_grid), z and valid, or segments")
            segments = _flat_segments(offsets, y, y_grid, z, valid, intensity)
        self._segments = segments
        self._y, self._z, self._valid, self._intensity = y, z, valid, intensity
        if z is None and len(segments) == 1:  # one run: flat views, nothing to build
            s = segments[0]
            if s.codes is None:  # coded points: z decoded only if read (self.z)
                self._z = s.z.reshape(-1)
            self._valid = s.valid.reshape(-1)
            self._intensity = None if s.intensity is None else s.intensity.reshape(-1)
            if s.y.ndim == 2:
                self._y = s.y.reshape(-1)
        self._has_intensity = all(s.intensity is not None for s in segments)
        if points_per_profile is None and p and len({s.valid.shape[1] for s in segments}) == 1:
            n = np.diff(offsets)
            points_per_profile = int(n[0]) if n.min() == n.max() else None
        self.points_per_profile = points_per_profile
        """N when every profile has N points, else None (given: not checked)."""

    # ------------------------------------------------------------------ flat arrays

    def _flat(self, name: str) -> Any:
        parts = [getattr(s, name) for s in self._segments]
        if not parts:
            return np.zeros(0, dtype=np.bool_ if name == "valid" else np.float64)
        return np.concatenate([a.reshape(-1) for a in parts])

    @property
    def z(self) -> FloatArray:
        """Range of each point (m), flat."""
        if self._z is None:
            self._z = self._flat("z")
        return self._z

    @property
    def valid(self) -> BoolArray:
        """Whether the sensor measured each point, flat."""
        if self._valid is None:
            self._valid = self._flat("valid")
        return self._valid

    @property
    def intensity(self) -> NDArray[np.uint8] | None:
        """Intensity of each point, flat (None unless every profile has one)."""
        if self._intensity is None and self._has_intensity and self._segments:
            self._intensity = self._flat("intensity")
        return self._intensity if self._has_intensity else None

    @property
    def y(self) -> FloatArray:
        """Lateral coordinate of each point (m), flat."""
        if self._y is None:
            if self.y_grid is not None:
                self._y = np.tile(self.y_grid, self.n_profiles)
            else:
                self._y = np.concatenate([s.y_rows().reshape(-1) for s in self._segments])
        return self._y

    @property
    def profile_index(self) -> NDArray[np.uint32]:
        """The profile of each point (uint32), built from ``offsets`` on first read."""
        if self._profile_index is None:
            n = np.diff(self.offsets)
            self._profile_index = np.repeat(np.arange(n.shape[0], dtype=np.uint32), n)
        return self._profile_index  # type: ignore[return-value]

    # ------------------------------------------------------------------ shape

    @property
    def n_profiles(self) -> int:
        return int(self.exposure_ns.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.offsets[-1])

    def segments(self) -> list[Segment]:
        """The runs of profiles of equal length, in order, as ``(n, N)`` arrays (views)."""
        return list(self._segments)

    def rows(self) -> tuple[FloatArray, FloatArray, BoolArray]:
        """``y``, ``z``, ``valid`` as ``(P, N)`` (views for one segment, a read-only broadcast of
        ``y_grid`` when shared). Only when ``points_per_profile`` is not None."""
        n = self.points_per_profile
        if n is None:
            raise ValueError("PairedBatch.rows: the profiles have different numbers of points")
        p = self.n_profiles
        if self.y_grid is not None:
            y = np.broadcast_to(self.y_grid, (p, n))
        else:
            y = self.y.reshape(p, n)
        return y, self.z.reshape(p, n), self.valid.reshape(p, n)

    def __repr__(self) -> str:
        return (
            f"PairedBatch({self.n_profiles} profiles, {self.n_points} points, "
            f"{len(self._segments)} segments)"
        )


def concat_batches(batches: list[PairedBatch]) -> PairedBatch:
    """One batch of the profiles of ``batches``, in order (their segments are joined: the
    points are not copied until a flat array is read)."""
    if len(batches) == 1:
        return batches[0]

    def cat(name: str) -> Any:
        parts = [getattr(b, name) for b in batches]
        return None if any(p is None for p in parts) else np.concatenate(parts)

    sizes = np.cumsum([0, *[b.n_profiles for b in batches]])
    point_base = np.cumsum([0, *[b.n_points for b in batches[:-1]]])
    offsets = np.concatenate(
        [[0], *[b.offsets[1:] + p for b, p in zip(batches, point_base, strict=True)]]
    ).astype(np.int64)
    grid = batches[0].y_grid
    shared = grid is not None and all(
        b.y_grid is grid or (b.y_grid is not None and np.array_equal(b.y_grid, grid))
        for b in batches[1:]
    )
    segments = [
        s.shifted(int(first))
        for b, first in zip(batches, sizes[:-1], strict=True)
        for s in b.segments()
    ]
    return PairedBatch(
        sensor_id=cat("sensor_id"),
        frame_counter=cat("frame_counter"),
        exposure_ns=cat("exposure_ns"),
        clock_uncertainty_ns=cat("clock_uncertainty_ns"),
        flange2base=cat("flange2base"),
        table_angle=cat("table_angle"),
        offsets=offsets,
        arrival_ns=cat("arrival_ns"),
        y_grid=grid if shared else None,
        segments=segments,
    )
