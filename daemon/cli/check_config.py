"""``wristscan check-config``: validate a config file (or the embedded default) and summarise it.

Beyond what loading checks, it finds what ``wristscan run`` would refuse that is known without
the devices: a ``table`` or ``part`` frame without the table calibration, calibration files that
are missing, directories, unreadable, corrupt, of another kind or made for another robot model
or sensor, and ``[ros2] enabled`` without its extra. (The robot's serial number needs the
controller: ``run`` compares it at start.)
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer

from wristscan.daemon.cli._common import EXIT_USAGE, fail

if TYPE_CHECKING:
    from wristscan.daemon.config import Config

__all__ = ["check_config", "register", "service_problems"]


def _calibration_problem(cfg: Config, key: str, path: Path) -> str | None:
    """Why ``run`` could not use the calibration file ``path`` (``[calibration] key``)."""
    from wristscan.daemon.io.calibfile import CalibrationFileError, identities, read_calibration

    sensor = key == "file"
    verb = "wristscan calibrate sensor" if sensor else "wristscan calibrate table"
    where = f"{cfg.source}: calibration.{key}"
    if path.is_dir():
        return f"{where}: {path} is a directory, not a calibration file"
    if not path.exists():
        return f"{where}: {path} does not exist ({verb} writes it)"
    robot, sensor_id = (None, None)
    if cfg.calibration.check_identity:
        robot, sensor_id = identities(cfg, ask_controller=False)
    try:
        read_calibration(
            path, robot, sensor_id if sensor else None, kind="sensor2flange" if sensor else "table"
        )
    except CalibrationFileError as exc:
        return f"{where}: {exc}"
    return None


def service_problems(cfg: Config, files: bool = True) -> list[str]:
    """What ``wristscan run`` would refuse in ``cfg`` that is known without the devices, one
    line each (empty: nothing); ``files`` False leaves out the calibration files and the
    ``[zenoh]`` checks that only hold on the cell PC (listen hosts, the zenoh security file)."""
    problems = []
    c, frame = cfg.calibration, cfg.pipeline.frame
    if frame != "base" and c.table_file is None:
        problems.append(
            f'{cfg.source}: calibration.table_file: pipeline.frame = "{frame}" needs the table '
            "calibration (wristscan calibrate table writes it)"
        )
    named = [("file", c.file)] + ([("table_file", c.table_file)] if frame != "base" else [])
    for key, path in named if files else []:
        problem = None if path is None else _calibration_problem(cfg, key, path)
        if problem is not None:
            problems.append(problem)
    if files:  # this machine's: the listen hosts must be its own, the zenoh file readable here
        problems += [f"{cfg.source}: {line}" for line in cfg.zenoh.problems()]
    if files and cfg.robot.kinematics_file is not None:
        from wristscan.daemon.io.kinematics_file import KinematicsFileError, read_kinematics

        try:
            read_kinematics(cfg.robot.kinematics_file, cfg.robot.model)
        except KinematicsFileError as exc:
            problems.append(f"{cfg.source}: robot.kinematics_file: {exc}")
    if cfg.ros2.enabled:
        try:
            import wristscan.daemon.cloud.ros2pub  # noqa: F401
        except ImportError as exc:
            problems.append(
                f"{cfg.source}: ros2.enabled: needs the extra: pip install 'wristscan[ros2]' "
                f"({exc})"
            )
    return problems


def _refuse(source: str, problems: list[str]) -> NoReturn:
    for line in problems:
        typer.echo(line, err=True)
    n = len(problems)
    typer.echo(f"{source}: {n} problem{'s' if n != 1 else ''}, not usable", err=True)
    raise typer.Exit(EXIT_USAGE)


def check_config(
    file: Annotated[
        Path | None, typer.Argument(help="The TOML config file to check.", show_default=False)
    ] = None,
    default: Annotated[
        bool, typer.Option("--default", help="Check the embedded default (the simulated cell).")
    ] = False,
    no_files: Annotated[
        bool,
        typer.Option(
            "--no-files",
            help="Leave out the calibration files (a configuration for another machine).",
        ),
    ] = False,
) -> None:
    """Validate a config file: print a summary (exit 0) or every problem, one per line (exit 2).

    Also checks what wristscan run needs that can be known without the devices: the
    calibration files (present, readable, for this robot model and sensor) and the table
    calibration of a table or part frame (--no-files: not the files)."""
    from wristscan.daemon.config import ConfigError, load_config, load_default

    if (file is None) == (not default):
        fail("give a config FILE or --default (one of the two)", EXIT_USAGE)
    try:
        config = load_default() if file is None else load_config(file)
    except ConfigError as exc:
        _refuse(exc.source, exc.problems)
    problems = service_problems(config, files=not no_files)
    if problems:
        _refuse(config.source, problems)
    typer.echo(f"{config.source}: OK (schema_version {config.schema_version})")
    for line in config.summary():
        typer.echo(f"  {line}")
    if config.calibration.file is None:
        typer.echo("  note: no calibration file: wristscan run needs --uncalibrated")


def register(app: typer.Typer) -> None:
    app.command("check-config")(check_config)
