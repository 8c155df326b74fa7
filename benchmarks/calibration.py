"""Benchmark: ``wristscan calibrate sensor`` on the simulated cell (issue 7, items 1, 2, 4, 5).

The whole procedure runs against the simulated cell (real ur_rtde client, LPF1 datagrams over
UDP, the synchroniser pairing profiles with robot states while the robot moves), from a start
pose where the laser line crosses the ball and a nominal tool a few millimetres and 1.6 degrees
off the truth ("the drawing value").

Conditions (the issue's):

* tooling ball R = 12.7 mm; sensor noise 0.02 mm (along each ray); 1 kHz profiles of 512 points
  (the loaded 2-core test host does not keep up with 2048 points at 1 kHz in Python);
* sensor latency 1.5 ms in the simulator while the daemon's configuration says 0: the procedure
  is not told. It sweeps every place both ways, measures the apparent time offset from the
  passes' disagreement and removes it per pair (``calibrate.sensor.solve.compensate_timing``);
* robot repeatability 0.03 mm. A UR data sheet's "pose repeatability +-0.03 mm" is the ISO 9283
  figure RP = mean + 3 std of the 3-D distance to the mean position; for an isotropic Gaussian
  error of per-axis sigma, RP = 3.62 sigma, so sigma = 8.3 um per axis. The simulated
  controller's ``repeatability_m`` is the RMS length of the 3-D offset (sigma * sqrt(3)), so the
  targeted case runs it at 14.4 um. The literal reading (``repeatability_m`` = 0.03 mm, 17 um
  per axis, twice the data sheet's scatter) is run as information, without targets.

Sessions: (A) latency unknown (configured 0); (B) the same with ``[sensor] latency_s`` set to
the value session A measured (what the report tells the operator to do); (C, information) the
literal repeatability reading. After A and B, two scan passes of the part on the rotary table,
from orientations 30 degrees apart and in opposite directions, are mapped with the new
calibration (as the daemon would, no re-timing) and compared before ICP
(``calib.icp.point_to_plane_rms``, no distance limit) over the region where they overlap, chosen
on the same passes mapped with the TRUE tool (pass-2 points within 0.5 mm of a pass-1 point), so
that the calibration under test cannot take its worst points out of the comparison; the same
passes with the true calibration give the noise floor. The figure as computed before 2026-11-26
(pairs more than 0.5 mm apart silently dropped) is printed beside it.

Targets: sensor2flange translation error <= 0.05 mm and rotation error <= 0.02 deg (joint
refinement, sessions A and B); the two passes agree to <= 0.05 mm RMS (after B); the robot time
(first motion to the end of the last, the check scan included) <= 120 s (issue 18). The paper's
two-step figures are printed beside the joint ones, on the same sweeps.

The peers' way on the same cell, beside ours (information): a stop-and-go session (HandEyeSync,
lls_calibration: stop, settle 0.3 s, read one profile with the robot's pose) at as many taught
poses as session A swept places (tilts up to 45 degrees, the ball cut off its centre on one
side), solved by ``calibrate import``'s path; its robot time and errors.

Run: ``.venv/bin/python benchmarks/calibration.py [--quick] [--json FILE] [--keep DIR]
[--no-literal] [--no-stopgo]``;
exits 1 on a miss. ``--quick``: fewer places and faster sweeps (a smoke run, no targets).
``--passes-with FILE [--latency-s S]``: only the two scan passes, mapped with a calibration file
the benchmark kept (target: the two-pass agreement).
"""

from __future__ import annotations

import argparse
import math
import re
import socket
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from wristscan.calib import handeye, icp, kinematics, se3
from wristscan.daemon.calibrate import sensor as cs
from wristscan.daemon.config import Config, parse_config
from wristscan.daemon.io.urpose import parse_ur_pose
from wristscan.daemon.procedure.acquisition import Acquisition
from wristscan.daemon.simcell.cell import start_cell
from wristscan.daemon.simcell.scenarios import jog_to_ball
from wristscan.drivers.base import DriverTimeout
from wristscan.drivers.sim.ur.controller import pick_free_loopback_host

sys.path.insert(0, str(Path(__file__).parent))
from _report import Figure, report

ROOT = Path(__file__).resolve().parent.parent
ISO_RP_M = 0.03e-3
SIGMA_AXIS_M = cs.iso9283_axis_sigma(ISO_RP_M)
SIM_RMS_ISO_M = SIGMA_AXIS_M * math.sqrt(3.0)
SIM_RMS_LITERAL_M = 0.03e-3
SIM_LATENCY_S = 1.5e-3
NOMINAL = "p[0.062, 0.008, 0.197, 0, 0, 0]"
TARGET_T_MM = 0.05
TARGET_R_DEG = 0.02
TARGET_PASSES_MM = 0.05
TARGET_ROBOT_S = 120.0
SCAN_SPEED_M_S = 0.02
OVERLAP_M = 0.5e-3
"""The two scan passes overlap where a pass-2 point lies this close to a pass-1 point, both mapped
with the true tool."""


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(
    repeatability_m: float,
    configured_latency_s: float,
    text: str | None = None,
    calibration_file: Path | None = None,
) -> tuple[Config, str]:
    """The simulated cell's configuration (and its text, to derive variants on the same
    addresses): free addresses, no rotary table process, the benchmark's noise and latency."""
    if text is None:
        text = (ROOT / "config" / "sim.toml").read_text()
        text = text.replace('host = "127.0.0.2"', f'host = "{pick_free_loopback_host()}"')
        text = text.replace("port = 50002", f"port = {_free_udp_port()}")
        # No rotary table process: the part stays at angle 0 (objects mounted on the table do).
        text = re.sub(r"\n\[table\]\n.*?\n(?=\[)", "\n", text, flags=re.S)
        text = text.replace("[sim.table]\nenabled = true", "[sim.table]\nenabled = false")
        text = text.replace("n_points = 2048", "n_points = 512")
        text = text.replace("repeatability_m = 0.0", f"repeatability_m = {repeatability_m!r}")
        text = text.replace(
            "latency_s = 0.002\nclock_offset_s", f"latency_s = {SIM_LATENCY_S}\nclock_offset_s"
        )
    out = re.sub(
        r"\nlatency_s = [0-9.e-]+ ", f"\nlatency_s = {configured_latency_s!r} ", text, count=1
    )
    if calibration_file is not None:
        out = out.replace("[calibration]\n", f'[calibration]\nfile = "{calibration_file}"\n')
    cfg = parse_config(out, "<benchmark>", ROOT)
    assert cfg.sim is not None and cfg.sim.sensor.latency_s == SIM_LATENCY_S
    assert cfg.sensor.latency_s == configured_latency_s
    return cfg, text


def _realistic_arm(text: str) -> str:
    """The configuration text with an arm of realistic DH deviations (seed 4) and a controller
    computing with the nominal table."""
    for key, value in (("kinematic_errors", '"realistic"'), ("kinematic_seed", "4"),
                       ("factory_calibration", '"none"')):  # fmt: skip
        text = re.sub(rf"^{key} = \S+", f"{key} = {value}", text, flags=re.M)
    return text


def _errors(X: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return (
        float(np.linalg.norm(X[:3, 3] - truth[:3, 3])) * 1e3,
        math.degrees(float(se3.rotation_angle(X[:3, :3].T @ truth[:3, :3]))),
    )


@dataclass
class Session:
    name: str
    result: cs.SensorCalibrationResult
    truth: np.ndarray
    seconds: float
    passes: dict[str, float] | None = None


def _scan_passes(
    cfg: Config, X: np.ndarray, truth: np.ndarray, part_top: np.ndarray
) -> dict[str, float]:
    """Two passes over the part (30 degrees apart, opposite directions), mapped with ``X`` and
    with the true tool: point-to-plane RMS of pass 2 against pass 1 (m) for both."""
    model = kinematics.get_model(cfg.robot.model)
    depth = 0.10
    # Pass 1: looking down, laser line along base X, sweeping along base +Y over the part.
    R1 = np.column_stack([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    # Pass 2: tilted 30 degrees about the sweep axis, sweeping back along -Y.
    R2 = se3.rot_y(math.radians(30.0)) @ R1
    y0, y1 = part_top[1] - 0.07, part_top[1] + 0.07
    clouds: dict[str, list[np.ndarray]] = {"cal": [], "true": []}
    with Acquisition(cfg) as acq:
        cell = cs.RobotCell(acq, model)
        t_end = time.monotonic() + 20.0
        while cell.record_for(0.4).n_profiles < 200 and time.monotonic() < t_end:
            pass
        inv = se3.invert(X)
        for R, ya, yb in ((R1, y0, y1), (R2, y1, y0)):

            def flange(y: float, R: np.ndarray = R) -> np.ndarray:
                p = np.array([part_top[0], y, part_top[2]])
                return se3.make(R, p - R @ np.array([0.0, 0.0, depth])) @ inv

            start, end = flange(ya), flange(yb)
            above = se3.make(None, (0, 0, 0.05)) @ start
            q = kinematics.inverse_nearest(model, above, cell.joints())
            cell.move_j(q, 0.6, 1.2)
            cell.move_l(start, 0.1, 0.5)
            for attempt in range(4):
                data, took = cell.sweep_to(end, SCAN_SPEED_M_S, 0.5)
                if data.n_profiles > 0.7 * 1000 * took or attempt == 3:
                    break
                cell.move_l(start, 0.1, 0.5)
            cell.move_l(se3.make(None, (0, 0, 0.05)) @ end, 0.1, 0.5)
            m = data.valid & np.isfinite(data.z)
            sw = handeye.Sweep.from_yz(
                data.flange2base, data.y[m], data.z[m], data.profile_index[m]
            )
            pick = np.random.default_rng(0).permutation(sw.n_points)[:150_000]
            sub = sw.subset(np.isin(np.arange(sw.n_points), pick))
            clouds["cal"].append(sub.points_base(X))
            clouds["true"].append(sub.points_base(truth))
    # Where the passes overlap is decided on the clouds mapped with the TRUE tool (the pass-2
    # points within OVERLAP_M of a pass-1 point), so that the calibration under test cannot
    # move points out of the comparison; both mappings are then compared over exactly those
    # points with no distance limit.
    true_a, true_b = clouds["true"]
    print(f"    two passes: {len(true_a)} and {len(true_b)} points", flush=True)
    overlap = np.zeros(len(true_b), dtype=bool)
    if len(true_a) and len(true_b):
        d_true, _ = cKDTree(true_a).query(true_b)
        overlap = d_true <= OVERLAP_M
    out = {"overlap_fraction": float(overlap.mean()) if overlap.size else 0.0}
    if not overlap.any():  # a pass recorded nothing usable (a loaded machine): no figure
        nan = float("nan")
        return out | {k: nan for k in ("cal", "true", "cal_beyond", "cal_trimmed")}
    for key, (a, b) in clouds.items():
        normals = icp.estimate_normals(a, k=16)
        out[key] = icp.point_to_plane_rms(b[overlap], a, normals)
        d, _ = cKDTree(a).query(b[overlap])
        out[f"{key}_beyond"] = float(np.mean(d > OVERLAP_M))
        out[f"{key}_trimmed"] = icp.point_to_plane_rms(b, a, normals, max_distance=OVERLAP_M)
    return out


def _latency_procedure(cfg_text: str, calibration: Path, cell: Any) -> float | None:
    """``wristscan calibrate latency`` (the other procedure of issue 7) with the new sensor
    calibration, when it is there: the latency to configure (s), or None."""
    try:
        from wristscan.daemon.calibrate.latency import calibrate_latency
    except ImportError:
        return None
    cfg, _ = _config(0.0, 0.0, cfg_text, calibration)
    jog_to_ball(cell)
    try:
        res = calibrate_latency(cfg, confirmed=True)
    except Exception as exc:  # another part's procedure: report and go on with ours
        print(f"    latency procedure failed: {exc}")
        return None
    print(
        f"    latency procedure: {res.latency_s * 1e3:.3f} ms (+- {res.estimate.std_s * 1e3:.3f})"
    )
    return float(res.latency_s)


def _session(
    name: str,
    cfg: Config,
    text: str,
    settings: cs.Settings,
    workdir: Path,
    *,
    passes: bool,
    latency: bool = False,
) -> tuple[Session, float | None]:
    """One calibration on a fresh cell; then optionally the latency procedure and the scan
    passes. Returns the session and the latency procedure's figure (None if not run)."""
    cell = start_cell(cfg)
    try:
        truth = np.array(cell.truth()["sensor2flange"])
        jog_to_ball(cell)
        t0 = time.monotonic()

        def progress(e: cs.ProgressEvent) -> None:
            print(f"    {time.monotonic() - t0:6.1f} s {e}", flush=True)

        out = workdir / f"{name}.json"
        for attempt in range(3):
            try:
                result = cs.run(
                    cfg,
                    settings,
                    nominal=se3.pose_to_matrix(parse_ur_pose(NOMINAL)),
                    out=out,
                    report=workdir / f"{name}-report.html",
                    progress=progress,
                )
                break
            except DriverTimeout as exc:  # the robot stream did not open on a loaded machine
                if attempt == 2:
                    raise
                print(f"    {exc}: trying again", flush=True)
        seconds = time.monotonic() - t0
        session = Session(name, result, truth, seconds)
        measured = _latency_procedure(text, out, cell) if latency else None
        if passes:
            assert cfg.sim is not None
            top = np.array(cfg.sim.truth.table_axis_point_m) + np.array([0.02, 0.01, 0.07])
            session.passes = _scan_passes(cfg, result.sensor2flange, truth, top)
        return session, measured
    finally:
        cell.stop()


def _stopgo_poses(ball: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` sensor poses looking at the ball (a peer's taught set): tilts spread over 0-45 deg
    and the azimuths, a random yaw, the ball at varied places of the laser plane and of the
    measuring range, cut off its centre by 0.15-0.8 R (one side, as stop-and-go needs)."""
    out = np.empty((n, 4, 4))
    tilts = np.radians(45.0) * np.sqrt((np.arange(n) + 0.5) / n)
    az = rng.permutation(np.linspace(0.0, 2 * math.pi, n, endpoint=False))
    R = 0.0127
    for k in range(n):
        axis = np.array([math.cos(az[k]), math.sin(az[k]), 0.0])
        Rs = se3.rotvec_to_matrix(axis * tilts[k]) @ se3.rot_x(math.pi)
        Rs = Rs @ se3.rot_z(rng.uniform(-0.6, 0.6))
        c = np.array([R * rng.uniform(0.15, 0.8), rng.uniform(-0.009, 0.009),
                      rng.uniform(0.075, 0.14)])  # fmt: skip
        out[k] = se3.make(Rs, ball - Rs @ c)
    return out


def _stopgo_session(cfg: Config, n_poses: int, settle_s: float = 0.3) -> list[Figure]:
    """The peers' way on the same cell (HandEyeSync, lls_calibration): stop at each of
    ``n_poses`` taught poses, settle, read one profile with the robot's pose; solved by
    ``calibrate import``'s path. Returns its robot time and accuracy."""
    from wristscan.daemon.calibrate import imported

    assert cfg.sim is not None
    ball = np.asarray(cfg.sim.scene.ball_centre_m, dtype=np.float64)
    cell = start_cell(cfg)
    try:
        truth = np.array(cell.truth()["sensor2flange"])
        jog_to_ball(cell)
        model = kinematics.get_model(cfg.robot.model)
        poses, profiles = [], []
        with Acquisition(cfg) as acq:
            rc = cs.RobotCell(acq, model)
            t_end = time.monotonic() + 20.0
            while rc.record_for(0.4).n_profiles < 200 and time.monotonic() < t_end:
                pass
            t0 = time.monotonic()
            for S in _stopgo_poses(ball, n_poses, np.random.default_rng(5)):
                q = kinematics.inverse_nearest(model, S @ se3.invert(truth), rc.joints())
                rc.move_j(q, 1.0, 1.5)
                time.sleep(settle_s)
                data = rc.record_for(0.05)
                if data.n_profiles == 0:
                    continue
                k = data.n_profiles // 2
                m = (data.profile_index == k) & data.valid & np.isfinite(data.z)
                poses.append(data.flange2base[k])
                profiles.append(np.column_stack([data.y[m], data.z[m]]))
            robot_s = time.monotonic() - t0
    finally:
        cell.stop()
    names = tuple(f"p{k + 1:02d}" for k in range(len(poses)))
    ds = imported.ImportedDataset(Path("stopgo"), "ur-rotvec", "m", names, np.array(poses),
                                  tuple(profiles))  # fmt: skip
    res = imported.calibrate_dataset(ds, 0.0127)
    t, r = _errors(res.joint.sensor2flange, truth)
    tag = f"stop-and-go ({len(poses)} poses, peers' way)"
    return [
        Figure(f"{tag}: robot time (move, settle {settle_s:g} s, one profile)", robot_s, "s", "",
               None),
        Figure(f"{tag}: translation error", t, "mm", "", None),
        Figure(f"{tag}: rotation error", r, "deg", "", None),
    ]  # fmt: skip


def _kinematics_session(cfg: Config, workdir: Path) -> list[Figure]:
    """``wristscan calibrate kinematics`` with its default plan on a cell whose arm has realistic
    DH deviations and whose controller computes with the nominal table (information): its robot
    time and the ball-centre scatter across its sweeps before and after."""
    from wristscan.daemon.calibrate import kinematics as ck

    cell = start_cell(cfg)
    try:
        jog_to_ball(cell)
        settings = ck.settings_for_kinematics(cfg, sweep_speed_m_s=0.04, fov_grid=3)
        res = ck.run(cfg, settings, nominal=se3.pose_to_matrix(parse_ur_pose(NOMINAL)),
                     out=workdir / "kinematics.json")  # fmt: skip
    finally:
        cell.stop()
    tag = "calibrate kinematics (nominal table, realistic arm)"
    return [
        Figure(f"{tag}: robot time", res.sensor.robot_time_s, "s", "", None),
        Figure(f"{tag}: ball-centre scatter before", res.scatter_before_m * 1e3, "mm", "", None),
        Figure(f"{tag}: ball-centre scatter after", res.scatter_after_m * 1e3, "mm", "", None),
        Figure(f"{tag}: sweeps", res.ident.n_scans, "", "", None),
    ]


def _figures(s: Session, targets: bool) -> list[Figure]:
    r = s.result
    tj, rj = _errors(r.joint.sensor2flange, s.truth)
    tt, rt = _errors(r.two_step.sensor2flange, s.truth)
    tag = s.name
    ok_t = (tj <= TARGET_T_MM) if targets else None
    ok_r = (rj <= TARGET_R_DEG) if targets else None
    figs = [
        Figure(f"{tag}: translation error, joint", tj, "mm", f"<= {TARGET_T_MM}", ok_t),
        Figure(f"{tag}: rotation error, joint", rj, "deg", f"<= {TARGET_R_DEG}", ok_r),
        Figure(f"{tag}: translation error, two-step", tt, "mm", "(paper)", None),
        Figure(f"{tag}: rotation error, two-step", rt, "deg", "(paper)", None),
        Figure(f"{tag}: residual RMS, joint", r.joint.rms * 1e3, "mm", "", None),
        Figure(f"{tag}: residual RMS, two-step", r.two_step.rms * 1e3, "mm", "", None),
        Figure(f"{tag}: 1 sigma translation (max axis)",
               float(r.joint.sigma_translation_m.max()) * 1e3, "mm", "reported", None),
        Figure(f"{tag}: 1 sigma rotation (max axis)",
               math.degrees(float(r.joint.sigma_rotation_rad.max())), "deg", "reported", None),
    ]  # fmt: skip
    if r.uncompensated is not None:
        tu, ru = _errors(r.uncompensated.sensor2flange, s.truth)
        figs += [
            Figure(f"{tag}: translation error, no timing fix", tu, "mm", "", None),
            Figure(f"{tag}: rotation error, no timing fix", ru, "deg", "", None),
            Figure(
                f"{tag}: residual RMS, no timing fix", r.uncompensated.rms * 1e3, "mm", "", None
            ),
        ]
    if r.latency is not None:
        figs.append(Figure(
            f"{tag}: apparent latency offset (simulator {SIM_LATENCY_S * 1e3:.1f} ms, configured "
            f"{r.configured_latency_s * 1e3:.2f} ms)", r.latency.offset_s * 1e3, "ms", "", None
        ))  # fmt: skip
    if r.loo is not None:
        figs += [
            Figure(f"{tag}: leave-one-out max translation change",
                   r.loo.max_translation_dev_m * 1e3, "mm", "", None),
            Figure(f"{tag}: leave-one-out max rotation change",
                   math.degrees(r.loo.max_rotation_dev_rad), "deg", "", None),
        ]  # fmt: skip
    if r.check is not None:
        figs += [
            Figure(f"{tag}: check scan centre error", r.check.centre_error_m * 1e3, "mm", "", None),
            Figure(f"{tag}: check scan radius error", r.check.radius_error_m * 1e3, "mm", "", None),
        ]
    figs += _pass_figures(s, targets)
    ok_time = (r.robot_time_s <= TARGET_ROBOT_S) if targets else None
    figs += [
        Figure(f"{tag}: sweeps used / profiles", len(r.sweeps),
               f"/{sum(w.n_profiles for w in r.sweeps)}", "", None),
        Figure(f"{tag}: robot time (first motion to last)", r.robot_time_s, "s",
               f"<= {TARGET_ROBOT_S:g}", ok_time),
        Figure(f"{tag}: of which moving", r.motion_time_s, "s", "", None),
        Figure(f"{tag}: duration", s.seconds, "s", "", None),
    ]  # fmt: skip
    return figs


def _pass_figures(s: Session, targets: bool) -> list[Figure]:
    if s.passes is None:
        return []
    p, tag = s.passes, s.name
    return [
        Figure(f"{tag}: two passes, point-to-plane RMS before ICP", p["cal"] * 1e3,
               "mm", f"<= {TARGET_PASSES_MM}",
               (p["cal"] * 1e3 <= TARGET_PASSES_MM) if targets else None),
        Figure(f"{tag}: two passes with the true tool (noise floor)", p["true"] * 1e3,
               "mm", "", None),
        Figure(f"{tag}: two passes, overlap (pass 2 within 0.5 mm of pass 1, true tool)",
               p["overlap_fraction"] * 100, "%", "", None),
        Figure(f"{tag}: two passes, overlap points > 0.5 mm from pass 1 (calibrated)",
               p["cal_beyond"] * 100, "%", "", None),
        Figure(f"{tag}: two passes, RMS as before (pairs > 0.5 mm dropped)",
               p["cal_trimmed"] * 1e3, "mm", "", None),
    ]  # fmt: skip


def run(json_out: str | None = None, quick: bool = False, keep: str | None = None,
        literal: bool = True, stopgo: bool = True, kin: bool = False) -> int:  # fmt: skip
    """Run the sessions and print the figures; returns the exit code (1 on a missed target)."""
    workdir = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="wristscan-calbench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    overrides: dict[str, Any] = {"leave_one_out": True}
    if quick:
        overrides.update(sweep_speed_m_s=0.05, fov_grid=2, n_orientations=4)
    print(f"robot repeatability: ISO 9283 RP {ISO_RP_M * 1e3:.3f} mm -> sigma "
          f"{SIGMA_AXIS_M * 1e6:.1f} um per axis -> simulated RMS {SIM_RMS_ISO_M * 1e6:.1f} um "
          f"(literal reading, information: RMS {SIM_RMS_LITERAL_M * 1e6:.1f} um = "
          f"{SIM_RMS_LITERAL_M / math.sqrt(3) * 1e6:.1f} um per axis)")  # fmt: skip
    print(f"files in {workdir}")
    figures: list[Figure] = []
    targets = not quick

    print("session A: latency not told (configured 0, simulator 1.5 ms)")
    cfg, text = _config(SIM_RMS_ISO_M, 0.0)
    a, measured = _session("A", cfg, text, cs.settings_for(cfg, **overrides), workdir,
                           passes=True, latency=True)  # fmt: skip
    figures += _figures(a, targets)
    for f in figures:  # before the latency is configured, the passes are information only
        if f.name.startswith("A: two passes, point"):
            f.ok, f.target = None, "(latency unset)"
    own = a.result.latency.offset_s if a.result.latency is not None else 0.0
    figures.append(
        Figure("A: latency from the sweep pairs (simulator 1.5 + link)", own * 1e3, "ms", "", None)
    )
    if measured is not None:
        figures.append(
            Figure("A: latency procedure (simulator 1.5 + link)", measured * 1e3, "ms", "", None)
        )
    est = measured if measured is not None else own
    print(f"session B: [sensor] latency_s = {est * 1e3:.3f} ms (measured after A)")
    cfg, _ = _config(SIM_RMS_ISO_M, max(0.0, est), text)
    b, _ = _session("B", cfg, text, cs.settings_for(cfg, **overrides), workdir, passes=True)
    figures += _figures(b, targets)

    if stopgo:
        n = len({w.location for w in a.result.sweeps})
        print(f"stop-and-go baseline: {n} poses (as many as session A's places)")
        cfg, _ = _config(SIM_RMS_ISO_M, 0.0)
        figures += _stopgo_session(cfg, n)
    if kin:
        print("calibrate kinematics: realistic arm, controller on the nominal table")
        cfg, _ = _config(SIM_RMS_ISO_M, 0.0, _realistic_arm(text))
        figures += _kinematics_session(cfg, workdir)
    if literal:
        print("session C (information): repeatability_m = 0.03 mm RMS, latency not told")
        cfg, text = _config(SIM_RMS_LITERAL_M, 0.0)
        c, _ = _session("C", cfg, text, cs.settings_for(cfg, **overrides), workdir, passes=False)
        figures += _figures(c, False)
    return report("sensor2flange calibration on the simulated cell", figures, json_out)


def passes_only(calibration: str, latency_s: float, json_out: str | None = None) -> int:
    """The two scan passes alone, mapped with the sensor2flange of ``calibration`` (a file this
    benchmark wrote with ``--keep``; the simulated cell is the benchmark's, so its truth is the
    same) and with ``[sensor] latency_s`` = ``latency_s``: the two-pass figures of a calibration
    without running it again."""
    from wristscan.daemon.io.calibfile import read_calibration

    X = np.asarray(read_calibration(calibration, kind="sensor2flange").transform)
    cfg, _ = _config(SIM_RMS_ISO_M, latency_s)
    cell = start_cell(cfg)
    try:
        truth = np.array(cell.truth()["sensor2flange"])
        assert cfg.sim is not None
        top = np.array(cfg.sim.truth.table_axis_point_m) + np.array([0.02, 0.01, 0.07])
        for attempt in range(3):
            try:
                passes = _scan_passes(cfg, X, truth, top)
                break
            except DriverTimeout as exc:  # the robot stream did not open on a loaded machine
                if attempt == 2:
                    raise
                print(f"    {exc}: trying again", flush=True)
    finally:
        cell.stop()
    tj, rj = _errors(X, truth)
    session = Session(f"{Path(calibration).stem} ({tj:.3f} mm, {rj:.4f} deg off)", None, truth,  # type: ignore[arg-type]
                      0.0, passes)  # fmt: skip
    figs = _pass_figures(session, True)
    return report("two scan passes mapped with a calibration file", figs, json_out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", help="write the figures as JSON")
    ap.add_argument("--quick", action="store_true", help="smoke run: fewer places, no targets")
    ap.add_argument("--keep", help="folder for the calibration files and reports")
    ap.add_argument("--no-literal", action="store_true", help="skip information session C")
    ap.add_argument("--no-stopgo", action="store_true", help="skip the stop-and-go baseline")
    ap.add_argument("--kinematics", action="store_true", help="also run calibrate kinematics")
    ap.add_argument(
        "--passes-with",
        metavar="FILE",
        help="only the two scan passes, mapped with this calibration file (written with --keep)",
    )
    ap.add_argument(
        "--latency-s",
        type=float,
        default=SIM_LATENCY_S,
        help="[sensor] latency_s for --passes-with (default: the simulator's)",
    )
    args = ap.parse_args()
    if args.passes_with:
        sys.exit(passes_only(args.passes_with, args.latency_s, args.json))
    sys.exit(run(args.json, args.quick, args.keep, not args.no_literal, not args.no_stopgo,
                 args.kinematics))  # fmt: skip


if __name__ == "__main__":
    main()
