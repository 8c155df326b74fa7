"""Kinematics of the simulated controller fast enough for its 1 ms tick.

The vectorised :mod:`wristscan.calib.kinematics` is made for batches; the controller evaluates
one configuration at a time, every tick, where NumPy's per-call overhead dominates. Here: the
forward kinematics and TCP Jacobian of one configuration in plain floats
(:class:`FastKinematics`), a scalar rotation vector (:func:`rotvec_of`), and the batched TCP
Jacobian (:func:`tcp_jacobian`) they are checked against.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics

__all__ = ["FastKinematics", "fast_kinematics", "rotvec_of", "tcp_jacobian"]

FloatArray = NDArray[np.float64]


def rotvec_of(R: ArrayLike) -> tuple[float, float, float]:
    """Rotation vector of one rotation matrix (angle in [0, pi]).

    The controller converts a pose every 2 ms; scipy's batched conversion costs ~0.2 ms per call,
    this scalar one (unit quaternion, Shepperd's branch choice) a few microseconds.
    """
    r = np.asarray(R, dtype=np.float64).tolist()
    tr = r[0][0] + r[1][1] + r[2][2]
    if tr >= max(r[0][0], r[1][1], r[2][2]):
        f = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        w, x, y, z = (
            0.25 * f,
            (r[2][1] - r[1][2]) / f,
            (r[0][2] - r[2][0]) / f,
            (r[1][0] - r[0][1]) / f,
        )
    elif r[0][0] >= r[1][1] and r[0][0] >= r[2][2]:
        f = 2.0 * math.sqrt(max(1.0 + r[0][0] - r[1][1] - r[2][2], 0.0))
        w, x, y, z = (
            (r[2][1] - r[1][2]) / f,
            0.25 * f,
            (r[0][1] + r[1][0]) / f,
            (r[0][2] + r[2][0]) / f,
        )
    elif r[1][1] >= r[2][2]:
        f = 2.0 * math.sqrt(max(1.0 - r[0][0] + r[1][1] - r[2][2], 0.0))
        w, x, y, z = (
            (r[0][2] - r[2][0]) / f,
            (r[0][1] + r[1][0]) / f,
            0.25 * f,
            (r[1][2] + r[2][1]) / f,
        )
    else:
        f = 2.0 * math.sqrt(max(1.0 - r[0][0] - r[1][1] + r[2][2], 0.0))
        w, x, y, z = (
            (r[1][0] - r[0][1]) / f,
            (r[0][2] + r[2][0]) / f,
            (r[1][2] + r[2][1]) / f,
            0.25 * f,
        )
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(x * x + y * y + z * z)
    if n < 1e-300:
        return (0.0, 0.0, 0.0)
    k = 2.0 * math.atan2(n, w) / n
    return (x * k, y * k, z * k)


class FastKinematics:
    """Forward kinematics and TCP Jacobian of ONE joint configuration, in plain floats.

    :func:`wristscan.calib.kinematics.forward` / ``jacobian`` are vectorised for batches; for a
    single configuration NumPy's per-call overhead dominates (~0.3-1 ms on a loaded machine),
    too slow for a 1 kHz loop. This evaluates the same standard-DH chain (any calibrated
    parameters) in ~50 us; tests check it against the vectorised functions.
    """

    def __init__(self, model: kinematics.DHParams) -> None:
        self.model = model
        self._joints = [
            (float(d), float(a), math.cos(al), math.sin(al), float(off))
            for d, a, al, off in zip(model.d, model.a, model.alpha, model.theta_offset, strict=True)
        ]

    def _chain(
        self, q: ArrayLike
    ) -> tuple[list[list[float]], list[float], list[tuple[list[float], list[float]]]]:
        R = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        p = [0.0, 0.0, 0.0]
        axes: list[tuple[list[float], list[float]]] = []
        for qi, (d, a, ca, sa, off) in zip(
            np.asarray(q, dtype=np.float64).tolist(), self._joints, strict=True
        ):
            axes.append(([R[0][2], R[1][2], R[2][2]], p))
            ct, st = math.cos(qi + off), math.sin(qi + off)
            # Joint transform Rz(theta) Tz(d) Tx(a) Rx(alpha): columns of its rotation and offset.
            c0 = (ct, st, 0.0)
            c1 = (-st * ca, ct * ca, sa)
            c2 = (st * sa, -ct * sa, ca)
            t = (a * ct, a * st, d)
            p = [p[i] + R[i][0] * t[0] + R[i][1] * t[1] + R[i][2] * t[2] for i in range(3)]
            R = [
                [R[i][0] * c[0] + R[i][1] * c[1] + R[i][2] * c[2] for c in (c0, c1, c2)]
                for i in range(3)
            ]
        return R, p, axes

    def forward(self, q: ArrayLike) -> FloatArray:
        """``flange2base`` (4, 4) of one configuration ``q`` (6,) rad."""
        R, p, _ = self._chain(q)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = p
        return T

    def tcp_jacobian(self, q: ArrayLike, tcp2flange: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``(J, tcp2base)``: the TCP point's geometric Jacobian (6, 6), rows ``[v; omega]`` in
        base, and the TCP pose (4, 4)."""
        R, p, axes = self._chain(q)
        t = tcp2flange[:3, 3].tolist()
        pe = [p[i] + R[i][0] * t[0] + R[i][1] * t[1] + R[i][2] * t[2] for i in range(3)]
        J = np.empty((6, 6))
        for j, (z, o) in enumerate(axes):
            r0, r1, r2 = pe[0] - o[0], pe[1] - o[1], pe[2] - o[2]
            J[0, j] = z[1] * r2 - z[2] * r1
            J[1, j] = z[2] * r0 - z[0] * r2
            J[2, j] = z[0] * r1 - z[1] * r0
            J[3, j], J[4, j], J[5, j] = z
        F = np.eye(4)
        F[:3, :3] = R
        F[:3, 3] = p
        return J, F @ tcp2flange


@functools.lru_cache(maxsize=16)
def fast_kinematics(model: kinematics.DHParams) -> FastKinematics:
    return FastKinematics(model)


def tcp_jacobian(model: kinematics.DHParams, q: ArrayLike, tcp2flange: FloatArray) -> FloatArray:
    """Geometric Jacobian ``(..., 6, 6)`` of the TCP point: rows ``[v_tcp; omega]`` in base."""
    qa = np.asarray(q, dtype=np.float64)
    J = kinematics.jacobian(model, qa)
    F = kinematics.forward(model, qa)
    r = F[..., :3, :3] @ tcp2flange[:3, 3]  # flange origin -> TCP, base coordinates
    # v_tcp = v_flange + omega x r = v_flange - [r]x omega
    Jw = J[..., 3:, :]
    J[..., :3, :] -= np.cross(r[..., None, :], np.swapaxes(Jw, -1, -2)).swapaxes(-1, -2)
    return J
