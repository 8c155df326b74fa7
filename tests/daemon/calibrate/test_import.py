"""``wristscan calibrate import``: a stop-and-go data set on disk -> the calibration file.

The shipped example (tests/data/import_example/, made by the simulator with
``wristscan.daemon.simcell.stopgo.make_example``: a UR5e with realistic DH deviations and a
partial factory calibration, 15 poses) calibrates to the simulator's truth; every convention
reads the same poses; bad data sets end with one line naming the file and the line, never a
traceback.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from wristscan.calib import pose_conventions as pc
from wristscan.calib import se3
from wristscan.daemon.calibrate import imported
from wristscan.daemon.calibrate.sensor import COVARIANCE_PARAMETERS
from wristscan.daemon.io.calibfile import read_calibration

EXAMPLE = Path(__file__).parents[2] / "data" / "import_example"
RADIUS = "12.7mm"


def _cli(*args: str) -> tuple[int, str]:
    from wristscan.daemon.cli.app import app

    res = CliRunner().invoke(app, ["calibrate", "import", *args], catch_exceptions=False)
    return res.exit_code, res.output


@pytest.fixture
def example(tmp_path: Path) -> Path:
    """A copy of the shipped example to spoil."""
    return Path(shutil.copytree(EXAMPLE, tmp_path / "set"))


def test_the_shipped_example_calibrates_to_the_simulators_truth(tmp_path: Path) -> None:
    out = tmp_path / "s2f.json"
    code, text = _cli(str(EXAMPLE), "--ball-radius", RADIUS, "--poses", "fanuc-xyzwpr",
                      "--out", str(out))  # fmt: skip
    assert code == 0, text
    truth = json.loads((EXAMPLE / "truth.json").read_text())
    X_true = np.array(truth["sensor2flange_matrix_rows"])
    cal = read_calibration(out, kind="sensor2flange")
    assert cal.covariance is not None
    assert cal.covariance_parameters == COVARIANCE_PARAMETERS  # the file calibrate sensor writes
    X = cal.transform
    # The simulated arm reports each flange pose 15-75 um from where it is (truth.json); 15
    # profiles of a 12.7 mm ball turn that into 20-60 um of uncertainty per axis (the file's
    # covariance), and 0.02-0.1 deg about the sensor axes (about Z the ball spans only +-10 mm
    # of the laser line). The truth must lie within 3 of those sigmas, 0.2 mm and 0.3 deg.
    sig = np.sqrt(np.diag(cal.covariance))
    err_t = X[:3, 3] - X_true[:3, 3]
    err_r = se3.matrix_to_rotvec(X_true[:3, :3].T @ X[:3, :3])
    assert np.all(np.abs(err_t) < 3 * sig[3:]), (err_t, sig[3:])
    assert np.all(np.abs(err_r) < 3 * sig[:3]), (err_r, sig[:3])
    assert np.linalg.norm(err_t) < 0.2e-3 and np.linalg.norm(err_r) < np.radians(0.3)
    p = cal.parameters
    np.testing.assert_allclose(
        [p["ball_centre_x_m"], p["ball_centre_y_m"], p["ball_centre_z_m"]],
        truth["ball_centre_base_m"],
        atol=0.2e-3,
    )
    assert p["ball_side"] == truth["side"] and p["n_poses"] == 15
    assert len(cal.residuals.per_pose_m) == 15
    # The cross-check over poses is written beside the covariance's sigmas.
    jk = np.array([p[f"jackknife_sigma_{a}_m"] for a in "xyz"])
    assert np.all((jk > sig[3:] / 3) & (jk < 3 * sig[3:])), (jk, sig[3:])
    report = out.with_name("s2f-report.html")
    assert "Side of the laser plane" in report.read_text()
    assert "sensor2flange  p[" in text and "jackknife" in text


@pytest.mark.parametrize("convention", [c for c in pc.CONVENTIONS if c != "fanuc-xyzwpr"])
def test_every_convention_and_unit_reads_the_same_poses(example: Path, convention: str) -> None:
    ref = imported.read_dataset(EXAMPLE, "fanuc-xyzwpr", "mm")
    rows = pc.from_matrix(convention, ref.flange2base)  # positions in metres
    lines = [",".join(("pose", *pc.columns(convention)))]
    lines += [
        ",".join((n, *(repr(float(v)) for v in r))) for n, r in zip(ref.names, rows, strict=True)
    ]
    (example / "poses.csv").write_text("\n".join(lines) + "\n")
    for f in (example / "profiles").glob("*.csv"):  # the profiles in metres as well
        out = ["y,z,valid"]
        for line in f.read_text().splitlines()[1:]:
            y, z, v = line.split(",")
            out.append(f"{float(y) * 1e-3!r},{float(z) * 1e-3 if z else ''},{v}")
        f.write_text("\n".join(out) + "\n")
    got = imported.read_dataset(example, convention, "m")
    assert got.names == ref.names
    np.testing.assert_allclose(got.flange2base, ref.flange2base, atol=1e-9)
    for a, b in zip(got.profiles, ref.profiles, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)


def _edit(path: Path, line: int, new: str | None) -> None:
    """Replace (or with None delete) 1-based ``line`` of ``path``."""
    lines = path.read_text().splitlines()
    if new is None:
        del lines[line - 1]
    else:
        lines[line - 1] = new
    path.write_text("\n".join(lines) + "\n")


def _run_bad(folder: Path, *extra: str, poses: str = "fanuc-xyzwpr", radius: str = RADIUS) -> str:
    out = folder.parent / "s2f.json"
    code, text = _cli(str(folder), "--ball-radius", radius, "--poses", poses, "--out", str(out),
                      *extra)  # fmt: skip
    assert code in (1, 2), text
    assert "Traceback" not in text and text.startswith("error: ")
    assert not out.exists()  # nothing written
    return text


def test_a_missing_folder_poses_file_or_profile_is_named(example: Path) -> None:
    assert "no such folder" in _run_bad(example.parent / "nothing")
    (example / "profiles" / "p03.csv").unlink()
    assert "p03.csv: missing" in _run_bad(example)
    (example / "poses.csv").unlink()
    assert "poses.csv: missing" in _run_bad(example)


def test_columns_of_another_convention_are_named(example: Path) -> None:
    text = _run_bad(example, poses="kuka-abc")
    assert "poses.csv: no column a, b, c" in text
    assert "those of --poses fanuc-xyzwpr" in text
    _edit(example / "profiles" / "p02.csv", 1, "y,depth,valid")
    assert "p02.csv: no column z" in _run_bad(example)


def test_nan_and_text_name_the_file_and_the_line(example: Path) -> None:
    poses = example / "poses.csv"
    row = poses.read_text().splitlines()[4].split(",")
    _edit(poses, 5, ",".join([*row[:3], "nan", *row[4:]]))
    assert "poses.csv, line 5: z = 'nan' is not a finite number" in _run_bad(example)
    _edit(poses, 5, ",".join(row))
    prof = example / "profiles" / "p07.csv"
    first_valid = next(i for i, t in enumerate(prof.read_text().splitlines(), 1) if t[-1] == "1")
    _edit(prof, first_valid, "1.0,,1")
    assert f"p07.csv, line {first_valid}: z = '' is not a number" in _run_bad(example)
    _edit(prof, first_valid, "1.0,abc,1")
    assert f"p07.csv, line {first_valid}: z = 'abc' is not a number" in _run_bad(example)


def test_duplicate_pose_names_and_bad_rotations_are_named(example: Path) -> None:
    poses = example / "poses.csv"
    rows = poses.read_text().splitlines()
    _edit(poses, 4, rows[2])
    assert "poses.csv, line 4: pose 'p02' appears twice" in _run_bad(example)
    m = example / "matrix.csv"
    ref = imported.read_dataset(EXAMPLE, "fanuc-xyzwpr")
    vals = pc.from_matrix("matrix", ref.flange2base)
    vals[6, 3:] = [1, 0, 0, 0, 1, 0, 0, 0, -1]  # a reflection
    lines = [",".join(("pose", *pc.columns("matrix")))]
    lines += [",".join((n, *map(str, r))) for n, r in zip(ref.names, vals, strict=True)]
    m.write_text("\n".join(lines) + "\n")
    m.replace(poses)
    text = _run_bad(example, "--units", "m", poses="matrix")
    assert "poses.csv, line 8: pose p07: rotation matrix is a reflection" in text


def test_too_few_poses_are_refused(example: Path) -> None:
    poses = example / "poses.csv"
    poses.write_text("\n".join(poses.read_text().splitlines()[:6]) + "\n")
    assert "poses.csv: 5 poses; the calibration needs >= 6" in _run_bad(example)


def test_orientations_that_never_change_are_refused(example: Path) -> None:
    poses = example / "poses.csv"
    rows = [r.split(",") for r in poses.read_text().splitlines()]
    for r in rows[2:]:
        r[4:] = rows[1][4:]  # every pose with the first one's w, p, r
    poses.write_text("\n".join(",".join(r) for r in rows) + "\n")
    text = _run_bad(example)
    assert "calibration failed" in text and "do not determine sensor2flange" in text


def test_a_ball_radius_wrong_by_two_is_refused(example: Path) -> None:
    text = _run_bad(example, radius="25.4mm")
    assert "calibration failed" in text and "radius, not the diameter" in text
    text = _run_bad(example, radius="6.35mm")
    assert "profiles/p01.csv: no circle of at most the ball radius 6.350 mm" in text
    assert "is the ball radius right?" in text
    assert "not a positive length" in _run_bad(example, radius="12.7 inches")


def test_lengths_with_units() -> None:
    assert imported.parse_length("40mm") == pytest.approx(0.04)
    assert imported.parse_length("0.04 m") == pytest.approx(0.04)
    assert imported.parse_length("40", "mm") == pytest.approx(0.04)
    assert imported.parse_length("0.04", "m") == pytest.approx(0.04)
    with pytest.raises(ValueError, match="positive length"):
        imported.parse_length("-3mm")


def test_the_simulators_writer_and_the_reader_agree(tmp_path: Path) -> None:
    from wristscan.daemon.simcell import stopgo

    data = stopgo.make_stopgo(n_poses=6, seed=5, n_points=200)
    for conv, units in (("ur-rotvec", "m"), ("abb-quaternion", "mm")):
        folder = stopgo.write_dataset(tmp_path / conv, data, convention=conv, units=units)
        got = imported.read_dataset(folder, conv, units)
        assert got.names == data.names
        np.testing.assert_allclose(got.flange2base, data.flange2base, atol=1e-8)
        for k, pts in enumerate(got.profiles):  # only the valid points, to 10 nm
            np.testing.assert_allclose(pts, data.points(k), atol=1e-8)


def test_a_jackknife_wider_than_the_sigma_is_noted() -> None:
    from types import SimpleNamespace

    from wristscan.calib import perpose

    cov = np.diag([1e-8, 1e-8, 1e-8, 1e-10, 1e-10, 1e-10])
    jk_cov = cov.copy()
    jk_cov[5, 5] = 4e-10  # z: the jackknife 2x the sigma
    jk = perpose.Jackknife(np.zeros((15, 6)), jk_cov, np.zeros(15), np.zeros(15))
    notes = imported._jackknife_notes(SimpleNamespace(cov=cov), jk)  # type: ignore[arg-type]
    assert notes == [
        "z: the jackknife over poses gives 2.0x the reported 1 sigma; the robot's pose errors "
        "are probably systematic (trust the larger)"
    ]
