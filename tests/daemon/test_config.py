"""The daemon's TOML config: examples validate, mistakes give one readable line each."""

from __future__ import annotations

import math
import re
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from wristscan.calib import se3
from wristscan.daemon.cli.app import main
from wristscan.daemon.config import (
    Config,
    ConfigError,
    GocatorSensorConfig,
    Lpf1SerialSensorConfig,
    Lpf1UdpSensorConfig,
    Rf627SensorConfig,
    ScipSensorConfig,
    load_config,
    load_default,
    parse_config,
)

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "config").glob("*.toml"))
SIM_TEXT = (ROOT / "config" / "sim.toml").read_text()


def _section_span(lines: list[str], section: str) -> tuple[int, int]:
    """Index of the ``[section]`` header and of the first line after the section."""
    header = [i for i, line in enumerate(lines) if line.split("#")[0].strip() == f"[{section}]"]
    assert len(header) == 1, f"[{section}] not found once"
    start = header[0]
    end = next(
        (i for i in range(start + 1, len(lines)) if lines[i].lstrip().startswith("[")), len(lines)
    )
    return start, end


def edit(text: str, section: str, key: str, value: str | None) -> str:
    """Set ``key = value`` (raw TOML) in ``[section]``, or remove the key when value is None."""
    lines = text.splitlines()
    start, end = _section_span(lines, section)
    pattern = re.compile(rf"^\s*#?\s*{re.escape(key)}\s*=")
    found = [i for i in range(start + 1, end) if pattern.match(lines[i])]
    if value is None:
        assert found, f"{section}.{key} not in the text"
        del lines[found[0]]
    elif found:
        lines[found[0]] = f"{key} = {value}"
    else:
        lines.insert(start + 1, f"{key} = {value}")
    return "\n".join(lines) + "\n"


def drop_section(text: str, section: str) -> str:
    lines = text.splitlines()
    start, end = _section_span(lines, section)
    return "\n".join(lines[:start] + lines[end:]) + "\n"


def problems_of(tmp_path: Path, text: str) -> tuple[str, list[str]]:
    path = tmp_path / "cell.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert isinstance(info.value, ValueError)
    assert str(info.value) == "\n".join(info.value.problems)
    return str(path), info.value.problems


# ----------------------------------------------------------------------------------------------
# Valid files


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_every_example_validates(path: Path) -> None:
    cfg = load_config(path)
    assert cfg.schema_version == 1
    assert cfg.source == str(path)
    assert cfg.zenoh.prefix
    assert cfg.summary()[0].split() == ["cell", cfg.cell.name]


def test_the_three_example_cells_exist() -> None:
    assert {p.name for p in EXAMPLES} >= {
        "sim.toml",
        "ur5e-rf627.toml",
        "ur10e-lpf1-serial-table.toml",
    }


def test_embedded_default_is_a_byte_copy_of_config_sim_toml() -> None:
    packaged = resources.files("wristscan.daemon") / "default_sim.toml"
    assert packaged.read_bytes() == (ROOT / "config" / "sim.toml").read_bytes()
    assert (ROOT / "daemon" / "default_sim.toml").read_bytes() == packaged.read_bytes()


def test_default_is_the_simulated_cell() -> None:
    cfg = load_default()
    assert cfg.source == "<default>"
    assert cfg.model_dump() == load_config(ROOT / "config" / "sim.toml").model_dump()
    assert cfg.robot.host == "127.0.0.2" and cfg.robot.model == "UR5e"
    assert isinstance(cfg.sensor, Lpf1UdpSensorConfig)
    assert cfg.sensor.options.port == 50002 and cfg.sensor.time_modulus_ns is None
    assert cfg.table is not None and cfg.table.transport == "tcp" and cfg.table.driver == "modbus"
    assert cfg.zenoh.mode == "peer" and cfg.zenoh.listen == ["tcp/127.0.0.1:7447"]
    assert cfg.zenoh.multicast_scouting is False
    assert cfg.zenoh.prefix == "wristscan/sim"
    assert cfg.pipeline.batch_s == 0.010
    assert cfg.calibration.file is None
    assert cfg.sim is not None
    assert cfg.sim.sensor.n_points == 2048 and cfg.sim.sensor.kind == "lpf1-udp"
    # the sensor 0.1 m from the tooling ball, the laser line across it (issue 22)
    assert cfg.sim.controller.q0_rad == pytest.approx(
        tuple(math.radians(a) for a in (-15.23, -174.02, 58.1, 25.92, -90.0, -15.23))
    )


def test_sim_truth_matches_the_simulator_defaults() -> None:
    from wristscan.drivers.sim.sensors import DEFAULT_SENSOR2FLANGE_POSE

    cfg = load_default()
    assert cfg.sim is not None
    truth = cfg.sim.truth
    assert truth.sensor2flange_pose == pytest.approx(DEFAULT_SENSOR2FLANGE_POSE)
    # Near the paper's TCP (60, 10, 200) mm with a small rotation.
    T = truth.sensor2flange()
    assert np.allclose(T[:3, 3], [0.060, 0.010, 0.200])
    assert 0 < se3.rotation_angle(T[:3, :3]) < np.radians(3)
    # The demo scene's table: axis through (0.45, 0.25, 0) leaning 0.2 degrees about base X.
    expected = se3.make(se3.rot_x(np.radians(0.2)), (0.45, 0.25, 0.0))
    assert np.allclose(truth.table_zero2base(), expected, atol=1e-12)


def test_hardware_examples() -> None:
    rf = load_config(ROOT / "config" / "ur5e-rf627.toml")
    assert isinstance(rf.sensor, Rf627SensorConfig)
    assert rf.robot.model == "UR5e" and rf.robot.host.startswith("192.168.")
    assert rf.table is None and rf.pipeline.frame == "base"
    assert rf.zenoh.prefix == "wristscan/cell-ur5e-rf627"

    serial = load_config(ROOT / "config" / "ur10e-lpf1-serial-table.toml")
    assert serial.robot.model == "UR10e"
    assert isinstance(serial.sensor, Lpf1SerialSensorConfig)
    assert serial.sensor.options.url == "/dev/ttyUSB0" and serial.sensor.options.baudrate == 921600
    t = serial.table
    assert t is not None and t.transport == "rtu" and t.serial_port is not None
    assert t.rad_per_count == pytest.approx(2 * math.pi / 3_600_000)
    assert serial.zenoh.mode == "client" and serial.zenoh.connect


def test_relative_paths_resolve_against_the_config_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = tmp_path / "etc" / "cell"
    folder.mkdir(parents=True)
    text = edit(SIM_TEXT, "calibration", "file", '"calib/../calib/s2f.json"')
    text = edit(text, "calibration", "table_file", '"/var/lib/wristscan/table.json"')
    (folder / "cell.toml").write_text(text)
    monkeypatch.chdir(tmp_path)  # somewhere else than the config's folder
    cfg = load_config("etc/cell/cell.toml")
    assert cfg.calibration.file == folder.resolve() / "calib" / "s2f.json"
    assert cfg.calibration.table_file == Path("/var/lib/wristscan/table.json")


def _scip_text(url: str) -> str:
    """The embedded default read by the SCIP driver at ``url`` (the simulator left as it is)."""
    text = edit(SIM_TEXT, "sensor", "driver", '"scip"')
    text = edit(text, "sensor", "clock_bits", None)
    text = edit(text, "sensor", "clock_tick_s", None)
    text = edit(text, "sensor.options", "bind_host", None)
    text = edit(text, "sensor.options", "port", None)
    return edit(text, "sensor.options", "url", f'"{url}"')


def test_scip_sensor_defaults_to_a_24_bit_millisecond_clock() -> None:
    text = edit(_scip_text("socket://192.168.0.10:10940"), "sim.sensor", "kind", '"scip-tcp"')
    text = edit(text, "sim.sensor", "n_points", "1081")
    cfg = parse_config(text)
    assert isinstance(cfg.sensor, ScipSensorConfig)
    assert cfg.sensor.clock_bits == 24 and cfg.sensor.clock_tick_s == 1e-3
    assert cfg.sensor.time_modulus_ns == 2**24 * 10**6


def test_the_simulated_sensor_must_speak_the_driver() -> None:
    """A daemon reading one protocol beside a simulator speaking another would start and then
    see nothing; a SCIP scan longer than the simulated scanner's ARES failed deep inside it."""
    scip = _scip_text("socket://127.0.0.1:10940")
    with pytest.raises(ConfigError, match=r'sim\.sensor\.kind: "lpf1-udp" is not what .*"scip"'):
        parse_config(scip)
    with pytest.raises(ConfigError, match=r"sim\.sensor\.n_points: a SCIP scan has at most 1440"):
        parse_config(edit(scip, "sim.sensor", "kind", '"scip-tcp"'))
    tcp = edit(edit(scip, "sim.sensor", "kind", '"scip-tcp"'), "sim.sensor", "n_points", "1081")
    assert parse_config(tcp).sim is not None
    with pytest.raises(ConfigError, match=r"sensor\.options\.url: .*serial device"):
        parse_config(edit(tcp, "sim.sensor", "kind", '"scip-serial"'))
    with pytest.raises(ConfigError, match=r'sim\.sensor\.kind: "rf627-udp" is not what'):
        parse_config(edit(SIM_TEXT, "sim.sensor", "kind", '"rf627-udp"'))


def _gocator_text(*options: tuple[str, str]) -> str:
    """The embedded default read by the Gocator driver, with the simulated Gocator."""
    text = edit(SIM_TEXT, "sensor", "driver", '"gocator"')
    text = edit(text, "sensor.options", "bind_host", None)
    text = edit(text, "sensor.options", "port", None)
    text = edit(text, "sensor.options", "host", '"127.0.0.1"')
    for key, value in options:
        text = edit(text, "sensor.options", key, value)
    return edit(text, "sim.sensor", "kind", '"gocator"')


def test_gocator_options_are_checked_and_match_the_simulators_ports() -> None:
    cfg = parse_config(_gocator_text())
    assert isinstance(cfg.sensor, GocatorSensorConfig)
    assert (cfg.sensor.options.control_port, cfg.sensor.options.data_port) == (3190, 3196)
    # the simulated Gocator serves the data and health channels at control_port + 6 and + 4
    with pytest.raises(ConfigError, match=r"sensor\.options\.data_port: the simulated Gocator"):
        parse_config(_gocator_text(("control_port", "4190")))
    ok = _gocator_text(("control_port", "4190"), ("data_port", "4196"), ("health_port", "4194"))
    cfg = parse_config(ok)
    assert isinstance(cfg.sensor, GocatorSensorConfig) and cfg.sensor.options.health_port == 4194
    with pytest.raises(ConfigError, match=r"sensor\.options\.hots"):
        parse_config(_gocator_text(("hots", '"x"')))
    with pytest.raises(ConfigError, match=r"sensor\.options\.control_port"):
        parse_config(_gocator_text(("control_port", "70000")))


def test_the_sim_scip_ares_is_the_simulators() -> None:
    from wristscan.daemon.config.sim import SIM_SCIP_ARES
    from wristscan.drivers.sim.sensor_config import SensorSimConfig

    assert SensorSimConfig(kind="scip-tcp", n_points=1081).scip_ares == SIM_SCIP_ARES


def test_explicit_prefix_and_scale_table() -> None:
    text = edit(SIM_TEXT, "zenoh", "prefix", '"plant/cell-3"')
    text = edit(text, "table", "counts_per_rev", None)
    text = edit(text, "table", "scale_rad_per_count", "1e-6")
    text = edit(text, "table", "invert", "true")
    cfg = parse_config(text)
    assert cfg.zenoh.prefix == "plant/cell-3"
    assert cfg.table is not None and cfg.table.rad_per_count == -1e-6


def test_config_is_immutable() -> None:
    cfg = load_default()
    with pytest.raises(ValueError, match="frozen"):
        cfg.robot.host = "10.0.0.1"


# ----------------------------------------------------------------------------------------------
# Mistakes: one line per problem, naming the file, the field and what is expected

CASES: list[tuple[str, str, str, str, list[str]]] = [
    ("robot", "max_speed_m_s", "-1", "range", ["robot.max_speed_m_s: must be > 0 (got -1)"]),
    (
        "robot",
        "max_joint_speed_rad_s",
        "4.0",
        "upper bound",
        ["robot.max_joint_speed_rad_s: must be <= 3.14159 (got 4.0)"],
    ),
    (
        "robot",
        "motion_enabled",
        "1",
        "bool",
        ["robot.motion_enabled: must be true or false (got 1)"],
    ),
    (
        "robot",
        "frequency_hz",
        '"500"',
        "number",
        ['robot.frequency_hz: must be a number (got "500")'],
    ),
    (
        "sensor.options",
        "port",
        '"50002"',
        "integer",
        ['sensor.options.port: must be an integer (got "50002")'],
    ),
    (
        "sensor.options",
        "port",
        "70000",
        "port",
        ["sensor.options.port: must be <= 65535 (got 70000)"],
    ),
    (
        "sim.scene",
        "ball_radius_m",
        "nan",
        "nan",
        ["sim.scene.ball_radius_m: must be a finite number (got nan)"],
    ),
    (
        "pipeline",
        "frame",
        '"world"',
        "literal",
        ["pipeline.frame: must be 'base', 'table' or 'part' (got \"world\")"],
    ),
    (
        "robot",
        "workspace_max_m",
        "[0.9, 0.9]",
        "vector length",
        ["robot.workspace_max_m: expected 3 numbers [x, y, z] (got [0.9, 0.9])"],
    ),
    (
        "robot",
        "workspace_max_m",
        "[0.9, -0.95, 1.0]",
        "box",
        [
            "robot.workspace_max_m: must be above workspace_min_m on every axis "
            "(min [-0.9, -0.9, 0.02], max [0.9, -0.95, 1.0])"
        ],
    ),
    (
        "robot",
        "model",
        '"UR6e"',
        "model",
        [
            "robot.model: unknown UR model 'UR6e' (did you mean 'UR16e'?); known: UR3, UR5, UR10, "
            "UR3e, UR5e, UR10e, UR16e, UR20"
        ],
    ),
    (
        "robot",
        "host",
        '"robot controller"',
        "host",
        ['robot.host: not an IP address or host name (got "robot controller")'],
    ),
    (
        "cell",
        "name",
        '"cell/1"',
        "cell name",
        [
            "cell.name: must start with a letter or digit and hold only letters, digits, '_', "
            "'.', '-' (at most 64 characters) (got \"cell/1\")"
        ],
    ),
    (
        "zenoh",
        "listen",
        '["tcp/127.0.0.1"]',
        "endpoint",
        [
            "zenoh.listen: item 0: not a zenoh endpoint 'tcp/127.0.0.1' (expected e.g. "
            "'tcp/127.0.0.1:7447') (got [\"tcp/127.0.0.1\"])"
        ],
    ),
    (
        "zenoh",
        "mode",
        '"client"',
        "client needs connect",
        ['zenoh.connect: mode = "client" needs at least one endpoint to connect to'],
    ),
    (
        "zenoh",
        "prefix",
        '"wristscan/*"',
        "key",
        [
            "zenoh.prefix: not a plain zenoh key: non-empty chunks separated by '/', no wildcards "
            "('*', '$'), '?', '#' or spaces (got \"wristscan/*\")"
        ],
    ),
    (
        "table",
        "scale_rad_per_count",
        "1e-6",
        "scale twice",
        ["table.counts_per_rev: give exactly one of counts_per_rev and scale_rad_per_count"],
    ),
    (
        "sim.controller",
        "initial_q_rad",
        "[0, 0, 0, 0, 0, 0]",
        "q twice",
        ["sim.controller.initial_q_deg: give initial_q_rad or initial_q_deg, not both"],
    ),
    (
        "sim.sensor",
        "dropout_prob",
        "1.5",
        "probability",
        ["sim.sensor.dropout_prob: must be <= 1 (got 1.5)"],
    ),
    (
        "sensor",
        "driver",
        '"lpf1-udpx"',
        "driver",
        [
            "sensor.driver: unknown sensor driver 'lpf1-udpx' (did you mean 'lpf1-udp'?); known: "
            "lpf1-udp, lpf1-tcp, lpf1-serial, rf627-udp, scip, gocator"
        ],
    ),
    (
        "robot",
        "driver",
        '"ur_rtde"',
        "robot driver",
        ["robot.driver: unknown robot driver 'ur_rtde' (did you mean 'ur-rtde'?); known: ur-rtde"],
    ),
    (
        "calibration",
        "file",
        '""',
        "empty path",
        ['calibration.file: must not be empty (leave the key out for none) (got "")'],
    ),
]


@pytest.mark.parametrize(
    ("section", "key", "value", "expected"),
    [(*c[:3], c[4]) for c in CASES],
    ids=[c[3] for c in CASES],
)
def test_a_mistake_gives_one_readable_line(
    tmp_path: Path, section: str, key: str, value: str, expected: list[str]
) -> None:
    path, problems = problems_of(tmp_path, edit(SIM_TEXT, section, key, value))
    assert problems == [f"{path}: {line}" for line in expected]


def test_unknown_key_suggests_the_close_one(tmp_path: Path) -> None:
    text = edit(SIM_TEXT, "robot", "max_speed_m_s", None)
    text = edit(text, "robot", "max_sped_m_s", "0.2")
    path, problems = problems_of(tmp_path, text)
    assert problems == [
        f"{path}: robot.max_sped_m_s: unknown field (did you mean 'max_speed_m_s'?)"
    ]

    text = edit(SIM_TEXT, "sensor.options", "port", None)
    text = edit(text, "sensor.options", "prot", "50002")
    path, problems = problems_of(tmp_path, text)
    assert problems == [f"{path}: sensor.options.prot: unknown field (did you mean 'port'?)"]


def test_unknown_section_and_missing_section(tmp_path: Path) -> None:
    text = SIM_TEXT.replace("\n[robot]\n", "\n[robt]\n")
    path, problems = problems_of(tmp_path, text)
    assert problems == [
        f"{path}: robot: section missing",
        f"{path}: robt: unknown field (did you mean 'robot'?)",
    ]


def test_missing_required_field(tmp_path: Path) -> None:
    path, problems = problems_of(tmp_path, edit(SIM_TEXT, "robot", "host", None))
    assert problems == [f"{path}: robot.host: required, but not given"]


def test_options_are_checked_against_the_chosen_driver(tmp_path: Path) -> None:
    # Switching to SCIP but keeping LPF1-over-UDP options: every mismatch is named.
    path, problems = problems_of(tmp_path, edit(SIM_TEXT, "sensor", "driver", '"scip"'))
    assert problems == [
        f"{path}: sensor.options.url: required, but not given",
        f"{path}: sensor.options.bind_host: unknown field",
        f"{path}: sensor.options.port: unknown field",
    ]


def test_several_problems_are_all_reported(tmp_path: Path) -> None:
    text = edit(SIM_TEXT, "robot", "max_speed_m_s", "0")
    text = edit(text, "sync", "interpolation", '"linear"')
    text = edit(text, "sim.table", "port", "-5")
    path, problems = problems_of(tmp_path, text)
    assert problems == [
        f"{path}: robot.max_speed_m_s: must be > 0 (got 0)",
        f"{path}: sync.interpolation: must be 'joint' or 'tcp' (got \"linear\")",
        f"{path}: sim.table.port: must be >= 0 (got -5)",
    ]


def test_frame_table_needs_a_table(tmp_path: Path) -> None:
    text = edit(drop_section(SIM_TEXT, "table"), "pipeline", "frame", '"part"')
    path, problems = problems_of(tmp_path, text)
    assert problems == [f'{path}: pipeline.frame: frame = "part" needs an enabled [table] section']


def test_toml_syntax_error_names_line_and_column(tmp_path: Path) -> None:
    lines = SIM_TEXT.splitlines()
    n = next(i for i, line in enumerate(lines) if line.startswith("max_accel_m_s2"))
    lines[n] = "max_accel_m_s2 = 0.5 0.6"
    path, problems = problems_of(tmp_path, "\n".join(lines))
    assert len(problems) == 1
    assert problems[0].startswith(f"{path}: line {n + 1}, column 22: invalid TOML: ")


def test_toml_error_at_end_of_file(tmp_path: Path) -> None:
    path, problems = problems_of(tmp_path, SIM_TEXT + "\n[robot\n")
    assert len(problems) == 1 and problems[0].startswith(f"{path}: line ")
    assert "invalid TOML" in problems[0]


@pytest.mark.parametrize(
    ("first_line", "expected"),
    [
        ("", "schema_version: missing; the file must start with 'schema_version = 1'"),
        (
            "schema_version = 2",
            "schema_version: version 2 is not supported; this wristscan reads schema_version = 1",
        ),
        ('schema_version = "1"', 'schema_version: must be an integer (got "1")'),
    ],
)
def test_schema_version(tmp_path: Path, first_line: str, expected: str) -> None:
    text = SIM_TEXT.replace("schema_version = 1\n", first_line + "\n")
    assert text != SIM_TEXT
    path, problems = problems_of(tmp_path, text)
    assert problems == [f"{path}: {expected}"]


def test_unreadable_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError) as info:
        load_config(missing)
    assert info.value.problems == [f"{missing}: cannot read: No such file or directory"]
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"schema_version = 1\n\xff\xfe")
    with pytest.raises(ConfigError, match=r"bin\.toml: not UTF-8 text"):
        load_config(binary)


def test_parse_config_returns_a_config() -> None:
    assert isinstance(parse_config(SIM_TEXT, "x.toml"), Config)


# ----------------------------------------------------------------------------------------------
# wristscan check-config


def test_check_config_ok(capsys: pytest.CaptureFixture[str]) -> None:
    path = str(ROOT / "config" / "ur10e-lpf1-serial-table.toml")
    assert main(["check-config", "--no-files", path]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == f"{path}: OK (schema_version 1)"
    assert "UR10e at 192.168.2.10" in out and "modbus rtu /dev/ttyUSB1" in out


def test_check_config_default(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", "--default"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("<default>: OK")
    assert "lpf1-udp 2048 points" in out


def test_check_config_reports_problems_without_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(edit(edit(SIM_TEXT, "robot", "max_speed_m_s", "-1"), "robot", "tpyo", "1"))
    assert main(["check-config", str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == [
        f"{path}: robot.max_speed_m_s: must be > 0 (got -1)",
        f"{path}: robot.tpyo: unknown field",
        f"{path}: 2 problems, not usable",
    ]
    assert "Traceback" not in captured.err


@pytest.mark.parametrize(
    "argv",
    [["check-config"], ["check-config", "--default", "x.toml"], ["check-config", "/no/such.toml"]],
    ids=["nothing", "both", "missing file"],
)
def test_check_config_usage_errors(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.strip() and "Traceback" not in err


def test_check_config_toml_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "syntax.toml"
    path.write_text("schema_version = 1\n[cell\n")
    assert main(["check-config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"{path}: line 2, column 6: invalid TOML")
    assert "Traceback" not in err
