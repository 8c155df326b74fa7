"""The point model of the joint hand-eye problem (:mod:`wristscan.calib.handeye`, (*)) over
all sweeps at once, and how well the data determine it.

:class:`PointStack` holds the points of several sweeps with the flange pose of each point's
profile, for vectorised residuals ``|| flange2base_j @ sensor2flange @ p_j - c || - R``, normals
and the analytic Jacobian (rotation increments about the sensor axes, :func:`right_jacobian`
away from zero). :func:`identifiability` gives the column-equilibrated condition
number of that Jacobian and advice on which data would constrain the weakest directions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.calib.handeye_model import Identifiability, Sweep, rows_times

__all__ = ["COND_HARD", "COND_SOFT", "PointStack", "identifiability", "right_jacobian", "skew"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

#: Condition number (column-equilibrated point Jacobian) above which the solution is *weakly
#: constrained*: a warning with advice is logged and the advice goes into the result. Good pose
#: sets (>= 30 deg tilts about two axes) give 5-11; 15 deg tilts about 20.
COND_SOFT = 15.0
#: Condition number above which the solution is taken as *not unique* and
#: :class:`PoorlyConstrained` is raised. Tilts of ``a`` degrees about two axes give about
#: ``300 / a`` (3 deg: 100, 1 deg: 300); 1e4 means tilts of ~0.03 deg, no more than an arm's own
#: orientation error, i.e. data that cannot be told from a pose set with a null direction (which
#: gives an infinite condition number). Below it the solution is unique and its covariance says
#: how weakly the weakest direction is determined (docs/calibration.md).
COND_HARD = 1e4

_AXES = ("X", "Y", "Z")


def skew(v: FloatArray) -> FloatArray:
    """Cross-product matrices ``[v]x`` (..., 3, 3) of vectors ``v`` (..., 3)."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def right_jacobian(w: FloatArray) -> FloatArray:
    """Right Jacobian of SO(3) at rotation vector ``w``: ``exp(w + e) ~ exp(w) exp(Jr(w) e)``."""
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 6.0
    return np.eye(3) - (1.0 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * (K @ K)


@dataclass
class PointStack:
    """Points of several sweeps stacked with their flange pose, for vectorised residuals."""

    p: FloatArray  # (N, 3) sensor frame
    Rf: FloatArray  # (N, 3, 3) flange2base rotation of each point's profile
    Tf: FloatArray  # (N, 3)
    sweep: IntArray  # (N,) sweep number
    n_sweeps: int

    @classmethod
    def build(cls, sweeps: Sequence[Sweep], masks: Sequence[BoolArray] | None = None) -> PointStack:
        ps, Rs, Ts, ks = [], [], [], []
        for k, s in enumerate(sweeps):
            m = np.ones(s.n_points, bool) if masks is None else np.asarray(masks[k], bool)
            idx = s.pose_index[m]
            ps.append(s.points_sensor[m])
            Rs.append(s.flange2base[idx, :3, :3])
            Ts.append(s.flange2base[idx, :3, 3])
            ks.append(np.full(idx.shape, k, dtype=np.intp))
        return cls(
            np.concatenate(ps),
            np.concatenate(Rs),
            np.concatenate(Ts),
            np.concatenate(ks),
            len(sweeps),
        )

    def subset(self, mask: BoolArray) -> PointStack:
        return PointStack(
            self.p[mask], self.Rf[mask], self.Tf[mask], self.sweep[mask], self.n_sweeps
        )

    def to_base(self, Rsf: FloatArray, tsf: FloatArray) -> FloatArray:
        """Points in the base frame ``(N, 3)`` (m)."""
        pf = rows_times(self.p, Rsf.T) + tsf
        return np.matmul(self.Rf, pf[:, :, None])[:, :, 0] + self.Tf

    def residuals(
        self, Rsf: FloatArray, tsf: FloatArray, c: FloatArray, radius: float
    ) -> FloatArray:
        w = self.to_base(Rsf, tsf) - c
        return np.sqrt(np.einsum("ni,ni->n", w, w)) - radius

    def normals(self, Rsf: FloatArray, tsf: FloatArray, c: FloatArray) -> FloatArray:
        """Unit vectors from the ball centre to each point, base frame ``(N, 3)``."""
        w = self.to_base(Rsf, tsf) - c
        return w / np.sqrt(np.einsum("ni,ni->n", w, w))[:, None]

    def jacobian(
        self,
        Rsf: FloatArray,
        tsf: FloatArray,
        c: FloatArray,
        fit_radius: bool,
        Jr: FloatArray | None = None,
    ) -> FloatArray:
        """d residual / d [w (sensor-axis rotation increment), t_sf, c, (radius)], ``(N, 9|10)``.

        With ``n`` the unit normal in base and ``m = R_f^T n``: d/dt = m, d/dc = -n and, for
        ``R_sf exp(w)``, d/dw = p x (R_sf^T m) (times the right Jacobian ``Jr`` away from w = 0)."""
        n = self.normals(Rsf, tsf, c)
        m_f = np.matmul(n[:, None, :], self.Rf)[:, 0, :]
        g = np.cross(self.p, rows_times(m_f, Rsf))
        if Jr is not None:
            g = rows_times(g, Jr)
        cols = [g, m_f, -n]
        if fit_radius:
            cols.append(-np.ones((n.shape[0], 1)))
        return np.concatenate(cols, axis=1)

    def rms(self, r: FloatArray) -> tuple[FloatArray, float]:
        cnt = np.bincount(self.sweep, minlength=self.n_sweeps).astype(np.float64)
        ss = np.bincount(self.sweep, weights=r**2, minlength=self.n_sweeps)
        with np.errstate(invalid="ignore", divide="ignore"):
            per = np.sqrt(ss / cnt)
        return per, float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


def identifiability(J: FloatArray, Rsf: FloatArray, soft: float = COND_SOFT) -> Identifiability:
    """Column-equilibrated condition number of ``J`` and advice from its weak directions.

    A direction is weak when its singular value is below ``s_max / soft`` (the smallest one always
    counts). Weak directions dominated by the rotation call for more FOV locations; those
    dominated by the sensor origin (confounded with the ball centre) call for tilts about the axes
    perpendicular to them, since a rotation about ``u`` leaves the origin along ``u`` unobserved.
    """
    norms = np.sqrt(np.einsum("ni,ni->i", J, J))
    norms[norms == 0.0] = 1.0
    Js = J / norms
    # Eigen-decomposition of the small normal matrix instead of an SVD of the tall Jacobian: the
    # condition numbers of interest (< 1e8) keep its eigenvalues well above rounding.
    lam, V = np.linalg.eigh(Js.T @ Js)
    lam, V = lam[::-1], V[:, ::-1]
    s = np.sqrt(np.clip(lam, 0.0, None))
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    weakest = V[:, -1] / norms
    weakest = weakest / np.linalg.norm(weakest)
    weak = [i for i in range(len(s)) if s[i] * soft < s[0]] or [len(s) - 1]
    rot_axes: list[str] = []
    trans_dirs: list[FloatArray] = []
    for i in weak:
        v = V[:, i]
        if float(np.sum(v[:3] ** 2)) >= float(np.sum(v[3:6] ** 2)):
            rot_axes.append(_AXES[int(np.argmax(np.abs(v[:3])))])
        else:
            u = Rsf.T @ v[3:6]
            trans_dirs.append(u / np.linalg.norm(u))
    parts: list[str] = []
    if trans_dirs:
        # Rank of the weak translation subspace: 1 -> one axis unobserved, >= 2 -> too few tilts.
        rank = int(np.linalg.matrix_rank(np.array(trans_dirs), tol=0.3))
        if rank >= 2:
            parts.append(
                "the sensor origin is unobserved in several directions: add orientations tilted "
                "about two different axes, e.g. the sensor X and Y axes (>= 45 deg between tool Z "
                "axes)"
            )
        else:
            i = int(np.argmax(np.abs(trans_dirs[0])))
            others = [a for j, a in enumerate(_AXES) if j != i]
            parts.append(
                f"the sensor origin along the sensor {_AXES[i]} axis is the least constrained: add "
                f"orientations tilted about the sensor {others[0]} or {others[1]} axis (>= 45 deg "
                "between tool Z axes)"
            )
    if rot_axes:
        axes = " and ".join(sorted(set(rot_axes)))
        parts.append(
            f"the rotation about the sensor {axes} axis is the least constrained: place the ball "
            "at more field-of-view locations, spread both along the laser line (sensor Y) and in "
            "depth (sensor Z)"
        )
    return Identifiability(cond, s, weakest, "; ".join(parts))
