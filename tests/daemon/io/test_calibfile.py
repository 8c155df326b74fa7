"""Calibration files: round trip, atomic replacement, refusal of corrupt or foreign files."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap
from datetime import UTC, datetime
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from wristscan.calib import se3
from wristscan.daemon.io.calibfile import (
    Calibration,
    CalibrationFileError,
    CalibrationStore,
    Residuals,
    RobotIdentity,
    SensorIdentity,
    read_calibration,
    ur_pose_text,
    write_calibration,
)

POSE = (0.060, 0.010, 0.200, 0.010, -0.020, 0.0)
ROBOT = RobotIdentity("UR5e", "20235500001")
SENSOR = SensorIdentity("lpf1-udp", "1")


def make(pose: tuple[float, ...] = POSE, **overrides: Any) -> Calibration:
    fields: dict[str, Any] = dict(
        kind="sensor2flange",
        transform=se3.pose_to_matrix(pose),
        robot=ROBOT,
        sensor=SENSOR,
        method="sphere-tcp-lstsq",
        residuals=Residuals.from_per_pose([[1e-5, 0, 0], [0, 2e-5, 0], [0, 0, 2e-5]]),
        covariance=np.diag([1e-10, 2e-10, 3e-10]),
        covariance_parameters=("x_m", "y_m", "z_m"),
        created_utc=datetime(2026, 5, 9, 7, 35, 25, 123456, tzinfo=UTC),
        notes="test",
    )
    fields.update(overrides)
    return Calibration(**fields)


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_round_trip(tmp_path: Path) -> None:
    calib = make()
    path = write_calibration(tmp_path / "s2f.json", calib)
    back = read_calibration(path, ROBOT, SENSOR)
    assert np.array_equal(back.transform, calib.transform)
    assert back.kind == "sensor2flange" and back.transform_name == "sensor2flange"
    assert back.covariance is not None and calib.covariance is not None
    assert np.array_equal(back.covariance, calib.covariance)
    assert back.covariance_parameters == ("x_m", "y_m", "z_m")
    assert back.residuals == calib.residuals
    assert back.residuals.rms_m == pytest.approx(np.sqrt((1e-10 + 4e-10 + 4e-10) / 3))
    assert back.residuals.max_m == pytest.approx(2e-5)
    assert back.created_utc == calib.created_utc
    assert back.robot == ROBOT and back.sensor == SENSOR
    assert back.method == "sphere-tcp-lstsq" and back.notes == "test"
    assert back.software_version == version("wristscan")
    assert np.allclose(back.ur_pose, POSE, atol=1e-15)


def test_document_layout(tmp_path: Path) -> None:
    path = write_calibration(tmp_path / "s2f.json", make())
    doc = json.loads(path.read_text())
    assert doc["format"] == "wristscan-calibration" and doc["version"] == 1
    rows = doc["transform"]["matrix_rows"]
    # Row-major: the translation is the last column of the first three rows.
    assert [r[3] for r in rows] == [0.060, 0.010, 0.200, 1.0]
    assert rows[3] == [0.0, 0.0, 0.0, 1.0]
    assert doc["transform"]["ur_pose"] == pytest.approx(list(POSE), abs=1e-15)
    assert doc["transform"]["ur_pose_text"] == (
        "p[0.06000, 0.01000, 0.20000, 0.0100, -0.0200, 0.0000]"
    )
    assert doc["covariance"]["parameters"] == ["x_m", "y_m", "z_m"]
    assert doc["created_utc"] == "2026-05-09T07:35:25.123456Z"
    assert doc["robot"] == {"model": "UR5e", "serial": "20235500001"}
    assert doc["sensor"] == {"driver": "lpf1-udp", "id": "1"}
    assert len(doc["residuals"]["per_pose_m"]) == 3


def test_ur_pose_text_has_no_negative_zero() -> None:
    assert ur_pose_text([-1e-9, 0.5, -0.25, -0.0, 1e-6, -3.14159265]) == (
        "p[0.00000, 0.50000, -0.25000, 0.0000, 0.0000, -3.1416]"
    )


def test_table_calibration(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="encoder_offset_rad"):
        make(kind="table")
    calib = make(kind="table", parameters={"encoder_offset_rad": 0.125, "radius_m": 0.1})
    path = write_calibration(tmp_path / "table.json", calib)
    back = read_calibration(path, kind="table")
    assert back.transform_name == "base2table"
    assert dict(back.parameters) == {"encoder_offset_rad": 0.125, "radius_m": 0.1}
    with pytest.raises(CalibrationFileError, match="a table calibration, but a sensor2flange"):
        read_calibration(path, kind="sensor2flange")


def test_construction_refuses_bad_values() -> None:
    T = se3.pose_to_matrix(POSE)
    T[0, 0] = 1.5
    with pytest.raises(ValueError, match="not orthonormal"):
        make(transform=T)
    with pytest.raises(ValueError, match="not symmetric"):
        make(covariance=np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]) * 1e-10)
    with pytest.raises(ValueError, match="positive semi-definite"):
        make(covariance=np.diag([1e-10, -1e-10, 1e-10]))
    with pytest.raises(ValueError, match="3x3 for 3 parameters"):
        make(covariance=np.eye(6))
    with pytest.raises(ValueError, match="timezone"):
        make(created_utc=datetime(2026, 1, 1))
    with pytest.raises(ValueError, match="finite"):
        make(residuals=Residuals(float("nan")))


def test_write_replaces_atomically_and_leaves_no_temp_files(tmp_path: Path) -> None:
    path = tmp_path / "s2f.json"
    write_calibration(path, make())
    first_inode = path.stat().st_ino
    write_calibration(path, make(pose=(0.07, 0.0, 0.21, 0.0, 0.0, 0.0)))
    assert listing(tmp_path) == ["s2f.json"]
    assert path.stat().st_ino != first_inode  # a new file renamed over the old one
    assert read_calibration(path).ur_pose[0] == pytest.approx(0.07)


def test_a_refused_document_leaves_the_old_file_intact(tmp_path: Path) -> None:
    path = tmp_path / "s2f.json"
    write_calibration(path, make())
    before = path.read_bytes()
    broken = make()
    T = np.array(broken.transform)
    T[:3, :3] *= 1.01  # a scaled rotation slipped in after construction (a bug elsewhere)
    object.__setattr__(broken, "transform", T)
    with pytest.raises(CalibrationFileError, match="not orthonormal"):
        write_calibration(path, broken)
    assert path.read_bytes() == before
    assert listing(tmp_path) == ["s2f.json"]


def test_a_write_failing_midway_leaves_the_old_file_intact(tmp_path: Path) -> None:
    """A real I/O failure after the temp file exists: the file-size limit makes the write fail
    with EFBIG (a full disk behaves the same way)."""
    path = tmp_path / "s2f.json"
    write_calibration(path, make())
    before = path.read_bytes()
    script = textwrap.dedent(
        f"""
        import errno, resource, signal, sys
        from wristscan.calib import se3
        from wristscan.daemon.io.calibfile import Calibration, Residuals, write_calibration
        from wristscan.daemon.io.calibfile import RobotIdentity, SensorIdentity
        calib = Calibration(
            "sensor2flange", se3.pose_to_matrix([0.1, 0.2, 0.3, 0, 0, 0]),
            RobotIdentity("UR5e"), SensorIdentity("lpf1-udp"), "m", Residuals(0.0),
        )
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (200, resource.RLIM_INFINITY))
        try:
            write_calibration({str(path)!r}, calib)
        except OSError as exc:
            print("failed", errno.errorcode[exc.errno])
            sys.exit(0)
        print("written")
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "failed EFBIG"
    assert path.read_bytes() == before
    assert listing(tmp_path) == ["s2f.json"]


def _write_doc(path: Path, doc: dict[str, Any]) -> None:
    path.write_text(json.dumps(doc))


def _doc() -> dict[str, Any]:
    return make().to_dict()


def _no_method(d: dict[str, Any]) -> None:
    del d["method"]


def _scaled(d: dict[str, Any]) -> None:
    d["transform"]["matrix_rows"][0][0] = 1.2


def _pose_off(d: dict[str, Any]) -> None:
    d["transform"]["ur_pose"][2] += 0.001


def _version2(d: dict[str, Any]) -> None:
    d["version"] = 2


def _format(d: dict[str, Any]) -> None:
    d["format"] = "something-else"


def _nan_text(d: dict[str, Any]) -> None:
    d["residuals"]["rms_m"] = "x"


def _short_row(d: dict[str, Any]) -> None:
    d["transform"]["matrix_rows"][1] = [0.0, 1.0, 0.0]


def _naive_date(d: dict[str, Any]) -> None:
    d["created_utc"] = "2026-05-09T07:35:25"


def _wrong_name(d: dict[str, Any]) -> None:
    d["transform"]["name"] = "flange2sensor"


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (_no_method, "method: required, but not given"),
        (_scaled, "transform.matrix_rows: rotation part is not orthonormal"),
        (_pose_off, "transform.ur_pose disagrees with transform.matrix_rows"),
        (_version2, "calibration file version 2 is not supported; this wristscan reads version 1"),
        (_format, "not a wristscan calibration (format is 'something-else'"),
        (_nan_text, 'residuals.rms_m: must be a number (got "x")'),
        (_short_row, "transform.matrix_rows[1]: list should have at least 4 items"),
        (_naive_date, "created_utc: the time zone is missing"),
        (_wrong_name, "transform.name: a sensor2flange calibration stores 'sensor2flange'"),
    ],
    ids=lambda v: v.__name__.strip("_") if callable(v) else None,
)
def test_corrupt_files_are_refused(tmp_path: Path, mutate: Any, message: str) -> None:
    doc = _doc()
    mutate(doc)
    path = tmp_path / "c.json"
    _write_doc(path, doc)
    with pytest.raises(CalibrationFileError) as info:
        read_calibration(path)
    text = str(info.value)
    assert text.startswith(f"{path}: ")
    assert message in text


def test_truncated_and_missing_files_are_refused(tmp_path: Path) -> None:
    path = write_calibration(tmp_path / "c.json", make())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CalibrationFileError, match=r"not valid JSON \(line \d+, column \d+\)"):
        read_calibration(path)
    path.write_text("[1, 2]")
    with pytest.raises(CalibrationFileError, match="a JSON object expected"):
        read_calibration(path)
    with pytest.raises(CalibrationFileError, match="cannot read: No such file"):
        read_calibration(tmp_path / "absent.json")


@pytest.mark.parametrize(
    ("robot", "sensor", "message"),
    [
        (RobotIdentity("UR10e", None), None, "made for robot UR5e serial 20235500001, but this "),
        (RobotIdentity("UR5e", "999"), None, "this robot is UR5e serial 999"),
        (None, SensorIdentity("rf627-udp", None), "made for sensor lpf1-udp id 1"),
        (None, SensorIdentity("lpf1-udp", "2"), "this sensor is lpf1-udp id 2"),
    ],
)
def test_foreign_calibrations_are_refused(
    tmp_path: Path, robot: RobotIdentity | None, sensor: SensorIdentity | None, message: str
) -> None:
    path = write_calibration(tmp_path / "c.json", make())
    with pytest.raises(CalibrationFileError, match="recalibrate") as info:
        read_calibration(path, robot, sensor)
    assert message in str(info.value)
    # Fields not asked for are not compared.
    assert read_calibration(path, RobotIdentity("UR5e"), SensorIdentity("lpf1-udp")).robot == ROBOT


def test_store_keeps_the_last_good_calibration(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "s2f.json"
    store = CalibrationStore(path, ROBOT, SENSOR)
    with caplog.at_level(logging.ERROR, logger="wristscan.daemon.io.calibfile"):
        err = store.reload()
    assert isinstance(err, CalibrationFileError) and store.current is None
    assert store.generation == 0 and store.last_error is err

    write_calibration(path, make())
    assert store.reload() is None
    good = store.current
    assert good is not None and store.generation == 1 and store.last_error is None

    path.write_text(path.read_text()[:100])  # corrupted in place (hand edit, bad copy ...)
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="wristscan.daemon.io.calibfile"):
        err = store.reload()
    assert isinstance(err, CalibrationFileError)
    assert store.current is good and store.generation == 1 and store.last_error is err
    assert [r.levelno for r in caplog.records] == [logging.ERROR]
    assert "previous calibration stays in force" in caplog.records[0].getMessage()

    write_calibration(path, make(pose=(0.061, 0.01, 0.2, 0.0, 0.0, 0.0), robot=ROBOT))
    assert store.reload() is None
    current = store.current
    assert current is not None and current is not good and store.generation == 2
    assert current.ur_pose[0] == pytest.approx(0.061)

    # A calibration for another robot never replaces the one in force.
    write_calibration(path, make(robot=RobotIdentity("UR5e", "other")))
    assert isinstance(store.reload(), CalibrationFileError)
    assert store.current is current


def test_files_are_refused_before_a_kind_mismatch_can_slip_through(tmp_path: Path) -> None:
    path = write_calibration(
        tmp_path / "t.json", make(kind="table", parameters={"encoder_offset_rad": 0.0})
    )
    store = CalibrationStore(path)  # default kind: sensor2flange
    err = store.reload()
    assert err is not None and "a sensor2flange one is needed" in str(err)
    assert store.current is None


def test_written_file_mode(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        path = write_calibration(tmp_path / "new.json", make())
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o640
    os.chmod(path, 0o600)
    write_calibration(path, make())
    assert path.stat().st_mode & 0o777 == 0o600  # an existing file keeps its mode
