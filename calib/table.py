"""Rotary-table axis calibration and the table/part frames of Eq. (1).

A tooling ball fixed on the table top is measured (sphere centre in the robot base frame) at
``k >= 3`` table angles. The centres lie on a circle around the rotation axis; the fit returns the
axis direction, a point on it and the encoder offset.

Conventions (all SI):

* ``direction`` is a unit vector in the base frame, signed so that the table turns right-handed
  about it as the encoder angle increases (a positive angle step moves the ball counter-clockwise
  seen from the tip of ``direction``).
* ``point`` is the centre of the circle described by the ball centre, i.e. the foot of the ball
  on the axis. The table frame has its origin there (optionally shifted along the axis).
* Table frame: Z = ``direction``; X = base X projected onto the plane normal to Z (base Y projected
  when the axis is within ~25 degrees of base X, where the projection of X becomes ill-defined);
  Y = Z x X. The table frame is fixed in the base frame.
* Part frame: fixed to the table top, it turns with it. At table angle ``theta`` (rad, encoder
  reading as delivered by the table driver) the table top has turned by ``theta +
  encoder_offset_rad`` about table Z, so ``part2table = Rz(theta + offset)`` and
  ``table2part = Rz(-(theta + offset))``. With Eq. (1):
  ``sensor2part = table2part(theta) @ base2table @ flange2base(q) @ sensor2flange``.
* Gauge of the offset: ball centres alone cannot tell an encoder offset from where the ball sits
  on the table. With ``estimate_offset=True`` (default) the part frame is chosen so that the ball
  lies on the part's +X axis (``ball_in_part = [r, 0, 0]``) and ``encoder_offset_rad`` is the
  table angle of the ball measured from table X at encoder zero. With ``estimate_offset=False``
  the encoder zero is trusted (offset 0) and the ball's azimuth shows in ``ball_in_part``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import OptimizeResult, least_squares

from wristscan.calib import se3
from wristscan.calib.se3 import FloatArray

__all__ = [
    "COV_ORDER",
    "TableAxis",
    "base2part",
    "base2table",
    "base2table_from",
    "fit_table_axis",
    "table2part",
    "table_rotation",
    "table_x_axis",
]

log = logging.getLogger(__name__)

COV_ORDER: tuple[str, ...] = (
    "tilt_about_table_x_rad",
    "tilt_about_table_y_rad",
    "point_x_m",
    "point_y_m",
    "point_z_m",
    "radius_m",
    "phase_rad",
)
"""Order of ``TableAxis.cov``. The tilts are small rotations of the axis direction about the
table X and Y axes; the point is in the base frame; ``phase_rad`` is the encoder offset when it is
estimated, else the ball's azimuth in the part frame."""

_X_FALLBACK_SIN = np.sin(np.deg2rad(25.0))


@dataclass(frozen=True)
class TableAxis:
    """Result of :func:`fit_table_axis` (base frame, metres, radians)."""

    direction: FloatArray
    """(3,) unit axis direction, right-handed with increasing table angle."""
    point: FloatArray
    """(3,) a point on the axis: the centre of the ball's circle (m)."""
    encoder_offset_rad: float
    """Added to the encoder angle to get the part's rotation from the table frame."""
    rms_m: float
    """RMS over the centres of the 3D distance between measured and modelled centre (m)."""
    cov: FloatArray
    """(7, 7) covariance of the parameters in :data:`COV_ORDER` order."""
    tilt_deg: float
    """Angle between the axis line and the base Z line, degrees in [0, 90] (reporting only)."""
    radius_m: float
    """Radius of the circle described by the ball centre (m)."""
    ball_in_part: FloatArray
    """(3,) ball centre in the part frame (m)."""
    residuals_m: FloatArray
    """(k, 3) measured minus modelled centre (m)."""
    n_angles: int

    def base2table(self, origin_along_axis_m: float = 0.0) -> FloatArray:
        """The fixed base-to-table transform, see :func:`base2table`."""
        return base2table(self, origin_along_axis_m)

    def sigma(self) -> dict[str, float]:
        """One-sigma uncertainty of each parameter, keyed by :data:`COV_ORDER` names."""
        return dict(zip(COV_ORDER, np.sqrt(np.diag(self.cov)).tolist(), strict=True))


def table_x_axis(direction: ArrayLike) -> FloatArray:
    """The table frame's X axis for a unit axis ``direction`` (3,): base X projected onto the
    plane normal to the axis, or base Y projected when the axis is within ~25 deg of base X."""
    a = _unit(np.asarray(direction, dtype=np.float64), "direction")
    for ref in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        proj = ref - (ref @ a) * a
        norm = float(np.linalg.norm(proj))
        if norm >= _X_FALLBACK_SIN:
            return proj / norm
    raise AssertionError("unreachable: X and Y cannot both be within 25 deg of one axis")


def base2table_from(
    direction: ArrayLike, point: ArrayLike, origin_along_axis_m: float = 0.0
) -> FloatArray:
    """Base-to-table transform (4, 4) from an axis ``direction`` (3,) and a ``point`` (3,) on it
    (base frame, metres). The origin is ``point + origin_along_axis_m * direction``, e.g. to put
    it on the table top when the ball height above it is known (pass minus that height)."""
    a = _unit(np.asarray(direction, dtype=np.float64), "direction")
    p = np.asarray(point, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"point: expected 3 finite values, got {p!r}")
    x = table_x_axis(a)
    y = np.cross(a, x)
    table2base = se3.make(np.stack([x, y, a], axis=1), p + float(origin_along_axis_m) * a)
    return se3.invert(table2base)


def base2table(axis: TableAxis, origin_along_axis_m: float = 0.0) -> FloatArray:
    """Base-to-table transform (4, 4) of a fitted axis (see module docstring for the frame)."""
    return base2table_from(axis.direction, axis.point, origin_along_axis_m)


def table_rotation(theta_rad: ArrayLike, encoder_offset_rad: float = 0.0) -> FloatArray:
    """``part2table`` at table angle(s) ``theta_rad`` (...,): ``Rz(theta + offset)``,
    (..., 4, 4)."""
    th = np.asarray(theta_rad, dtype=np.float64) + float(encoder_offset_rad)
    if not np.all(np.isfinite(th)):
        raise ValueError("table angle contains NaN or infinity")
    c, s = np.cos(th), np.sin(th)
    T = se3.identity(th.shape)
    T[..., 0, 0] = c
    T[..., 0, 1] = -s
    T[..., 1, 0] = s
    T[..., 1, 1] = c
    return T


def table2part(theta_rad: ArrayLike, encoder_offset_rad: float = 0.0) -> FloatArray:
    """``table2part`` at table angle(s) ``theta_rad`` (...,): undoes the table's turn,
    ``Rz(-(theta + offset))``, (..., 4, 4)."""
    return table_rotation(-np.asarray(theta_rad, dtype=np.float64) - float(encoder_offset_rad))


def base2part(
    axis: TableAxis, theta_rad: ArrayLike, origin_along_axis_m: float = 0.0
) -> FloatArray:
    """``table2part(theta) @ base2table`` for a fitted axis, (..., 4, 4)."""
    return table2part(theta_rad, axis.encoder_offset_rad) @ base2table(axis, origin_along_axis_m)


def fit_table_axis(
    centres: ArrayLike,
    angles_rad: ArrayLike,
    *,
    estimate_offset: bool = True,
    centre_sigma_m: float | None = None,
    min_span_rad: float = float(np.deg2rad(20.0)),
) -> TableAxis:
    """Fit the table axis to ball centres ``centres`` (k, 3) (base frame, m) measured at encoder
    angles ``angles_rad`` (k,).

    Steps: plane fit of the centres (SVD) for the axis direction, circle fit in that plane for
    the axis point, sign of the direction from the angles, then a least-squares refinement of
    ``centre_k = point + r (cos(theta_k + phi) X + sin(theta_k + phi) Y)`` over axis direction
    (2 DOF), point (3), radius and phase ``phi``. ``cov`` is scaled by ``centre_sigma_m**2`` when
    given (a-priori std of each centre coordinate), else by the residual variance.

    Raises ``ValueError`` with advice for fewer than 3 distinct angles, angles spanning less than
    ``min_span_rad``, coincident or collinear centres, and non-finite input.
    """
    C = np.asarray(centres, dtype=np.float64)
    th = np.asarray(angles_rad, dtype=np.float64)
    if C.ndim != 2 or C.shape[1] != 3:
        raise ValueError(f"centres: expected shape (k, 3), got {C.shape}")
    if th.shape != (C.shape[0],):
        raise ValueError(f"angles_rad: expected shape ({C.shape[0]},), got {th.shape}")
    if not (np.all(np.isfinite(C)) and np.all(np.isfinite(th))):
        raise ValueError("centres/angles contain NaN or infinity")
    k = C.shape[0]
    _check_angles(th, min_span_rad)

    p0, r0, e1, n = _initial_circle(C)
    a0, u0, v0, phi0 = _axis_sign(C, th, p0, n, e1)
    direction, point, radius, phase, sol2 = _refine(C, th, p0, r0, (a0, u0, v0), phi0)

    res = sol2.fun.reshape(k, 3)
    dof = 3 * k - 7
    s2 = centre_sigma_m**2 if centre_sigma_m is not None else float(res.ravel() @ res.ravel()) / dof
    J = sol2.jac
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError as exc:
        raise ValueError("table axis fit is singular: spread the table angles wider") from exc

    if estimate_offset:
        offset, ball = phase, np.array([radius, 0.0, 0.0])
    else:
        offset, ball = 0.0, np.array([radius * np.cos(phase), radius * np.sin(phase), 0.0])
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    tilt = float(np.degrees(np.arccos(min(1.0, abs(float(direction[2]))))))
    log.debug("table axis fit: k=%d rms=%.3g m tilt=%.4f deg offset=%.6f rad", k, rms, tilt, offset)
    return TableAxis(
        direction=direction,
        point=point,
        encoder_offset_rad=float(offset),
        rms_m=rms,
        cov=cov,
        tilt_deg=tilt,
        radius_m=radius,
        ball_in_part=ball,
        residuals_m=res,
        n_angles=k,
    )


def _initial_circle(C: FloatArray) -> tuple[FloatArray, float, FloatArray, FloatArray]:
    """The circle of the centres ``C`` (k, 3): centre (m), radius (m), first in-plane axis and
    plane normal, from an SVD plane fit and an algebraic circle fit in that plane."""
    k = C.shape[0]
    # Plane fit: the normal is the direction of least spread of the centres.
    mean = C.mean(axis=0)
    _, sv, Vt = np.linalg.svd(C - mean, full_matrices=False)
    rms_spread = sv[0] / np.sqrt(k)
    if rms_spread < 1e-6:
        raise ValueError(
            "ball centres coincide: the ball sits on the axis or the table did not turn; "
            "fix the ball away from the table centre"
        )
    if sv[1] < 1e-6 * sv[0]:
        raise ValueError(
            "ball centres are collinear: check that the table really turned between measurements"
        )
    e1, e2, n = Vt[0], Vt[1], Vt[2]

    # Algebraic circle fit in the plane: x^2 + y^2 = 2 a x + 2 b y + c.
    xy = (C - mean) @ np.stack([e1, e2], axis=1)
    A = np.column_stack([2.0 * xy, np.ones(k)])
    (ca, cb, cc), *_ = np.linalg.lstsq(A, (xy**2).sum(axis=1), rcond=None)
    r0 = float(np.sqrt(max(cc + ca * ca + cb * cb, 0.0)))
    p0 = mean + ca * e1 + cb * e2
    if r0 < 1e-6:
        raise ValueError("ball circle radius is ~0: fix the ball away from the table centre")
    return p0, r0, e1, n


def _axis_sign(
    C: FloatArray, th: FloatArray, p0: FloatArray, n: FloatArray, e1: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Sign of the axis: the one for which ball azimuth minus table angle is most nearly
    constant. Returns the axis, the anchor frame's X and Y, and the phase (rad)."""
    d = C - p0
    best: tuple[float, FloatArray, FloatArray, FloatArray, float] | None = None
    for a in (n, -n):
        v = np.cross(a, e1)
        psi = np.arctan2(d @ v, d @ e1)
        z = np.mean(np.exp(1j * (psi - th)))
        if best is None or abs(z) > best[0]:
            best = (abs(z), a, e1, v, float(np.angle(z)))
    assert best is not None
    _, a0, u0, v0, phi0 = best
    return a0, u0, v0, phi0


def _refine(
    C: FloatArray,
    th: FloatArray,
    p0: FloatArray,
    r0: float,
    frame: tuple[FloatArray, FloatArray, FloatArray],
    phi0: float,
) -> tuple[FloatArray, FloatArray, float, float, OptimizeResult]:
    """Least squares of the circle model from the start (axis ``frame`` = (a0, u0, v0)), then
    again anchored on the deterministic table X: direction, point, radius, phase and the
    second solution (its residuals and Jacobian read in that frame)."""
    a0, u0, v0 = frame
    x_init = np.array([0.0, 0.0, *p0, r0, phi0])
    sol = least_squares(_residuals, x_init, args=(C, th, a0, u0, v0), method="lm", x_scale="jac")
    w = sol.x[0] * u0 + sol.x[1] * v0
    Rw = se3.rotvec_to_matrix(w)
    a_f, u_f = Rw @ a0, Rw @ u0
    p_f, r_f, phi_f = sol.x[2:5], float(sol.x[5]), float(sol.x[6])
    if r_f < 0:  # a negative radius is the same circle with the phase turned by pi
        r_f, phi_f = -r_f, phi_f + np.pi

    # Re-anchor on the deterministic table X so the phase and the covariance read in that frame.
    x_det = table_x_axis(a_f)
    y_det = np.cross(a_f, x_det)
    beta = float(np.arctan2(np.cross(x_det, u_f) @ a_f, x_det @ u_f))
    x_fin = np.array([0.0, 0.0, *p_f, r_f, _wrap(phi_f + beta)])
    sol2 = least_squares(
        _residuals, x_fin, args=(C, th, a_f, x_det, y_det), method="lm", x_scale="jac"
    )
    w2 = sol2.x[0] * x_det + sol2.x[1] * y_det
    R2 = se3.rotvec_to_matrix(w2)
    direction = R2 @ a_f
    x_out = table_x_axis(direction)
    beta2 = float(np.arctan2(np.cross(x_out, R2 @ x_det) @ direction, x_out @ (R2 @ x_det)))
    point = sol2.x[2:5].copy()
    radius = float(sol2.x[5])
    phase = _wrap(float(sol2.x[6]) + beta2)
    return direction, point, radius, phase, sol2


def _residuals(
    x: FloatArray, C: FloatArray, th: FloatArray, a0: FloatArray, u0: FloatArray, v0: FloatArray
) -> FloatArray:
    """Measured minus modelled centres, flattened (3k,). The anchor frame (a0, u0, v0) is turned
    by the small rotation vector ``x[0] u0 + x[1] v0``; the ball runs on the circle of centre
    ``x[2:5]`` and radius ``x[5]`` with phase ``x[6]`` relative to the turned u0."""
    R = se3.rotvec_to_matrix(x[0] * u0 + x[1] * v0)
    u, v = R @ u0, R @ v0
    ang = th + x[6]
    model = x[2:5] + x[5] * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v)
    out: FloatArray = (C - model).ravel()
    return out


def _check_angles(th: FloatArray, min_span_rad: float) -> None:
    if th.shape[0] < 3:
        raise ValueError(
            f"need the ball at >= 3 table angles, got {th.shape[0]}; "
            "measure it at 3 or more angles spread over the table's range"
        )
    a = np.sort(np.mod(th, 2.0 * np.pi))
    gaps = np.diff(np.append(a, a[0] + 2.0 * np.pi))
    distinct = int(np.count_nonzero(gaps > 1e-4))
    if distinct < 3:
        raise ValueError(
            f"need >= 3 distinct table angles, got {distinct}; turn the table between measurements"
        )
    span = 2.0 * np.pi - float(gaps.max())
    if span < min_span_rad:
        raise ValueError(
            f"table angles span only {np.degrees(span):.1f} deg "
            f"(< {np.degrees(min_span_rad):.1f}); spread the measurements wider "
            "(ideally over a full turn)"
        )


def _unit(v: FloatArray, name: str) -> FloatArray:
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: expected 3 finite values, got {v!r}")
    norm = float(np.linalg.norm(v))
    if norm < 1e-12:
        raise ValueError(f"{name}: zero vector")
    return v / norm


def _wrap(angle: float) -> float:
    """Wrap to (-pi, pi]."""
    return float(np.pi - np.mod(np.pi - angle, 2.0 * np.pi))
