"""The simulated laser: the sensor's laser plane ray-cast against a :class:`~.scene.Scene`.

Geometry (sensor frame, DESIGN.md: the laser plane is the sensor Y-Z plane, +Z towards the part):

``"parallel"`` (default, a triangulation profile sensor)
    ``n_points`` rays at fixed lateral positions ``y_i = linspace(-half_width, +half_width)``, each
    starting at ``(0, y_i, 0)`` and running along +Z. The measured value is ``z = t`` and a point
    is valid when a surface is hit with ``z_min <= z <= z_max`` (the measuring range). This is the
    usual "calibrated, resampled to a uniform X grid" output of industrial profile sensors; the
    real field of view is a trapezoid, which only changes which points are in range.
``"fan"`` (a scanning range finder, used for the SCIP sensors)
    Rays from the sensor origin at angles ``theta_i`` from +Z towards +Y: direction
    ``(0, sin theta, cos theta)``; the measured value is the range ``r = t``, valid when
    ``range_min <= r <= range_max`` (``z_min``/``z_max`` hold those bounds); ``y = r sin theta``,
    ``z = r cos theta``.

Occlusion is laser-side only: the nearest surface along each ray is the one measured, including a
surface closer than the measuring range (which blanks the point). The camera's view of the line is
not modelled. Noise: Gaussian along the ray (``noise_std_m``), independent per point (exact
draws, or with ``noise_model="table"`` a 65536-level quantile table truncated at 4.3 sigma, which
is several times cheaper); dropouts clear random valid points; outliers replace random points
with a uniform value in the range.
Invalid points get NaN coordinates (``z``, and ``y`` for the fan) but keep their slot.
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtri

from wristscan.drivers.sim.scene import Scene

__all__ = ["LaserModel", "Measurement"]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@functools.cache
def _gauss_table() -> NDArray[np.float32]:
    """Unit Gaussian quantiles at 65536 equiprobable levels, rescaled to unit variance.

    Indexing it with uniform 16-bit integers draws from a discretised Gaussian truncated at
    4.3 sigma, several times faster than exact draws (what a 10 kHz sensor needs).
    """
    table = ndtri((np.arange(1 << 16) + 0.5) / (1 << 16))
    return np.asarray(table / table.std(), dtype=np.float32)


class Measurement:
    """A batch of ``P`` profiles: ``t (P, N)`` (distance along each ray, m), ``valid (P, N)``,
    and the derived sensor-frame coordinates ``y``, ``z`` (m, NaN where invalid; for the
    parallel geometry ``y`` is a read-only broadcast of the lateral grid and ``z`` is ``t``)."""

    __slots__ = ("t", "valid", "y", "z")

    def __init__(self, t: FloatArray, valid: BoolArray, y: FloatArray, z: FloatArray) -> None:
        self.t, self.valid, self.y, self.z = t, valid, y, z


class LaserModel:
    """Ray-casts the laser plane and adds sensor imperfections.

    Parameters are SI: lengths in metres, angles in radians. ``rng`` (a ``numpy`` Generator or a
    seed) drives noise, dropouts and outliers. ``cache_size`` keeps the noiseless result of recent
    poses: a still robot (or the standalone mode) then costs no ray casting.
    """

    def __init__(
        self,
        n_points: int = 2048,
        half_width_m: float = 0.025,
        z_min_m: float = 0.05,
        z_max_m: float = 0.15,
        noise_std_m: float = 0.0,
        dropout_prob: float = 0.0,
        outlier_prob: float = 0.0,
        rng: np.random.Generator | int | None = None,
        *,
        geometry: Literal["parallel", "fan"] = "parallel",
        angles_rad: ArrayLike | None = None,
        cache_size: int = 64,
        noise_model: Literal["gaussian", "table"] = "gaussian",
    ) -> None:
        if n_points < 1:
            raise ValueError("n_points must be >= 1")
        if not 0 <= z_min_m < z_max_m:
            raise ValueError("need 0 <= z_min_m < z_max_m")
        for name, p in (("dropout_prob", dropout_prob), ("outlier_prob", outlier_prob)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be in [0, 1]")
        if noise_std_m < 0:
            raise ValueError("noise_std_m must be >= 0")
        self.n_points = int(n_points)
        self.half_width_m = float(half_width_m)
        self.z_min_m = float(z_min_m)
        self.z_max_m = float(z_max_m)
        self.noise_std_m = float(noise_std_m)
        self.dropout_prob = float(dropout_prob)
        self.outlier_prob = float(outlier_prob)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.geometry = geometry
        if noise_model not in ("gaussian", "table"):
            raise ValueError(f"unknown noise_model {noise_model!r}")
        self.noise_model = noise_model
        self.cache_size = int(cache_size)
        self._cache: OrderedDict[bytes, FloatArray] = OrderedDict()
        """Noiseless results by pose; call :meth:`clear_cache` after editing the scene."""
        n = self.n_points
        if geometry == "parallel":
            self.lateral_m: FloatArray = np.linspace(-half_width_m, half_width_m, n)
            self.origins = np.column_stack([np.zeros(n), self.lateral_m, np.zeros(n)])
            self.dirs = np.tile([0.0, 0.0, 1.0], (n, 1))
            self.angles_rad: FloatArray | None = None
        elif geometry == "fan":
            if angles_rad is None:
                raise ValueError("the fan geometry needs angles_rad")
            a = np.asarray(angles_rad, dtype=np.float64).reshape(-1)
            if a.shape[0] != n:
                raise ValueError(f"angles_rad has {a.shape[0]} angles for {n} points")
            self.angles_rad = a
            self.lateral_m = np.full(n, np.nan)
            self.origins = np.zeros((n, 3))
            self.dirs = np.column_stack([np.zeros(n), np.sin(a), np.cos(a)])
        else:
            raise ValueError(f"unknown geometry {geometry!r}")

    def _unit_noise(self, n: int) -> NDArray[np.float32]:
        """``n`` unit-variance Gaussian draws (float32 is precise enough for noise)."""
        if self.noise_model == "table":
            return _gauss_table()[self.rng.integers(0, 1 << 16, n, dtype=np.uint16)]
        return self.rng.standard_normal(n, dtype=np.float32)

    def clear_cache(self) -> None:
        self._cache.clear()

    def ideal(
        self, sensor2base: ArrayLike, scene: Scene, table_angle_rad: ArrayLike = 0.0
    ) -> FloatArray:
        """Noiseless distance along each ray ``(P, N)`` (inf on a miss), batched over poses."""
        s2b = np.asarray(sensor2base, dtype=np.float64).reshape(-1, 4, 4)
        n_prof = s2b.shape[0]
        ang = np.broadcast_to(np.asarray(table_angle_rad, dtype=np.float64), (n_prof,))
        out = np.empty((n_prof, self.n_points))
        if self.cache_size <= 0:
            out[:] = self._cast(scene, s2b, ang)
            return out
        keys = [s2b[i].tobytes() + ang[i].tobytes() + id(scene).to_bytes(8) for i in range(n_prof)]
        todo: dict[bytes, list[int]] = {}
        for i, k in enumerate(keys):
            hit = self._cache.get(k)
            if hit is not None:
                out[i] = hit
                self._cache.move_to_end(k)
            else:
                todo.setdefault(k, []).append(i)
        if todo:
            first = [rows[0] for rows in todo.values()]
            t = self._cast(scene, s2b[first], ang[first])
            for j, (k, rows) in enumerate(todo.items()):
                out[rows] = t[j]
                self._cache[k] = t[j]
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return out

    def _cast(self, scene: Scene, s2b: FloatArray, ang: FloatArray) -> FloatArray:
        t, _ = scene.raycast_bundles(s2b, self.origins, self.dirs, ang, reach_m=self.z_max_m)
        return t

    def measure(
        self, sensor2base: ArrayLike, scene: Scene, table_angle_rad: ArrayLike = 0.0
    ) -> Measurement:
        """Ray-cast ``P`` exposures (``sensor2base (P, 4, 4)``) and apply noise, dropouts and
        outliers."""
        t = self.ideal(sensor2base, scene, table_angle_rad)
        rng = self.rng
        flat_t = t.reshape(-1)  # ideal() returns a fresh contiguous array
        if self.noise_std_m > 0:
            hit = np.flatnonzero(np.isfinite(flat_t))
            flat_t[hit] += self._unit_noise(hit.size) * np.float32(self.noise_std_m)
        size = flat_t.size
        # Rare events are drawn as a count and distinct positions: far cheaper than a uniform
        # draw per point.
        if self.outlier_prob > 0:
            k = rng.binomial(size, self.outlier_prob)
            idx = rng.choice(size, k, replace=False, shuffle=False)
            flat_t[idx] = rng.uniform(self.z_min_m, self.z_max_m, k)
        valid = (t >= self.z_min_m) & (t <= self.z_max_m)  # inf (a miss) fails the test
        if self.dropout_prob > 0:
            k = rng.binomial(size, self.dropout_prob)
            valid.reshape(-1)[rng.choice(size, k, replace=False, shuffle=False)] = False
        t[~valid] = np.nan
        if self.geometry == "parallel":
            y = np.broadcast_to(self.lateral_m, t.shape)
            z = t
        else:
            assert self.angles_rad is not None
            y = t * np.sin(self.angles_rad)
            z = t * np.cos(self.angles_rad)
        return Measurement(t, valid, y, z)

    def profile(
        self, sensor2base: ArrayLike, scene: Scene, table_angle_rad: ArrayLike = 0.0
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """``y``, ``z`` ``(P, N)`` (sensor frame, metres, NaN where invalid) and ``valid``."""
        m = self.measure(sensor2base, scene, table_angle_rad)
        return np.array(m.y), m.z, m.valid
