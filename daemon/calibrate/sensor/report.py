"""The sensor calibration's report (:func:`build_report`): the result, its uncertainty, the
paper's two-step solution beside the joint refinement, the validation (leave-one-out, check
scan, apparent sensor time offset), the notes, and figures when matplotlib is there."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye, se3
from wristscan.daemon.calibrate.sensor.plan import rotation_between
from wristscan.daemon.calibrate.sensor.result import (
    SensorCalibrationResult,
    predicted_point_error,
    working_volume,
)

if TYPE_CHECKING:
    from wristscan.daemon.io.report import Report

__all__ = ["build_report"]

FloatArray = NDArray[np.float64]


def _fmt_um(v: float) -> str:
    return f"{v * 1e6:.1f}" if math.isfinite(v) else "-"


def build_report(
    result: SensorCalibrationResult, title: str = "Sensor-to-flange calibration", subtitle: str = ""
) -> Report:
    """The procedure's report: results, uncertainties, two-step vs joint, validation, figures
    (when matplotlib is available)."""
    from wristscan.daemon.io.report import Report, have_matplotlib

    s = result.settings
    rep = Report(title, subtitle)
    _result_section(rep, result)
    rep.section("Parameters and uncertainty")
    rep.table(
        ["parameter", "nominal", "two-step", "1 sigma", "joint", "1 sigma", "LOO jackknife"],
        _param_rows(result),
        "Translation of the sensor origin in the flange frame; rotation uncertainty about the "
        "sensor axes. 1 sigma from the covariance (joint: sensor noise and the robot's pose "
        "error, see below); the jackknife over the orientations beside it as a cross-check.",
    )
    rep.text(_uncertainty_text(result))
    _validation_section(rep, result)
    if result.notes:
        rep.section("Notes")
        rep.text("\n".join(f"- {n}" for n in result.notes), preformatted=True)
    if have_matplotlib():
        _figures(rep, result)
    else:
        rep.text("Figures need matplotlib: pip install 'wristscan[plot]'.")
    rep.section("Settings")
    rep.table(
        ["setting", "value"],
        [
            [k, f"{v:g}" if isinstance(v, float) else str(v)]
            for k, v in dataclasses.asdict(s).items()
        ],
    )
    return rep


def _result_section(rep: Report, result: SensorCalibrationResult) -> None:
    """sensor2flange as typed on the teach pendant; the two-step and joint solutions side by
    side."""
    from wristscan.daemon.io.urpose import ur_pose_text

    j, t = result.joint, result.two_step
    rep.section("Result")
    pose = se3.matrix_to_pose(j.sensor2flange)
    rep.text(
        f"sensor2flange (joint refinement): {ur_pose_text(pose)}  (metres, rotation vector in "
        f"radians; on the teach pendant the TCP is x {pose[0] * 1e3:.3f} mm, y "
        f"{pose[1] * 1e3:.3f} mm, z {pose[2] * 1e3:.3f} mm, rx {pose[3]:.5f}, ry {pose[4]:.5f},"
        f" rz {pose[5]:.5f} rad)."
    )
    summary = [
        ["residual RMS (um)", _fmt_um(t.rms), _fmt_um(j.rms)],
        ["points used", str(t.n_points), str(j.n_points)],
        ["condition number", f"{t.condition:.1f}", f"{j.condition:.1f}"],
        [
            "ball centre (mm)",
            str(np.round(t.ball_centre_base * 1e3, 3).tolist()),
            str(np.round(j.ball_centre_base * 1e3, 3).tolist()),
        ],
    ]
    if result.check is not None:
        c = result.check
        summary += [
            [
                "check scan: centre error (um)",
                _fmt_um(c.two_step_centre_error_m),
                _fmt_um(c.centre_error_m),
            ],
            [
                "check scan: radius error (um)",
                _fmt_um(c.two_step_radius_error_m),
                _fmt_um(c.radius_error_m),
            ],
        ]
    d_t = float(np.linalg.norm(t.sensor2flange[:3, 3] - j.sensor2flange[:3, 3]))
    d_r = math.degrees(rotation_between(t.sensor2flange, j.sensor2flange))
    rep.table(
        ["", "two-step (paper)", "joint refinement"],
        summary,
        "The paper's two-step solution beside the joint refinement, on the same sweeps",
    )
    rep.text(
        f"The two solutions differ by {d_t * 1e3:.4f} mm and {d_r:.5f} deg. "
        f"{len(result.sweeps)} sweeps ({sum(w.stage == 'fov' for w in result.sweeps)} at "
        f"field-of-view locations), {sum(w.n_profiles for w in result.sweeps)} profiles; "
        f"smallest angle between sensor Z axes of two orientations "
        f"{result.min_z_angle_deg:.1f} deg; {result.duration_s:.0f} s in all, the robot kept "
        f"{result.robot_time_s:.0f} s ({result.motion_time_s:.0f} s moving)."
    )


def _param_rows(result: SensorCalibrationResult) -> list[list[str]]:
    j, t = result.joint, result.two_step
    pj, pt = se3.matrix_to_pose(j.sensor2flange), se3.matrix_to_pose(t.sensor2flange)
    pn = None if result.nominal is None else se3.matrix_to_pose(result.nominal)
    sj_t, st_t = j.sigma_translation_m, t.sigma_translation_m
    sj_r, st_r = j.sigma_rotation_rad, t.sigma_rotation_rad
    loo_t = None if result.loo is None else result.loo.spread_translation_m
    rows: list[list[str]] = []
    for i, a in enumerate("xyz"):
        rows.append(
            [
                f"{a} (mm)",
                "-" if pn is None else f"{pn[i] * 1e3:.3f}",
                f"{pt[i] * 1e3:.4f}",
                f"{st_t[i] * 1e3:.4f}",
                f"{pj[i] * 1e3:.4f}",
                f"{sj_t[i] * 1e3:.4f}",
                "-" if loo_t is None else f"{loo_t[i] * 1e3:.4f}",
            ]
        )
    for i, a in enumerate("xyz"):
        rows.append(
            [
                f"r{a} (deg, rotation vector)",
                "-" if pn is None else f"{math.degrees(pn[3 + i]):.4f}",
                f"{math.degrees(pt[3 + i]):.5f}",
                "",
                f"{math.degrees(pj[3 + i]):.5f}",
                "",
                "",
            ]
        )
    loo_r = None if result.loo is None else result.loo.sigma[:3]
    for i, a in enumerate("XYZ"):
        rows.append(
            [
                f"rotation about sensor {a} (deg)",
                "",
                "0",
                f"{math.degrees(st_r[i]):.5f}",
                "0",
                f"{math.degrees(sj_r[i]):.5f}",
                "-" if loo_r is None else f"{math.degrees(loo_r[i]):.5f}",
            ]
        )
    return rows


def _uncertainty_text(result: SensorCalibrationResult) -> str:
    """How the joint solution's sigmas were made, and what they mean for a measured point."""
    s, j = result.settings, result.joint
    vc = j.components
    rms, top = predicted_point_error(result)
    (y0, y1), (z0, z1) = working_volume(s)
    parts = []
    if vc is not None:
        est = vc.sweep_sigma_estimated_m
        parts.append(
            "The covariance models the sensor noise "
            f"({_fmt_um(vc.noise_sigma_m)} um per point) and the robot's pose error, which every "
            "point of a sweep shares: per sweep "
            f"{_fmt_um(vc.sweep_sigma_m)} um per axis (at least "
            f"{_fmt_um(result.robot_sigma_m or s.robot_sigma_m)} um: the larger of the data "
            "sheet's repeatability and the places' scatter"
            + (f", the sweeps' scatter {_fmt_um(est)} um" if math.isfinite(est) else "")
            + f") and per pose (orientation) {_fmt_um(vc.pose_sigma_m)} um, both estimated from "
            "the residuals."
        )
    parts.append(
        f"Predicted error of a measured point due to the calibration: {_fmt_um(rms)} um RMS, "
        f"{_fmt_um(top)} um at worst over the working volume (laser line "
        f"{y0 * 1e3:.0f}..{y1 * 1e3:.0f} mm, depth {z0 * 1e3:.0f}..{z1 * 1e3:.0f} mm)."
    )
    if j.advice:
        parts.append(f"Weakly constrained (condition {j.condition:.1f}): {j.advice}.")
    return " ".join(parts)


def _validation_section(rep: Report, result: SensorCalibrationResult) -> None:
    """Leave-one-out, the check scan and the apparent sensor time offset."""
    rep.section("Validation")
    if result.loo is not None:
        loo = result.loo
        rep.table(
            [
                "left out",
                "translation change (um)",
                "rotation change (mdeg)",
                "prediction RMS (um)",
            ],
            [
                [lab, _fmt_um(a), f"{math.degrees(b) * 1e3:.2f}", _fmt_um(c)]
                for lab, a, b, c in zip(
                    loo.labels,
                    loo.translation_dev_m,
                    loo.rotation_dev_rad,
                    loo.prediction_rms_m,
                    strict=True,
                )
            ],
            "Leave-one-out over the orientations: the joint refinement without each one",
        )
    else:
        rep.text("Leave-one-out was not run (fewer than 3 orientations, or switched off).")
    if result.check is not None:
        c = result.check
        rep.text(
            f"Check scan ({c.label}, not used by the solution): sphere of free radius through "
            f"{c.n_points} points mapped with the new calibration; centre "
            f"{c.centre_error_m * 1e6:.1f} um from the calibrated ball centre, radius "
            f"{c.radius_m * 1e3:.4f} mm ({c.radius_error_m * 1e6:+.1f} um), RMS "
            f"{c.rms_m * 1e6:.1f} um."
        )
    if result.latency is not None:
        _latency_text(rep, result)


def _latency_text(rep: Report, result: SensorCalibrationResult) -> None:
    """The apparent sensor time offset, the latency it suggests, and what the re-timing
    changed."""
    assert result.latency is not None
    j = result.joint
    lat = result.latency
    suggest = result.configured_latency_s + lat.offset_s
    rep.text(
        f"Apparent sensor time offset from {lat.n_pairs} forward/backward pairs at "
        f"{lat.speed_m_s * 1e3:.1f} mm/s: {lat.offset_s * 1e3:+.3f} ms (+- "
        f"{lat.std_s * 1e3:.3f} ms). Configured latency {result.configured_latency_s * 1e3:.3f}"
        f" ms; the data suggest {suggest * 1e3:.3f} ms (set [sensor] latency_s, or run "
        "wristscan calibrate latency). Sweeping both ways cancels this offset in the "
        "solution; each forward/backward pair was re-timed by its own offset before it."
    )
    if result.uncompensated is not None:
        u = result.uncompensated
        d_t = float(np.linalg.norm(u.sensor2flange[:3, 3] - j.sensor2flange[:3, 3]))
        rep.text(
            f"Without the re-timing the joint refinement had a residual RMS of "
            f"{u.rms * 1e6:.1f} um (now {j.rms * 1e6:.1f} um) and sensor2flange "
            f"{d_t * 1e3:.4f} mm / "
            f"{math.degrees(rotation_between(u.sensor2flange, j.sensor2flange)):.5f} deg "
            "from the final one."
        )


# --------------------------------------------------------------------------------------------
# Figures


def _figures(rep: Report, result: SensorCalibrationResult) -> None:
    _residual_figures(rep, result)
    _pose_set_figure(rep, result)
    if result.check is not None:
        _check_scan_figure(rep, result)


def _residual_figures(rep: Report, result: SensorCalibrationResult) -> None:
    """Residuals of the inlier points, two-step beside joint; residual RMS per sweep."""
    from wristscan.daemon.io.report import new_figure

    j, t = result.joint, result.two_step
    solver = [w.for_solver() for w in result.sweeps]

    def residuals(res: handeye.HandEyeResult) -> FloatArray:
        r = handeye.sphere_residuals(
            [w.subset(m) for w, m in zip(solver, res.inliers, strict=True)],
            res.sensor2flange,
            res.ball_centre_base,
            res.ball_radius_m,
        )
        return np.concatenate(r)

    rt, rj = residuals(t) * 1e6, residuals(j) * 1e6
    lim = float(np.percentile(np.abs(np.concatenate([rt, rj])), 99.5)) or 1.0
    fig, axes = new_figure(1, 2, figsize=(9.0, 3.6), sharey=True)
    for ax, r, name in ((axes[0], rt, "two-step (paper)"), (axes[1], rj, "joint refinement")):
        ax.hist(r, bins=80, range=(-lim, lim), color="tab:blue")
        ax.set_title(f"{name}: RMS {np.sqrt(np.mean(r**2)):.1f} um")
        ax.set_xlabel("distance to the ball surface (um)")
    axes[0].set_ylabel("points")
    rep.figure(fig, "Residuals of all inlier points, two-step beside joint refinement")

    labels = [w.label for w in result.sweeps]
    x = np.arange(len(labels))
    fig, ax = new_figure(figsize=(9.0, 3.8))
    ax.bar(x - 0.2, t.per_sweep_rms * 1e6, 0.4, label="two-step")
    ax.bar(x + 0.2, j.per_sweep_rms * 1e6, 0.4, label="joint")
    ax.set_xticks(x, labels, rotation=70, ha="right", fontsize=7)
    ax.set_ylabel("RMS residual (um)")
    ax.legend()
    rep.figure(fig, "Residual RMS per sweep")


def _pose_set_figure(rep: Report, result: SensorCalibrationResult) -> None:
    """The sensor origins and Z axes (mid-sweep) around the ball, per stage."""
    from wristscan.daemon.io.report import axis_equal_3d, new_figure

    R = result.settings.ball_radius_m
    j = result.joint
    fig, ax = new_figure(figsize=(6.5, 6.0), subplot_kw={"projection": "3d"})
    c = j.ball_centre_base
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
    ax.plot_wireframe(
        c[0] + R * np.cos(u) * np.sin(v),
        c[1] + R * np.sin(u) * np.sin(v),
        c[2] + R * np.cos(v),
        color="0.6",
        linewidth=0.5,
    )
    pts = [c]
    for group_sweeps, colour, name in (
        ([w for w in result.sweeps if w.stage == "fov"], "tab:gray", "field of view"),
        ([w for w in result.sweeps if w.stage == "tilt"], "tab:blue", "orientations"),
        (list(result.check_sweeps), "tab:red", "check scan"),
    ):
        if not group_sweeps:
            continue
        S = np.array(
            [w.sweep.flange2base[w.sweep.n_poses // 2] @ j.sensor2flange for w in group_sweeps]
        )
        o, z = S[:, :3, 3], S[:, :3, 2]
        length = float(np.median(np.linalg.norm(o - c, axis=1)))
        ax.quiver(
            o[:, 0],
            o[:, 1],
            o[:, 2],
            z[:, 0],
            z[:, 1],
            z[:, 2],
            length=length,
            color=colour,
            label=name,
            linewidth=1.0,
            arrow_length_ratio=0.08,
        )
        pts.extend(o)
    axis_equal_3d(ax, np.array(pts))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.legend(loc="upper left", fontsize=8)
    rep.figure(fig, "Pose set: sensor origins and Z axes (mid-sweep) around the ball, base frame")


def _check_scan_figure(rep: Report, result: SensorCalibrationResult) -> None:
    """The check scan's points coloured by their residual, and the residuals' histogram."""
    from wristscan.daemon.io.report import axis_equal_3d, blank_figure

    assert result.check is not None
    ck = result.check
    fig = blank_figure(figsize=(9.5, 4.0))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    p = ck.points_base
    sc = ax3.scatter(p[:, 0], p[:, 1], p[:, 2], c=ck.residuals_m * 1e6, s=2, cmap="coolwarm")
    fig.colorbar(sc, ax=ax3, shrink=0.7, label="residual (um)")
    axis_equal_3d(ax3, p)
    ax3.set_title("check scan in base (new calibration)", fontsize=9)
    ax2 = fig.add_subplot(1, 2, 2)
    ax2.hist(ck.residuals_m * 1e6, bins=60, color="tab:red")
    ax2.set_xlabel("distance to the fitted sphere (um)")
    ax2.set_title(
        f"centre error {ck.centre_error_m * 1e6:.1f} um, radius {ck.radius_error_m * 1e6:+.1f} um",
        fontsize=9,
    )
    rep.figure(fig, "Check scan: sphere fit of a sweep at an orientation not used")
