"""Sensor-to-flange calibration from stop-and-go data: one profile of the ball per robot pose.

Every open-source peer calibrates this way: the robot stops, the sensor takes one profile of a
tooling ball of known radius ``R``, the controller reports the flange pose. The laser plane (the
sensor's ``x = 0`` plane) cuts the ball in a circle of radius ``r_k`` centred at ``(y_k, z_k)``;
the ball centre is then at ``c_k = (s h_k, y_k, z_k)`` in the sensor frame, ``h_k =
sqrt(R^2 - r_k^2)``, where the *side* ``s = +1`` or ``-1`` says on which side of the laser plane
the centre lies (one profile cannot tell). For every pose ``k`` with flange pose ``(R_k, T_k)``::

    c_base = R_k (R_sf c_k + t_sf) + T_k                                        (1)

**Closed-form start** (no initial guess, any orientations). With the columns ``a, b, d`` of
``R_sf`` as unknowns, (1) is linear in ``(a, b, d, t_sf, c_base)``::

    R_k (s h_k a + y_k b + z_k d + t_sf) - c_base = -T_k                         (2)

15 unknowns, 3 equations per pose. It is solved by linear least squares with ``s = +1`` (the
other side only negates ``a``). ``b`` and ``d`` are always determined; the rotation is the proper
rotation nearest to them (orthogonal Procrustes on two columns), so that ``a = b x d``. With the
rotation known, (2) is linear in ``(t_sf, c_base)`` for each side: two starts. A wrong side is
not always visible: when every profile cuts the ball at the same height ``h``, shifting the
sensor by ``2 h`` along its X axis explains the data as well (the laser plane on the other side
of the centre). Only the variation of ``h_k`` between poses tells the sides apart.

**Side and joint refinement.** From each start the joint refinement of
:func:`wristscan.calib.handeye.refine` runs on every point of every profile (each pose a
one-profile sweep). The point model does not fix the side: when both starts end in the same
optimum, the data have settled it, pose by pose (:func:`pose_sides`; the sides may differ between
poses). When they end in different optima, the one keeping clearly more points on the ball or
leaving a clearly smaller RMS wins (:data:`SIDE_INLIER_MARGIN`, :data:`SIDE_RMS_RATIO`); when
neither is clearly better the calibration is refused with :class:`AmbiguousSide` (give the side,
or add poses whose laser line cuts the ball at different heights). A wrong ball radius is looked
for first (it also makes the sides look alike): the poses' ball centres are fitted with the
radius free (:func:`~wristscan.calib.perpose_closed.centre_fit`).

Circle centres alone (:func:`calibrate_from_circles`, in :mod:`~wristscan.calib.perpose_closed`
with the closed form) get the same start and a least-squares fit of (1) over the poses instead
of the point refinement. :func:`jackknife` leaves out each pose in turn: the cross-check of the
reported uncertainty.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3, sphere
from wristscan.calib.handeye import HandEyeResult, PoorlyConstrained, Sweep, refine
from wristscan.calib.handeye_model import CovarianceSigmas
from wristscan.calib.perpose_closed import (
    CIRCLE_RADIUS_SLACK,
    MIN_POSES,
    ClosedForm,
    PerPoseDataError,
    calibrate_from_circles,
    centre_fit,
    check_poses,
    check_radius,
    closed_form,
)

__all__ = [
    "MIN_POSES",
    "SIDE_INLIER_MARGIN",
    "SIDE_RMS_RATIO",
    "AmbiguousSide",
    "ClosedForm",
    "Jackknife",
    "PerPoseDataError",
    "PerPoseResult",
    "PoseCircle",
    "SideTrial",
    "calibrate_from_circles",
    "calibrate_per_pose",
    "closed_form",
    "fit_pose_circles",
    "jackknife",
    "pose_sides",
    "pose_sweeps",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Side = Literal["auto", 1, -1]

SIDE_RMS_RATIO = 1.5
"""The wrong side must leave an RMS at least this many times the right side's ..."""
SIDE_INLIER_MARGIN = 0.10
"""... or keep this share of the points fewer on the ball; otherwise the side is ambiguous."""
RADIUS_TOL = 0.05
"""The radius the profiles show (fitted freely over the poses' ball centres) must be within this
share of the given one."""
MISFIT_RATIO = 10.0
MISFIT_M = 0.5e-3
"""Residuals above both ``MISFIT_RATIO`` times the circles' RMS and ``MISFIT_M`` mean a wrong
ball radius when the data cannot fit the radius themselves (robot errors of 0.2 mm leave
0.1-0.2 mm)."""
MIN_CIRCLE_POINTS = 10
"""Fewest points on the ball's arc a profile must have."""
_DEGENERATE_COND = 1e5
"""Condition number of the equilibrated system (2) without ``a`` above which the poses do not
determine the solution at all (no tilt between orientations, or the ball at one place in the
laser plane)."""


class AmbiguousSide(PoorlyConstrained):
    """Both sides of the laser plane explain the data about equally well."""


@dataclass(frozen=True, eq=False)
class PoseCircle:
    """The ball's arc in one profile: centre ``(y, z)`` and radius in the laser plane (m)."""

    centre_yz: FloatArray
    radius: float
    rms: float
    n_points: int
    inliers: BoolArray

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


@dataclass(frozen=True, eq=False)
class SideTrial:
    """The joint refinement from one side's start (``result`` None when it failed: ``error``)."""

    side: int
    start: ClosedForm
    result: HandEyeResult | None
    rms_m: float
    inlier_fraction: float
    """Share of all the profiles' points the refinement kept on the ball."""
    error: str = ""


@dataclass(frozen=True, eq=False)
class PerPoseResult:
    """A stop-and-go calibration: the joint solution, the side chosen, both sides' trials, the
    circles of the profiles and the one-profile sweeps the solution was computed on."""

    joint: HandEyeResult
    side: int
    """+1 or -1: the side of the laser plane the ball centre is on at every pose; 0: mixed (see
    ``sides``)."""
    sides: NDArray[np.int8]
    """(K,) the side at each pose (:func:`pose_sides`)."""
    start: ClosedForm
    """The closed-form start the solution was refined from."""
    trials: tuple[SideTrial, ...]
    circles: tuple[PoseCircle, ...]
    sweeps: tuple[Sweep, ...]

    @property
    def sensor2flange(self) -> FloatArray:
        return self.joint.sensor2flange


@dataclass(frozen=True, eq=False)
class Jackknife(CovarianceSigmas):
    """Leave-one-pose-out estimates and the jackknife covariance (order of
    ``HandEyeResult.cov``: rotation increments about the sensor axes (rad), then the sensor
    origin (m))."""

    increments: FloatArray
    """(K, 6) each leave-one-out estimate relative to the full solution."""
    cov: FloatArray
    translation_dev_m: FloatArray
    rotation_dev_rad: FloatArray


# --------------------------------------------------------------------------------------------
# Circles


def fit_pose_circles(profiles: Sequence[ArrayLike], ball_radius: float) -> list[PoseCircle]:
    """The ball's circle in each profile ``(N_k, 2)`` of ``(y, z)`` points (m), robust to the
    post, the table and stray points. Raises :class:`PerPoseDataError` naming the pose when a
    profile holds too few points of the ball or a circle larger than the ball."""
    R = check_radius(ball_radius)
    out = []
    for k, prof in enumerate(profiles):
        P = np.asarray(prof, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 2:
            raise PerPoseDataError(f"expected (N, 2) points (y, z), got {P.shape}", k)
        if P.shape[0] < MIN_CIRCLE_POINTS:
            raise PerPoseDataError(
                f"{P.shape[0]} valid points; the ball's arc needs >= {MIN_CIRCLE_POINTS}", k
            )
        try:
            fit = sphere.fit_circle(P, radius_range=(0.05 * R, (1 + 3 * CIRCLE_RADIUS_SLACK) * R))
        except ValueError as exc:
            raise PerPoseDataError(
                f"no circle of at most the ball radius {R * 1e3:.3f} mm fits this profile "
                f"({exc}): is the ball radius right?",
                k,
            ) from None
        if fit.n_inliers < MIN_CIRCLE_POINTS:
            raise PerPoseDataError(
                f"only {fit.n_inliers} points lie on a circle; the ball's arc needs "
                f">= {MIN_CIRCLE_POINTS}",
                k,
            )
        if fit.radius > (1 + CIRCLE_RADIUS_SLACK) * R:
            raise PerPoseDataError(
                f"the ball's arc has a radius of {fit.radius * 1e3:.3f} mm, more than the ball "
                f"radius {R * 1e3:.3f} mm: is the ball radius right?",
                k,
            )
        out.append(
            PoseCircle(
                np.asarray(fit.centre, dtype=np.float64),
                float(fit.radius),
                float(fit.rms),
                int(P.shape[0]),
                np.asarray(fit.inliers, dtype=bool),
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# Profiles: side trials and the joint refinement


def pose_sweeps(flange2base: ArrayLike, profiles: Sequence[ArrayLike]) -> list[Sweep]:
    """One one-profile :class:`~wristscan.calib.handeye.Sweep` per pose: the ``(y, z)`` points
    (m) at ``x = 0`` with the flange pose."""
    F = np.asarray(flange2base, dtype=np.float64)
    out = []
    for k, prof in enumerate(profiles):
        P = np.asarray(prof, dtype=np.float64)
        out.append(Sweep.from_yz(F[k : k + 1], P[:, 0], P[:, 1], np.zeros(len(P), dtype=np.intp)))
    return out


@contextlib.contextmanager
def _quiet_solver() -> Iterator[None]:
    """The solver's "weakly constrained" warnings off for the trial and jackknife runs (the
    final solution is checked, and warned about, once)."""
    logger = logging.getLogger("wristscan.calib.handeye")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def _start_result(start: ClosedForm, R: float, masks: Sequence[BoolArray]) -> HandEyeResult:
    """A closed-form start in the form :func:`~wristscan.calib.handeye.refine` starts from."""
    nan = float("nan")
    return HandEyeResult(
        sensor2flange=start.sensor2flange,
        ball_centre_base=start.ball_centre_base,
        ball_radius_m=R,
        cov=np.full((6, 6), nan),
        per_sweep_rms=np.full(len(masks), nan),
        rms=start.centre_rms_m,
        n_points=int(sum(int(m.sum()) for m in masks)),
        condition=nan,
        method="closed-form",
        inliers=tuple(masks),
    )


def _trial(
    sweeps: Sequence[Sweep],
    start: ClosedForm,
    R: float,
    masks: Sequence[BoolArray],
    robot_sigma_m: float,
) -> SideTrial:
    n_all = sum(s.n_points for s in sweeps)
    try:
        with _quiet_solver():
            res = refine(
                sweeps, _start_result(start, R, masks), R, robot_sigma_m=robot_sigma_m, check=False
            )
    except (ValueError, np.linalg.LinAlgError) as exc:
        return SideTrial(start.side, start, None, math.inf, 0.0, str(exc))
    kept = sum(int(np.count_nonzero(m)) for m in res.inliers)
    return SideTrial(start.side, start, res, float(res.rms), kept / max(n_all, 1))


def _same_solution(a: HandEyeResult, b: HandEyeResult) -> bool:
    """Whether two refinements ended in the same minimum (within 5 sigma, at least 10 um and
    0.001 deg): the other side's start then only was a start."""
    dt = float(np.linalg.norm(a.sensor2flange[:3, 3] - b.sensor2flange[:3, 3]))
    dr = float(se3.rotation_angle(a.sensor2flange[:3, :3].T @ b.sensor2flange[:3, :3]))
    sig_t = np.nan_to_num(np.concatenate([a.sigma_translation_m, b.sigma_translation_m]))
    sig_r = np.nan_to_num(np.concatenate([a.sigma_rotation_rad, b.sigma_rotation_rad]))
    return dt <= max(10e-6, 5.0 * float(sig_t.max())) and dr <= max(
        math.radians(1e-3), 5.0 * float(sig_r.max())
    )


def _choose(trials: Sequence[SideTrial]) -> SideTrial:
    """The trial to keep: the better one when both ended in the same minimum or one is clearly
    better (more points on the ball, or a clearly smaller RMS); else :class:`AmbiguousSide`."""
    ok = [t for t in trials if t.result is not None]
    if not ok:
        raise PoorlyConstrained(
            "the joint refinement failed from both sides' starts: "
            + "; ".join(f"side {t.side:+d}: {t.error}" for t in trials)
        )
    if len(ok) == 1:
        return ok[0]
    best, other = sorted(ok, key=lambda t: (-round(t.inlier_fraction, 2), t.rms_m))
    assert best.result is not None and other.result is not None
    if _same_solution(best.result, other.result):
        # One minimum: keep the refinement from the start that fitted the poses better.
        return min(ok, key=lambda t: t.start.centre_rms_m)
    if (
        other.rms_m >= SIDE_RMS_RATIO * best.rms_m
        or best.inlier_fraction - other.inlier_fraction >= SIDE_INLIER_MARGIN
    ):
        return best
    dt = float(np.linalg.norm(best.result.sensor2flange[:3, 3] - other.result.sensor2flange[:3, 3]))
    raise AmbiguousSide(
        "cannot tell on which side of the laser plane the ball centre lies: the two sides give "
        f"solutions {dt * 1e3:.3f} mm apart that fit about equally well (side "
        f"{best.side:+d}: {best.rms_m * 1e6:.1f} um RMS, {best.inlier_fraction:.0%} of the points "
        f"on the ball; side {other.side:+d}: {other.rms_m * 1e6:.1f} um, "
        f"{other.inlier_fraction:.0%})",
        "give the side, or add poses whose laser line cuts the ball at different heights "
        "(some near the equator, some near the top)",
    )


def pose_sides(result: HandEyeResult, flange2base: ArrayLike) -> NDArray[np.int8]:
    """On which side of each pose's laser plane the solution puts the ball centre: the sign of
    its sensor-frame X (+1 or -1; 0 within 1 um of the plane)."""
    F = np.asarray(flange2base, dtype=np.float64)
    S = F @ result.sensor2flange
    d = result.ball_centre_base - S[:, :3, 3]
    x = np.einsum("ki,ki->k", S[:, :3, 0], d)
    return np.where(np.abs(x) < 1e-6, 0, np.sign(x)).astype(np.int8)


def _check_ball_radius(
    F: FloatArray, circles: Sequence[PoseCircle], joint: HandEyeResult, sides: NDArray[np.int8]
) -> None:
    """Refuse when the profiles show a ball of another radius: the fit of the poses' ball
    centres with the radius free (:func:`~wristscan.calib.perpose_closed.centre_fit`, from the
    solution) ends more than :data:`RADIUS_TOL` away and fits better, or (when the data do not
    determine the radius) the residuals exceed :data:`MISFIT_RATIO` times the circles' RMS and
    :data:`MISFIT_M`."""
    R = joint.ball_radius_m
    C = np.array([[*c.centre_yz, c.radius] for c in circles])
    circle_rms = float(np.median([c.rms for c in circles]))
    s = np.where(sides == 0, 1.0, sides).astype(np.float64)
    start = ClosedForm(0, joint.sensor2flange, joint.ball_centre_base, math.nan, math.nan)
    fixed = centre_fit(F, C, s, start, R)
    free = centre_fit(F, C, s, start, R, fit_radius=True)
    if abs(free.radius - R) <= RADIUS_TOL * R:
        return
    if free.rms_m < 0.8 * fixed.rms_m and free.radius < 9.9 * R:
        shown = f"the poses' ball centres fit best with a radius of {free.radius * 1e3:.3f} mm"
    elif joint.rms > max(MISFIT_RATIO * circle_rms, MISFIT_M):
        shown = f"the profiles' circles fit to {circle_rms * 1e6:.0f} um"
    else:
        return  # the data do not determine the radius, and the given one fits them
    raise PerPoseDataError(
        f"the profiles do not fit a ball of radius {R * 1e3:.3f} mm ({shown}; residual RMS "
        f"{joint.rms * 1e6:.0f} um): is the ball radius right (the radius, not the diameter)?"
    )


def calibrate_per_pose(
    flange2base: ArrayLike,
    profiles: Sequence[ArrayLike],
    ball_radius: float,
    *,
    side: Side = "auto",
    robot_sigma_m: float = 0.0,
    check: bool = True,
) -> PerPoseResult:
    """sensor2flange from one profile per pose: ``profiles[k]`` ``(N_k, 2)`` the ``(y, z)``
    points (m, sensor frame) taken at flange pose ``flange2base[k]``; ``ball_radius`` (m).

    Circles are fitted per profile (:func:`fit_pose_circles`), the closed form gives a start per
    side (:func:`closed_form`), the joint refinement
    (:func:`wristscan.calib.handeye.refine`, each pose a one-profile sweep, ``robot_sigma_m``
    the per-axis flange position error of a pose) runs from each start, and the clearly better
    side wins (``side`` +1 or -1 imposes one). ``check`` applies the refinement's
    identifiability check to the solution. Raises :class:`PerPoseDataError`,
    :class:`AmbiguousSide` or :class:`~wristscan.calib.handeye.PoorlyConstrained`."""
    R = check_radius(ball_radius)
    F = check_poses(flange2base, len(profiles))
    circles = fit_pose_circles(profiles, R)
    C = np.array([[*c.centre_yz, c.radius] for c in circles])
    starts = closed_form(F, C, R)
    sweeps = pose_sweeps(F, profiles)
    masks = [c.inliers for c in circles]
    chosen = [s for s in starts if side == "auto" or s.side == side]
    trials = tuple(_trial(sweeps, s, R, masks, robot_sigma_m) for s in chosen)
    fitted = [t.result for t in trials if t.result is not None]
    if fitted:  # a wrong radius first: it also makes the sides look alike
        tightest = min(fitted, key=lambda r: r.rms)
        _check_ball_radius(F, circles, tightest, pose_sides(tightest, F))
    best = _choose(trials)
    assert best.result is not None
    joint = best.result
    if check:  # the solver's own identifiability check, from its converged solution
        joint = refine(sweeps, joint, R, robot_sigma_m=robot_sigma_m, check=True)
    sides = pose_sides(joint, F)
    nz = sides[sides != 0]
    one = int(nz[0]) if nz.size and np.all(nz == nz[0]) else 0
    return PerPoseResult(joint, one, sides, best.start, trials, tuple(circles), tuple(sweeps))


# --------------------------------------------------------------------------------------------
# Cross-check


def jackknife(result: PerPoseResult, robot_sigma_m: float = 0.0) -> Jackknife:
    """Leave each pose out in turn, refine from the full solution, and the jackknife covariance
    ``(K - 1) / K sum (e_i - mean e)(e_i - mean e)^T`` of the estimates ``e_i`` (rotation
    increments about the sensor axes, sensor origin), the cross-check of the reported sigmas."""
    j = result.joint
    sw = list(result.sweeps)
    K = len(sw)
    X = j.sensor2flange
    inc = np.zeros((K, 6))
    for i in range(K):
        keep = [k for k in range(K) if k != i]
        init = dataclasses.replace(j, inliers=tuple(j.inliers[k] for k in keep))
        with _quiet_solver():
            r = refine(
                [sw[k] for k in keep], init, j.ball_radius_m, robot_sigma_m=robot_sigma_m,
                check=False,
            )  # fmt: skip
        Xi = r.sensor2flange
        inc[i, :3] = se3.matrix_to_rotvec(X[:3, :3].T @ Xi[:3, :3])
        inc[i, 3:] = Xi[:3, 3] - X[:3, 3]
    dev = inc - inc.mean(axis=0)
    cov = (K - 1) / K * dev.T @ dev
    return Jackknife(
        inc,
        cov,
        np.linalg.norm(inc[:, 3:], axis=1),
        np.linalg.norm(inc[:, :3], axis=1),
    )
