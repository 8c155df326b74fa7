"""How far to trust a sensor calibration, from its own data: the joint refinement repeated
without each tilted orientation (:func:`leave_one_out`) and a sweep at an orientation the
solution did not use, fitted with a sphere of free radius (:func:`check_scan_fit`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye, sphere
from wristscan.calib import handeye_uncertainty as uncertainty
from wristscan.daemon.calibrate.sensor.errors import CalibrationFailed
from wristscan.daemon.calibrate.sensor.plan import rotation_between
from wristscan.daemon.calibrate.sensor.sweeps import RecordedSweep, base_label, sample_indices

__all__ = ["CheckScan", "LeaveOneOut", "check_scan_fit", "leave_one_out"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

_LOO_MIN_GROUPS = 3
_FIGURE_POINTS = 4000


@dataclass(frozen=True, eq=False)
class LeaveOneOut:
    """The joint refinement repeated without each tilted orientation (both passes).

    ``translation_dev_m`` / ``rotation_dev_rad``: distance of each estimate from the full one;
    ``prediction_rms_m``: RMS residual of the left-out sweeps under the estimate without them
    (how well the calibration predicts an orientation it did not see)."""

    labels: tuple[str, ...]
    sensor2flange: FloatArray
    translation_dev_m: FloatArray
    rotation_dev_rad: FloatArray
    prediction_rms_m: FloatArray

    @property
    def max_translation_dev_m(self) -> float:
        return float(self.translation_dev_m.max())

    @property
    def max_rotation_dev_rad(self) -> float:
        return float(self.rotation_dev_rad.max())

    @property
    def spread_translation_m(self) -> FloatArray:
        """Per-axis standard deviation of the estimates, scaled by ``(n-1)/sqrt(n)`` (the
        jackknife standard error of the full estimate), metres ``(3,)``."""
        t = self.sensor2flange[:, :3, 3]
        n = t.shape[0]
        return np.asarray(np.sqrt((n - 1) / n * np.sum((t - t.mean(0)) ** 2, axis=0)))

    @property
    def sigma(self) -> FloatArray:
        """Jackknife standard error of ``[w_x, w_y, w_z (rad, about the sensor axes), t_x, t_y,
        t_z (m)]``, the order of the covariance: a cross-check of the reported sigmas over the
        orientations (the field-of-view group is always kept, so it cannot show its own share)."""
        d = uncertainty.local_errors(self.sensor2flange, self.sensor2flange[0])
        return np.sqrt(np.clip(np.diag(uncertainty.jackknife_cov(d)), 0.0, None))


def leave_one_out(
    sweeps: Sequence[RecordedSweep],
    joint: handeye.HandEyeResult,
    ball_radius_m: float,
    max_points: int = 2000,
) -> LeaveOneOut | None:
    """Leave-one-out over the tilted orientation groups of ``sweeps`` (the order of ``joint``).
    None when there are fewer than 3 groups (leaving one out would leave too few)."""
    groups = sorted({s.group for s in sweeps if s.stage == "tilt"})
    if len(groups) < _LOO_MIN_GROUPS:
        return None
    # Each refit runs on a thinned copy of the sweeps: the spread it measures comes from the
    # orientations, not from the sensor noise, so a third of the points is plenty.
    solver, masks = [], []
    for w, m in zip(sweeps, joint.inliers, strict=True):
        pick = np.zeros(w.sweep.n_points, dtype=bool)
        pick[sample_indices(w.sweep.n_points, max_points)] = True
        solver.append(w.for_solver().subset(pick))
        masks.append(np.asarray(m)[pick])
    labels, Xs, dts, drs, preds = [], [], [], [], []
    X = joint.sensor2flange
    for g in groups:
        keep = [i for i, s in enumerate(sweeps) if s.group != g]
        out = [i for i, s in enumerate(sweeps) if s.group == g]
        init = dataclasses.replace(joint, inliers=tuple(masks[i] for i in keep))
        try:
            r = handeye.refine([solver[i] for i in keep], init, ball_radius_m, check=False)
        except ValueError as exc:
            log.warning("leave-one-out without group %d failed: %s", g, exc)
            continue
        res = handeye.sphere_residuals(
            [solver[i].subset(masks[i]) for i in out],
            r.sensor2flange,
            r.ball_centre_base,
            ball_radius_m,
        )
        allr = np.concatenate(res)
        labels.append(base_label(sweeps[out[0]].label))
        Xs.append(r.sensor2flange)
        dts.append(float(np.linalg.norm(r.sensor2flange[:3, 3] - X[:3, 3])))
        drs.append(rotation_between(r.sensor2flange, X))
        preds.append(float(np.sqrt(np.mean(allr**2))) if allr.size else float("nan"))
    if len(labels) < _LOO_MIN_GROUPS:
        return None
    return LeaveOneOut(tuple(labels), np.array(Xs), np.array(dts), np.array(drs), np.array(preds))


@dataclass(frozen=True, eq=False)
class CheckScan:
    """A sweep at an orientation not used by the solution, mapped with the new calibration and
    fitted with a sphere of free radius: its centre against the calibrated ball centre and its
    radius against the known one (metres). The ``two_step_*`` figures are the same check with
    the two-step calibration. ``points_base`` / ``residuals_m`` are a sample for the figure."""

    label: str
    centre_base_m: FloatArray
    radius_m: float
    rms_m: float
    centre_error_m: float
    radius_error_m: float
    n_points: int
    two_step_centre_error_m: float
    two_step_radius_error_m: float
    points_base: FloatArray = field(repr=False)
    residuals_m: FloatArray = field(repr=False)


def check_scan_fit(
    check: Sequence[RecordedSweep],
    joint: handeye.HandEyeResult,
    two_step: handeye.HandEyeResult,
    ball_radius_m: float,
) -> CheckScan:
    """:class:`CheckScan` of the check sweeps (all passes together). Raises
    :class:`CalibrationFailed` when no sphere can be fitted."""

    def fit(X: FloatArray) -> tuple[sphere.SphereFit, FloatArray]:
        pts = np.concatenate([s.sweep.points_base(X) for s in check])
        try:
            return sphere.fit_sphere(pts, radius=None, robust="tukey"), pts
        except ValueError as exc:
            raise CalibrationFailed(f"the check scan could not be fitted: {exc}") from None

    f, pts = fit(joint.sensor2flange)
    f2, _ = fit(two_step.sensor2flange)
    inl = np.flatnonzero(f.inliers)
    pick = inl[np.unique(np.linspace(0, inl.size - 1, min(_FIGURE_POINTS, inl.size)).astype(int))]
    return CheckScan(
        label=base_label(check[0].label),
        centre_base_m=np.asarray(f.centre),
        radius_m=float(f.radius),
        rms_m=float(f.rms),
        centre_error_m=float(np.linalg.norm(f.centre - joint.ball_centre_base)),
        radius_error_m=float(f.radius - ball_radius_m),
        n_points=int(f.n_inliers),
        two_step_centre_error_m=float(np.linalg.norm(f2.centre - two_step.ball_centre_base)),
        two_step_radius_error_m=float(f2.radius - ball_radius_m),
        points_base=pts[pick],
        residuals_m=np.asarray(f.residuals)[pick],
    )
