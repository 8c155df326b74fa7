"""Log a running daemon's clouds into a rerun recording (``wristscan view``; extra ``view``).

What is shown comes only from what the daemon publishes over zenoh (DESIGN.md, zenoh contract):

- ``world/cloud``: each batch as ``Points3D`` at its exposure time, coloured by height (grey
  by intensity when the batch carries it); from ``<prefix>/cloud`` (WSC1);
- ``world/laser_trail``: the path of the laser line, the centroid of each batch as a line;
  from ``<prefix>/cloud``;
- ``world/sensor``: the sensor's pose in the frame of the clouds (axes), at each batch's last
  profile; from ``<prefix>/pose`` (WSP1);
- ``world/flange_trail``: the path of the robot's flange in the frame of the clouds, one point
  per batch (in the table and part frames only once the calibration is known); from
  ``<prefix>/pose``;
- ``calibration/flange/sensor``: the sensor frame relative to the flange (axes), the
  calibration in force; from ``<prefix>/calibration``;
- ``calibration``: the calibration document (JSON text); from ``<prefix>/calibration``.

Timelines: ``exposure`` (the batch's first profile, UTC; a pose at its own profile's exposure)
and ``seq`` (the batch's sequence number).
"""

from __future__ import annotations

import json
from collections import deque
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import se3
from wristscan.daemon.cloud.wsc1 import Cloud
from wristscan.daemon.cloud.wsp1 import PoseBatch

__all__ = ["APP_ID", "LiveView", "ViewUnavailable", "height_colours", "new_recording"]

APP_ID = "wristscan_view"

_VIRIDIS = np.array(
    [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float64
)
"""Anchor colours of the height colour map (viridis at 0, 1/4, 1/2, 3/4, 1)."""


class ViewUnavailable(RuntimeError):
    """rerun-sdk (the ``view`` extra) is not installed."""


def new_recording(application_id: str = APP_ID) -> Any:
    """A ``rerun.RecordingStream`` of its own (no global state); raises :class:`ViewUnavailable`
    naming the extra when rerun-sdk is missing."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise ViewUnavailable(
            f"wristscan view needs rerun-sdk: pip install 'wristscan[view]' ({exc})"
        ) from exc
    return rr.RecordingStream(application_id)


def height_colours(z: NDArray[np.floating], lo: float, hi: float) -> NDArray[np.uint8]:
    """(N, 3) RGB for heights ``z`` on a viridis ramp from ``lo`` to ``hi`` (clipped)."""
    t = np.clip((np.asarray(z, np.float64) - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    pos = t * (len(_VIRIDIS) - 1)
    i = np.minimum(pos.astype(np.int64), len(_VIRIDIS) - 2)
    f = (pos - i)[:, None]
    rgb = _VIRIDIS[i] * (1.0 - f) + _VIRIDIS[i + 1] * f
    return np.round(rgb).astype(np.uint8)


def _matrix(doc: dict[str, Any]) -> NDArray[np.float64] | None:
    """sensor -> flange from the calibration queryable's answer (either the sensor file's
    document, or ``{"sensor2flange": ..., "table": ...}`` in the table and part frames)."""
    inner = doc.get("sensor2flange", doc)
    rows = inner.get("transform", {}).get("matrix_rows") if isinstance(inner, dict) else None
    if rows is None:
        return None
    m = np.asarray(rows, dtype=np.float64)
    return m if m.shape == (4, 4) and np.all(np.isfinite(m)) else None


class LiveView:
    """Logs batches and the calibration into ``rec`` (a ``rerun.RecordingStream``)."""

    def __init__(
        self, rec: Any, trail_batches: int = 5000, trail_every: int = 10, stride: int = 1
    ) -> None:
        """``stride`` > 1 logs every ``stride``-th point of a batch (a lighter recording)."""
        import rerun as rr

        self.rr = rr
        self.rec = rec
        self.batches = 0
        self.points = 0
        self.z_range: tuple[float, float] | None = None
        self.trail: deque[NDArray[np.float64]] = deque(maxlen=trail_batches)
        self.flange_trail: deque[NDArray[np.float64]] = deque(maxlen=trail_batches)
        self.poses = 0
        self.sensor2flange: NDArray[np.float64] | None = None
        self.trail_every = trail_every
        self.stride = max(1, stride)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def calibration(self, doc: dict[str, Any]) -> bool:
        """Log the calibration in force (static); False when it carries no sensor transform."""
        rr = self.rr
        self.rec.log(
            "calibration",
            rr.TextDocument(json.dumps(doc, indent=1), media_type="text/plain"),
            static=True,
        )
        m = _matrix(doc)
        if m is None:
            return False
        self.sensor2flange = m
        self.rec.log(
            "calibration/flange/sensor",
            rr.Transform3D(translation=m[:3, 3], mat3x3=m[:3, :3]),
            rr.TransformAxes3D(0.05),
            static=True,
        )
        self.rec.log("calibration/flange", rr.TransformAxes3D(0.05), static=True)
        return True

    def _colours(self, cloud: Cloud) -> NDArray[np.uint8]:
        if cloud.intensity is not None:
            return np.repeat(cloud.intensity[:: self.stride, None], 3, axis=1)
        z = cloud.xyz[:: self.stride, 2]
        lo, hi = float(z.min()), float(z.max())
        if self.z_range is not None:
            lo, hi = min(lo, self.z_range[0]), max(hi, self.z_range[1])
        self.z_range = (lo, hi)
        return height_colours(z, lo, hi)

    def batch(self, cloud: Cloud) -> None:
        """Log one batch at its exposure time; every ``trail_every`` batches the laser trail."""
        rr = self.rr
        self.rec.set_time("exposure", timestamp=np.datetime64(cloud.t_first_ns, "ns"))
        self.rec.set_time("seq", sequence=cloud.seq)
        self.batches += 1
        if cloud.n_points == 0:
            return
        xyz = cloud.xyz[:: self.stride]
        self.rec.log("world/cloud", rr.Points3D(xyz, colors=self._colours(cloud)))
        self.points += int(xyz.shape[0])
        self.trail.append(cloud.xyz.mean(axis=0, dtype=np.float64))
        if self.batches % self.trail_every == 0:
            self.log_trail()

    def log_trail(self) -> None:
        if len(self.trail) >= 2:
            self.rec.log("world/laser_trail", self.rr.LineStrips3D([np.array(self.trail)]))
        if len(self.flange_trail) >= 2:
            self.rec.log("world/flange_trail", self.rr.LineStrips3D([np.array(self.flange_trail)]))

    def pose(self, batch: PoseBatch) -> None:
        """Log the sensor where the batch's last profile saw from and extend the flange trail."""
        if batch.n_poses == 0:
            return
        rr = self.rr
        self.rec.set_time("exposure", timestamp=np.datetime64(int(batch.t_ns[-1]), "ns"))
        self.rec.set_time("seq", sequence=batch.seq)
        s = batch.sensor2frame[-1]
        self.rec.log(
            "world/sensor",
            rr.Transform3D(translation=s[:3, 3], mat3x3=s[:3, :3]),
            rr.TransformAxes3D(0.05),
        )
        self.poses += 1
        flange = self._flange_in_frame(batch)
        if flange is not None:
            self.flange_trail.append(flange)
        if self.poses % self.trail_every == 0:
            self.log_trail()

    def _flange_in_frame(self, batch: PoseBatch) -> NDArray[np.float64] | None:
        """The last profile's flange origin in the clouds' frame: the pose itself in the base
        frame, else through the calibration (sensor in frame times flange-from-sensor)."""
        if batch.frame_id == "base":
            return np.array(batch.flange2base[-1, :3, 3])
        if self.sensor2flange is None:
            return None
        return np.array((batch.sensor2frame[-1] @ se3.invert(self.sensor2flange))[:3, 3])
