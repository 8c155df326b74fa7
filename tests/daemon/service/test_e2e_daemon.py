"""End to end on the simulated cell: ``wristscan run`` as a systemd-style service, a subscriber in
another process decoding WSC1 from the documented layout, the real ur_rtde control client sweeping
the sensor over the tooling ball forward and back; the published points against the simulator's
truth (each sweep's ball centre, their disagreement along the motion, the distances to the true
sphere against the configured sensor noise); then SIGHUP (bad and good reloads) and SIGTERM."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rtde_control
from support import TRUE_POSES_ONLY

from wristscan.calib import kinematics, se3
from wristscan.calib.sphere import fit_sphere
from wristscan.daemon.cloud.client import CloudClient
from wristscan.daemon.config import load_config
from wristscan.daemon.io.calibfile import (
    Calibration,
    Residuals,
    RobotIdentity,
    SensorIdentity,
    write_calibration,
)
from wristscan.daemon.simcell.cell import dump_toml, free_sim_config, start_cell
from wristscan.drivers.sim.scene import sensor_looking_down

HELPER = Path(__file__).resolve().parents[2] / "helpers" / "wsc1_subscriber.py"


def _calibration(transform: np.ndarray, method: str) -> Calibration:
    return Calibration(
        kind="sensor2flange",
        transform=transform,
        robot=RobotIdentity("UR5e"),
        sensor=SensorIdentity("lpf1-udp", "1"),
        method=method,
        residuals=Residuals(rms_m=0.0),
    )


class NotifyListener:
    """The systemd side of sd_notify: a real AF_UNIX datagram socket."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.messages: list[str] = []

    def wait_for(self, needle: str, timeout: float) -> list[str]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(needle in m for m in self.messages):
                return self.messages
            self.sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except TimeoutError:
                break
        raise AssertionError(f"no {needle!r} from the daemon; got {self.messages}")

    def close(self) -> None:
        self.sock.close()


SWEEP_HALF_M = 0.03
"""The sweeps run from 30 mm before the ball's centre to 30 mm after it (and back)."""
SWEEP_SPEED_M_S = 0.10
"""At 100 mm/s a timing error of 1 ms moves the two sweeps' points 0.1 mm apart along the
motion (0.05 mm each way), and pairing with the nearest robot sample (500 Hz states, 1 kHz
profiles: +-0.5 ms alternating) adds about 25 um RMS to the distances from the true sphere."""
SWEEP_ACCEL_M_S2 = 1.0
"""Full speed 5 mm into the sweep, before the line reaches the ball (17 mm in)."""
CENTRE_TOL_M = 30e-6
"""Each sweep's fitted centre from the true one (a sphere fit of ~10^5 points is good to a few
um; 30 um is 0.3 ms of timing error at 100 mm/s, 3x the synchroniser's 0.1 ms target: on an
idle machine the sweeps land within 10 um, on a 2-core machine loaded to 8 runnable processes
one came out 23 um off, 0.17 ms)."""
TIMING_TOL_S = 0.3e-3
"""The timing error the forward/backward disagreement along the motion implies (both ways)."""
CLOCK_SPAN_S = 5.0
"""How long the daemon runs before the sweeps, so that the sensor clock's fit spans several
seconds of its -100 ppm drift: ignored, it would cost 0.5 ms by then (caught), where right
after the start it costs only 0.2-0.3 ms."""


def _noise_m(cfg: Any) -> float:
    """The simulated sensor's noise (1 sigma along the ray) of the configuration."""
    return float(cfg.sim.sensor.noise_m)


def _split_sweeps(t: np.ndarray) -> np.ndarray:
    """True for the points of the second pass over the ball: the profiles that saw it fall in
    two runs of time, with the turn beyond the ball (no points near it) between them."""
    times = np.unique(t)
    cut = int(np.argmax(np.diff(times)))
    return np.asarray(t > times[cut])


def _check_sweeps_against_truth(got: Any, ball: np.ndarray, radius: float, noise_m: float) -> None:
    """The ball's points of the forward and of the backward sweep, each fitted by a sphere of
    the true radius: both centres on the true one, no opposite shifts along the motion (a timing
    error moves the sweeps by ``+-speed * error``), and every point as close to the true sphere
    as the sensor's noise allows (along the ray 20 um: 14 um RMS normal to this cap)."""
    xyz = got["xyz"].astype(np.float64)
    near = np.linalg.norm(xyz - ball, axis=1) < radius + 0.002
    pts = xyz[near]
    second = _split_sweeps(got["point_t"][near])
    fits = []
    for name, m in (("forward", ~second), ("backward", second)):
        assert m.sum() > 5000, f"{name}: {m.sum()} points on the ball"
        fits.append(fit_sphere(pts[m], radius=radius))
    fwd, bwd = fits
    d_fwd, d_bwd = fwd.centre - ball, bwd.centre - ball
    dist = np.abs(np.linalg.norm(pts - ball, axis=1) - radius)
    true_rms = float(np.sqrt(np.mean(dist**2)))
    timing_s = float(d_fwd[0] - d_bwd[0]) / (2 * SWEEP_SPEED_M_S)
    figures = (
        f"centre - truth (um): forward {np.round(d_fwd * 1e6, 1)}, backward "
        f"{np.round(d_bwd * 1e6, 1)}; timing error implied {timing_s * 1e3:+.3f} ms; fit RMS "
        f"{fwd.rms * 1e6:.1f} / {bwd.rms * 1e6:.1f} um; to the true sphere {true_rms * 1e6:.1f} "
        f"um (noise {noise_m * 1e6:.0f} um along the ray)"
    )
    print(figures)
    assert np.linalg.norm(d_fwd) < CENTRE_TOL_M, figures
    assert np.linalg.norm(d_bwd) < CENTRE_TOL_M, figures
    assert abs(timing_s) < TIMING_TOL_S, figures
    assert max(fwd.rms, bwd.rms) < noise_m, figures
    assert true_rms < noise_m, figures


@pytest.mark.slow
def test_daemon_end_to_end(tmp_path: Path) -> None:
    doc = free_sim_config(
        {
            "calibration": {"file": "sensor2flange.json"},
            # Every batch must arrive: "drop" (the default) sheds batches by design when the
            # subscriber falls behind, which a loaded test machine makes it do now and then.
            "zenoh": {"status_period_s": 0.5, "congestion_control": "block"},
            # Each point's profile: the subscriber tells the sweeps apart by exposure time.
            "pipeline": {"publish_profile_index": True},
            # A sensor clock slower than the host's: a mapping that ignored the drift would rest
            # on the oldest receipts and be 0.1 ms late per second of running (a faster clock
            # rests it on the newest ones, where ignoring the drift costs nothing).
            "sim.sensor": {"clock_drift_ppm": -100.0},
            # An arm built as a real one is (its DH parameters off by ~0.1 mm / 0.01 deg, the
            # flange 0.3 mm from where the nominal table puts it) whose factory calibration the
            # controller reports: the daemon must pair with that model, not the nominal one.
            "sim.controller": {"kinematic_errors": "realistic", "factory_calibration": "exact"},
            "robot": {"use_factory_kinematics": True},
        }
    )
    cfg_path = tmp_path / "cell.toml"
    cfg_path.write_text(dump_toml(doc))
    cfg = load_config(cfg_path)
    endpoint = cfg.zenoh.listen[0]
    cell = start_cell(cfg, **TRUE_POSES_ONLY)
    notify = NotifyListener(tmp_path / "notify.sock")
    daemon: subprocess.Popen[str] | None = None
    subscriber: subprocess.Popen[str] | None = None
    try:
        truth = cell.truth()
        s2f = np.array(truth["sensor2flange"])
        ball = np.array(truth["ball_centre_base_m"])
        radius = truth["ball_radius_m"]
        write_calibration(tmp_path / "sensor2flange.json", _calibration(s2f, "simulation truth"))

        # The sensor looks down at the ball from 0.1 m; sweeps run along sensor X (= base X).
        def flange_at(dx: float) -> np.ndarray:
            return sensor_looking_down(ball + np.array([dx, 0.0, 0.0]), 0.10) @ se3.invert(s2f)

        assert cell.controller is not None
        q0 = np.array(cell.controller.state()["q"])
        q_start = kinematics.inverse_nearest("UR5e", flange_at(-SWEEP_HALF_M), q0)
        assert cell.controller.set_joint_positions(q_start)

        env = dict(os.environ, NOTIFY_SOCKET=str(notify.path), WATCHDOG_USEC="4000000")
        env.pop("WATCHDOG_PID", None)  # the daemon's pid is not known before it starts
        daemon = subprocess.Popen(
            [sys.executable, "-m", "wristscan.daemon.cli", "run", "--config", str(cfg_path)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        notify.wait_for("READY=1", timeout=60)

        subscriber = subprocess.Popen(
            [
                sys.executable,
                str(HELPER),
                endpoint,
                cfg.zenoh.prefix,
                str(tmp_path / "got.npz"),
                "120",
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert subscriber.stdout is not None and subscriber.stdin is not None
        assert subscriber.stdout.readline().strip() == "ready"
        time.sleep(CLOCK_SPAN_S)

        control = rtde_control.RTDEControlInterface(cfg.robot.host)
        try:
            end = se3.matrix_to_pose(flange_at(+SWEEP_HALF_M))
            start = se3.matrix_to_pose(flange_at(-SWEEP_HALF_M))
            assert control.moveL(end.tolist(), SWEEP_SPEED_M_S, SWEEP_ACCEL_M_S2)
            assert control.moveL(start.tolist(), SWEEP_SPEED_M_S, SWEEP_ACCEL_M_S2)
        finally:
            control.stopScript()
            control.disconnect()
        # Everything exposed until now is in once a batch exposed after it has come.
        subscriber.stdin.write(f"stop {time.time_ns()}\n")
        subscriber.stdin.flush()
        assert subscriber.wait(timeout=150) == 0
        got = np.load(tmp_path / "got.npz")
        assert list(got["encodings"]) == ["application/octet-stream;wsc1"]
        assert set(got["frames"].tolist()) == {"base"}
        seq = got["seq"]
        assert np.all(np.diff(seq) == 1), "batches were lost on loopback"

        _check_sweeps_against_truth(got, ball, radius, _noise_m(cfg))

        with CloudClient(cfg.zenoh.prefix, connect=[endpoint], subscribe=False) as client:
            stats = client.query("stats")
            assert stats["received"] > 0
            assert stats["received"] == (
                stats["published"] + sum(stats["dropped"].values()) + stats["pending"]
            )
            # Where the latency goes, per stage; the stages add up to the total.
            lat = stats["latency_ms"]
            assert set(lat) == {"transport", "wait", "process", "total"}
            assert 0.0 <= lat["transport"]["p50"] <= lat["total"]["p50"] <= lat["total"]["p99"]
            # The longest tick is kept; every driver read went well.
            assert stats["tick_ms_max"] > 0.0 and stats["slow_ticks"] >= 0
            assert stats["read_errors"] == {}
            assert client.query("calibration")["method"] == "simulation truth"

            # SIGHUP with a corrupt calibration: refused, the old one stays in force.
            (tmp_path / "sensor2flange.json").write_text("{ not json")
            daemon.send_signal(signal.SIGHUP)
            notify.wait_for("reload refused", timeout=30)
            assert client.query("calibration")["method"] == "simulation truth"
            assert daemon.poll() is None

            # SIGHUP with a good one: in force.
            write_calibration(tmp_path / "sensor2flange.json", _calibration(s2f, "second"))
            daemon.send_signal(signal.SIGHUP)
            notify.wait_for("running (reloaded)", timeout=30)
            assert client.query("calibration")["method"] == "second"

        assert any(m.startswith("WATCHDOG=1") or "\nWATCHDOG=1" in m for m in notify.messages)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=30) == 0
        notify.wait_for("STOPPING=1", timeout=5)
    finally:
        for proc in (subscriber, daemon):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
        if daemon is not None and daemon.stdout is not None:
            log = daemon.stdout.read()
            if log:
                print(log[-4000:])
        cell.stop()
        notify.close()


def test_run_refuses_a_bad_config_clearly(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('schema_version = 1\n[sensor]\ndriver = "lpf1-udp"\nlatency_s = "fast"\n')
    out = subprocess.run(
        [sys.executable, "-m", "wristscan.daemon.cli", "run", "--config", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "sensor.latency_s" in out.stderr + out.stdout
    assert "Traceback" not in out.stderr + out.stdout


def test_run_without_calibration_says_what_to_do(tmp_path: Path) -> None:
    cfg_path = tmp_path / "cell.toml"
    cfg_path.write_text(dump_toml(free_sim_config()))
    out = subprocess.run(
        [sys.executable, "-m", "wristscan.daemon.cli", "run", "--config", str(cfg_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "wristscan calibrate sensor" in out.stderr + out.stdout
