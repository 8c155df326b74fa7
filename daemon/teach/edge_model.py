"""The edge model in the profiles (:class:`wristscan.calib.edge.EdgeModel`): teaching one from
an example edge under the sensor (``wristscan teach edge-model``; nothing moves, the model lives
in the laser plane) and finding the edge with it in the profiles of a sweep, as edge learning
(:mod:`.edge`) does after every step. Both read the profiles of a sweep one by one and run
:func:`wristscan.calib.edge.detect_edge` on them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib.edge import EdgeDetection, EdgeModel, detect_edge
from wristscan.daemon.config import Config
from wristscan.daemon.teach.kit import TeachError, record_still, teach_acquisition

if TYPE_CHECKING:
    from wristscan.daemon.procedure.acquisition import Sweep

__all__ = [
    "RawEdge",
    "detections_from_sweep",
    "model_from_sweep",
    "model_toml",
    "teach_edge_model",
]

FloatArray = NDArray[np.float64]


@dataclass
class RawEdge:
    """Edge points found in single profiles (base frame), in acquisition order."""

    points: list[FloatArray] = field(default_factory=list)
    normals: list[FloatArray] = field(default_factory=list)
    """Surface normals measured in the laser plane (towards the sensor)."""
    view_x: list[FloatArray] = field(default_factory=list)
    """The sensor's X axis (normal to the laser plane) for each point."""
    confidence: list[float] = field(default_factory=list)
    t_ns: list[int] = field(default_factory=list)

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` points."""
        for lst in (self.points, self.normals, self.view_x, self.confidence, self.t_ns):
            del lst[n:]

    def extend(self, other: RawEdge) -> None:
        self.points += other.points
        self.normals += other.normals
        self.view_x += other.view_x
        self.confidence += other.confidence
        self.t_ns += other.t_ns

    def __len__(self) -> int:
        return len(self.points)

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        return (
            np.asarray(self.points, dtype=np.float64).reshape(-1, 3),
            np.asarray(self.normals, dtype=np.float64).reshape(-1, 3),
            np.asarray(self.view_x, dtype=np.float64).reshape(-1, 3),
            np.asarray(self.confidence, dtype=np.float64),
        )


def _by_profile(sweep: Sweep) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The points of ``sweep`` grouped by profile: profile ``i`` holds the points
    ``order[starts[i] : starts[i + 1]]`` (in acquisition order within the profile)."""
    order = np.argsort(sweep.profile_index, kind="stable")
    starts = np.searchsorted(sweep.profile_index[order], np.arange(sweep.n_profiles + 1))
    return order, starts


def detections_from_sweep(
    sweep: Sweep,
    sensor2flange: ArrayLike,
    model: EdgeModel,
    *,
    min_spacing_m: float = 0.0,
    last: int = 3,
    prior_y: float | None = 0.0,
) -> tuple[RawEdge, list[EdgeDetection]]:
    """Detect the edge in the profiles of ``sweep``: those whose sensor origin moved at least
    ``min_spacing_m`` since the previous one used, plus the ``last`` ones. Returns the found
    points in the base frame and the detections of the ``last`` profiles (found or not)."""
    s2f = np.asarray(sensor2flange, dtype=np.float64)
    raw = RawEdge()
    n = sweep.n_profiles
    if n == 0:
        return raw, []
    s2b = sweep.flange2base @ s2f
    order, starts = _by_profile(sweep)
    chosen: list[int] = []
    last_pos: FloatArray | None = None
    for i in range(n):
        pos = s2b[i, :3, 3]
        if last_pos is None or float(np.linalg.norm(pos - last_pos)) >= min_spacing_m:
            chosen.append(i)
            last_pos = pos
    tail = list(range(max(0, n - last), n))
    chosen = sorted(set(chosen) | set(tail))
    tail_dets: list[EdgeDetection] = []
    prior = prior_y
    for i in chosen:
        sel = order[starts[i] : starts[i + 1]]
        det = detect_edge(sweep.y[sel], sweep.z[sel], sweep.valid[sel], model, prior_y=prior)
        if i in tail:
            tail_dets.append(det)
        if not det.found:
            continue
        prior = float(det.point[0])
        T = s2b[i]
        R = T[:3, :3]
        raw.points.append(np.asarray(T[:3, 3] + R[:, 1] * det.point[0] + R[:, 2] * det.point[1]))
        raw.normals.append(np.asarray(R[:, 1] * det.normal[0] + R[:, 2] * det.normal[1]))
        raw.view_x.append(np.asarray(R[:, 0]).copy())
        raw.confidence.append(det.confidence)
        raw.t_ns.append(int(sweep.exposure_ns[i]))
    return raw, tail_dets


def model_from_sweep(
    sweep: Sweep,
    kind: str,
    *,
    height_tolerance: float = 0.3,
    angle_tolerance_deg: float = 15.0,
    min_confidence: float = 0.6,
) -> EdgeModel:
    """Teach an edge model from still profiles of an example edge: the edge of ``kind`` is
    looked for with wide ranges, and the model keeps what was seen - the step height within
    ``+-height_tolerance`` (relative), the included angle within ``+-angle_tolerance_deg``, the
    side of the upper face. Raises :class:`~.kit.TeachError` when no such edge is seen
    in most profiles."""
    loose = EdgeModel(
        kind,  # type: ignore[arg-type]
        height_m=(0.0003, 0.3),
        angle_deg=(5.0, 175.0),
        face_angle_deg=60.0,
        min_confidence=0.3,
    )
    order, starts = _by_profile(sweep)
    dets = []
    for i in range(sweep.n_profiles):
        sel = order[starts[i] : starts[i + 1]]
        dets.append(detect_edge(sweep.y[sel], sweep.z[sel], sweep.valid[sel], loose))
    found = [d for d in dets if d.found]
    if len(found) < max(3, len(dets) // 2):
        why = next((d.reason for d in dets if not d.found and d.reason), "")
        raise TeachError(
            f"no clear {kind} edge in view ({len(found)} of {len(dets)} profiles; {why}): place "
            "the laser line across the example edge"
        )
    kw: dict[str, Any] = {"kind": kind, "min_confidence": min_confidence}
    heights = np.array([d.height_m for d in found])
    if np.isfinite(heights).sum() >= len(found) // 2 + 1:
        h = float(np.nanmedian(heights))
        kw["height_m"] = (h * (1 - height_tolerance), h * (1 + height_tolerance))
    elif kind == "step":
        kw["height_m"] = (0.001, 0.3)  # the lower face out of range: any height
    if kind in ("v_groove", "outer_corner"):
        a = float(np.median([d.angle_deg for d in found]))
        kw["angle_deg"] = (max(0.0, a - angle_tolerance_deg), min(180.0, a + angle_tolerance_deg))
    sides = [d.side for d in found if d.side]
    if sides:
        kw["side"] = max(set(sides), key=sides.count)
    return EdgeModel(**kw)


def model_toml(model: EdgeModel) -> str:
    """The model as an ``[edge]`` TOML table (the file ``teach edge`` reads)."""
    lines = ["[edge]"]
    for k, v in model.to_dict().items():
        if isinstance(v, str):
            lines.append(f'{k} = "{v}"')
        elif isinstance(v, bool):
            lines.append(f"{k} = {'true' if v else 'false'}")
        elif isinstance(v, list):
            lines.append(f"{k} = [{', '.join(repr(float(x)) for x in v)}]")
        else:
            lines.append(f"{k} = {v!r}")
    return "\n".join(lines) + "\n"


def teach_edge_model(cfg: Config, kind: str, dwell_s: float = 0.2) -> EdgeModel:
    """Teach the edge model from the example edge under the sensor (nothing moves; the model
    lives in the laser plane, so no calibration is needed)."""
    with teach_acquisition(cfg) as acq:
        sweep = record_still(acq, dwell_s, 0.0)
    return model_from_sweep(sweep, kind)
