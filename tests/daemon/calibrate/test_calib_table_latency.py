"""``wristscan calibrate table`` and ``wristscan calibrate latency``: the procedures' pieces on
synthetic sweeps with known truth, and the whole procedures on the simulated cell."""

from __future__ import annotations

import json
import math
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from support import TRUE_POSES_ONLY
from typer.testing import CliRunner

from wristscan.calib import se3
from wristscan.calib.latency import estimate_latency
from wristscan.calib.table import fit_table_axis
from wristscan.daemon.calibrate.ball import ball_from_sweep
from wristscan.daemon.calibrate.latency import (
    LatencyOptions,
    LatencyResult,
    LatencySweep,
    calibrate_latency,
    latency_report,
    outlier_sweeps,
    write_latency_result,
)
from wristscan.daemon.calibrate.table import (
    TableOptions,
    TableResult,
    _predict,
    calibrate_table,
    direction_cov,
    table_calibration,
    tilt_sigma_deg,
)
from wristscan.daemon.calibrate.table_report import table_report
from wristscan.daemon.cli.app import app
from wristscan.daemon.config import Config, load_config, parse_config
from wristscan.daemon.io.calibfile import (
    Calibration,
    Residuals,
    RobotIdentity,
    SensorIdentity,
    read_calibration,
    write_calibration,
)
from wristscan.daemon.procedure.acquisition import Sweep
from wristscan.daemon.procedure.errors import BallNotFound, MotionNotConfirmed
from wristscan.daemon.procedure.motion import require_motion
from wristscan.daemon.simcell.cell import dump_toml, free_sim_config
from wristscan.daemon.simcell.scenarios import (
    pairing_truth_tap,
    table_ball_cell,
    table_truth,
    truth_offset_s,
    write_truth_calibration,
)
from wristscan.drivers.sim.cell import SimulatedCell

SIM_TOML = Path(__file__).resolve().parents[3] / "config" / "sim.toml"
R_BALL = 0.0127

# --------------------------------------------------------------------------------------------
# Synthetic sweeps: a sensor looking down moves along its X axis over a ball.


def synthetic_sweep(
    centre: np.ndarray,
    *,
    speed: float,
    direction: int = 1,
    latency_error_s: float = 0.0,
    rate_hz: float = 1000.0,
    half_m: float = 0.025,
    noise_m: float = 20e-6,
    seed: int = 0,
) -> Sweep:
    """Profiles exposed at ``t_k`` from the true sensor pose; paired with the pose at
    ``t_k + latency_error_s`` (the synchroniser's exposure instant is late by that much)."""
    rng = np.random.default_rng(seed)
    R = se3.rot_x(np.pi)  # sensor Z down, X along base X
    standoff = 0.10
    n_prof = int(2 * half_m / speed * rate_hz)
    t = np.arange(n_prof) / rate_hz

    def origins(tt: np.ndarray) -> np.ndarray:
        # The ball centre is at (-s, 0, standoff) in the sensor frame at sweep offset s.
        ss = direction * (-half_m + speed * tt)
        return centre + ss[:, None] * R[:, 0] - standoff * R[:, 2]

    o_true = origins(t)
    y = np.linspace(-0.025, 0.025, 400)
    c_s = (centre - o_true) @ R  # ball centre in each sensor frame (P, 3)
    h2 = R_BALL**2 - c_s[:, None, 0] ** 2 - (y[None, :] - c_s[:, None, 1]) ** 2
    valid = h2 > 0
    z = c_s[:, None, 2] - np.sqrt(np.where(valid, h2, 0.0))
    z = z + rng.normal(0.0, noise_m, z.shape)
    o_paired = origins(t + latency_error_s)
    flange2base = np.broadcast_to(se3.make(R), (n_prof, 4, 4)).copy()
    flange2base[:, :3, 3] = o_paired
    t_ns = (1_000_000_000 + np.round((t + latency_error_s) * 1e9)).astype(np.int64)
    return Sweep(
        y=np.broadcast_to(y, z.shape).ravel().copy(),
        z=z.ravel(),
        valid=valid.ravel(),
        profile_index=np.repeat(np.arange(n_prof), y.size),
        flange2base=flange2base,
        exposure_ns=t_ns,
        table_angle=None,
    )


def test_ball_from_sweep_recovers_centre_and_velocity() -> None:
    centre = np.array([0.4, -0.2, 0.16])
    sw = synthetic_sweep(centre, speed=0.05)
    ball = ball_from_sweep(sw, np.eye(4), R_BALL)
    np.testing.assert_allclose(ball.centre, centre, atol=3e-6)
    np.testing.assert_allclose(ball.velocity_m_s, [0.05, 0.0, 0.0], atol=1e-6)
    assert ball.speed_spread < 1e-3
    assert ball.n_points > 1000 and ball.rms_m < 40e-6


def test_a_latency_error_shifts_the_centre_along_the_motion() -> None:
    """The sign convention end to end: sweeps paired ``dt`` late give ``dt`` back."""
    centre = np.array([0.4, -0.2, 0.16])
    dt = 1.5e-3
    P, V = [], []
    for i, v in enumerate((0.025, 0.05, 0.1)):
        for d in (1, -1):
            sw = synthetic_sweep(centre, speed=v, direction=d, latency_error_s=dt, seed=i)
            b = ball_from_sweep(sw, np.eye(4), R_BALL)
            np.testing.assert_allclose(b.centre - centre, b.velocity_m_s * dt, atol=3e-6)
            P.append(b.centre)
            V.append(b.velocity_m_s)
    est = estimate_latency(np.array(P), np.array(V))
    assert est.latency_s == pytest.approx(dt, abs=20e-6)
    np.testing.assert_allclose(est.feature_position, centre, atol=2e-6)


def test_one_bad_sweep_is_singled_out() -> None:
    rng = np.random.default_rng(3)
    v = np.array([[s * d, 0.0, 0.0] for s in (0.025, 0.05, 0.1) for d in (1, -1)] * 2)
    p = np.array([0.4, -0.2, 0.16]) + v * 1.5e-3 + rng.normal(0, 8e-6, v.shape)
    assert outlier_sweeps(estimate_latency(p, v)) == []
    p[4, 0] += 300e-6  # poses wrong for part of that sweep
    assert outlier_sweeps(estimate_latency(p, v)) == [4]


def test_a_sweep_that_misses_the_ball_says_so() -> None:
    sw = synthetic_sweep(np.array([0.4, -0.2, 0.16]), speed=0.05)
    empty = replace(sw, valid=np.zeros_like(sw.valid))
    with pytest.raises(BallNotFound, match="0 valid points"):
        ball_from_sweep(empty, np.eye(4), R_BALL)


def _circle(n: int, tilt_deg: float, seed: int = 0, noise: float = 10e-6) -> tuple:
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3
    R = se3.rot_x(np.radians(tilt_deg))
    local = np.stack([0.1 * np.cos(ang), 0.1 * np.sin(ang), np.full(n, 0.09)], axis=1)
    C = local @ R.T + np.array([0.45, 0.25, 0.0]) + rng.normal(0, noise, (n, 3))
    return C, ang


def test_reported_uncertainties_match_the_scatter() -> None:
    """One-sigma of the axis direction and of its tilt, against a Monte Carlo of fits."""
    d_err, sig_d, tilt, sig_tilt = [], [], [], []
    for seed in range(300):
        C, ang = _circle(8, 0.2, seed=seed, noise=10e-6)
        axis = fit_table_axis(C, ang)
        d_err.append(axis.direction[:2] - [0.0, -math.sin(math.radians(0.2))])
        sig_d.append(np.sqrt(np.diag(direction_cov(axis)))[:2])
        tilt.append(axis.tilt_deg)
        sig_tilt.append(tilt_sigma_deg(axis))
    np.testing.assert_allclose(np.std(d_err, axis=0), np.median(sig_d, axis=0), rtol=0.2)
    assert np.std(tilt) == pytest.approx(np.median(sig_tilt), rel=0.2)
    assert np.mean(tilt) == pytest.approx(0.2, abs=3 * np.std(tilt) / np.sqrt(300))


def test_prediction_of_the_next_ball_position() -> None:
    C, ang = _circle(12, 0.2, noise=5e-6)
    # Bootstrap-like start: three close angles, then a 35 degree step.
    th = np.radians([0.0, 5.0, 10.0, 45.0]) + 0.3
    R = se3.rot_x(np.radians(0.2))
    pts = np.stack([0.1 * np.cos(th), 0.1 * np.sin(th), np.full(4, 0.09)], axis=1) @ R.T + [
        0.45,
        0.25,
        0.0,
    ]
    centres = [pts[0], pts[1], pts[2]]
    guess = _predict(centres, list(th[:3] - 0.3), th[3] - 0.3)
    assert np.linalg.norm(guess - pts[3]) < 2e-3
    guess2 = _predict(centres[:2], list(th[:2] - 0.3), th[2] - 0.3)
    assert np.linalg.norm(guess2 - pts[2]) < 1e-3
    # The encoder wrapped between the readings (359.9 deg, then 4.9 deg): the same prediction.
    a = [2 * np.pi - 0.002, 0.0853]
    wrapped = _predict(centres[:2], a, a[1] + np.radians(5.0))
    assert np.linalg.norm(wrapped - guess2) < 1e-3
    del C, ang


def test_plan_has_bootstrap_steps_and_spans_the_turn() -> None:
    plan = TableOptions(n_angles=6).plan(0.5)
    assert len(plan) == 8
    np.testing.assert_allclose(np.diff(plan)[:2], np.radians(5.0))
    assert plan[-1] - plan[0] == pytest.approx(2 * np.pi * 5 / 6)
    with pytest.raises(ValueError):
        TableOptions(n_angles=2)


def _table_result(tmp_path: Path) -> TableResult:
    from wristscan.daemon.calibrate.ball import BallMeasurement

    C, ang = _circle(8, 0.2)
    axis = fit_table_axis(C, ang)
    ms = tuple(
        BallMeasurement(
            centre=c,
            cov=np.eye(3) * 1e-12,
            rms_m=2e-5,
            n_points=5000,
            n_profiles=300,
            velocity_m_s=np.array([0.02, 0, 0]),
            speed_spread=0.0,
            t_mid_ns=0,
            table_angle_rad=float(a),
        )
        for c, a in zip(C, ang, strict=True)
    )
    return TableResult(
        axis=axis,
        measurements=ms,
        angles_rad=ang,
        ball_height_m=0.09,
        tilt_sigma_deg=tilt_sigma_deg(axis),
        sensor_calibration=str(tmp_path / "s2f.json"),
        duration_s=1.0,
        sweeps=8,
    )


def test_table_file_and_report(tmp_path: Path) -> None:
    cfg = parse_config(SIM_TOML.read_text(), "sim.toml", tmp_path)
    result = _table_result(tmp_path)
    assert result.axis.tilt_deg == pytest.approx(0.2, abs=0.01)
    assert 0 < result.tilt_sigma_deg < 0.01
    path = write_calibration(tmp_path / "table.json", table_calibration(result, cfg))
    back = read_calibration(path, RobotIdentity("UR5e"), kind="table")
    # The table frame's origin lies on the table top: 0.09 m below the ball-centre plane.
    t2b = se3.invert(np.asarray(back.transform))
    np.testing.assert_allclose(t2b[:3, 2], result.axis.direction, atol=1e-12)
    assert float(result.axis.direction @ (result.axis.point - t2b[:3, 3])) == pytest.approx(0.09)
    assert back.parameters["encoder_offset_rad"] == pytest.approx(result.axis.encoder_offset_rad)
    assert back.covariance is not None and back.covariance.shape == (7, 7)
    assert len(back.residuals.per_pose_m) == 8
    for suffix in (".html", ".md"):
        rep = table_report(result, "test").write(tmp_path / f"table{suffix}")
        text = rep.read_text()
        assert "axis tilt from base Z" in text and "encoder offset" in text
    assert any((tmp_path / "table_files").glob("*.png"))


def test_latency_result_file_and_report(tmp_path: Path) -> None:
    from wristscan.daemon.calibrate.ball import BallMeasurement

    centre = np.array([0.4, -0.2, 0.16])
    sweeps = []
    for v in (0.025, 0.05, 0.1):
        for d in (1, -1):
            vel = np.array([d * v, 0.0, 0.0])
            sweeps.append(
                LatencySweep(
                    v,
                    d,
                    BallMeasurement(
                        centre + vel * 4e-4, np.eye(3) * 1e-14, 2e-5, 9000, 400, vel, 0.0, 0
                    ),
                )
            )
    est = estimate_latency(
        np.stack([s.ball.centre for s in sweeps]), np.stack([s.ball.velocity_m_s for s in sweeps])
    )
    res = LatencyResult(
        configured_latency_s=0.0011,
        estimate=est,
        sweeps=tuple(sweeps),
        ball_centre_m=est.feature_position,
        sweep_axis=np.array([1.0, 0.0, 0.0]),
        speed_cap_m_s=0.25,
        sensor_calibration="s2f.json",
        duration_s=3.0,
    )
    assert res.latency_s == pytest.approx(0.0015)
    assert res.toml_line() == "latency_s = 0.001500"
    np.testing.assert_allclose(res.along_motion_m(), res.signed_speeds_m_s() * 4e-4, atol=1e-12)
    doc = json.loads(write_latency_result(tmp_path / "lat.json", res).read_text())
    assert doc["latency_s"] == pytest.approx(0.0015) and len(doc["sweeps"]) == 6
    text = latency_report(res).write(tmp_path / "lat.html").read_text()
    assert "latency_s = 0.001500" in text and "data:image/png;base64" in text


# --------------------------------------------------------------------------------------------
# Refusals: nothing may move without motion enabled and confirmed


def test_refusals_before_anything_moves(tmp_path: Path) -> None:
    cfg = parse_config(SIM_TOML.read_text(), "sim.toml", tmp_path)
    with pytest.raises(MotionNotConfirmed, match="--yes"):
        require_motion(cfg, confirmed=False)
    off = parse_config(
        SIM_TOML.read_text().replace("motion_enabled = true", "motion_enabled = false"),
        "off.toml",
        tmp_path,
    )
    with pytest.raises(MotionNotConfirmed, match="motion_enabled"):
        calibrate_table(off, confirmed=True)
    with pytest.raises(MotionNotConfirmed, match="motion_enabled"):
        calibrate_latency(off, confirmed=True)


def _unreachable_config(tmp_path: Path, motion: bool = True) -> Path:
    """A config whose robot address has nothing listening: a command that tried to connect
    would fail with a driver error instead of refusing."""
    text = SIM_TOML.read_text().replace('"127.0.0.2"', '"127.0.0.254"')
    if not motion:
        text = text.replace("motion_enabled = true", "motion_enabled = false")
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("command", ["table", "latency"])
def test_cli_refuses_without_yes(tmp_path: Path, command: str) -> None:
    cfg = _unreachable_config(tmp_path)
    out = tmp_path / "out.json"
    r = CliRunner().invoke(app, ["calibrate", command, "--config", str(cfg), "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert "--yes" in r.output
    assert "Traceback" not in r.output
    assert not out.exists()


def test_cli_refuses_without_motion_enabled(tmp_path: Path) -> None:
    cfg = _unreachable_config(tmp_path, motion=False)
    r = CliRunner().invoke(app, ["calibrate", "latency", "--config", str(cfg), "--yes"])
    assert r.exit_code == 2 and "motion_enabled" in r.output


def test_cli_rejects_bad_speeds(tmp_path: Path) -> None:
    cfg = _unreachable_config(tmp_path)
    r = CliRunner().invoke(
        app, ["calibrate", "latency", "--config", str(cfg), "--yes", "--speeds", "25,abc"]
    )
    assert r.exit_code == 2 and "--speeds" in r.output


# --------------------------------------------------------------------------------------------
# On the simulated cell


def sim_config(
    tmp_path: Path, *, latency_s: float = 0.0015, configured_latency_s: float = 0.0
) -> tuple[Path, Config]:
    """The default simulated cell on free loopback addresses, with a sensor calibration file
    (the truth) and a lighter sensor (512 points at 500 Hz) so that the test stays quick."""
    doc = free_sim_config(
        {
            "sensor": {"latency_s": configured_latency_s},
            "sim.sensor": {"latency_s": latency_s, "n_points": 512, "rate_hz": 500.0},
            "calibration": {"file": "s2f.json", "table_file": "table.json"},
        }
    )
    path = tmp_path / "cell.toml"
    path.write_text(dump_toml(doc))
    return path, load_config(path)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_table_procedure_on_the_simulated_cell(tmp_path: Path) -> None:
    """``calibrate table`` (6 angles, 40 mm/s) against the simulator's true axis: the axis
    direction within 0.01 deg (the benchmark's target, ``benchmarks/calibration_table_latency.py``,
    which measures 0.0024 deg with the data sheet's robot repeatability; this cell's robot is
    perfect), the encoder offset within 0.01 deg (a table whose encoder reads 0.05 deg off fails
    here), the table frame's origin on the platter top on the true axis (the sweeps run one way:
    a configured latency 1 ms off moves every ball centre, and so the axis, by 40 um)."""
    path, cfg = sim_config(tmp_path, latency_s=0.0015, configured_latency_s=0.0015)
    spec = table_ball_cell(cfg, start_above="table_ball", **TRUE_POSES_ONLY)
    write_truth_calibration(cfg, spec)
    truth = table_truth(spec)
    with SimulatedCell(spec):
        r = CliRunner().invoke(
            app,
            [
                *("calibrate", "table", "--config", str(path), "--yes", "--angles", "6"),
                *("--speed-mm-s", "40", "--ball-height-mm", "60"),
            ],
        )
    assert r.exit_code == 0, r.output
    assert "tilt" in r.output and "encoder offset" in r.output
    calib = read_calibration(tmp_path / "table.json", RobotIdentity("UR5e"), kind="table")
    table2base = se3.invert(np.asarray(calib.transform))
    direction = table2base[:3, 2]
    axis_err = math.degrees(math.acos(min(1.0, float(direction @ truth["axis_direction"]))))
    tilt_err = calib.parameters["tilt_deg"] - truth["tilt_deg"]
    offset_err = math.degrees(
        math.remainder(
            calib.parameters["encoder_offset_rad"] - truth["encoder_offset_rad"], math.tau
        )
    )
    # The origin is on the platter top: 60 mm below the ball centre, on the true axis.
    origin = table2base[:3, 3]
    rel = origin - np.asarray(truth["axis_point_m"])
    off_axis = float(np.linalg.norm(rel - (rel @ direction) * direction))
    figures = (
        f"axis {axis_err:.4f} deg, tilt {tilt_err:+.4f} deg, encoder offset {offset_err:+.4f} deg, "
        f"origin {off_axis * 1e6:.1f} um off the axis, height {(origin[2] - 0.03) * 1e6:+.1f} um"
    )
    print(figures)
    assert axis_err < 0.01 and abs(tilt_err) < 0.01, figures
    assert abs(offset_err) < 0.01, figures
    assert off_axis < 20e-6 and abs(origin[2] - 0.03) < 20e-6, figures
    assert (tmp_path / "table-report.html").exists()


SIM_LATENCY_S = 0.0026
"""The latency test's simulated sensor: not a value an estimator could guess."""
CONFIGURED_LATENCY_S = 0.0004
"""What the latency test tells the daemon (the procedure measures the rest)."""


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_latency_procedure_on_the_simulated_cell(tmp_path: Path) -> None:
    """2.6 ms simulated, 0.4 ms configured. The truth to meet is the simulator's latency plus
    the links' delays, measured from its ground truth independently of the synchroniser
    (``pairing_truth_tap``); within 0.15 ms (the benchmark's target is 0.1 ms,
    ``benchmarks/calibration_table_latency.py``, which uses three sweep pairs per speed where
    this test has one)."""
    _, cfg = sim_config(
        tmp_path, latency_s=SIM_LATENCY_S, configured_latency_s=CONFIGURED_LATENCY_S
    )
    spec = table_ball_cell(cfg, start_above="ball", batch_s=2e-4, **TRUE_POSES_ONLY)
    write_truth_calibration(cfg, spec)
    with SimulatedCell(spec) as cell:
        assert cell.sensor is not None and cell.controller is not None
        tap = pairing_truth_tap(cfg, cell.sensor.info(), cell.controller.host_time_ns(0.0))
        res = calibrate_latency(
            cfg, LatencyOptions(speeds_m_s=(0.05, 0.1, 0.2)), confirmed=True, acquisition=tap
        )
    actual = truth_offset_s(tap, res)
    figures = (
        f"found {res.latency_s * 1e3:.4f} ms (+- {res.std_s * 1e3:.4f}), truth {actual * 1e3:.4f}"
        f" ms (simulator {SIM_LATENCY_S * 1e3:.1f} ms plus the links)"
    )
    print(figures)
    # The links add the smallest delay of the profiles and take off the robot stream's own.
    assert abs(actual - SIM_LATENCY_S) < 0.3e-3, figures
    assert abs(res.latency_s - actual) < 0.15e-3, figures
    assert res.std_s < 0.1e-3 and res.estimate.n_sweeps == 6, figures
    assert res.configured_latency_s == CONFIGURED_LATENCY_S
    assert res.toml_line() == f"latency_s = {res.latency_s:.6f}"


def test_protective_stop_aborts_and_keeps_the_calibration(tmp_path: Path) -> None:
    path, cfg = sim_config(tmp_path)
    spec = table_ball_cell(cfg, start_above="table_ball")
    write_truth_calibration(cfg, spec)
    # The calibration in force before the run.
    old = Calibration(
        kind="table",
        transform=np.eye(4),
        robot=RobotIdentity("UR5e"),
        sensor=SensorIdentity("lpf1-udp", "1"),
        method="previous",
        residuals=Residuals(0.0),
        parameters={"encoder_offset_rad": 0.0},
    )
    before = write_calibration(tmp_path / "table.json", old).read_bytes()
    with SimulatedCell(spec) as cell:
        ctl = cell.controller
        assert ctl is not None
        done = threading.Event()

        def stop_on_first_motion() -> None:
            while not done.wait(0.02):
                if ctl.state()["moving"]:
                    ctl.protective_stop()
                    return

        watcher = threading.Thread(target=stop_on_first_motion)
        watcher.start()
        try:
            r = CliRunner().invoke(app, ["calibrate", "table", "--config", str(path), "--yes"])
        finally:
            done.set()
            watcher.join()
        assert ctl.state()["safety_mode"] != 1  # the stop really happened
    assert r.exit_code == 1, r.output
    assert "aborted" in r.output and "nothing was written" in r.output
    assert "Traceback" not in r.output
    assert (tmp_path / "table.json").read_bytes() == before
    assert not (tmp_path / "table-report.html").exists()
