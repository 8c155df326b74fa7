"""Multi-view merge of scan passes: down-sampling, sensor-facing normals, and the
point-to-plane registration of the passes onto each other (Borangiu et al. 2009, section 4:
passes "already almost aligned" by the calibration, refined with ICP).

Pure maths on point clouds (metres): the scan job (:mod:`wristscan.daemon.scan.job`) records the
passes and aligns them with the calibrations in force (Eq. (1)); this module measures how they
disagree, and by how much each one has to move to agree with the consensus of all of them.

:func:`merge_passes`
--------------------
1. Every pass is down-sampled (:func:`voxel_mean`, ``icp_voxel_m``) and given normals facing
   the sensor that saw its points (:func:`oriented_normals`), once.
2. Coarse: every pass is registered onto the union of the others as they stand
   (:func:`~wristscan.calib.icp.icp_point_to_plane`, trimmed pairs: robust to partial
   overlap) after selecting its overlap (nearest point of the others close enough, normals
   agreeing). The step keeps only the directions the overlap constrains; the mean correction
   is removed, so the consensus of all passes is the reference.
3. Fine: all passes at once (:func:`~wristscan.calib.multiview.joint_step`, multi-view
   point-to-plane), until the steps are below ``converged_m`` or after ``rounds`` steps.
4. Each pass's correction is measured against the others (shift, rotation, 1-sigma, RMS before
   and after) and **flagged** when above the thresholds: a sign of a calibration or timing
   fault, never silently absorbed.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from wristscan.calib import se3
from wristscan.calib.icp import estimate_normals, icp_point_to_plane
from wristscan.calib.multiview import (
    MIN_OVERLAP_POINTS,
    OrientedCloud,
    constraint,
    joint_step,
    overlap,
    restrict,
    rms_against,
    strong_directions,
    transform_points,
    union,
)

__all__ = [
    "MergeOptions",
    "MergeResult",
    "PassCloud",
    "PassCorrection",
    "corrected_clouds",
    "merge_passes",
    "merged_cloud",
    "oriented_normals",
    "voxel_mean",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass
class PassCloud:
    """One pass in the plan frame: points and, per point, the sensor origin that saw it."""

    index: int
    label: str
    xyz: FloatArray
    origins: FloatArray

    @property
    def n_points(self) -> int:
        return int(self.xyz.shape[0])


# --------------------------------------------------------------------------------------------
# Down-sampling and normals


def voxel_mean(
    xyz: FloatArray,
    voxel_m: float,
    *extra: FloatArray,
    grid: Literal["cloud", "origin"] = "cloud",
) -> tuple[FloatArray, ...]:
    """One point per occupied voxel of edge ``voxel_m`` (m): the mean of its points, and the
    mean of each ``extra`` (N, k) array over the same points, in float64, voxels in
    lexicographic order of their grid index. ``voxel_m <= 0`` returns copies.

    ``grid``: where the voxel grid starts: at the cloud's lower corner (``"cloud"``, the
    default: the scan job's clouds) or at the coordinate origin (``"origin"``: the same grid for
    every cloud, as the demo's merged cloud uses)."""
    if voxel_m <= 0.0 or xyz.shape[0] == 0:
        return (xyz.copy(), *(e.copy() for e in extra))
    corner = xyz.min(axis=0) if grid == "cloud" else 0.0
    ijk = np.floor((xyz - corner) / voxel_m).astype(np.int64)
    # Indices from 0 (a no-op for the cloud's own grid) so that they ravel into one key each;
    # the key keeps the lexicographic order of the indices.
    ijk -= ijk.min(axis=0)
    dims = ijk.max(axis=0) + 1
    key = np.ravel_multi_index(ijk.T, tuple(int(d) for d in dims))
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return tuple(_sums_by(inverse, a, counts.size) / counts[:, None] for a in (xyz, *extra))


def _sums_by(inverse: NDArray[np.intp], a: NDArray[np.floating], n: int) -> FloatArray:
    """The (n, k) float64 sums of the rows of ``a`` (N, k) by group ``inverse`` (N,)."""
    s = np.zeros((n, a.shape[1]))
    for j in range(a.shape[1]):  # bincount per column: much faster than np.add.at
        s[:, j] = np.bincount(inverse, weights=a[:, j], minlength=n)
    return s


_KEY_BITS = 21
"""Bits per voxel index in :func:`voxel_mean_chunks`' keys (indices within +-2**20 voxels)."""


def voxel_mean_chunks(chunks: Sequence[NDArray[np.floating]], voxel_m: float) -> FloatArray:
    """:func:`voxel_mean` of the concatenated ``chunks`` ((n_i, 3) each, metres) on the origin's
    grid, without concatenating them: each chunk is reduced to its voxels' sums and counts
    first, then those are merged (5-6x faster for 25 M points in batches of 200 k, and no
    float64 copy of the whole cloud). The same voxels in the same order; the means differ from
    :func:`voxel_mean`'s at most by the order of the float64 sums."""
    if voxel_m <= 0.0 or not chunks:
        return voxel_mean(_stacked(chunks), voxel_m, grid="origin")[0]
    keys, sums, counts = [], [], []
    lim = 1 << (_KEY_BITS - 1)
    for c in chunks:
        if c.shape[0] == 0:
            continue
        ijk = np.floor(c.astype(np.float64) / voxel_m).astype(np.int64)
        if int(np.abs(ijk).max()) >= lim:  # beyond the keys' reach: the plain way
            return voxel_mean(_stacked(chunks), voxel_m, grid="origin")[0]
        ijk += lim
        key = (ijk[:, 0] << (2 * _KEY_BITS)) | (ijk[:, 1] << _KEY_BITS) | ijk[:, 2]
        u, inv, n = np.unique(key, return_inverse=True, return_counts=True)
        keys.append(u)
        counts.append(n)
        sums.append(_sums_by(inv, c, u.size))
    if not keys:
        return np.zeros((0, 3))
    u, inv = np.unique(np.concatenate(keys), return_inverse=True)
    total = _sums_by(inv, np.concatenate(sums), u.size)
    return np.asarray(total / np.bincount(inv, np.concatenate(counts), u.size)[:, None])


def _stacked(chunks: Sequence[NDArray[np.floating]]) -> FloatArray:
    if not chunks:
        return np.zeros((0, 3))
    return np.concatenate(chunks).astype(np.float64)


def oriented_normals(xyz: FloatArray, origins: FloatArray, k: int = 12) -> FloatArray:
    """Unit normals of ``xyz`` (PCA of ``k`` neighbours), each turned towards the sensor origin
    that saw its point."""
    if xyz.shape[0] < k:
        return np.tile([0.0, 0.0, 1.0], (xyz.shape[0], 1))
    n = estimate_normals(xyz, k)
    flip = np.einsum("ij,ij->i", n, origins - xyz) < 0.0
    n[flip] *= -1.0
    return n


# --------------------------------------------------------------------------------------------
# Merging


@dataclass(frozen=True)
class MergeOptions:
    """Settings of :func:`merge_passes` and of the clouds a scan job writes
    (:func:`wristscan.daemon.scan.output.write_outputs`), SI units."""

    icp: bool = True
    icp_voxel_m: float = 0.0005
    """Voxel of the clouds that ICP works on (m)."""
    max_distance_m: float = 0.002
    """Farthest pair ICP uses (m): the paper saw up to 0.5 mm between passes."""
    fine_distance_m: float = 0.001
    """Pairing distance of the overlap once the passes are close (m)."""
    trim_fraction: float = 0.9
    normal_agreement_deg: float = 30.0
    """A source point belongs to the overlap when the nearest point of the others is within
    the pairing distance and their normals agree within this angle (so that points of a face
    that only this pass sees are not pulled onto a neighbouring face)."""
    rounds: int = 8
    """Most joint refinement steps after the coarse round."""
    converged_m: float = 0.5e-6
    """The refinement stops when no pass moves by more than this (m)."""
    weak_ratio: float = 1e-2
    """Coarse round: directions of a pass's correction stiffer than this fraction of its
    stiffest are corrected, the others are left as calibrated."""
    joint_ratio: float = 1e-4
    """Joint refinement: the same, relative to each pass's mean stiffness; the 1-sigma limit
    below is what usually decides there."""
    weak_sigma_m: float = 1e-5
    """... and only directions whose 1-sigma from the fit is at most this (m)."""
    flag_translation_m: float = 5e-5
    """A pass whose correction moves its centroid by more than this is flagged (m)."""
    flag_rotation_deg: float = 0.05
    """A pass whose correction turns it by more than this is flagged (degrees)."""
    normals_k: int = 12
    voxel_m: float = 0.00025
    """Voxel of the written clouds (m); 0 keeps every point."""
    surface: bool = False
    """Also write a Poisson surface (needs the ``surface`` extra)."""
    surface_depth: int = 9
    surface_trim_m: float = 0.001
    """Surface triangles farther than this from the merged cloud are removed (m)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.trim_fraction <= 1.0:
            raise ValueError("trim_fraction must be in (0, 1]")
        if self.icp_voxel_m < 0 or self.voxel_m < 0:
            raise ValueError("voxel sizes must be >= 0")
        if self.max_distance_m <= 0 or self.fine_distance_m <= 0:
            raise ValueError("pairing distances must be > 0")
        if self.rounds < 1:
            raise ValueError("rounds must be >= 1")


@dataclass(frozen=True)
class PassCorrection:
    """The ICP correction of one pass relative to the consensus of all passes."""

    index: int
    label: str
    transform: FloatArray
    """(4, 4) maps the pass as aligned by the calibration onto the merged cloud."""
    shift_m: float
    """Displacement of the pass's centroid (m)."""
    rotation_deg: float
    max_displacement_m: float
    """Largest displacement of any of its points (m)."""
    sigma_m: float
    """Largest 1-sigma (m of displacement) of the corrected directions, from the fit."""
    free_directions: int
    """Directions (of 6) the overlap did not constrain: not corrected."""
    overlap_points: int
    rms_before_m: float
    """Point-to-plane RMS against the others before ICP (m)."""
    rms_after_m: float
    status: str
    """``"ok"``, ``"flagged"`` (correction above a threshold) or ``"not measured"``."""
    note: str = ""

    @property
    def flagged(self) -> bool:
        return self.status == "flagged"


@dataclass
class MergeResult:
    corrections: list[PassCorrection]
    rounds: int
    options: MergeOptions

    @property
    def flagged(self) -> list[PassCorrection]:
        return [c for c in self.corrections if c.flagged]

    def transform(self, index: int) -> FloatArray:
        for c in self.corrections:
            if c.index == index:
                return c.transform
        return np.eye(4)


def merge_passes(clouds: Sequence[PassCloud], options: MergeOptions | None = None) -> MergeResult:
    """Refine the alignment of the passes with point-to-plane ICP and measure the corrections.

    Every pass is down-sampled (``icp_voxel_m``) and given sensor-facing normals once.

    1. Coarse: every pass is registered onto the union of the others as they stand
       (:func:`~wristscan.calib.icp.icp_point_to_plane`, pairs within ``max_distance_m``,
       trimmed: robust to partial overlap) after selecting its overlap (nearest point of the
       others close enough, normals agreeing). The step keeps only the directions that the
       overlap constrains (a cylinder leaves a rotation about its axis free, which noise alone
       would otherwise drive); the mean correction is removed.
    2. Fine: all passes at once (:func:`~wristscan.calib.multiview.joint_step`, pairs within
       ``fine_distance_m``), which also settles groups of passes that only loosely hold each
       other, until the steps are below ``converged_m`` or after ``rounds`` steps.

    The consensus of all passes is the reference. A pass whose overlap is too small or
    constrains almost nothing is left as the calibration put it and reported as
    ``"not measured"``.
    """
    o = options or MergeOptions()
    n = len(clouds)
    ds: list[OrientedCloud] = []
    for c in clouds:
        xyz, org = voxel_mean(c.xyz, o.icp_voxel_m, c.origins)
        ds.append(OrientedCloud(xyz, oriented_normals(xyz, org, o.normals_k)))
    T = [np.eye(4) for _ in range(n)]
    notes: list[str] = [""] * n
    cos_agree = math.cos(math.radians(o.normal_agreement_deg))
    _coarse_round(ds, T, notes, cos_agree, o)
    rounds_done = 1
    for _ in range(o.rounds):
        step_m = joint_step(ds, T, o.fine_distance_m, cos_agree, o.joint_ratio, o.weak_sigma_m)
        rounds_done += 1
        log.debug("merge step %d: largest step %.2g m", rounds_done, step_m)
        if step_m < o.converged_m:
            break
    corrections = [_correction(c, i, ds, T, notes[i], cos_agree, o) for i, c in enumerate(clouds)]
    return MergeResult(corrections, rounds_done, o)


def _others(ds: Sequence[OrientedCloud], i: int) -> list[int]:
    """The passes other than ``i`` that have points."""
    return [j for j in range(len(ds)) if j != i and ds[j].xyz.shape[0]]


def _coarse_step(
    ds: Sequence[OrientedCloud], T: Sequence[FloatArray], i: int, cos_agree: float, o: MergeOptions
) -> tuple[FloatArray | None, str]:
    """The coarse correction of pass ``i`` onto the union of the others as they stand (None
    when the overlap constrains no direction), or None and why it could not be measured."""
    if ds[i].xyz.shape[0] < MIN_OVERLAP_POINTS:
        return None, f"only {ds[i].xyz.shape[0]} points after down-sampling"
    others = _others(ds, i)
    if not others:
        return None, "no other pass to compare with"
    tgt = union(ds, T, others)
    src = union(ds, T, [i])
    tree = cKDTree(tgt.xyz)
    ok, _ = overlap(src, tgt, tree, o.max_distance_m, cos_agree)
    if ok.sum() < MIN_OVERLAP_POINTS:
        return None, f"overlap with the other passes too small ({int(ok.sum())} points)"
    try:
        res = icp_point_to_plane(
            src.xyz[ok],
            tgt.xyz,
            tgt.normals,
            max_distance=o.max_distance_m,
            trim_fraction=o.trim_fraction,
            max_iter=30,
            tol=1e-8,
        )
    except ValueError as exc:
        return None, f"ICP: {exc}"
    con = constraint(transform_points(res.source2target, src.xyz[ok]), tgt, tree, o.max_distance_m)
    if con is None:
        return None, "overlap lost during ICP"
    step, free, _ = restrict(res.source2target, con, o.weak_ratio, o.weak_sigma_m)
    return (step if free < 6 else None), ""


def _coarse_round(
    ds: Sequence[OrientedCloud],
    T: list[FloatArray],
    notes: list[str],
    cos_agree: float,
    o: MergeOptions,
) -> None:
    """Step 1 of :func:`merge_passes`: each pass in turn onto the others as they stand, then the
    mean correction removed (about the centre of all points). Updates ``T`` and ``notes`` (why a
    pass could not be measured) in place."""
    n = len(ds)
    pts = [d.xyz for d in ds if d.xyz.shape[0]]
    centre = np.concatenate(pts).mean(axis=0) if pts else np.zeros(3)
    coarse = [False] * n
    for i in range(n):
        step, notes[i] = _coarse_step(ds, T, i, cos_agree, o)
        if step is not None:
            T[i] = step @ T[i]
            coarse[i] = True
    idx = [i for i in range(n) if coarse[i]]
    if idx:
        w = np.mean([se3.matrix_to_rotvec(T[i][:3, :3]) for i in idx], axis=0)
        dc = np.mean([transform_points(T[i], centre[None])[0] - centre for i in idx], axis=0)
        Rm = se3.rotvec_to_matrix(w)
        Gi = se3.invert(se3.make(Rm, centre + dc - Rm @ centre))
        for i in idx:
            T[i] = Gi @ T[i]


def _correction(
    c: PassCloud,
    i: int,
    ds: Sequence[OrientedCloud],
    T: Sequence[FloatArray],
    note: str,
    cos_agree: float,
    o: MergeOptions,
) -> PassCorrection:
    """The merged correction of pass ``i`` measured against the others: before (every pass as
    the calibration put it) and after (as merged), flagged above the thresholds."""
    n = len(ds)
    d = ds[i]
    others = _others(ds, i)
    if d.xyz.shape[0] < MIN_OVERLAP_POINTS or not others:
        return _unmeasured(c, note or "no points")
    ci = d.xyz.mean(axis=0)
    moved = transform_points(T[i], d.xyz)
    before = union(ds, [np.eye(4)] * n, others)
    after = union(ds, T, others)
    tb, ta = cKDTree(before.xyz), cKDTree(after.xyz)
    ok_b, _ = overlap(d, before, tb, o.fine_distance_m, cos_agree)
    src_a = OrientedCloud(moved, d.normals @ T[i][:3, :3].T)
    ok_a, _ = overlap(src_a, after, ta, o.fine_distance_m, cos_agree)
    con = constraint(moved[ok_a], after, ta, o.fine_distance_m)
    free, sigma = 6, math.inf
    if con is not None:
        E, sigma = strong_directions(con, o.weak_ratio, o.weak_sigma_m)
        free = 6 - E.shape[1]
    if free == 6:
        why = note or (
            "overlap with the other passes too small"
            if con is None
            else "the overlap constrains no direction well enough"
        )
        return _unmeasured(c, why)
    disp = np.linalg.norm(moved - d.xyz, axis=1)
    shift = float(np.linalg.norm(transform_points(T[i], ci[None])[0] - ci))
    rot = math.degrees(float(se3.rotation_angle(T[i][:3, :3])))
    flagged = shift > o.flag_translation_m or rot > o.flag_rotation_deg
    return PassCorrection(
        index=c.index,
        label=c.label,
        transform=T[i],
        shift_m=shift,
        rotation_deg=rot,
        max_displacement_m=float(disp.max()),
        sigma_m=sigma,
        free_directions=free,
        overlap_points=int(ok_a.sum()),
        rms_before_m=rms_against(d.xyz[ok_b], before, tb, o.fine_distance_m),
        rms_after_m=rms_against(moved[ok_a], after, ta, o.fine_distance_m),
        status="flagged" if flagged else "ok",
        note=_flag_note(shift, rot, flagged, free, o),
    )


def _flag_note(shift: float, rot: float, flagged: bool, free: int, o: MergeOptions) -> str:
    if flagged:
        return (
            f"correction {shift * 1e3:.3f} mm / {rot:.4f} deg above the thresholds "
            f"{o.flag_translation_m * 1e3:g} mm / {o.flag_rotation_deg:g} deg: calibration "
            "or timing fault suspected"
        )
    if free:
        return f"{free} of 6 directions weakly constrained by the overlap"
    return ""


def _unmeasured(c: PassCloud, note: str) -> PassCorrection:
    return PassCorrection(
        index=c.index,
        label=c.label,
        transform=np.eye(4),
        shift_m=math.nan,
        rotation_deg=math.nan,
        max_displacement_m=math.nan,
        sigma_m=math.nan,
        free_directions=6,
        overlap_points=0,
        rms_before_m=math.nan,
        rms_after_m=math.nan,
        status="not measured",
        note=note,
    )


def corrected_clouds(clouds: Sequence[PassCloud], merge: MergeResult | None) -> list[PassCloud]:
    """The passes moved by their ICP corrections (unchanged without a merge)."""
    if merge is None:
        return list(clouds)
    out = []
    for c in clouds:
        T = merge.transform(c.index)
        out.append(
            PassCloud(c.index, c.label, transform_points(T, c.xyz), transform_points(T, c.origins))
        )
    return out


def merged_cloud(
    clouds: Sequence[PassCloud], voxel_m: float, normals_k: int = 12
) -> tuple[FloatArray, FloatArray]:
    """Union of ``clouds`` down-sampled to ``voxel_m`` (m): points and sensor-facing normals."""
    if not clouds:
        return np.zeros((0, 3)), np.zeros((0, 3))
    xyz = np.concatenate([c.xyz for c in clouds])
    org = np.concatenate([c.origins for c in clouds])
    v, o = voxel_mean(xyz, voxel_m, org)
    return v, oriented_normals(v, o, normals_k)
