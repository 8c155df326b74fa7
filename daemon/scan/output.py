"""The files of a scan job: each pass corrected and down-sampled as binary PLY with
sensor-facing normals (and its number as CloudCompare's scalar field ``pass``), the merged
cloud, an NPZ with everything, the JSON report, optionally a screened Poisson surface (the
``surface`` extra: pymeshlab, MeshLab's own filters), and the scan as one E57 or MCAP file
(:func:`write_scan_file`, the ``e57`` and ``mcap`` extras)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from wristscan.calib.merge import (
    MergeOptions,
    MergeResult,
    PassCloud,
    corrected_clouds,
    merged_cloud,
    oriented_normals,
    voxel_mean,
)
from wristscan.daemon.scan.errors import ScanError, SurfaceUnavailable

if TYPE_CHECKING:
    from wristscan.daemon.io.mcap_out import McapCloudWriter
    from wristscan.daemon.scan.job import ScanCalibration
    from wristscan.daemon.scan.record import RecordedPass

__all__ = ["SCAN_FILE_FORMATS", "poisson_surface", "write_outputs", "write_scan_file"]

SCAN_FILE_FORMATS = ("e57", "mcap")
"""Formats :func:`write_scan_file` writes (chosen by the file's extension)."""
POSE_PERIOD_NS = 10_000_000
"""The flange poses of a scan's MCAP file are at least this far apart (100 Hz)."""

FloatArray = NDArray[np.float64]


def write_outputs(
    out_dir: Path,
    clouds: Sequence[PassCloud],
    merge: MergeResult | None,
    opts: MergeOptions,
    report: dict[str, Any],
) -> list[Path]:
    """Write ``pass_NN.ply`` (each pass, corrected), ``merged.ply``, ``scan.npz``,
    ``report.json`` and, with ``opts.surface``, ``surface.ply`` into ``out_dir``."""
    from wristscan.daemon.io.ply import write_ply

    out_dir.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    fixed = corrected_clouds(clouds, merge)
    frame = report.get("frame", "?")
    npz: dict[str, Any] = {}
    for c in fixed:
        v, o = voxel_mean(c.xyz, opts.voxel_m, c.origins)
        nrm = oriented_normals(v, o, opts.normals_k)
        path = out_dir / f"pass_{c.index + 1:02d}.ply"
        write_ply(
            path,
            v,
            normals=nrm,
            comments=[f"wristscan scan pass {c.index + 1}: {c.label}", f"frame {frame}, metres"],
            scalars={"scalar_pass": c.index + 1},
        )
        files.append(path)
        npz[f"pass_{c.index + 1:02d}_xyz"] = v.astype(np.float32)
        npz[f"pass_{c.index + 1:02d}_normals"] = nrm.astype(np.float32)
    xyz, normals = merged_cloud(fixed, opts.voxel_m, opts.normals_k)
    path = out_dir / "merged.ply"
    write_ply(
        path,
        xyz,
        normals=normals,
        comments=[
            f"wristscan scan: {len(fixed)} passes merged, frame {frame}, metres",
            f"voxel {opts.voxel_m * 1e3:g} mm, ICP {'on' if merge is not None else 'off'}",
        ],
    )
    files.append(path)
    npz["merged_xyz"] = xyz.astype(np.float32)
    npz["merged_normals"] = normals.astype(np.float32)
    if merge is not None:
        npz["corrections"] = np.stack([c.transform for c in merge.corrections])
        npz["correction_pass"] = np.array([c.index + 1 for c in merge.corrections])
    npz["report_json"] = np.array(json.dumps(report))
    path = out_dir / "scan.npz"
    np.savez_compressed(path, **npz)
    files.append(path)
    if opts.surface:
        path = out_dir / "surface.ply"
        faces = poisson_surface(xyz, normals, path, opts.surface_depth, opts.surface_trim_m)
        report["surface"] = {"file": path.name, "faces": faces, "depth": opts.surface_depth}
        files.append(path)
    path = out_dir / "report.json"
    path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    files.append(path)
    return files


def poisson_surface(
    xyz: FloatArray,
    normals: FloatArray,
    path: Path,
    depth: int = 9,
    trim_m: float = 0.001,
) -> int:
    """Screened Poisson surface of an oriented cloud (MeshLab's filter, through pymeshlab),
    with the triangles farther than ``trim_m`` from the cloud removed (Poisson closes the
    surface where there are no points); written as binary PLY. Returns the face count.
    Raises :class:`SurfaceUnavailable` when pymeshlab is not installed."""
    try:
        import pymeshlab  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        raise SurfaceUnavailable(
            "the surface model needs the optional dependency pymeshlab: "
            "pip install 'wristscan[surface]'"
        ) from None
    if xyz.shape[0] < 100:
        raise ScanError(f"too few points for a surface ({xyz.shape[0]})")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=xyz, v_normals_matrix=normals))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, preclean=True)
    mesh = ms.current_mesh()
    verts = np.asarray(mesh.vertex_matrix(), dtype=np.float64)
    faces = np.asarray(mesh.face_matrix(), dtype=np.int64)
    dist, _ = cKDTree(xyz).query(verts, k=1)
    near = dist <= trim_m
    keep = near[faces].all(axis=1)
    faces = faces[keep]
    used = np.unique(faces)
    remap = np.full(verts.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    out = pymeshlab.MeshSet()
    out.add_mesh(pymeshlab.Mesh(vertex_matrix=verts[used], face_matrix=remap[faces]))
    path.parent.mkdir(parents=True, exist_ok=True)
    out.save_current_mesh(str(path), binary=True, save_vertex_normal=False)
    return int(faces.shape[0])


def write_scan_file(
    path: Path,
    clouds: Sequence[PassCloud],
    merge: MergeResult | None,
    recorded: Sequence[RecordedPass],
    frame: str,
    calibration: ScanCalibration | None = None,
) -> Path:
    """The scan as one file, the format by the extension of ``path``:

    - ``.e57``: one scan per pass, named by the pass, its points (all of them, in ``frame`` as
      the calibration aligned them) with the pass's ICP correction as the scan's pose (identity
      without ICP), its first and last exposure as acquisition start and end;
    - ``.mcap``: one ``PointCloud2`` per pass (corrected, in ``frame``) stamped with its first
      exposure, and the flange's ``PoseStamped`` in the base frame every 10 ms of each pass;
      with ``calibration``, also the sensor's (``/wristscan/sensor_pose``) in ``frame``,
      corrected as its pass, so that the trail is drawn with the clouds.

    Raises :class:`~wristscan.daemon.io.cloudfile.CloudFormatError` for another extension or a
    missing extra."""
    from wristscan.daemon.io.cloudfile import cloud_format

    fmt = cloud_format(path, allowed=SCAN_FILE_FORMATS)
    times = {r.index: r.sweep.exposure_ns for r in recorded}
    if fmt == "e57":
        from wristscan.daemon.io.e57_out import E57Writer

        with E57Writer(path) as w:
            for c in clouds:
                t = times.get(c.index)
                pose = merge.transform(c.index) if merge is not None else None
                t0, t1 = (None, None) if t is None or not t.size else (int(t[0]), int(t[-1]))
                w.add_scan(c.xyz, f"pass {c.index + 1}: {c.label}", pose, None, t0, t1)
        return path
    from wristscan.daemon.io.mcap_out import McapCloudWriter

    passes = {r.index: r for r in recorded}
    with McapCloudWriter(path, metadata={"frame": frame, "units": "metres"}) as m:
        for c in corrected_clouds(clouds, merge):
            rec = passes.get(c.index)
            if rec is None or not rec.sweep.exposure_ns.size:
                continue
            m.write_cloud(c.xyz, int(rec.sweep.exposure_ns[0]), frame)
            correction = merge.transform(c.index) if merge is not None else np.eye(4)
            _write_trail(m, rec, frame, calibration, correction)
    return path


def _write_trail(
    m: McapCloudWriter,
    rec: RecordedPass,
    frame: str,
    calibration: ScanCalibration | None,
    correction: FloatArray,
) -> None:
    """The flange (base frame) and, with the calibration, the sensor (``frame``, corrected)
    every :data:`POSE_PERIOD_NS` of a pass."""
    from wristscan.calib.align import sensor_poses
    from wristscan.daemon.io.mcap_out import SENSOR_POSE_TOPIC

    sw = rec.sweep
    t = sw.exposure_ns
    keep, last = [], None
    for k, tk in enumerate(t.tolist()):
        if last is None or tk - last >= POSE_PERIOD_NS:
            keep.append(k)
            last = tk
    sensor = None
    if calibration is not None and (frame == "base" or rec.table_angle_rad is not None):
        sensor = correction @ sensor_poses(
            sw.flange2base[keep],
            calibration.sensor2flange,
            calibration.base2table,
            rec.table_angle_rad,
            calibration.encoder_offset_rad,
            frame="part" if frame == "part" else "base",
        )
    for j, k in enumerate(keep):
        m.write_pose(sw.flange2base[k], int(t[k]))
        if sensor is not None:
            m.write_pose(sensor[j], int(t[k]), frame, SENSOR_POSE_TOPIC)
