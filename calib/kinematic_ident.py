"""The arm's kinematic errors identified with the probe: DH deviations estimated jointly with
sensor2flange and the ball centre(s) from ball sweeps made at many poses.

A controller computes flange poses with a kinematic model (the nominal DH table or its factory
calibration) that misses the arm by 0.1-0.5 mm; a sensor calibration on such poses absorbs what
all poses share into sensor2flange and leaves the rest, which depends on the pose, in every cloud.
Ball sweeps from many poses hold what a kinematic calibration needs: every point ``p`` (sensor
frame) of every profile lies on the ball of known radius ``R``::

    | F(DH + dDH, q_i) X p_j - c_k | = R        q_i: the joints of profile i (reported),
                                                 X: sensor2flange, c_k: centre of ball place k

which :func:`identify` solves for ``dDH`` (24 deviations: ``theta_1..6, a_1..6, d_1..6,
alpha_1..6``, rad and m; the order of :mod:`~wristscan.calib.handeye_kinematic`), ``X`` and the
centres by Gauss-Newton, with the flange's sensitivity to each DH parameter
(:func:`~wristscan.calib.handeye_kinematic.flange_sensitivity`) in the Jacobian.

Not everything is observable (:func:`identifiability`). The ball centres are free, so any change
of the base frame is absorbed by them (``theta_1``, ``d_1``); sensor2flange absorbs the last link
(``theta_6``, ``d_6``, ``a_6``, ``alpha_6``); the parallel joints 2-4 see only the sum of their
offsets ``d``. The DH columns of the scaled Jacobian (each scaled by the parameter's prior
sigma), with sensor2flange and the centres projected out, are taken in DH order: a column that
adds nothing to those before it is unobservable, its parameter is fixed at the model's value and
named with what it cannot be told from. Directions that are observed, but weakly (small singular
values), are held by the prior (the model's 1-sigma per parameter, as a regularising term): the
solution is the maximum a posteriori estimate and its covariance includes the prior. The
covariance is clustered by sweep (a sweep's points share the robot's repeatability error), so
the sigmas do not shrink with the number of points of a sweep.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.calib.dh import DHParams, get_model
from wristscan.calib.handeye_kinematic import flange_sensitivity
from wristscan.calib.handeye_model import Sweep

__all__ = [
    "PARAM_NAMES",
    "BallScan",
    "Identifiability",
    "KinematicIdentification",
    "apply_deltas",
    "fit_sensor2flange",
    "identifiability",
    "identify",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

PARAM_NAMES: tuple[str, ...] = tuple(
    f"{k}{j}" for k in ("theta", "a", "d", "alpha") for j in range(1, 7)
)
"""Names of the 24 DH deviations, in the order of a DH vector."""

_RANK_TOL = 1e-6
"""Relative singular value (of the scaled, projected DH block) below which a direction is
unobservable: its parameters are fixed."""
_WEAK_TOL = 2e-2
"""... below which a direction is weakly observed (named; the prior holds it)."""
_NOISE_FLOOR_M = 2e-6
_MIN_POINTS = 200


@dataclass(frozen=True, eq=False)
class BallScan:
    """One sweep over a tooling ball: ``sweep`` (points in the sensor frame, the flange pose of
    each profile as the model computed it), the ``joints`` ``(P, 6)`` (rad) of each profile and
    which ball ``place`` (0, 1, ...) was swept."""

    sweep: Sweep
    joints: FloatArray
    place: int = 0

    def __post_init__(self) -> None:
        q = np.asarray(self.joints, dtype=np.float64)
        if q.shape != (self.sweep.n_poses, 6) or not np.all(np.isfinite(q)):
            raise ValueError(
                f"joints: expected ({self.sweep.n_poses}, 6) finite values, got {q.shape}"
            )
        if self.place < 0:
            raise ValueError(f"place must be >= 0, got {self.place}")
        object.__setattr__(self, "joints", q)


@dataclass(frozen=True, eq=False)
class Identifiability:
    """What the data tell apart: singular values of the scaled DH block (sensor2flange and the
    ball centres projected out, largest first), the parameters fixed (with what each cannot be
    told from) and the weakly observed combinations (held by the prior)."""

    singular_values: FloatArray
    fixed: tuple[int, ...]
    unobservable: tuple[str, ...]
    weak: tuple[str, ...]
    equivalent: FloatArray = field(repr=False)
    """``(24, 24)``: a deviation vector as the free parameters see it (``equivalent @ d``): each
    fixed parameter's effect carried by the free ones it cannot be told from (e.g. ``d2``
    carries ``d2 + d3 + d4``), zero where only sensor2flange or the centres absorb it."""

    @property
    def fixed_names(self) -> tuple[str, ...]:
        return tuple(PARAM_NAMES[i] for i in self.fixed)

    @property
    def free(self) -> tuple[int, ...]:
        return tuple(i for i in range(24) if i not in self.fixed)


@dataclass(frozen=True, eq=False)
class KinematicIdentification:
    """An identified arm: ``model`` (``base_model`` plus ``delta``), sensor2flange and the ball
    centres estimated with it, 1-sigma of every deviation (the prior's for fixed ones),
    the full covariance (order: 24 DH, 6 sensor2flange as in ``HandEyeResult.cov``, 3 per
    centre), residual RMS before (the base model, sensor2flange and centres refitted: the sensor
    calibration's joint solution, ``sensor2flange_before``) and after, and the identifiability
    analysis."""

    model: DHParams
    base_model: DHParams
    delta: FloatArray
    sigma: FloatArray
    sensor2flange: FloatArray
    ball_centres: FloatArray
    cov: FloatArray = field(repr=False)
    rms_m: float
    rms_before_m: float
    sensor2flange_before: FloatArray = field(repr=False)
    n_points: int
    n_scans: int
    iterations: int
    ident: Identifiability

    @property
    def delta_vector(self) -> FloatArray:
        return np.asarray(self.delta.reshape(-1), dtype=np.float64)


def apply_deltas(model: DHParams, delta: ArrayLike, name: str | None = None) -> DHParams:
    """``model`` plus the DH deviations ``delta`` (24 values or ``(4, 6)``: theta, a, d, alpha)."""
    dv = np.asarray(delta, dtype=np.float64).reshape(4, 6)
    d, a, alpha, theta = model.arrays()
    return DHParams(
        name=name or model.name,
        d=tuple(float(v) for v in d + dv[2]),
        a=tuple(float(v) for v in a + dv[1]),
        alpha=tuple(float(v) for v in alpha + dv[3]),
        theta_offset=tuple(float(v) for v in theta + dv[0]),
    )


# --------------------------------------------------------------------------------------------
# Data


@dataclass(frozen=True, eq=False)
class _Stack:
    """Points of all scans: sensor frame ``p`` (N, 3), global profile ``prof`` (N,), ball place
    ``place`` (N,), scan ``scan`` (N,); joints ``q`` (P, 6) of every profile."""

    p: FloatArray
    prof: IntArray
    place: IntArray
    scan: IntArray
    q: FloatArray
    n_places: int

    def subset(self, keep: NDArray[np.bool_]) -> _Stack:
        return _Stack(
            self.p[keep], self.prof[keep], self.place[keep], self.scan[keep], self.q, self.n_places
        )


def _stack(scans: Sequence[BallScan], max_points: int, seed: int) -> _Stack:
    rng = np.random.default_rng(seed)
    ps, profs, places, scan_ids, qs = [], [], [], [], []
    offset = 0
    for k, s in enumerate(scans):
        idx = np.arange(s.sweep.n_points)
        if idx.size > max_points:
            idx = np.sort(rng.choice(idx.size, size=max_points, replace=False))
        ps.append(s.sweep.points_sensor[idx])
        profs.append(s.sweep.pose_index[idx] + offset)
        places.append(np.full(idx.size, s.place, dtype=np.intp))
        scan_ids.append(np.full(idx.size, k, dtype=np.intp))
        qs.append(s.joints)
        offset += s.sweep.n_poses
    place = np.concatenate(places)
    return _Stack(
        np.concatenate(ps),
        np.concatenate(profs).astype(np.intp),
        place,
        np.concatenate(scan_ids),
        np.concatenate(qs),
        int(place.max()) + 1,
    )


def _check_scans(scans: Sequence[BallScan]) -> list[BallScan]:
    out = list(scans)
    if not out:
        raise ValueError("no ball scans")
    for k, s in enumerate(out):
        if not isinstance(s, BallScan):
            raise TypeError(f"scans[{k}] is {type(s).__name__}, expected BallScan")
    places = sorted({s.place for s in out})
    if places != list(range(len(places))):
        raise ValueError(f"ball places must be numbered 0..n-1, got {places}")
    return out


# --------------------------------------------------------------------------------------------
# Residuals and Jacobian


def _residuals(
    st: _Stack, model: DHParams, X: FloatArray, c: FloatArray, R: float, with_jacobian: bool
) -> tuple[FloatArray, FloatArray | None]:
    """Signed distances (N,) of the points to their ball, and the Jacobian ``(N, 24 + 6 + 3K)``
    (DH deviations, sensor2flange increments, centres)."""
    F = kinematics.forward(model, st.q)
    pf = st.p @ X[:3, :3].T + X[:3, 3]
    Fi = F[st.prof]
    b = np.einsum("nij,nj->ni", Fi[:, :3, :3], pf) + Fi[:, :3, 3]
    e = b - c[st.place]
    dist = np.linalg.norm(e, axis=1)
    r = dist - R
    if not with_jacobian:
        return r, None
    n = e / np.maximum(dist, 1e-12)[:, None]
    m = np.einsum("nji,nj->ni", Fi[:, :3, :3], n)  # the normal in the flange frame
    G = flange_sensitivity(model, st.q)  # (P, 6, 24)
    z = np.hstack([np.cross(pf, m), m])
    J_dh = np.einsum("na,nab->nb", z, G[st.prof])
    J_x = np.hstack([np.cross(st.p, m @ X[:3, :3]), m])
    J_c = np.zeros((r.size, 3 * st.n_places))
    for k in range(st.n_places):  # a few places
        sel = st.place == k
        J_c[sel, 3 * k : 3 * k + 3] = -n[sel]
    return r, np.hstack([J_dh, J_x, J_c])


# --------------------------------------------------------------------------------------------
# Identifiability


def _describe(i: int, M: FloatArray, free: list[int], scale: float) -> tuple[str, FloatArray]:
    """What parameter ``i`` cannot be told from (its scaled column ``M[:, i]`` regressed on the
    free ones), and the regression coefficients (scaled units; zero when nothing is left of
    it once sensor2flange and the centres are projected out)."""
    col = M[:, i]
    if np.linalg.norm(col) <= 1e-4 * scale:
        text = f"{PARAM_NAMES[i]}: indistinguishable from sensor2flange or the ball centre(s)"
        return text, np.zeros(len(free))
    beta = np.linalg.lstsq(M[:, free], col, rcond=None)[0]
    big = np.argsort(-np.abs(beta))[:3]
    terms = [f"{beta[j]:+.2f} {PARAM_NAMES[free[j]]}" for j in big if abs(beta[j]) > 0.1]
    text = f"{PARAM_NAMES[i]}: indistinguishable from {' '.join(terms) or 'the others'}"
    return text, np.asarray(beta, dtype=np.float64)


def _dependent_columns(M: FloatArray, tol: float) -> list[int]:
    """Columns of ``M`` that add nothing to the earlier ones (norm of what is left after
    projecting those out below ``tol``): in DH order, so the choice is the same for every arm
    (of ``d2, d3, d4`` the first is kept and carries their sum)."""
    basis = np.zeros((M.shape[0], 0))
    fixed = []
    for i in range(M.shape[1]):  # 24 columns
        col = M[:, i] - basis @ (basis.T @ M[:, i])
        norm = float(np.linalg.norm(col))
        if norm <= tol:
            fixed.append(i)
        else:
            basis = np.hstack([basis, (col / norm)[:, None]])
    return fixed


def identifiability(J: FloatArray, prior_sigma: ArrayLike) -> Identifiability:
    """The analysis of the module doc on a Jacobian ``(N, 24 + p)`` whose first 24 columns are
    the DH deviations and the rest sensor2flange and the centres; ``prior_sigma`` (24,) scales
    the DH columns (a parameter's effect at the size it may have)."""
    s = np.asarray(prior_sigma, dtype=np.float64).reshape(24)
    Q, _ = np.linalg.qr(J[:, 24:])
    Jd = J[:, :24] - Q @ (Q.T @ J[:, :24])
    M = Jd * s
    sv = np.linalg.svd(M, compute_uv=False)
    top = float(sv[0]) if sv.size and sv[0] > 0 else 1.0
    fixed = _dependent_columns(M, _RANK_TOL * top)
    free = [i for i in range(24) if i not in fixed]
    B = np.eye(24)
    unobs: list[str] = []
    for i in fixed:
        text, beta = _describe(i, M, free, top)
        unobs.append(text)
        B[i, i] = 0.0
        B[free, i] = beta * s[i] / s[free]  # back from scaled units
    weak: list[str] = []
    if free:
        _, sf, Vt = np.linalg.svd(M[:, free], full_matrices=False)
        for k in np.flatnonzero(sf < _WEAK_TOL * top):
            v = Vt[k] / np.max(np.abs(Vt[k]))
            terms = [f"{v[j]:+.2f} {PARAM_NAMES[free[j]]}" for j in np.argsort(-np.abs(v))[:4]]
            weak.append(f"{' '.join(t for t in terms if abs(float(t.split()[0])) > 0.2)} "
                        f"(relative singular value {sf[k] / top:.1e})")  # fmt: skip
    rel = np.asarray(sv / top, dtype=np.float64)
    return Identifiability(rel, tuple(fixed), tuple(unobs), tuple(weak), B)


# --------------------------------------------------------------------------------------------
# The solution


def _initial_centres(st: _Stack, model: DHParams, X: FloatArray, R: float) -> FloatArray:
    """Per place, the centre that best fits its points (a few Gauss-Newton steps from the mean
    point pushed ``R`` away from the sensor)."""
    F = kinematics.forward(model, st.q)
    pf = st.p @ X[:3, :3].T + X[:3, 3]
    Fi = F[st.prof]
    b = np.einsum("nij,nj->ni", Fi[:, :3, :3], pf) + Fi[:, :3, 3]
    view = np.einsum("nij,j->ni", Fi[:, :3, :3], X[:3, 2])  # sensor Z in base
    out = np.empty((st.n_places, 3))
    for k in range(st.n_places):
        sel = st.place == k
        c = b[sel].mean(axis=0) + R * view[sel].mean(axis=0)
        for _ in range(10):
            e = b[sel] - c
            d = np.linalg.norm(e, axis=1)
            n = e / d[:, None]
            c = c + np.linalg.lstsq(n, d - R, rcond=None)[0]
        out[k] = c
    return out


def _step(
    J: FloatArray, r: FloatArray, free: list[int], prior_inv: FloatArray, delta: FloatArray,
    sigma_r: float,
) -> FloatArray:  # fmt: skip
    """The Gauss-Newton step on the free columns with the prior term (MAP)."""
    cols = free + list(range(24, J.shape[1]))
    A = J[:, cols]
    H = A.T @ A / sigma_r**2
    g = A.T @ r / sigma_r**2
    nf = len(free)
    H[:nf, :nf] += np.diag(prior_inv[free])
    g[:nf] += prior_inv[free] * delta[free]
    return np.asarray(-np.linalg.solve(H, g), dtype=np.float64)


def _apply_step(
    dx: FloatArray, free: list[int], delta: FloatArray, X: FloatArray, c: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    nf = len(free)
    delta = delta.copy()
    delta[free] += dx[:nf]
    w, t = dx[nf : nf + 3], dx[nf + 3 : nf + 6]
    X = se3.make(X[:3, :3] @ se3.rotvec_to_matrix(w), X[:3, 3] + t)
    c = c + dx[nf + 6 :].reshape(-1, 3)
    return delta, X, c


def _covariance(
    J: FloatArray, r: FloatArray, st: _Stack, free: list[int], prior_inv: FloatArray,
    sigma_r: float,
) -> FloatArray:  # fmt: skip
    """The covariance of all parameters (fixed DH ones: their prior), clustered by scan: the
    sandwich ``H^-1 (sum_k s_k s_k^T + P^-1) H^-1`` with ``s_k`` the score of scan ``k``; never
    below the model-based ``H^-1``."""
    cols = free + list(range(24, J.shape[1]))
    A = J[:, cols] / sigma_r
    H = A.T @ A
    nf = len(free)
    H[:nf, :nf] += np.diag(prior_inv[free])
    H_inv = np.linalg.pinv(H)
    S = np.stack([np.bincount(st.scan, A[:, i] * r / sigma_r) for i in range(A.shape[1])], axis=1)
    meat = S.T @ S
    meat[:nf, :nf] += np.diag(prior_inv[free])
    C = H_inv @ meat @ H_inv
    C = 0.5 * (C + C.T)
    d = np.maximum(np.diag(C), np.diag(H_inv))
    sd = np.sqrt(np.maximum(np.diag(C), 1e-300))
    C = C / np.outer(sd, sd) * np.outer(np.sqrt(d), np.sqrt(d))
    n = J.shape[1]
    full = np.zeros((n, n))
    idx = np.array(cols)
    full[np.ix_(idx, idx)] = C
    for i in range(24):
        if i not in free:
            full[i, i] = 1.0 / prior_inv[i]
    return full


def _prepare(
    scans: Sequence[BallScan], model: str | DHParams, sensor2flange: ArrayLike, radius_m: float,
    centres: ArrayLike | None, max_points: int, seed: int,
) -> tuple[DHParams, _Stack, FloatArray, FloatArray, float]:  # fmt: skip
    base = get_model(model)
    sc = _check_scans(scans)
    R = float(radius_m)
    if not (np.isfinite(R) and R > 0):
        raise ValueError(f"ball radius must be positive, got {radius_m!r}")
    st = _stack(sc, max_points, seed)
    if st.p.shape[0] < _MIN_POINTS:
        raise ValueError(f"only {st.p.shape[0]} points in the scans; at least {_MIN_POINTS}")
    X = se3.check_transform(np.asarray(sensor2flange, dtype=np.float64), "sensor2flange")
    c = _initial_centres(st, base, X, R) if centres is None else np.array(centres, dtype=float)
    if c.shape != (st.n_places, 3):
        raise ValueError(f"centres: expected ({st.n_places}, 3), got {c.shape}")
    return base, st, X, c, R


def fit_sensor2flange(
    scans: Sequence[BallScan],
    model: str | DHParams,
    sensor2flange: ArrayLike,
    radius_m: float,
    *,
    centres: ArrayLike | None = None,
    max_points_per_scan: int = 400,
    seed: int = 0,
) -> tuple[FloatArray, FloatArray, float]:
    """Sensor2flange and the ball centres with the arm's kinematics taken as ``model`` (the
    sensor calibration's joint solution on these scans, without per-sweep terms): returns them
    and the residual RMS (m)."""
    base, st, X, c, R = _prepare(
        scans, model, sensor2flange, radius_m, centres, max_points_per_scan, seed
    )
    f = _fit(st, base, X, c, R, [], np.ones(24), 12)
    return f.X, f.c, f.rms


def identify(
    scans: Sequence[BallScan],
    model: str | DHParams,
    sensor2flange: ArrayLike,
    radius_m: float,
    prior_sigma: ArrayLike,
    *,
    centres: ArrayLike | None = None,
    max_points_per_scan: int = 400,
    iterations: int = 12,
    seed: int = 0,
) -> KinematicIdentification:
    """Identify the arm's DH deviations from ``model`` (the model the controller or the
    synchroniser computed the scans' flange poses with; they are computed again from the joints)
    jointly with sensor2flange (start: ``sensor2flange``) and the ball centres (start:
    ``centres`` ``(K, 3)``, else fitted); ``prior_sigma`` ``(4, 6)`` (theta, a, d, alpha per
    joint) is the model's 1-sigma per parameter (it scales the identifiability analysis and
    regularises weak directions; :func:`~wristscan.calib.handeye_kinematic.prior_sigma`).
    ``max_points_per_scan`` points of each scan are used (a seeded subset).

    Raises ``ValueError`` with one line for bad input or too few points."""
    ps = np.asarray(prior_sigma, dtype=np.float64)
    if ps.shape != (4, 6) or not np.all(np.isfinite(ps)) or np.any(ps <= 0):
        raise ValueError("prior_sigma: expected (4, 6) positive values (theta, a, d, alpha)")
    sc = _check_scans(scans)
    base, st, X, c, R = _prepare(
        sc, model, sensor2flange, radius_m, centres, max_points_per_scan, seed
    )
    prior_inv = 1.0 / ps.reshape(-1) ** 2
    before = _fit(st, base, X, c, R, [], prior_inv, iterations)
    st, X, c = before.stack, before.X, before.c
    ident = identifiability(before.J, ps.reshape(-1))
    free = list(ident.free)
    after = _fit(st, base, X, c, R, free, prior_inv, iterations)
    delta = after.delta
    cov = _covariance(after.J, after.r, after.stack, free, prior_inv, after.sigma_r)
    sigma = np.sqrt(np.clip(np.diag(cov)[:24], 0.0, None)).reshape(4, 6)
    log.info(
        "kinematic identification: %d points, %d scans, %d places; rms %.1f um -> %.1f um; "
        "fixed %s",
        after.r.size, len(sc), st.n_places, before.rms * 1e6, after.rms * 1e6,
        ", ".join(ident.fixed_names) or "none",
    )  # fmt: skip
    return KinematicIdentification(
        model=apply_deltas(base, delta, f"{base.name} identified"),
        base_model=base,
        delta=delta.reshape(4, 6),
        sigma=sigma,
        sensor2flange=after.X,
        ball_centres=after.c,
        cov=cov,
        rms_m=after.rms,
        rms_before_m=before.rms,
        sensor2flange_before=before.X,
        n_points=int(after.r.size),
        n_scans=len(sc),
        iterations=after.iterations,
        ident=ident,
    )


@dataclass(frozen=True, eq=False)
class _Fit:
    stack: _Stack
    delta: FloatArray
    X: FloatArray
    c: FloatArray
    r: FloatArray
    J: FloatArray
    rms: float
    sigma_r: float
    iterations: int


def _fit(
    st: _Stack, base: DHParams, X: FloatArray, c: FloatArray, R: float, free: list[int],
    prior_inv: FloatArray, iterations: int,
) -> _Fit:  # fmt: skip
    """Gauss-Newton on the ``free`` DH deviations, sensor2flange and the centres; points farther
    than 5 sigma (at least 0.2 mm) from their ball are dropped after the first step."""
    delta = np.zeros(24)
    it = 0
    for it in range(1, iterations + 1):
        model = apply_deltas(base, delta)
        r, J = _residuals(st, model, X, c, R, True)
        assert J is not None
        rms = float(np.sqrt(np.mean(r**2)))
        if it == 2:
            keep = np.abs(r) <= max(5.0 * rms, 0.2e-3)
            if not keep.all() and keep.sum() >= _MIN_POINTS:
                st = st.subset(keep)
                r, J = r[keep], J[keep]
                rms = float(np.sqrt(np.mean(r**2)))
        sigma_r = max(rms, _NOISE_FLOOR_M)
        dx = _step(J, r, free, prior_inv, delta, sigma_r)
        delta, X, c = _apply_step(dx, free, delta, X, c)
        nf = len(free)
        small = np.all(np.abs(dx[:nf]) * np.sqrt(prior_inv[free]) < 1e-3) and np.all(
            np.abs(dx[nf:]) < 1e-8
        )
        if small and it > 2:
            break
    model = apply_deltas(base, delta)
    r, J = _residuals(st, model, X, c, R, True)
    assert J is not None
    rms = float(np.sqrt(np.mean(r**2)))
    return _Fit(st, delta, X, c, r, J, rms, max(rms, _NOISE_FLOOR_M), it)
