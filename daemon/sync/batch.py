"""The pairer's output: :class:`PairedBatch`, profiles paired with their robot (and table)
states as flat arrays ready for vectorised alignment, and :func:`concat_batches` to join
consecutive ones (the points are copied once).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["PairedBatch", "concat_batches"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


@dataclass
class PairedBatch:
    """Profiles paired with their robot state, ready for vectorised alignment.

    Per profile ``(P,)``: ``sensor_id``, ``frame_counter``, ``exposure_ns`` and ``arrival_ns``
    (host monotonic: the estimated exposure and the driver's receipt), ``clock_uncertainty_ns``,
    ``flange2base (P, 4, 4)``, ``table_angle`` (rad) or None.
    Per point ``(N,)``: ``y``, ``z`` (m, sensor frame), ``valid``, ``intensity`` (only when every
    profile has one), ``profile_index`` into the profiles; profile ``k`` owns points
    ``offsets[k]:offsets[k + 1]``.
    """

    sensor_id: NDArray[np.int64]
    frame_counter: IntArray
    exposure_ns: IntArray
    clock_uncertainty_ns: FloatArray
    flange2base: FloatArray
    table_angle: FloatArray | None
    y: FloatArray
    z: FloatArray
    valid: NDArray[np.bool_]
    intensity: NDArray[np.uint8] | None
    profile_index: NDArray[np.uint32]
    offsets: IntArray
    arrival_ns: IntArray | None = None

    @property
    def n_profiles(self) -> int:
        return int(self.exposure_ns.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.y.shape[0])


def concat_batches(batches: list[PairedBatch]) -> PairedBatch:
    """One batch of the profiles of ``batches``, in order (the points are copied once)."""
    if len(batches) == 1:
        return batches[0]

    def cat(name: str) -> Any:
        parts = [getattr(b, name) for b in batches]
        return None if any(p is None for p in parts) else np.concatenate(parts)

    sizes = [b.n_profiles for b in batches]
    first = np.cumsum([0, *sizes[:-1]])
    point_base = np.cumsum([0, *[b.n_points for b in batches[:-1]]])
    index = np.concatenate(
        [b.profile_index + np.uint32(f) for b, f in zip(batches, first, strict=True)]
    )
    offsets = np.concatenate(
        [[0], *[b.offsets[1:] + p for b, p in zip(batches, point_base, strict=True)]]
    ).astype(np.int64)
    return PairedBatch(
        sensor_id=cat("sensor_id"),
        frame_counter=cat("frame_counter"),
        exposure_ns=cat("exposure_ns"),
        clock_uncertainty_ns=cat("clock_uncertainty_ns"),
        flange2base=cat("flange2base"),
        table_angle=cat("table_angle"),
        y=cat("y"),
        z=cat("z"),
        valid=cat("valid"),
        intensity=cat("intensity"),
        profile_index=index,
        offsets=offsets,
        arrival_ns=cat("arrival_ns"),
    )
