"""``wristscan calibrate kinematics``: the arm's kinematic errors identified with the tooling ball
(procedure in :mod:`wristscan.daemon.calibrate.kinematics`). It moves the robot: it needs
``[robot] motion_enabled`` and ``--yes`` (or a yes at the prompt on a terminal). Exit codes as
for every ``calibrate`` procedure: 0 done, 1 aborted or failed (nothing written), 2 usage or
configuration error (nothing moved).

The ``calibrate`` group (:mod:`.calibrate`) adds this command; it is kept apart for size.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from wristscan.daemon.cli._calibrate_table import ConfigOpt, _run, _write
from wristscan.daemon.cli._common import (
    EXIT_USAGE,
    QuietOpt,
    YesOpt,
    check_number,
    check_out_folder,
    confirm_motion,
    fail,
    load_config_or_exit,
    progress_printer,
)

__all__ = ["kinematics"]

_OutOpt = Annotated[
    Path | None,
    typer.Option(
        "--out",
        "-o",
        help="Kinematics file (default: [robot] kinematics_file, else ./kinematics.json).",
    ),
]
_NominalOpt = Annotated[
    str | None,
    typer.Option(
        "--nominal",
        help='Starting sensor2flange "p[x, y, z, rx, ry, rz]" (m, rad). Default: the '
        "calibration in force, or the simulated sensor's drawing value.",
    ),
]


def kinematics(
    config: ConfigOpt,
    yes: YesOpt = False,
    out: _OutOpt = None,
    nominal: _NominalOpt = None,
    speed_mm_s: Annotated[float, typer.Option("--speed-mm-s", help="Sweep speed.")] = 40.0,
    grid: Annotated[int, typer.Option("--grid", help="Field-of-view grid (n x n).")] = 3,
    orientations: Annotated[
        int, typer.Option("--orientations", help="Tilted orientations around the ball.")
    ] = 12,
    tilt_deg: Annotated[float, typer.Option("--tilt-deg", help="Tilt of the orientations.")] = 40.0,
    lateral_places: Annotated[
        int, typer.Option("--lateral-places", help="Ball places along the laser line (1 or 2).")
    ] = 2,
    one_way: Annotated[bool, typer.Option("--one-way", help="Sweep each place once.")] = False,
    quiet: QuietOpt = False,
) -> None:
    """Identify the arm's kinematic errors (DH deviations) with the tooling ball.

    Jog the robot so that the laser line crosses the ball, as for calibrate sensor. The ball is
    swept from many orientations; the DH deviations are estimated jointly with sensor2flange and
    the ball centre, and written as a kinematics file: name it in [robot] kinematics_file and run
    calibrate sensor again (its sensor2flange goes with these kinematics).
    """
    from wristscan.calib import se3
    from wristscan.daemon.calibrate import kinematics as ck
    from wristscan.daemon.calibrate.sensor import default_nominal
    from wristscan.daemon.io.kinematics_file import write_kinematics
    from wristscan.daemon.io.urpose import parse_ur_pose

    check_number("--speed-mm-s", speed_mm_s, gt=0, le=250)
    check_number("--grid", grid, ge=2, le=6)
    check_number("--orientations", orientations, ge=4, le=30)
    check_number("--tilt-deg", tilt_deg, ge=20, le=70)
    check_number("--lateral-places", lateral_places, ge=1, le=2)
    cfg = load_config_or_exit(config)
    target = out or (
        Path(cfg.robot.kinematics_file) if cfg.robot.kinematics_file else Path("kinematics.json")
    )
    check_out_folder(target, "--out")
    if nominal is not None:
        try:
            x0 = se3.pose_to_matrix(parse_ur_pose(nominal))
        except ValueError as exc:
            fail(f"--nominal: {exc}", EXIT_USAGE)
    else:
        found = default_nominal(cfg)
        if found is None:
            fail('give --nominal "p[x, y, z, rx, ry, rz]" (m, rad) to plan the motions', EXIT_USAGE)
        x0 = found[0]
    try:
        settings = ck.settings_for_kinematics(
            cfg, sweep_speed_m_s=speed_mm_s * 1e-3, fov_grid=grid, n_orientations=orientations,
            tilt_deg=tilt_deg, min_tilt_deg=min(30.0, tilt_deg), lateral_places=lateral_places,
            bidirectional=not one_way,
        )  # fmt: skip
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    confirm_motion(cfg, yes, "calibrate kinematics")
    progress = progress_printer(quiet)
    result = _run(lambda: ck.run(cfg, settings, nominal=x0, out=None, progress=progress))
    path = _write(lambda: write_kinematics(target, ck.kinematics_file_of(cfg, result)))
    for line in result.summary()[:3]:
        typer.echo(line)
    typer.echo(f"kinematics written to {path}; name it in [robot] kinematics_file")
