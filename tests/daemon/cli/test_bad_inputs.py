"""Bad input, as an operator types it: every case ends with exit code 2, one line naming the
option or the configuration field, and no traceback; and nothing is opened first.

CLI numbers: each verb checks its number options (finite, in range) before it reads its
configuration, so the configuration given here (a file that does not exist) is never reached,
and no device is. Configurations: ``check-config`` on the simulated cell's configuration with
one thing wrong, including what only ``wristscan run`` used to find (calibration files, the
table calibration of a part frame). Everything runs in this process: no cell, no network.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from wristscan.daemon.cli.app import app
from wristscan.daemon.io.calibfile import (
    Calibration,
    Residuals,
    RobotIdentity,
    SensorIdentity,
    write_calibration,
)

REPO = Path(__file__).resolve().parents[3]
SIM_TEXT = (REPO / "config" / "sim.toml").read_text()
NO_CONFIG = "/nonexistent/cell.toml"
"""Never read: the number checks come first."""

C = ["--config", NO_CONFIG]
PLAN = ["scan", "plan", "--bbox-mm", "-10", "-10", "0", "10", "10", "20"]
PLAN_OK = [*PLAN, "--fov-mm", "50", "--standoff-mm", "100"]
EDGE = ["teach", "edge", *C, "--edge-model", "/nonexistent/edge.toml"]
REPLAY = ["teach", "replay", "--path", "/nonexistent/path.json", "--tool", "p[0,0,0.1,0,0,0]"]
IMPORT = ["calibrate", "import", "/nonexistent", "--ball-radius", "12.7mm", "--poses", "ur-rotvec"]

# (argv, the option the one-line error must name)
CLI_CASES: list[tuple[list[str], str]] = [
    (["measure", *C, "--dwell-s", "nan"], "--dwell-s"),
    (["measure", *C, "--dwell-s", "0"], "--dwell-s"),
    (["measure", *C, "--dwell-s", "inf"], "--dwell-s"),
    (["measure", *C, "--sweep-mm", "-1"], "--sweep-mm"),
    (["measure", *C, "--sweep-mm", "nan"], "--sweep-mm"),
    (["measure", *C, "--standoff-mm", "nan"], "--standoff-mm"),
    (["teach", "plane", *C, "--spacing-mm", "nan"], "--spacing-mm"),
    (["teach", "plane", *C, "--spots", "5"], "--spots"),
    (["teach", "plane", *C, "--dwell-s", "-0.1"], "--dwell-s"),
    (["teach", "plane", *C, "--speed-mm-s", "inf"], "--speed-mm-s"),
    (["teach", "plane", *C, "--max-form-error-mm", "0"], "--max-form-error-mm"),
    (["teach", "edge-model", *C, "--kind", "step", "--dwell-s", "-1"], "--dwell-s"),
    (["teach", "edge-model", *C, "--kind", "step", "--dwell-s", "nan"], "--dwell-s"),
    ([*EDGE, "--resolution-mm", "nan"], "--resolution-mm"),
    ([*EDGE, "--length-mm", "-5"], "--length-mm"),
    ([*EDGE, "--step-mm", "25"], "--step-mm"),
    ([*EDGE, "--standoff-mm", "nan"], "--standoff-mm"),
    ([*EDGE, "--speed-mm-s", "0"], "--speed-mm-s"),
    ([*EDGE, "--direction", "2"], "--direction"),
    ([*REPLAY, "--offset-mm", "nan"], "--offset-mm"),
    ([*REPLAY, "--lead-deg", "90"], "--lead-deg"),
    ([*REPLAY, "--tilt-deg", "nan"], "--tilt-deg"),
    ([*REPLAY, "--speed-mm-s", "-1"], "--speed-mm-s"),
    ([*REPLAY, "--accel-m-s2", "nan"], "--accel-m-s2"),
    ([*REPLAY, "--blend-mm", "-1"], "--blend-mm"),
    ([*REPLAY, "--tolerance-mm", "inf"], "--tolerance-mm"),
    ([*REPLAY, "--approach-mm", "nan"], "--approach-mm"),
    ([*REPLAY, "--timeout-s", "0"], "--timeout-s"),
    (["scan", "--plan", "p.toml", *C, "--voxel-mm", "nan"], "--voxel-mm"),
    (["scan", "--plan", "p.toml", *C, "--voxel-mm", "-1"], "--voxel-mm"),
    (["scan", "--plan", "p.toml", *C, "--max-correction-mm", "inf"], "--max-correction-mm"),
    (["scan", "--plan", "p.toml", *C, "--max-correction-deg", "nan"], "--max-correction-deg"),
    (["scan", "--plan", "p.toml", *C, "--joints-deg", *"0 -90 90 0 0 nan".split()], "--joints-deg"),
    (
        [
            "scan",
            "plan",
            "--bbox-mm",
            *"0 0 0 1 1 nan".split(),
            "--fov-mm",
            "50",
            "--standoff-mm",
            "100",
        ],
        "--bbox-mm",
    ),
    ([*PLAN, "--fov-mm", "0", "--standoff-mm", "100"], "--fov-mm"),
    ([*PLAN_OK, "--overlap", "0.95"], "--overlap"),
    ([*PLAN_OK, "--overlap", "nan"], "--overlap"),
    ([*PLAN, "--fov-mm", "50", "--standoff-mm", "nan"], "--standoff-mm"),
    ([*PLAN_OK, "--table-deg", "0", "--table-deg", "nan"], "--table-deg"),
    ([*PLAN_OK, "--tilt-deg", "95"], "--tilt-deg"),
    ([*PLAN_OK, "--yaw-deg", "inf"], "--yaw-deg"),
    ([*PLAN_OK, "--depth-range-mm", "50", "nan"], "--depth-range-mm"),
    ([*PLAN_OK, "--speed-mm-s", "nan"], "--speed-mm-s"),
    ([*PLAN_OK, "--travel-mm-s", "0"], "--travel-mm-s"),
    ([*PLAN_OK, "--retract-mm", "-1"], "--retract-mm"),
    (["calibrate", "sensor", *C, "--speed-mm-s", "nan"], "--speed-mm-s"),
    (["calibrate", "sensor", *C, "--ball-radius-mm", "0.5"], "--ball-radius-mm"),
    (["calibrate", "sensor", *C, "--fov-width-mm", "nan"], "--fov-width-mm"),
    (["calibrate", "sensor", *C, "--depth-min-mm", "-1"], "--depth-min-mm"),
    (["calibrate", "sensor", *C, "--depth-max-mm", "inf"], "--depth-max-mm"),
    (["calibrate", "sensor", *C, "--grid", "6"], "--grid"),
    (["calibrate", "sensor", *C, "--orientations", "1"], "--orientations"),
    (["calibrate", "sensor", *C, "--tilt-deg", "30"], "--tilt-deg"),
    (["calibrate", "sensor", *C, "--tilt-deg", "nan"], "--tilt-deg"),
    (["calibrate", "sensor", *C, "--lateral-places", "3"], "--lateral-places"),
    (["calibrate", "table", *C, "--angles", "5"], "--angles"),
    (["calibrate", "table", *C, "--span-deg", "nan"], "--span-deg"),
    (["calibrate", "table", *C, "--ball-radius-mm", "nan"], "--ball-radius-mm"),
    (["calibrate", "table", *C, "--standoff-mm", "0"], "--standoff-mm"),
    (["calibrate", "table", *C, "--speed-mm-s", "inf"], "--speed-mm-s"),
    (["calibrate", "table", *C, "--ball-height-mm", "nan"], "--ball-height-mm"),
    (["calibrate", "table", *C, "--ball-m", "0.4,0.1,nan"], "--ball-m"),
    (["calibrate", "latency", *C, "--speeds-mm-s", "25,nan"], "--speeds-mm-s"),
    (["calibrate", "latency", *C, "--repeats", "0"], "--repeats"),
    (["calibrate", "latency", *C, "--standoff-mm", "nan"], "--standoff-mm"),
    (["calibrate", "latency", *C, "--ball-radius-mm", "0"], "--ball-radius-mm"),
    ([*IMPORT, "--robot-sigma-mm", "nan"], "--robot-sigma-mm"),
    (["simulate", "tcp", "--sigma", "nan"], "--sigma"),
    (["simulate", "tcp", "--trials", "1"], "--trials"),
    (["simulate", "tcp", "--poses", "2"], "--poses"),
    (["simulate", "tcp", "--seed", "-1"], "--seed"),
    (["simulate", "tcp", "--alpha", "10:nan:5"], "--alpha"),
    (["sim", *C, "--duration", "nan"], "--duration"),
    (["sim", *C, "--duration", "-1"], "--duration"),
    (["calibrate", "kinematics", *C, "--speed-mm-s", "nan"], "--speed-mm-s"),
    (["calibrate", "kinematics", *C, "--grid", "1"], "--grid"),
    (["calibrate", "kinematics", *C, "--orientations", "3"], "--orientations"),
    (["calibrate", "kinematics", *C, "--tilt-deg", "inf"], "--tilt-deg"),
    (["calibrate", "kinematics", *C, "--lateral-places", "3"], "--lateral-places"),
    (["record", "-o", "x.ply", "-d", "nan"], "--duration"),
    (["record", "-o", "x.ply", "-d", "-1"], "--duration"),
    (["record", "-o", "x.ply", "-n", "0"], "--points"),
    (["record", "-o", "x.ply", "--timeout", "nan"], "--timeout"),
    (["view", "--seconds", "nan"], "--seconds"),
    (["view", "--stride", "0"], "--stride"),
    (["view", "--timeout", "inf"], "--timeout"),
    (["status", "--timeout", "nan"], "--timeout"),
    (["status", "--timeout", "0"], "--timeout"),
    (["cells", "--timeout", "nan"], "--timeout"),
    (["scans", "list", "--timeout", "0"], "--timeout"),
    (["scans", "fetch", "job", "--timeout", "nan"], "--timeout"),
]


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    assert "Traceback" not in stderr
    return lines[0]


@pytest.mark.parametrize(
    ("argv", "option"), CLI_CASES, ids=[" ".join(a[:2]) + " " + o for a, o in CLI_CASES]
)
def test_a_bad_number_is_refused_naming_its_option(argv: list[str], option: str) -> None:
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit)  # no exception escaped
    line = _one_line(result.stderr)
    assert re.match(rf"error: (bad )?{re.escape(option)}\b", line), line
    assert NO_CONFIG not in line  # the configuration was never read


# ------------------------------------------------------------------------------ configurations


def _section_span(lines: list[str], section: str) -> tuple[int, int]:
    start = next(i for i, line in enumerate(lines) if line.split("#")[0].strip() == f"[{section}]")
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("[")), len(lines))
    return start, end


def edit(text: str, section: str, key: str, value: str) -> str:
    """``key = value`` (raw TOML) in ``[section]``, replacing the key or its commented line."""
    lines = text.splitlines()
    start, end = _section_span(lines, section)
    pattern = re.compile(rf"^\s*#?\s*{re.escape(key)}\s*=")
    found = [i for i in range(start + 1, end) if pattern.match(lines[i])]
    if found:
        lines[found[0]] = f"{key} = {value}"
    else:
        lines.insert(start + 1, f"{key} = {value}")
    return "\n".join(lines) + "\n"


def _calibration(folder: Path, name: str, model: str = "UR5e", kind: str = "sensor2flange") -> None:
    write_calibration(
        folder / name,
        Calibration(
            kind=kind,  # type: ignore[arg-type]
            transform=np.eye(4),
            robot=RobotIdentity(model, "20235500001"),
            sensor=SensorIdentity("lpf1-udp", "1"),
            method="test",
            residuals=Residuals(rms_m=0.0),
            parameters={"encoder_offset_rad": 0.0} if kind == "table" else {},
        ),
    )


def _no_files(folder: Path) -> None:
    pass


Setup = Callable[[Path], None]

# (edits (section, key, raw value), files to create, the field the one line must name)
CONFIG_CASES: list[tuple[list[tuple[str, str, str]], Setup, str]] = [
    ([("robot", "max_speed_m_s", "nan")], _no_files, "robot.max_speed_m_s"),
    ([("robot", "max_speed_m_s", "inf")], _no_files, "robot.max_speed_m_s"),
    ([("robot", "max_speed_m_s", "-1")], _no_files, "robot.max_speed_m_s"),
    ([("robot", "max_accel_m_s2", "0")], _no_files, "robot.max_accel_m_s2"),
    ([("robot", "frequency_hz", "nan")], _no_files, "robot.frequency_hz"),
    ([("robot", "workspace_min_m", "[-0.9, -0.9, nan]")], _no_files, "robot.workspace_min_m"),
    ([("robot", "workspace_max_m", "[0.9, 0.9]")], _no_files, "robot.workspace_max_m"),
    ([("robot", "host", '"not a host!"')], _no_files, "robot.host"),
    ([("robot", "model", '"UR6e"')], _no_files, "robot.model"),
    ([("sensor", "latency_s", "nan")], _no_files, "sensor.latency_s"),
    ([("sensor", "clock_tick_s", "0")], _no_files, "sensor.clock_tick_s"),
    ([("sensor.options", "port", "70000")], _no_files, "sensor.options.port"),
    ([("sync", "max_gap_s", "-inf")], _no_files, "sync.max_gap_s"),
    ([("sync", "max_wait_s", "nan")], _no_files, "sync.max_wait_s"),
    ([("pipeline", "batch_s", "0")], _no_files, "pipeline.batch_s"),
    ([("pipeline", "frame", '"part"')], _no_files, "calibration.table_file"),
    ([("pipeline", "frame", '"table"')], _no_files, "calibration.table_file"),
    ([("zenoh", "status_period_s", "nan")], _no_files, "zenoh.status_period_s"),
    ([("calibration", "file", '"missing.json"')], _no_files, "calibration.file"),
    (
        [("calibration", "file", '"folder.json"')],
        lambda d: (d / "folder.json").mkdir(),
        "calibration.file",
    ),
    (
        [("calibration", "file", '"corrupt.json"')],
        lambda d: (d / "corrupt.json").write_text('{"format": '),
        "calibration.file",
    ),
    (
        [("calibration", "file", '"ur10e.json"')],
        lambda d: _calibration(d, "ur10e.json", model="UR10e"),
        "calibration.file",
    ),
    (
        [("calibration", "file", '"table.json"')],
        lambda d: _calibration(d, "table.json", kind="table"),
        "calibration.file",
    ),
    (
        [("pipeline", "frame", '"part"'), ("calibration", "table_file", '"none.json"')],
        _no_files,
        "calibration.table_file",
    ),
    (
        [("pipeline", "frame", '"part"'), ("calibration", "table_file", '"s2f.json"')],
        lambda d: _calibration(d, "s2f.json"),
        "calibration.table_file",
    ),
    ([("calibration", "file", '""')], _no_files, "calibration.file"),
    ([("table", "port", "0")], _no_files, "table.port"),
    ([("sim.sensor", "rate_hz", "nan")], _no_files, "sim.sensor.rate_hz"),
    ([("sim.sensor", "noise_m", "-1e-6")], _no_files, "sim.sensor.noise_m"),
    (
        [("sim.controller", "initial_q_deg", "[0.0, -90.0, 90.0, nan, -90.0, 0.0]")],
        _no_files,
        "sim.controller.initial_q_deg",
    ),
    ([("sim.scene", "ball_radius_m", "inf")], _no_files, "sim.scene.ball_radius_m"),
    (
        [("sim.truth", "sensor2flange_pose", "[0.06, 0.01, nan, 0.0, 0.0, 0.0]")],
        _no_files,
        "sim.truth.sensor2flange_pose",
    ),
    ([("cell", "name", '"bad name"')], _no_files, "cell.name"),
    ([("robot", "kinematics_file", '"missing.json"')], _no_files, "robot.kinematics_file"),
]


@pytest.mark.parametrize(
    ("edits", "setup", "field"),
    CONFIG_CASES,
    ids=[f"{c[2]}-{i}" for i, c in enumerate(CONFIG_CASES)],
)
def test_a_bad_configuration_is_refused_by_check_config(
    tmp_path: Path, edits: list[tuple[str, str, str]], setup: Setup, field: str
) -> None:
    text = SIM_TEXT
    for section, key, value in edits:
        text = edit(text, section, key, value)
    path = tmp_path / "cell.toml"
    path.write_text(text)
    setup(tmp_path)
    result = CliRunner().invoke(app, ["check-config", str(path)])
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit)
    assert "Traceback" not in result.output
    lines = result.stderr.splitlines()
    assert lines[-1] == f"{path}: 1 problem, not usable", result.stderr
    assert lines[:-1] and len(lines) == 2, result.stderr
    assert re.match(rf"{re.escape(f'{path}: {field}')}(\[\d+\])?: ", lines[0]), lines[0]


# ------------------------------------------------------------------------------ completeness

ADOPTED = {
    "teach",
    "scan",
    "calibrate",
    "_calibrate_table",
    "simulate",
    "sim",
    "record",
    "view",
    "status",
    "cells",
    "scans",
}
"""Verb modules that check their numbers with ``check_number`` (at least these; record, demo,
status and view join when they call it, and their options then need cases here)."""


def _number_options(root: object) -> tuple[set[tuple[str, str]], set[str]]:
    """``(command path, option)`` of every option that takes numbers, of the commands whose
    module calls ``check_number``; and the names of those modules."""
    import inspect
    import sys
    import typing

    found: set[tuple[str, str]] = set()
    adopters: set[str] = set()

    def takes_numbers(annotation: object) -> bool:
        args = typing.get_args(annotation)
        return annotation in (int, float) or (bool(args) and all(a in (int, float) for a in args))

    def adopted(command: object) -> bool:
        callback = getattr(command, "callback", None)
        if callback is None:
            return False
        module = inspect.unwrap(callback).__module__
        if "check_number(" not in inspect.getsource(sys.modules[module]):
            return False
        adopters.add(module.rpartition(".")[2])
        return True

    def walk(command: object, path: list[str]) -> None:
        for p in getattr(command, "params", []) if adopted(command) else []:
            if p.param_type_name == "option" and not p.is_flag and not p.count:
                if takes_numbers(p.type_descriptor.annotation):
                    found.add((" ".join(path), p.opts[0]))
        for name, sub in (getattr(command, "commands", None) or {}).items():
            walk(sub, [*path, name])

    walk(root, [])
    return found, adopters


def _command_path(root: object, argv: list[str]) -> str:
    command = root
    path = []
    for word in argv:
        sub = (getattr(command, "commands", None) or {}).get(word)
        if sub is None:
            break
        path.append(word)
        command = sub
    return " ".join(path)


def test_every_number_option_has_a_bad_input_case() -> None:
    import typer

    root = typer.main.get_command(app)
    covered = {(_command_path(root, argv), option) for argv, option in CLI_CASES}
    options, adopters = _number_options(root)
    assert ADOPTED <= adopters
    assert options - covered == set()


def test_check_config_passes_good_calibration_files(tmp_path: Path) -> None:
    """The same checks pass files that fit (the sensor's and the table's, for a part frame)."""
    _calibration(tmp_path, "s2f.json")
    _calibration(tmp_path, "table.json", kind="table")
    text = edit(SIM_TEXT, "pipeline", "frame", '"part"')
    text = edit(text, "calibration", "file", '"s2f.json"')
    path = tmp_path / "cell.toml"
    path.write_text(edit(text, "calibration", "table_file", '"table.json"'))
    result = CliRunner().invoke(app, ["check-config", str(path)])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(f"{path}: OK")
    assert f"calibration {tmp_path / 's2f.json'}" in result.stdout
