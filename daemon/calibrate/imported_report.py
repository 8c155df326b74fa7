"""The report of ``wristscan calibrate import`` (:func:`build_report`): the result as typed on a
teach pendant, the parameters with their 1-sigma and the jackknife over poses beside them, the
side of the laser plane and how it was decided, every pose's profile and residual, the notes,
and a figure of the per-pose residuals when matplotlib is there."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from wristscan.calib import se3

if TYPE_CHECKING:
    from wristscan.daemon.calibrate.imported import ImportResult
    from wristscan.daemon.io.report import Report

__all__ = ["build_report"]


def _um(v: float) -> str:
    return f"{v * 1e6:.1f}" if math.isfinite(v) else "-"


def build_report(result: ImportResult) -> Report:
    """The report of an imported stop-and-go calibration."""
    from wristscan.daemon.io.report import Report, have_matplotlib
    from wristscan.daemon.io.urpose import ur_pose_text

    d, j, sol = result.dataset, result.joint, result.solution
    rep = Report(
        "Sensor-to-flange calibration (imported stop-and-go data)",
        f"{d.folder} ({len(d.names)} poses, {d.convention}, {d.units})",
    )
    pose = se3.matrix_to_pose(j.sensor2flange)
    rep.section("Result")
    rep.text(
        f"sensor2flange (joint refinement): {ur_pose_text(pose)}  (metres, rotation vector in "
        f"radians; x {pose[0] * 1e3:.3f} mm, y {pose[1] * 1e3:.3f} mm, z {pose[2] * 1e3:.3f} mm)."
        f" Residual RMS {_um(j.rms)} um over {j.n_points} points; condition number "
        f"{j.condition:.1f}; ball centre {np.round(j.ball_centre_base * 1e3, 3).tolist()} mm "
        f"(radius {result.ball_radius_m * 1e3:.3f} mm); {result.duration_s:.1f} s."
    )
    point_sigma = float(getattr(j, "point_sigma_m", math.nan))
    if math.isfinite(point_sigma):
        rep.text(f"Predicted 1-sigma error of a measured point: up to {_um(point_sigma)} um.")
    rep.section("Parameters and uncertainty")
    rep.table(
        ["parameter", "closed form", "joint", "1 sigma", "jackknife 1 sigma"],
        _param_rows(result),
        "Sensor origin in the flange frame and rotation uncertainty about the sensor axes. "
        "1 sigma from the joint solution's covariance; the jackknife leaves out each pose in "
        "turn (its spread should agree with the 1 sigma within about 1.5x).",
    )
    _side_section(rep, result)
    _pose_section(rep, result)
    if result.notes:
        rep.section("Notes")
        rep.text("\n".join(f"- {n}" for n in result.notes), preformatted=True)
    if have_matplotlib():
        _figure(rep, result)
    else:
        rep.text("Figures need matplotlib: pip install 'wristscan[plot]'.")
    del sol
    return rep


def _param_rows(result: ImportResult) -> list[list[str]]:
    j = result.joint
    start = result.solution.start.sensor2flange
    jk = result.jackknife
    rows: list[list[str]] = []
    for i, a in enumerate("xyz"):
        rows.append(
            [
                f"{a} (mm)",
                f"{start[i, 3] * 1e3:.4f}",
                f"{j.sensor2flange[i, 3] * 1e3:.4f}",
                f"{j.sigma_translation_m[i] * 1e3:.4f}",
                "-" if jk is None else f"{jk.sigma_translation_m[i] * 1e3:.4f}",
            ]
        )
    for i, a in enumerate("XYZ"):
        rows.append(
            [
                f"rotation about sensor {a} (deg)",
                "",
                "0",
                f"{math.degrees(j.sigma_rotation_rad[i]):.5f}",
                "-" if jk is None else f"{math.degrees(jk.sigma_rotation_rad[i]):.5f}",
            ]
        )
    return rows


def _side_section(rep: Report, result: ImportResult) -> None:
    sol = result.solution
    rep.section("Side of the laser plane")
    side = {1: "+X (ahead of the laser plane)", -1: "-X (behind it)", 0: "mixed"}[sol.side]
    rep.text(
        "One profile cannot tell on which side of the laser plane the ball centre lies; the "
        "closed form starts from both and the joint refinement runs from each. The ball centre "
        f"is on the sensor's {side} side."
    )
    rep.table(
        ["start side", "closed-form RMS (um)", "refined RMS (um)", "points on the ball", "note"],
        [
            [
                f"{t.side:+d}",
                _um(t.start.centre_rms_m),
                _um(t.rms_m),
                f"{t.inlier_fraction:.1%}",
                t.error,
            ]
            for t in sol.trials
        ],
    )


def _pose_section(rep: Report, result: ImportResult) -> None:
    d, sol, jk = result.dataset, result.solution, result.jackknife
    rows = []
    for k, name in enumerate(d.names):
        c = sol.circles[k]
        rows.append(
            [
                name,
                str(c.n_points),
                str(int(np.count_nonzero(sol.joint.inliers[k]))),
                f"{c.radius * 1e3:.3f}",
                _um(c.rms),
                _um(float(sol.joint.per_sweep_rms[k])),
                f"{int(sol.sides[k]):+d}",
                "-" if jk is None else _um(float(jk.translation_dev_m[k])),
            ]
        )
    rep.section("Poses")
    rep.table(
        [
            "pose",
            "points",
            "used",
            "arc radius (mm)",
            "circle RMS (um)",
            "residual RMS (um)",
            "side",
            "left out: origin moves (um)",
        ],
        rows,
        "Per pose: the profile's points, those the solution used, the ball's arc in the laser "
        "plane, the residual of the joint solution, and how far the sensor origin moves when "
        "the pose is left out.",
    )


def _figure(rep: Report, result: ImportResult) -> None:
    from wristscan.daemon.io.report import new_figure

    sol = result.solution
    fig, ax = new_figure(figsize=(7.0, 3.2))
    x = np.arange(len(result.dataset.names))
    ax.bar(x, np.nan_to_num(sol.joint.per_sweep_rms) * 1e6, color="tab:blue")
    ax.set_xticks(x, result.dataset.names, rotation=60, fontsize=7)
    ax.set_ylabel("residual RMS (um)")
    rep.figure(fig, "Residual RMS of each pose's profile (joint solution)", "pose-residuals")
