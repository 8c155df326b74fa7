"""Sensor-to-flange calibration (the paper's "tool transformation") from ball-matching sweeps.

A tooling ball of known radius sits somewhere in the workspace, at an unknown but fixed place. The
robot moves the wrist-mounted profile sensor over it in *sweeps*: passes of many profiles, each
profile paired with the flange pose (``flange2base``) at its instant. A profile point ``(y, z)``
lies in the laser plane, so in the sensor frame it is ``(0, y, z)`` (Borangiu et al. 2009, sec. 1).
Every point of every sweep must then satisfy::

    || flange2base_j @ sensor2flange @ (0, y_j, z_j) - c_base || = R          (*)

Two solvers are offered:

* :func:`two_step` follows the paper. Step 1 (:func:`solve_orientation`, "ball matching"): with
  the robot only *translating* (constant flange orientation ``R0``), the ball is placed at >= 3
  (default 9) field-of-view (FOV) locations; at each one a sweep along the sensor X axis gives the
  ball centre ``c_s,k`` in the sensor frame (sphere fit). As ``c_base = R0 (R_sf c_s,k + t_sf) +
  t_k`` is the same for every k, ``R0 R_sf (c_s,k - c_s,j) = -(t_k - t_j)``: an orthogonal
  Procrustes problem for the rotation ``R_sf`` (Kabsch, proper rotation). Step 2
  (:func:`solve_origin`): sweeps at >= 3 different orientations give ``c_base = R_i (R_sf c_s,i +
  t_sf) + T_i``; moving the now known part ``R_i R_sf c_s,i`` into the translation turns this into
  the paper's TCP problem, Eq. (2)-(9), solved by :func:`wristscan.calib.tcp.solve_tcp` (``t_sf`` =
  tool point, ``c_base`` = world point).
* :func:`refine` solves (*) jointly for all six degrees of freedom of ``sensor2flange`` and the ball
  centre (optionally the radius) by nonlinear least squares on all inlier points of all sweeps, with
  an analytic Jacobian, covariance, per-sweep residuals and an identifiability check.

Reference frame of a sweep: the sweep's *first* pose (profile 0). The sensor-frame ball centre of a
sweep is expressed in the sensor frame at that pose.

Parameter order of every covariance returned here (``HandEyeResult.cov``, 6x6)::

    [w_x, w_y, w_z, t_x, t_y, t_z]

``w`` is a rotation-vector increment about the *sensor* axes (radians, right perturbation:
``R_sf_true = R_sf_est @ exp(w)``), ``t`` the sensor origin in the flange frame (metres).
``HandEyeResult.cov_full`` continues with the ball centre in base ``c_x, c_y, c_z`` (metres) and,
when the radius was estimated, the radius (metres).

The data model is :mod:`wristscan.calib.handeye_model`, the point model (*) over all sweeps and
its conditioning :mod:`wristscan.calib.handeye_points`, the steps of :func:`refine`
:mod:`wristscan.calib.handeye_joint`, its error model (sensor noise and the robot's pose error,
estimated from the residuals) :mod:`wristscan.calib.handeye_uncertainty`, the jackknife over pose
clusters :mod:`wristscan.calib.handeye_jackknife`; the public names are importable from here.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import se3, sphere, tcp
from wristscan.calib.handeye_joint import joint_result, rounds, start
from wristscan.calib.handeye_kinematic import KinematicPrior, with_kinematic_prior
from wristscan.calib.handeye_model import (
    HandEyeResult,
    Identifiability,
    OrientationSolution,
    OriginSolution,
    PoorlyConstrained,
    Sweep,
    check_radius,
    check_sweeps,
    translation_only,
)
from wristscan.calib.handeye_points import (
    COND_HARD,
    COND_SOFT,
    PointStack,
    identifiability,
    skew,
)
from wristscan.calib.handeye_uncertainty import Jackknife, VarianceComponents

__all__ = [
    "COND_HARD",
    "COND_SOFT",
    "HandEyeResult",
    "Identifiability",
    "Jackknife",
    "KinematicPrior",
    "OrientationSolution",
    "OriginSolution",
    "PoorlyConstrained",
    "Sweep",
    "VarianceComponents",
    "check_identifiability",
    "refine",
    "solve_orientation",
    "solve_origin",
    "sphere_residuals",
    "sweep_points_at_start",
    "two_step",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

#: Step 1 refuses FOV ball centres whose second principal spread is below this share of the first.
_MIN_FOV_SPREAD_RATIO = 0.1


# --------------------------------------------------------------------------------------------
# Small helpers


def _kabsch(a: FloatArray, b: FloatArray) -> FloatArray:
    """Proper rotation ``R`` minimising ``sum |R (a_k - mean a) - (b_k - mean b)|^2``."""
    ac = a - a.mean(axis=0)
    bc = b - b.mean(axis=0)
    U, _, Vt = np.linalg.svd(bc.T @ ac)
    d = np.sign(np.linalg.det(U @ Vt))
    return U @ np.diag([1.0, 1.0, d if d != 0 else 1.0]) @ Vt


def _mean_rotation(R: FloatArray) -> FloatArray:
    """Chordal L2 mean of rotations ``(n, 3, 3)``."""
    U, _, Vt = np.linalg.svd(R.sum(axis=0))
    d = np.sign(np.linalg.det(U @ Vt))
    return U @ np.diag([1.0, 1.0, d]) @ Vt


# --------------------------------------------------------------------------------------------
# Two-step method (the paper)


def sweep_points_at_start(
    sweep: Sweep,
    sensor_rotation: ArrayLike | None = None,
    sweep_direction_sensor: ArrayLike = (1.0, 0.0, 0.0),
) -> FloatArray:
    """Points of a constant-orientation sweep in the sensor frame at the sweep's first pose (m).

    With a pure translation ``d_i = t_i - t_0`` of the flange (base frame) the sensor frame at
    profile ``i`` is the start frame shifted by ``R_sf^T R_0^T d_i``, so a point ``p`` of profile
    ``i`` is at ``p + R_sf^T R_0^T d_i`` in the start frame.

    ``sensor_rotation`` (sensor2flange rotation) unknown (``None``): the paper's ball matching
    assumption that the sweep was commanded along the sensor X axis is used, i.e. the shift is
    ``s_i * sweep_direction_sensor`` with ``s_i`` the signed travel along the sweep's principal
    direction (positive towards the last pose). :func:`solve_orientation` then iterates with the
    estimated rotation, which removes both the misalignment of the commanded axis and a wrong sign.
    """
    F = sweep.flange2base
    d = F[:, :3, 3] - F[0, :3, 3]
    if sensor_rotation is None:
        u = np.asarray(sweep_direction_sensor, dtype=np.float64)
        u = u / np.linalg.norm(u)
        _, _, Vt = np.linalg.svd(d - d.mean(axis=0), full_matrices=False)
        axis = Vt[0]
        if np.dot(d[-1], axis) < 0.0:
            axis = -axis
        shift = (d @ axis)[:, None] * u
    else:
        Rsf = np.asarray(sensor_rotation, dtype=np.float64)
        shift = d @ (F[0, :3, :3] @ Rsf)  # rows: (R_0 R_sf)^T d_i
    return sweep.points_sensor + shift[sweep.pose_index]


def _fit_centres(
    sweeps: Sequence[Sweep],
    ball_radius: float,
    sensor_rotation: FloatArray | None,
    sweep_direction_sensor: ArrayLike,
    robust: sphere.Robust,
) -> tuple[FloatArray, tuple[BoolArray, ...]]:
    """Ball centre (sensor frame at sweep start, m) and inlier mask of each sweep."""
    centres = np.empty((len(sweeps), 3))
    inl: list[BoolArray] = []
    for k, s in enumerate(sweeps):  # one fit per sweep; the fit itself is vectorised
        pts = sweep_points_at_start(s, sensor_rotation, sweep_direction_sensor)
        fit = sphere.fit_sphere(pts, radius=ball_radius, robust=robust)
        centres[k] = fit.centre
        inl.append(np.asarray(fit.inliers, dtype=bool))
    return centres, tuple(inl)


def solve_orientation(
    fov_sweeps: Sequence[Sweep],
    ball_radius: float,
    *,
    sweep_direction_sensor: ArrayLike = (1.0, 0.0, 0.0),
    orientation_tol_rad: float = 2e-3,
    robust: sphere.Robust = "tukey",
    max_iter: int = 10,
    tol_rad: float = 1e-12,
) -> OrientationSolution:
    """Step 1 (ball matching): the sensor2flange rotation from >= 3 FOV locations.

    All ``fov_sweeps`` must share one flange orientation (within ``orientation_tol_rad``) and only
    translate. Raises :class:`PoorlyConstrained` when the ball centres are (nearly) collinear in the
    sensor frame (the rotation about that line is then undetermined).
    """
    sw = check_sweeps(fov_sweeps, "fov_sweeps")
    if len(sw) < 3:
        raise PoorlyConstrained(
            f"orientation needs the ball at >= 3 field-of-view locations, got {len(sw)}",
            "place the ball at more field-of-view locations (9 by default)",
        )
    R = check_radius(ball_radius)
    for k, s in enumerate(sw):
        translation_only(s, k, orientation_tol_rad)
    R_start = np.stack([s.flange2base[0, :3, :3] for s in sw])
    R0 = _mean_rotation(R_start)
    spread = se3.rotation_angle(R0.T @ R_start)
    if float(spread.max()) > orientation_tol_rad:
        raise ValueError(
            f"fov_sweeps differ in orientation by up to {np.degrees(spread.max()):.3f} deg; "
            "step 1 needs the robot only translating between field-of-view locations"
        )
    # c_base = R0 (R_sf c_k + t_sf) + t_k  =>  R_sf c_k = -R0^T t_k + const.
    b = -np.stack([s.flange2base[0, :3, 3] for s in sw]) @ R0

    Rsf: FloatArray | None = None
    centres = np.zeros((len(sw), 3))
    inl: tuple[BoolArray, ...] = ()
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - number of iterations is reported
        centres, inl = _fit_centres(sw, R, Rsf, sweep_direction_sensor, robust)
        ac = centres - centres.mean(axis=0)
        sv = np.linalg.svd(ac, compute_uv=False)
        # The rotation about the line through the centres has a lever of only sv[1].
        if sv[1] < _MIN_FOV_SPREAD_RATIO * sv[0] or sv[0] < 1e-9:
            raise PoorlyConstrained(
                "the ball centres of the field-of-view sweeps are (nearly) collinear in the sensor "
                "frame, so the rotation about that line is undetermined",
                "place the ball at more field-of-view locations, spread both along the laser line "
                "(sensor Y) and in depth (sensor Z)",
            )
        R_new = _kabsch(centres, b)
        change = float("inf") if Rsf is None else float(se3.rotation_angle(Rsf.T @ R_new))
        Rsf = R_new
        if change < tol_rad:
            break
    assert Rsf is not None
    ac = centres - centres.mean(axis=0)
    res = ac @ Rsf.T - (b - b.mean(axis=0))
    dof = max(3 * len(sw) - 6, 1)
    s2 = float(np.sum(res**2)) / dof
    # Right perturbation: R (I + [w]x) a = R a - R [a]x w; |R .| is orthogonal so J^T J = sum A^T A.
    A = skew(ac)
    JtJ = np.einsum("kji,kjl->il", A, A)
    cov = s2 * np.linalg.pinv(JtJ)
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    return OrientationSolution(Rsf, centres, res, rms, cov, it, inl)


def solve_origin(
    sweeps: Sequence[Sweep],
    sensor_rotation: ArrayLike,
    ball_radius: float,
    *,
    robust: sphere.Robust = "tukey",
    orientation_tol_rad: float = 2e-3,
    method: Literal["lstsq", "variance"] = "lstsq",
) -> OriginSolution:
    """Step 2: sensor origin in the flange frame and ball centre in base, given the rotation.

    Each constant-orientation sweep gives the ball centre ``c_s,i`` in the sensor frame at its start
    pose ``(R_i, T_i)``; with ``T_i' = T_i + R_i R_sf c_s,i`` the condition
    ``R_i t_sf + T_i' = c_base`` is the paper's TCP problem, solved by ``calib.tcp.solve_tcp``.
    Needs >= 3 sufficiently different orientations; otherwise raises :class:`PoorlyConstrained`.
    """
    sw = check_sweeps(sweeps, "sweeps")
    R = check_radius(ball_radius)
    Rsf = np.asarray(sensor_rotation, dtype=np.float64)
    for k, s in enumerate(sw):
        translation_only(s, k, orientation_tol_rad)
    centres, inl = _fit_centres(sw, R, Rsf, (1.0, 0.0, 0.0), robust)
    return _origin_from_centres(sw, Rsf, centres, inl, method)


def _origin_from_centres(
    sw: Sequence[Sweep],
    Rsf: FloatArray,
    centres: FloatArray,
    inl: tuple[BoolArray, ...],
    method: Literal["lstsq", "variance"],
) -> OriginSolution:
    Ri = np.stack([s.flange2base[0, :3, :3] for s in sw])
    Ti = np.stack([s.flange2base[0, :3, 3] for s in sw])
    Tp = Ti + np.einsum("nij,jk,nk->ni", Ri, Rsf, centres)
    try:
        sol = tcp.solve_tcp(Ri, Tp, method=method)
    except tcp.DegeneratePoses as exc:
        raise PoorlyConstrained(
            f"the sweep orientations do not determine the sensor origin ({exc})",
            "add orientations tilted about the sensor X and Y axes (>= 45 deg between the tool Z "
            "axes, paper sec. 3)",
        ) from exc
    return OriginSolution(
        translation=np.asarray(sol.p_tool, dtype=np.float64),
        ball_centre_base=np.asarray(sol.p_world, dtype=np.float64),
        centres_sensor=centres,
        residuals=np.asarray(sol.residuals, dtype=np.float64),
        cov=np.asarray(sol.cov, dtype=np.float64),
        sigma=float(sol.sigma),
        inliers=inl,
    )


def two_step(
    fov_sweeps: Sequence[Sweep],
    tilt_sweeps: Sequence[Sweep],
    ball_radius: float,
    *,
    sweep_direction_sensor: ArrayLike = (1.0, 0.0, 0.0),
    robust: sphere.Robust = "tukey",
    orientation_tol_rad: float = 2e-3,
    check: bool = True,
    cond_soft: float = COND_SOFT,
    cond_hard: float = COND_HARD,
) -> HandEyeResult:
    """The paper's method: rotation from ``fov_sweeps`` (step 1), origin from all sweeps (step 2).

    ``fov_sweeps``: constant orientation, ball at >= 3 FOV locations. ``tilt_sweeps``: each at its
    own constant orientation; step 2 uses the FOV sweeps too. The covariance combines the
    Procrustes rotation covariance and the TCP translation covariance (their correlation is
    ignored). Residuals, inliers and the condition number are evaluated on the point model (*) at
    the solution, with the sphere-fit inliers. ``check`` raises :class:`PoorlyConstrained` above
    ``cond_hard``.
    """
    fov = check_sweeps(fov_sweeps, "fov_sweeps")
    tilt = check_sweeps(tilt_sweeps, "tilt_sweeps")
    R = check_radius(ball_radius)
    ori = solve_orientation(
        fov,
        R,
        sweep_direction_sensor=sweep_direction_sensor,
        orientation_tol_rad=orientation_tol_rad,
        robust=robust,
    )
    for k, sweep in enumerate(tilt):
        translation_only(sweep, len(fov) + k, orientation_tol_rad)
    # The FOV sweeps' centres from step 1's last pass were computed with the converged rotation.
    tc, t_inl = _fit_centres(tilt, R, ori.rotation, (1.0, 0.0, 0.0), robust)
    org = _origin_from_centres(
        [*fov, *tilt],
        ori.rotation,
        np.concatenate([ori.centres_sensor, tc]),
        (*ori.inliers, *t_inl),
        "lstsq",
    )
    X = se3.make(ori.rotation, org.translation)
    inliers = org.inliers
    stack = PointStack.build([*fov, *tilt], inliers)
    r = stack.residuals(X[:3, :3], X[:3, 3], org.ball_centre_base, R)
    cov = np.zeros((6, 6))
    cov[:3, :3] = ori.cov
    cov[3:, 3:] = org.cov
    ident = identifiability(
        stack.jacobian(X[:3, :3], X[:3, 3], org.ball_centre_base, fit_radius=False),
        X[:3, :3],
        cond_soft,
    )
    _apply_check(ident, check, cond_soft, cond_hard)
    per, rms = stack.rms(r)
    return HandEyeResult(
        sensor2flange=X,
        ball_centre_base=org.ball_centre_base,
        ball_radius_m=R,
        cov=cov,
        per_sweep_rms=per,
        rms=rms,
        n_points=int(r.size),
        condition=ident.condition,
        method="two-step",
        inliers=inliers,
        advice=ident.advice if ident.condition > cond_soft else "",
    )


def _apply_check(ident: Identifiability, check: bool, soft: float, hard: float) -> None:
    if ident.condition > hard and check:
        raise PoorlyConstrained(
            f"sensor2flange is poorly constrained by these sweeps (condition {ident.condition:.3g} "
            f"> {hard:.3g})",
            ident.advice,
            ident.condition,
        )
    if ident.condition > soft:
        log.warning(
            "sensor2flange weakly constrained (condition %.3g > %.3g): %s",
            ident.condition,
            soft,
            ident.advice,
        )


def sphere_residuals(
    sweeps: Sequence[Sweep],
    sensor2flange: ArrayLike,
    ball_centre_base: ArrayLike,
    ball_radius: float,
) -> list[FloatArray]:
    """Signed distance (m) of every point to the ball surface, one array per sweep."""
    sw = list(sweeps)
    X = np.asarray(sensor2flange, dtype=np.float64)
    c = np.asarray(ball_centre_base, dtype=np.float64)
    return [np.linalg.norm(s.points_base(X) - c, axis=1) - float(ball_radius) for s in sw]


def check_identifiability(
    sweeps: Sequence[Sweep],
    sensor2flange: ArrayLike,
    ball_centre_base: ArrayLike,
    *,
    fit_radius: bool = False,
    masks: Sequence[BoolArray] | None = None,
    cond_soft: float = COND_SOFT,
) -> Identifiability:
    """Condition number and advice for the joint problem at a given solution (no exception).

    ``advice`` always names what would help most; it matters when ``condition > cond_soft``."""
    X = se3.check_transform(sensor2flange, "sensor2flange")
    stack = PointStack.build(check_sweeps(sweeps, "sweeps"), masks)
    J = stack.jacobian(X[:3, :3], X[:3, 3], np.asarray(ball_centre_base, float), fit_radius)
    return identifiability(J, X[:3, :3], cond_soft)


def refine(
    sweeps: Sequence[Sweep],
    initial: HandEyeResult | ArrayLike,
    ball_radius: float | None,
    *,
    fit_radius: bool = False,
    masks: Sequence[BoolArray] | None = None,
    outlier_sigma: float = 4.0,
    min_threshold_m: float = 50e-6,
    max_rounds: int = 6,
    init_band_m: float = 2e-3,
    loss: str = "linear",
    robot_sigma_m: float = 0.0,
    check: bool = True,
    cond_soft: float = COND_SOFT,
    cond_hard: float = COND_HARD,
    robot_model: bool = True,
    clusters: ArrayLike | None = None,
    working_volume: tuple[tuple[float, float], tuple[float, float]] | None = None,
    kinematic_prior: KinematicPrior | None = None,
) -> HandEyeResult:
    """Joint least squares of sensor2flange (6 DOF) and the ball centre on all sweeps' points.

    Minimises ``sum_j (|| flange2base_j @ sensor2flange @ p_j - c || - R)^2`` over the inliers
    (scipy ``least_squares``, analytic Jacobian, rotation as a local rotation-vector increment about
    the sensor axes). Sweeps may have any motion (no constant-orientation assumption).

    Args:
        sweeps: all sweeps (FOV and tilted).
        initial: a :class:`HandEyeResult` (its ball centre and inliers are reused) or a ``(4, 4)``
            sensor2flange guess; then each sweep is mapped to base with it and robustly fitted
            (``calib.sphere.fit_sphere``) for its inlier mask, and the ball centre (and radius)
            start from the median of the fits.
        ball_radius: known radius (m). ``None`` estimates it (implies ``fit_radius``).
        fit_radius: estimate the radius, starting from ``ball_radius``.
        masks: initial inlier masks per sweep (default: ``initial.inliers`` or robust fits).
        outlier_sigma: after each round, points with ``|r| > max(outlier_sigma * sigma_robust,
            min_threshold_m)`` are excluded (``sigma_robust`` = 1.4826 MAD); repeated until the
            mask is stable or ``max_rounds``.
        init_band_m: distance (m) from the ball within which points of a sweep whose initial
            sphere fit failed are taken for the first round.
        loss: scipy robust loss (``"linear"``, ``"soft_l1"``, ``"huber"``, ``"cauchy"``); its
            scale is the robust sigma; ``cov`` always uses the plain Gauss-Newton form.
        robot_sigma_m: per-axis sigma (m) of a per-sweep error of the reported flange position
            (the data sheet's repeatability) in ``cov``; with ``robot_model`` the estimate's floor.
        check: raise :class:`PoorlyConstrained` when the solution is not unique (condition number
            above ``cond_hard``); above ``cond_soft`` a warning with advice is logged.
        robot_model: estimate the robot's pose error from the residuals (per sweep and per pose
            cluster, :mod:`~wristscan.calib.handeye_uncertainty`) and put it into ``cov``; False
            gives ``s^2 (J^T J)^-1`` plus the ``robot_sigma_m`` term alone.
        clusters: pose cluster of each sweep (sweeps sharing one robot pose error); default
            :func:`~wristscan.calib.handeye_uncertainty.pose_clusters` (same orientation, nearby).
        working_volume: laser-plane ``(y_min, y_max), (z_min, z_max)`` (m) over which the
            predicted point error is evaluated; default the inlier points' extent.
        kinematic_prior: the arm's model and the prior sigma of its DH parameters: the error
            common to all poses (:mod:`~wristscan.calib.handeye_kinematic`) added to ``cov``.

    Returns a :class:`HandEyeResult` (``method="joint"``): ``cov`` the sandwich covariance under
    the error model, for the 6 sensor2flange parameters, ``components``, ``point_sigma_m``
    (:func:`wristscan.calib.handeye_jackknife.with_jackknife` adds the jackknife).
    """
    sw = check_sweeps(sweeps, "sweeps")
    if not sw:
        raise ValueError("refine needs at least one sweep")
    fit_radius = fit_radius or ball_radius is None
    X0, c, radius, cur = start(sw, initial, ball_radius, masks, init_band_m)
    full = PointStack.build(sw)
    outliers = (outlier_sigma, min_threshold_m, max_rounds)
    R_base, t, c, radius, mask_all = rounds(
        full, X0, c, radius, np.concatenate(cur), fit_radius, loss, outliers
    )
    result, ident = joint_result(
        sw, full.subset(mask_all), mask_all, (R_base, t, c, radius), fit_radius, robot_sigma_m,
        cond_soft,
        robot_model=robot_model, clusters=clusters, working_volume=working_volume,
    )  # fmt: skip
    _apply_check(ident, check, cond_soft, cond_hard)
    if kinematic_prior is not None:
        result = with_kinematic_prior(result, sw, full.subset(mask_all), kinematic_prior)
    return result
