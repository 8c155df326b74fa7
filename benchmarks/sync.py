"""Synchronisation benchmark (issue 5): clock mapping, pairing, latency, throughput, resets.

A simulated cell with known truth, entirely in this process (no servers): a UR5e whose flange
follows a linear path at 250 mm/s (the joint trajectory comes from inverse kinematics, splined
in time, and *is* the truth), a 500 Hz controller stream and a 1 kHz profile stream, each with its
own clock, drift, offset, transport delay floor, arrival jitter, delay spikes and (robot) skipped
samples; then both streams at 500 Hz read by a process short of CPU (stalls, load, overload,
heavy-tailed spikes, a start-up backlog). See docs/sync.md for what each figure measures.

Run: ``.venv/bin/python benchmarks/sync.py [--json out.json] [--seed N]``; exits 1 on a miss.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline

from wristscan.calib import kinematics, se3
from wristscan.calib.latency import estimate_latency
from wristscan.calib.sphere import fit_sphere
from wristscan.daemon.sync import readytick
from wristscan.daemon.sync.batch import PairedBatch
from wristscan.daemon.sync.clockmap import ClockMapper
from wristscan.daemon.sync.pairing import Pairer, PairerConfig
from wristscan.drivers.records import Profile, ProfileBlock, RobotState

sys.path.insert(0, str(Path(__file__).parent))
from _clockfigs import figure_feed_blocks, figure_late_sender
from _report import Figure, report

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

MS = 1_000_000
S = 1_000_000_000
MODEL = "UR5e"
T0 = 100 * S  # host monotonic ns when the run starts
C0 = 7200 * S  # controller clock (ns) at T0: the controller booted two hours earlier

SENSOR_DRIFT = 50e-6
SENSOR_OFFSET_NS = 20e6
SENSOR_JITTER_NS = 1e6  # standard deviation of the arrival delay beyond its floor
SENSOR_LATENCY_NS = 1_500_000  # exposure to timestamp
SENSOR_PERIOD_NS = 1_000_000  # 1 kHz on the sensor's clock
ROBOT_DRIFT = -30e-6
ROBOT_JITTER_NS = 0.5e6
ROBOT_PERIOD_NS = 2_000_000  # 500 Hz on the controller's clock
DELAY_FLOOR_NS = 250_000  # smallest transport delay, both streams (cancels out, see docs)
SPIKE_P = 0.01  # share of arrivals delayed by a further 2..20 ms
ROBOT_SKIP_P = 0.01  # controller samples the client never gets

SPEED = 0.25  # m/s
ACCEL = 2.5  # m/s^2
FLANGE_R = se3.rot_x(math.pi)  # tool pointing down
CENTRE = np.array([0.45, -0.10, 0.35])  # flange position at the middle of the paths (m)
SENSOR2FLANGE = se3.make(None, [0.0, 0.04, 0.06])
POINT_SENSOR = np.array([0.0, 0.0, 0.15])  # a laser point at 150 mm stand-off (sensor frame)
N_POINTS = 2048
BALL_R = 0.0127  # 1 inch tooling ball


# ----------------------------------------------------------------------------- motion truth


@dataclass
class FlangePath:
    """Flange path of straight moves (trapezoidal speed) and dwells, orientation fixed."""

    start: FloatArray
    segments: list[tuple[float, float, FloatArray, FloatArray, float]] = field(default_factory=list)
    """(t_start s, duration s, p0, p1, peak speed m/s)."""

    @property
    def duration(self) -> float:
        if not self.segments:
            return 0.0
        t, d, *_ = self.segments[-1]
        return t + d

    @property
    def end(self) -> FloatArray:
        return self.segments[-1][3] if self.segments else self.start

    def dwell(self, seconds: float) -> FlangePath:
        p = self.end
        self.segments.append((self.duration, seconds, p, p, 0.0))
        return self

    def move(self, to: FloatArray, speed: float = SPEED, accel: float = ACCEL) -> FlangePath:
        p0 = self.end
        L = float(np.linalg.norm(to - p0))
        v = min(speed, math.sqrt(accel * L))
        dur = v / accel + L / v
        self.segments.append((self.duration, dur, p0, np.asarray(to, float), v))
        return self

    def _eval(self, t_s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Positions (M, 3) and velocities (M, 3) at times (s from the start)."""
        starts = np.array([s[0] for s in self.segments])
        k = np.clip(np.searchsorted(starts, t_s, side="right") - 1, 0, len(self.segments) - 1)
        pos = np.empty((t_s.shape[0], 3))
        vel = np.zeros((t_s.shape[0], 3))
        for i in np.unique(k):
            t0, dur, p0, p1, v = self.segments[i]
            m = k == i
            tau = np.clip(t_s[m] - t0, 0.0, dur)
            if v == 0.0:
                pos[m] = p0
                continue
            L = float(np.linalg.norm(p1 - p0))
            u = (p1 - p0) / L
            ta = v / ACCEL
            s = np.where(
                tau < ta,
                0.5 * ACCEL * tau**2,
                np.where(
                    tau > dur - ta,
                    L - 0.5 * ACCEL * (dur - tau) ** 2,
                    0.5 * ACCEL * ta**2 + v * (tau - ta),
                ),
            )
            sd = np.where(tau < ta, ACCEL * tau, np.where(tau > dur - ta, ACCEL * (dur - tau), v))
            pos[m] = p0 + s[:, None] * u
            vel[m] = sd[:, None] * u
        return pos, vel


class Truth:
    """Joint trajectory of the robot: IK of the path every 20 ms, cubic spline in time."""

    def __init__(self, path: FlangePath, grid_s: float = 0.02) -> None:
        self.path = path
        # One more second: the robot stream outlasts the profile stream (see make_streams).
        t = np.arange(0.0, path.duration + 1.0 + 3 * grid_s, grid_s)
        pos, _ = path._eval(t)
        q = np.empty((t.shape[0], 6))
        seed = np.array([0.0, -1.6, 1.6, -1.6, -1.57, 0.0])
        for i in range(t.shape[0]):
            seed = kinematics.inverse_nearest(MODEL, se3.make(FLANGE_R, pos[i]), seed)
            q[i] = seed
        self._spline = CubicSpline(t, q, axis=0)

    def q(self, t_ns: IntArray) -> FloatArray:
        return np.asarray(self._spline((np.asarray(t_ns) - T0) * 1e-9), dtype=np.float64)

    def flange2base(self, t_ns: IntArray) -> FloatArray:
        return kinematics.forward(MODEL, self.q(t_ns))

    def speed(self, t_ns: IntArray) -> FloatArray:
        t_s = (np.asarray(t_ns) - T0).astype(np.float64) * 1e-9
        _, vel = self.path._eval(t_s)
        return np.asarray(np.linalg.norm(vel, axis=-1), dtype=np.float64)


# ----------------------------------------------------------------------------- streams


def _delays(rng: np.random.Generator, n: int, std_ns: float) -> IntArray:
    """Floor + gamma(shape 2) with the given standard deviation + occasional spikes."""
    d = DELAY_FLOOR_NS + rng.gamma(2.0, std_ns / math.sqrt(2.0), n)
    spike = rng.random(n) < SPIKE_P
    d[spike] += rng.uniform(2 * MS, 20 * MS, int(spike.sum()))
    return np.rint(d).astype(np.int64)


@dataclass
class Streams:
    # robot
    ctrl_ns: IntArray  # controller clock of each sample
    robot_true_ns: IntArray  # host instant the sample was measured
    robot_arrival: IntArray
    q: FloatArray
    tcp: FloatArray  # controller TCP pose (TCP = flange: no offset set)
    # sensor
    exposure: IntArray  # true host instant of each exposure
    stamp_true: IntArray  # true host instant of the timestamp (exposure + latency)
    sensor_ns: IntArray  # what the sensor reports (device clock, maybe wrapping)
    sensor_arrival: IntArray
    frame: IntArray


def make_streams(
    truth: Truth,
    seconds: float,
    seed: int,
    profile_period_ns: int = SENSOR_PERIOD_NS,
    sensor_clock: Callable[[IntArray], IntArray] | None = None,
    outage: tuple[int, int] | None = None,
) -> Streams:
    rng = np.random.default_rng(seed)
    # The robot stream runs 0.5 s longer, so that every profile can be covered.
    n_r = int((seconds + 0.5) * S / ROBOT_PERIOD_NS)
    k = np.arange(n_r, dtype=np.int64)
    ctrl = C0 + k * ROBOT_PERIOD_NS
    h = T0 + np.rint(k * ROBOT_PERIOD_NS * (1.0 + ROBOT_DRIFT)).astype(np.int64)
    keep = rng.random(n_r) >= ROBOT_SKIP_P
    ctrl, h = ctrl[keep], h[keep]
    n_p = int(seconds * S / (profile_period_ns * (1.0 + SENSOR_DRIFT)))
    j = np.arange(n_p, dtype=np.int64)
    exposure = T0 + 370_000 + np.rint(j * profile_period_ns * (1.0 + SENSOR_DRIFT)).astype(np.int64)
    stamp = exposure + SENSOR_LATENCY_NS
    if sensor_clock is None:
        dev = np.rint((stamp - SENSOR_OFFSET_NS) / (1.0 + SENSOR_DRIFT)).astype(np.int64)
    else:
        dev = sensor_clock(stamp)
    keep_p = np.ones(n_p, dtype=bool)
    if outage is not None:
        keep_p &= ~((exposure >= outage[0]) & (exposure < outage[1]))
    return Streams(
        ctrl_ns=ctrl,
        robot_true_ns=h,
        robot_arrival=h + _delays(rng, h.shape[0], ROBOT_JITTER_NS),
        q=truth.q(h),
        tcp=se3.matrix_to_pose(truth.flange2base(h)),
        exposure=exposure[keep_p],
        stamp_true=stamp[keep_p],
        sensor_ns=dev[keep_p],
        sensor_arrival=stamp[keep_p] + _delays(rng, int(keep_p.sum()), SENSOR_JITTER_NS),
        frame=j[keep_p],
    )


ProfileMaker = Callable[[int], tuple[FloatArray, FloatArray, NDArray[np.bool_]]]

_Y = np.linspace(-0.025, 0.025, N_POINTS)
_Z = np.full(N_POINTS, 0.15)
_VALID = np.ones(N_POINTS, dtype=bool)


def flat_profile(_: int) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    return _Y, _Z, _VALID


def records(st: Streams, make_points: ProfileMaker = flat_profile) -> list[object]:
    """All records in host arrival order (profiles built here: excluded from timings)."""
    arrival = np.concatenate([st.robot_arrival, st.sensor_arrival])
    order = np.argsort(arrival, kind="stable")
    n_r = st.robot_arrival.shape[0]
    out: list[object] = []
    for i in order.tolist():
        if i < n_r:
            out.append(
                RobotState(st.ctrl_ns[i] / 1e9, int(st.robot_arrival[i]), st.q[i], st.tcp[i])
            )
        else:
            p = i - n_r
            y, z, valid = make_points(p)
            out.append(
                Profile(
                    1,
                    int(st.frame[p]),
                    int(st.sensor_ns[p]),
                    int(st.sensor_arrival[p]),
                    y,
                    z,
                    valid,
                )
            )
    return out


def run_pairer(
    pairer: Pairer,
    recs: list[object],
    poll_every: int = 16,
    on_batch: Callable[[PairedBatch], None] | None = None,
) -> list[PairedBatch]:
    batches: list[PairedBatch] = []
    add_p, add_r = pairer.add_profile, pairer.add_robot_state
    for i, r in enumerate(recs):
        if isinstance(r, Profile):
            add_p(r)
        else:
            add_r(r)  # type: ignore[arg-type]
        if i % poll_every == 0:
            got = pairer.poll()
            if on_batch is not None:
                for b in got:
                    on_batch(b)
            else:
                batches += got
    got = pairer.poll(pairer.latest_host_ns + 2 * S)
    if on_batch is not None:
        for b in got:
            on_batch(b)
    else:
        batches += got
    assert pairer.received == pairer.paired + sum(pairer.dropped.values()) + pairer.pending
    return batches


def point_displacement(truth: Truth, F: FloatArray, exposure_true: IntArray) -> FloatArray:
    """|reconstructed - true| of the stand-off laser point for each profile (m)."""
    p = np.append(POINT_SENSOR, 1.0)
    got = (F @ SENSOR2FLANGE @ p)[:, :3]
    true = (truth.flange2base(exposure_true) @ SENSOR2FLANGE @ p)[:, :3]
    return np.linalg.norm(got - true, axis=-1)


def naive_pairing(
    st: Streams, latest: bool = False, latency_ns: int = 0
) -> tuple[IntArray, FloatArray]:
    """Peers' method: the robot sample received nearest to (or last before) the profile's
    receipt less ``latency_ns`` (a peer told the sensor's latency subtracts it: the fair
    baseline). Returns the robot sample index per profile and flange2base."""
    order = np.argsort(st.robot_arrival, kind="stable")
    ra = st.robot_arrival[order]
    t = st.sensor_arrival - latency_ns
    i = np.searchsorted(ra, t, side="right")
    before = np.clip(i - 1, 0, ra.shape[0] - 1)
    if latest:
        k = before
    else:
        after = np.clip(i, 0, ra.shape[0] - 1)
        k = np.where(np.abs(ra[after] - t) < np.abs(t - ra[before]), after, before)
    idx = order[k]
    return idx, kinematics.forward(MODEL, st.q[idx])


def interpolated_peer(st: Streams, latency_ns: int) -> FloatArray:
    """A stronger peer: the profile's receipt less the known latency, the robot's joints
    interpolated at that instant between the samples' receipt times (flange2base)."""
    order = np.argsort(st.robot_arrival, kind="stable")
    ra = st.robot_arrival[order].astype(np.float64)
    q = st.q[order]
    t = (st.sensor_arrival - latency_ns).astype(np.float64)
    qi = np.column_stack([np.interp(t, ra, q[:, j]) for j in range(q.shape[1])])
    return np.asarray(kinematics.forward(MODEL, qi), dtype=np.float64)


# ----------------------------------------------------------------------------- scenarios


def back_and_forth(seconds: float, half_length: float = 0.15) -> FlangePath:
    a = CENTRE - np.array([half_length, 0.0, 0.0])
    b = CENTRE + np.array([half_length, 0.0, 0.0])
    path = FlangePath(start=a)
    while path.duration < seconds:
        path.move(b).move(a)
    return path


def pairer_config(latency_ns: int, **kw: object) -> PairerConfig:
    return PairerConfig(robot_model=MODEL, sensor_latency_ns=latency_ns, **kw)  # type: ignore[arg-type]


def figure_latency(seed: int) -> tuple[list[Figure], int]:
    """Ball sweeps both ways at 50..250 mm/s, paired with latency 0; fit centres; solve dt."""
    ball = CENTRE + np.array([0.0, -0.04 - 0.003, -0.06 - 0.16])  # below the sensor, 3 mm aside
    speeds = [0.05, 0.1, 0.15, 0.2, 0.25]
    path = FlangePath(start=CENTRE - [0.04, 0.0, 0.0]).dwell(5.0)  # the clocks settle meanwhile
    windows: list[tuple[float, float, FloatArray]] = []
    for v in speeds:
        for sign in (+1, -1):
            t_start = path.duration
            path.move(CENTRE + np.array([0.04 * sign, 0.0, 0.0]), speed=v).dwell(0.1)
            # Constant-speed part of the move (times from the start, s).
            ta = v / ACCEL
            windows.append((t_start + ta, path.duration - 0.1 - ta, np.array([sign * v, 0, 0])))
    truth = Truth(path)
    st = make_streams(truth, path.duration, seed)
    rng = np.random.default_rng(seed + 1000)
    ys = np.linspace(-0.02, 0.02, 512)
    S2B = truth.flange2base(st.exposure) @ SENSOR2FLANGE
    c_s = (se3.invert(S2B) @ np.append(ball, 1.0))[:, :3]
    empty = (ys, np.zeros_like(ys), np.zeros(ys.shape, dtype=bool))

    def ball_profile(p: int) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        cx, cy, cz = c_s[p]
        if abs(cx) >= BALL_R:
            return empty
        d2 = BALL_R**2 - cx**2 - (ys - cy) ** 2
        valid = d2 > 0
        z = np.where(valid, cz - np.sqrt(np.maximum(d2, 0.0)), 0.0)
        return ys, z + rng.normal(0.0, 10e-6, ys.shape) * valid, valid

    pts: list[FloatArray] = []
    t_pts: list[IntArray] = []

    def collect(b: PairedBatch) -> None:
        if not np.any(b.valid):
            return
        T = (b.flange2base @ SENSOR2FLANGE)[b.profile_index]
        local = np.stack([np.zeros_like(b.y), b.y, b.z], axis=-1)
        base = np.einsum("nij,nj->ni", T[:, :3, :3], local) + T[:, :3, 3]
        pts.append(base[b.valid])
        t_pts.append(b.exposure_ns[b.profile_index][b.valid])

    run_pairer(Pairer(pairer_config(0)), records(st, ball_profile), on_batch=collect)
    P = np.concatenate(pts)
    tp = np.concatenate(t_pts)
    centres: list[FloatArray] = []
    vels: list[FloatArray] = []
    for t_a, t_b, vel in windows:
        m = (tp >= T0 + t_a * S) & (tp < T0 + t_b * S)
        sel = np.flatnonzero(m)
        if sel.shape[0] > 20_000:
            sel = rng.choice(sel, 20_000, replace=False)
        fit = fit_sphere(P[sel], radius=BALL_R, robust=None)
        centres.append(fit.centre)
        vels.append(vel)
    est = estimate_latency(np.array(centres), np.array(vels))
    err = abs(est.latency_s - SENSOR_LATENCY_NS * 1e-9)
    figs = [
        Figure("latency: estimated", est.latency_s * 1e3, "ms", "1.5 (truth)", None),
        Figure("latency: error", err * 1e3, "ms", "<= 0.1", err <= 0.1e-3),
        Figure("latency: reported std", est.std_s * 1e3, "ms", "", None),
        Figure("latency: sweeps", len(windows), "", "", None),
    ]
    return figs, round(est.latency_s * 1e9)


def figure_clock_and_pairing(seed: int, latency_ns: int) -> list[Figure]:
    seconds = 20.0
    truth = Truth(back_and_forth(seconds))
    st = make_streams(truth, seconds, seed)
    # 1. Clock mapping alone, causally: each stamp mapped with the line known at its arrival.
    cfg = pairer_config(latency_ns)
    clk = ClockMapper(cfg.sensor_clock)
    order = np.argsort(st.sensor_arrival, kind="stable")
    err = np.full(order.shape[0], np.nan)
    unc = np.full(order.shape[0], np.nan)
    for n, i in enumerate(order.tolist()):
        e = clk.feed(int(st.sensor_ns[i]), int(st.sensor_arrival[i]))
        if clk.is_locked(e) and st.stamp_true[i] >= T0 + 5 * S:
            err[n] = float(clk.to_host(st.sensor_ns[i], e)) - (st.stamp_true[i] + DELAY_FLOOR_NS)
            unc[n] = float(clk.uncertainty_ns())
    late = ~np.isnan(err)
    rms_clock = float(np.sqrt(np.mean(err[late] ** 2)))
    figs = [
        Figure(
            "clock: mapped time error RMS (t >= 5 s)",
            rms_clock / 1e3,
            "us",
            "<= 100",
            rms_clock <= 100_000,
        ),
        Figure(
            "clock: max |error| (t >= 5 s)", float(np.max(np.abs(err[late]))) / 1e3, "us", "", None
        ),
        Figure("clock: mean reported uncertainty", float(np.mean(unc[late])) / 1e3, "us", "", None),
        Figure("clock: drift estimate", clk.drift * 1e6, "ppm", "50 (truth)", None),
    ]
    # 2. Pairing, ours vs host receive time + nearest sample.
    pairer = Pairer(cfg)
    batches = run_pairer(pairer, records(st))
    fc = np.concatenate([b.frame_counter for b in batches])
    F = np.concatenate([b.flange2base for b in batches])
    e_true = st.exposure[np.searchsorted(st.frame, fc)]
    steady = (e_true >= T0 + 5 * S) & (np.abs(truth.speed(e_true) - SPEED) < 1e-6)
    ours = point_displacement(truth, F[steady], e_true[steady])
    rms_ours = float(np.sqrt(np.mean(ours**2)))
    tcp_batches = run_pairer(Pairer(pairer_config(latency_ns, interpolation="tcp")), records(st))
    fc_t = np.concatenate([b.frame_counter for b in tcp_batches])
    F_t = np.concatenate([b.flange2base for b in tcp_batches])
    e_t = st.exposure[np.searchsorted(st.frame, fc_t)]
    steady_t = (e_t >= T0 + 5 * S) & (np.abs(truth.speed(e_t) - SPEED) < 1e-6)
    ours_tcp = point_displacement(truth, F_t[steady_t], e_t[steady_t])
    rms_tcp = float(np.sqrt(np.mean(ours_tcp**2)))
    sel = (st.exposure >= T0 + 5 * S) & (np.abs(truth.speed(st.exposure) - SPEED) < 1e-6)

    def peer_rms(F: FloatArray) -> float:
        d = point_displacement(truth, F[sel], st.exposure[sel])
        return float(np.sqrt(np.mean(d**2)))

    # The peers are told the sensor's true latency (a fair peer knows its sensor's data sheet);
    # wristscan uses the latency it measured itself (figure_latency).
    rms_near = peer_rms(naive_pairing(st, latency_ns=SENSOR_LATENCY_NS)[1])
    rms_last = peer_rms(naive_pairing(st, latest=True, latency_ns=SENSOR_LATENCY_NS)[1])
    rms_interp = peer_rms(interpolated_peer(st, SENSOR_LATENCY_NS))
    rms_near_untold = peer_rms(naive_pairing(st)[1])
    received = pairer.received
    figs += [
        Figure(
            "pairing: displacement RMS, wristscan",
            rms_ours * 1e3,
            "mm",
            "<= 0.025",
            rms_ours <= 25e-6,
        ),
        Figure("pairing: displacement max, wristscan", float(ours.max()) * 1e3, "mm", "", None),
        Figure("pairing: displacement RMS, wristscan tcp mode", rms_tcp * 1e3, "mm", "", None),
        Figure(
            "pairing: displacement RMS, receive time - latency + nearest",
            rms_near * 1e3,
            "mm",
            "",
            None,
        ),
        Figure(
            "pairing: displacement RMS, receive time - latency + latest",
            rms_last * 1e3,
            "mm",
            "",
            None,
        ),
        Figure(
            "pairing: displacement RMS, receive time - latency + interpolated",
            rms_interp * 1e3,
            "mm",
            "",
            None,
        ),
        Figure(
            "pairing: displacement RMS, receive time + nearest (latency not told)",
            rms_near_untold * 1e3,
            "mm",
            "",
            None,
        ),
        Figure(
            "pairing: ratio nearest (latency told) / wristscan", rms_near / rms_ours, "x", "", None
        ),
        Figure(
            "pairing: ratio interpolated (latency told) / wristscan",
            rms_interp / rms_ours,
            "x",
            "",
            None,
        ),
        Figure("pairing: profiles paired / received", pairer.paired / received, "", "", None),
    ]
    return figs


def figure_throughput(seed: int) -> list[Figure]:
    """Profiles paired per CPU second (process time, so per core even if a library used
    threads): add + poll of prebuilt records, batches built (point arrays concatenated)."""
    truth = Truth(back_and_forth(3.5))
    figs = []
    for label, period, n_points in (("16-point", 50_000, 16), ("2048-point", 1_000_000, 2048)):
        st = make_streams(truth, 3.0, seed, profile_period_ns=period)
        y = np.linspace(-0.02, 0.02, n_points)
        z = np.full(n_points, 0.15)
        v = np.ones(n_points, dtype=bool)
        recs = records(st, lambda _p, y=y, z=z, v=v: (y, z, v))  # type: ignore[misc]
        pairer = Pairer(pairer_config(SENSOR_LATENCY_NS))
        t = time.process_time()
        run_pairer(pairer, recs, poll_every=32, on_batch=lambda _b: None)
        elapsed = time.process_time() - t
        rate = pairer.paired / elapsed
        if n_points == 16:
            figs.append(
                Figure(
                    f"throughput: {label} profiles paired", rate, "1/s", ">= 20000", rate >= 20_000
                )
            )
        else:
            figs.append(Figure(f"throughput: {label} profiles paired", rate, "1/s", "", None))
    return figs


def figure_reset_and_wrap(seed: int, latency_ns: int) -> list[Figure]:
    """A 24-bit us counter wrapping at 4 s and a sensor reboot (50 ms outage) at 8 s."""
    seconds = 12.0
    m = 1 << 24
    t_reboot = T0 + 8 * S

    def sensor_clock(stamp: IntArray) -> IntArray:
        us = np.rint((stamp - SENSOR_OFFSET_NS - T0) / (1.0 + SENSOR_DRIFT) / 1e3).astype(np.int64)
        us += m - 4_000_000  # wraps 4 s into the run
        after = stamp >= t_reboot + 50 * MS
        us[after] = np.rint((stamp[after] - t_reboot - 50 * MS) / 1e3).astype(np.int64)
        return (us % m) * 1000

    truth = Truth(back_and_forth(seconds))
    st = make_streams(
        truth, seconds, seed, sensor_clock=sensor_clock, outage=(t_reboot, t_reboot + 50 * MS)
    )
    n_exposed = int(seconds * S / (SENSOR_PERIOD_NS * (1.0 + SENSOR_DRIFT)))
    inside = n_exposed - st.exposure.shape[0]
    pairer = Pairer(pairer_config(latency_ns, sensor_time_modulus_ns=m * 1000))
    batches = run_pairer(pairer, records(st))
    clk = pairer.sensor_clock(1)
    unwrapper = pairer.sensor_unwrapper(1)
    wraps = unwrapper.n_wraps if unwrapper is not None else 0
    lost = n_exposed - pairer.paired
    fc = np.concatenate([b.frame_counter for b in batches])
    F = np.concatenate([b.flange2base for b in batches])
    e_true = st.exposure[np.searchsorted(st.frame, fc)]
    after = e_true >= t_reboot
    disp = point_displacement(truth, F[after], e_true[after])
    return [
        Figure("reset+wrap: profiles inside the reset (outage)", inside, "", "", None),
        Figure(
            "reset+wrap: profiles lost, outage included", lost, "", f"<= {inside}", lost <= inside
        ),
        Figure(
            "reset+wrap: sensor clock fit restarts", clk.n_resets, "", "== 1", clk.n_resets == 1
        ),
        Figure("reset+wrap: counter wraps unwrapped", wraps, "", "== 1", wraps == 1),
        Figure(
            "reset+wrap: displacement RMS after reboot",
            float(np.sqrt(np.mean(disp**2))) * 1e3,
            "mm",
            "",
            None,
        ),
    ]


# ----------------------------------------------------------------------------- loaded receiver
#
# What a loaded 2-core host does to arrival times (measured with `wristscan demo`, see
# docs/sync.md): the receiving process is starved of CPU now and then, so records queue in the
# socket and are read late, in bursts. Both streams are read by the same process, so they share
# the schedule of these episodes.

LOADED_FLOOR_NS = 50_000  # smallest loopback delay
LOADED_JITTER_NS = 100_000  # gamma(shape 2) standard deviation on top of it
LOADED_SPIKE_P = 0.02  # share of records delayed by a heavy-tailed extra (Pareto, alpha 1.5)
LOADED_SERVICE_NS = 30_000  # CPU time the reader needs per record, normally
LOADED_BACKLOG_NS = 300_000_000  # sensor records queued before the daemon starts reading
LOADED_SENSOR_OFFSET_NS = 1000 * S  # as the simulated sensor: clock 1000 s ahead, 30 ppm fast
LOADED_SENSOR_DRIFT = 30e-6
LOADED_PERIOD_NS = 2_000_000  # both streams at 500 Hz, as in the demo


@dataclass(frozen=True)
class Load:
    """Episodes (host ns, ``(k, 2)`` start/end) when the receiving process is short of CPU."""

    stalls: IntArray
    """Nothing is read (50-800 ms); the queue is then read in a burst."""
    loads: IntArray
    """The reader wakes 1-5 ms late for each record (1-4 s)."""
    overloads: IntArray
    """Reading a record takes 1.2-1.6 record periods: a backlog grows linearly (0.3-1.5 s)."""


def _episodes(
    rng: np.random.Generator,
    t0: int,
    t1: int,
    gap_s: tuple[float, float],
    dur_s: tuple[float, float],
) -> IntArray:
    out: list[tuple[int, int]] = []
    t = t0 + rng.uniform(*gap_s) * S
    while t < t1:
        d = rng.uniform(*dur_s) * S
        out.append((round(t), round(t + d)))
        t += d + rng.uniform(*gap_s) * S
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def load_schedule(rng: np.random.Generator, seconds: float) -> Load:
    t1 = T0 + round(seconds * S)
    return Load(
        stalls=_episodes(rng, T0, t1, (1.0, 4.0), (0.05, 0.8)),
        loads=_episodes(rng, T0, t1, (2.0, 6.0), (1.0, 4.0)),
        overloads=_episodes(rng, T0, t1, (4.0, 10.0), (0.3, 1.5)),
    )


def _end_of(t: int, episodes: IntArray) -> int:
    """End of the episode containing host time ``t``, or -1."""
    k = int(np.searchsorted(episodes[:, 0], t, side="right")) - 1
    return int(episodes[k, 1]) if k >= 0 and t < episodes[k, 1] else -1


def receive(
    rng: np.random.Generator,
    sent: IntArray,
    start_ns: int,
    load: Load,
    period_ns: int,
    max_backlog_ns: int = S,
) -> tuple[IntArray, NDArray[np.bool_]]:
    """Host receive stamps of records sent at ``sent`` (sorted, ns), read one at a time in order
    by a process that starts reading at ``start_ns``, under ``load``. Records arriving when the
    queue is ``max_backlog_ns`` deep are lost (socket buffer full). Returns (stamps, kept)."""
    n = sent.shape[0]
    net = np.asarray(LOADED_FLOOR_NS + rng.gamma(2.0, LOADED_JITTER_NS / math.sqrt(2.0), n))
    spike = np.asarray(rng.random(n) < LOADED_SPIKE_P)
    net[spike] += np.minimum(rng.pareto(1.5, int(spike.sum())) * MS, 200 * MS)
    ready = (sent + np.rint(net).astype(np.int64)).tolist()
    late = np.asarray(rng.uniform(1 * MS, 5 * MS, n))  # wake-up delay under load
    slow = np.asarray(rng.uniform(1.2, 1.6, n)) * period_ns
    stamp = np.zeros(n, dtype=np.int64)
    kept = np.ones(n, dtype=bool)
    done = start_ns  # when the reader is free for the next record
    for i in range(n):
        r = ready[i]
        if done - r > max_backlog_ns:
            kept[i] = False
            continue
        s = done
        if r > done:  # queue empty: the reader sleeps until the record comes
            s = r + (int(late[i]) if _end_of(r, load.loads) >= 0 else 0)
        while (end := _end_of(s, load.stalls)) >= 0:
            s = end
        stamp[i] = s
        over = _end_of(s, load.overloads) >= 0
        done = s + (int(slow[i]) if over else LOADED_SERVICE_NS)
    return stamp, kept


def make_loaded_streams(truth: Truth, seconds: float, seed: int) -> tuple[Streams, Load]:
    """500 Hz robot and sensor streams read by a loaded process; the sensor's records of the
    0.3 s before the daemon starts reading are queued and read in a burst at start."""
    rng = np.random.default_rng(seed)
    load = load_schedule(rng, seconds)
    n_r = int((seconds + 0.5) * S / LOADED_PERIOD_NS)
    k = np.arange(n_r, dtype=np.int64)
    ctrl = C0 + k * LOADED_PERIOD_NS
    h = T0 + np.rint(k * LOADED_PERIOD_NS * (1.0 + ROBOT_DRIFT)).astype(np.int64)
    r_arr, r_kept = receive(rng, h, T0, load, LOADED_PERIOD_NS)
    j = np.arange(int((seconds + LOADED_BACKLOG_NS / S) * S / LOADED_PERIOD_NS), dtype=np.int64)
    exposure = T0 - LOADED_BACKLOG_NS + j * LOADED_PERIOD_NS
    stamp = exposure + SENSOR_LATENCY_NS
    dev = LOADED_SENSOR_OFFSET_NS + np.rint((stamp - T0) * (1.0 + LOADED_SENSOR_DRIFT)).astype(
        np.int64
    )
    s_arr, s_kept = receive(rng, stamp, T0, load, LOADED_PERIOD_NS)
    h = h[r_kept]
    st = Streams(
        ctrl_ns=ctrl[r_kept],
        robot_true_ns=h,
        robot_arrival=r_arr[r_kept],
        q=truth.q(h),
        tcp=se3.matrix_to_pose(truth.flange2base(h)),
        exposure=exposure[s_kept],
        stamp_true=stamp[s_kept],
        sensor_ns=dev[s_kept],
        sensor_arrival=s_arr[s_kept],
        frame=j[s_kept],
    )
    return st, load


def _total(episodes: IntArray) -> float:
    return float(np.sum(episodes[:, 1] - episodes[:, 0])) / S


def figure_load_and_stalls(seed: int) -> list[Figure]:
    """Clock mapping and pairing when the receiving process is starved of CPU (see receive)."""
    seconds = 20.0
    truth = Truth(back_and_forth(seconds))
    st, load = make_loaded_streams(truth, seconds, seed)
    after = T0 + S // 2
    # 1. The sensor clock alone, causally: each stamp mapped with the line known at its arrival.
    cfg = pairer_config(SENSOR_LATENCY_NS)
    clk = ClockMapper(cfg.sensor_clock)
    n = st.sensor_ns.shape[0]
    err = np.full(n, np.nan)
    drift = np.full(n, np.nan)
    for i in range(n):
        e = clk.feed(int(st.sensor_ns[i]), int(st.sensor_arrival[i]))
        if clk.is_locked(e):
            truth_ns = st.stamp_true[i] + LOADED_FLOOR_NS
            err[i] = float(clk.to_host(st.sensor_ns[i], e)) - truth_ns
            drift[i] = clk.drift
    locked = ~np.isnan(err)
    first_lock_ms = float(st.sensor_arrival[int(np.argmax(locked))] - T0) / 1e6
    late = st.sensor_arrival >= after
    unlocked_late = int(np.count_nonzero(late & ~locked))
    rms = float(np.sqrt(np.nanmean(err[late] ** 2)))
    true_drift = 1.0 / (1.0 + LOADED_SENSOR_DRIFT) - 1.0
    settled = st.sensor_arrival >= T0 + 5 * S
    drift_err = float(np.nanmax(np.abs(drift[settled] - true_drift)))
    delay = (st.sensor_arrival - st.stamp_true) / 1e6
    # 2. Pairing: profiles dropped for an unlocked clock once the first 0.5 s are over (counted
    # from the first profile received after 0.5 s: conservative, earlier ones may be included).
    pairer = Pairer(cfg)
    recs = records(st)
    base: dict[str, int] | None = None
    batches: list[PairedBatch] = []
    for i, r in enumerate(recs):
        if isinstance(r, Profile):
            if base is None and r.host_time_ns >= after:
                base = dict(pairer.dropped)
            pairer.add_profile(r)
        else:
            pairer.add_robot_state(r)  # type: ignore[arg-type]
        if i % 16 == 0:
            batches += pairer.poll()
    batches += pairer.poll(pairer.latest_host_ns + 2 * S)
    assert base is not None
    lost_clock = int(pairer.dropped["clock_unlocked"] - base["clock_unlocked"])
    lost_robot = int(pairer.dropped["robot_clock_unlocked"] - base["robot_clock_unlocked"])
    fc = np.concatenate([b.frame_counter for b in batches])
    ex = np.concatenate([b.exposure_ns for b in batches])
    F = np.concatenate([b.flange2base for b in batches])
    idx = np.searchsorted(st.frame, fc)
    e_true = st.exposure[idx]
    sel = st.sensor_arrival[idx] >= after
    # With equal delay floors the pose lookup needs only the sensor latency, but the exposure
    # reported on the host clock is then late by that floor (see docs/sync.md).
    ex_err = ex[sel] - LOADED_FLOOR_NS - e_true[sel]
    rms_ex = float(np.sqrt(np.mean(ex_err.astype(np.float64) ** 2)))
    steady = sel & (np.abs(truth.speed(e_true) - SPEED) < 1e-6)
    disp = point_displacement(truth, F[steady], e_true[steady])
    robot_resets = pairer.robot_clock.n_resets
    sensor = pairer.sensor_clock(1)
    dropped = {k: v for k, v in pairer.dropped.items() if v}
    return [
        Figure("load: stalls (50-800 ms)", len(load.stalls), "", "", None),
        Figure(
            "load: time under load / overload",
            _total(load.loads) + _total(load.overloads),
            "s",
            "",
            None,
        ),
        Figure("load: sensor delay median", float(np.median(delay)), "ms", "", None),
        Figure(
            "load: sensor delay 99th percentile", float(np.percentile(delay, 99)), "ms", "", None
        ),
        Figure("load: sensor clock restarts", clk.n_resets, "", "== 0", clk.n_resets == 0),
        Figure("load: sensor clock re-anchors", clk.n_reanchors, "", "", None),
        Figure("load: first lock after start", first_lock_ms, "ms", "<= 300", first_lock_ms <= 300),
        Figure(
            "load: arrivals unlocked after 0.5 s", unlocked_late, "", "== 0", unlocked_late == 0
        ),
        Figure("load: mapped time error RMS (t >= 0.5 s)", rms / 1e3, "us", "<= 200", rms <= 2e5),
        Figure(
            "load: max |error| (t >= 0.5 s)",
            float(np.nanmax(np.abs(err[late]))) / 1e3,
            "us",
            "",
            None,
        ),
        Figure(
            "load: drift estimate", clk.drift * 1e6, "ppm", f"{true_drift * 1e6:.2f} (truth)", None
        ),
        Figure("load: max drift error (t >= 5 s)", drift_err * 1e6, "ppm", "", None),
        Figure("load: robot clock restarts (pairer)", robot_resets, "", "== 0", robot_resets == 0),
        Figure("load: dropped clock_unlocked after 0.5 s", lost_clock, "", "== 0", lost_clock == 0),
        Figure(
            "load: dropped robot_clock_unlocked after 0.5 s",
            lost_robot,
            "",
            "== 0",
            lost_robot == 0,
        ),
        Figure("load: paired exposure error RMS (t >= 0.5 s)", rms_ex / 1e3, "us", "", None),
        Figure(
            "load: displacement RMS, wristscan",
            float(np.sqrt(np.mean(disp**2))) * 1e3,
            "mm",
            "",
            None,
        ),
        Figure("load: profiles paired / received", pairer.paired / pairer.received, "", "", None),
        Figure("load: profiles dropped, all reasons", sum(dropped.values()), "", "", None),
        Figure(
            "load: sensor clock restarts (pairer)",
            sensor.n_resets,
            "",
            "== 0",
            sensor.n_resets == 0,
        ),
    ]


# ----------------------------------------------------------------------------- block pairing


@dataclass
class TickStreams:
    """A fast sensor read in ticks: per tick, the profiles that arrived (a block's arrays)."""

    dev: IntArray
    arrive: IntArray
    y: FloatArray
    z: FloatArray
    valid: NDArray[np.bool_]
    states: list[RobotState]
    state_arrive: IntArray
    ticks: IntArray


def make_tick_streams(
    rate_hz: float, n_points: int, seconds: float, tick_ns: int, seed: int
) -> TickStreams:
    """Profiles at ``rate_hz`` (sensor clock +50 ppm, gamma delays) and a moving 500 Hz robot
    (controller clock -30 ppm), both as the pipeline reads them every ``tick_ns``."""
    rng = np.random.default_rng(seed)
    n = int(rate_hz * seconds)
    t_exp = T0 + np.rint(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    stamp = t_exp + SENSOR_LATENCY_NS
    dev = np.rint((stamp - T0) / (1.0 + SENSOR_DRIFT)).astype(np.int64) + 777 * S
    arrive = np.maximum.accumulate(stamp + DELAY_FLOOR_NS + _delays(rng, n, 100_000.0))
    y = np.linspace(-0.025, 0.025, n_points)
    y.flags.writeable = False  # a driver's shared lateral grid
    z = 0.15 + rng.normal(0.0, 20e-6, (n, n_points))
    c = np.arange(-100 * MS, int(seconds * S) + 200 * MS, ROBOT_PERIOD_NS)
    h = T0 + np.rint(c * (1.0 + ROBOT_DRIFT)).astype(np.int64)
    r_arrive = np.maximum.accumulate(h + DELAY_FLOOR_NS + _delays(rng, c.shape[0], 100_000.0))
    q0 = np.array([0.3, -1.2, 1.4, -1.8, -1.57, 0.2])
    w = np.array([0.2, -0.1, 0.15, 0.3, -0.25, 0.5])
    states = [
        RobotState((C0 + int(ci)) / 1e9, int(a), q0 + w * ci * 1e-9, np.zeros(6))
        for ci, a in zip(c.tolist(), r_arrive.tolist(), strict=True)
    ]
    ticks = np.arange(T0 + tick_ns, int(arrive[-1]) + 3 * tick_ns, tick_ns)
    return TickStreams(dev, arrive, y, z, np.ones(z.shape, bool), states, r_arrive, ticks)


def _timed(f: Callable[..., object], acc: list[int]) -> Callable[..., object]:
    def g(*a: object) -> object:
        t = time.thread_time_ns()
        out = f(*a)
        acc[0] += time.thread_time_ns() - t
        return out

    return g


def _stream_block(st: TickStreams, a: int, b: int) -> ProfileBlock:
    """Profiles ``a .. b - 1`` of a block stream as the driver would hand them over."""
    return ProfileBlock(
        np.ones(b - a, np.int64),
        np.arange(a, b),
        st.dev[a:b].copy(),
        st.arrive[a:b].copy(),
        st.y,
        st.z[a:b].copy(),
        st.valid[a:b].copy(),
    )


def pair_ticks(st: TickStreams, blocks: bool, warm_ns: int = 500 * MS) -> dict[str, float]:
    """Thread CPU per profile of pairing (add + poll, batches built) read tick by tick, after
    ``warm_ns``: the profiles of each tick handed over as one block, or record by record. The
    block's arrays are fresh each tick (just decoded) and records are built outside the timing;
    the robot states are added outside it too (their own stream)."""
    pairer = Pairer(pairer_config(SENSOR_LATENCY_NS))
    interp, feed = [0], [0]
    # Robot interpolation + FK: locating the instants and the poses (the poll's shortcut for
    # an all-ready tick calls these two directly, the general path through interpolate();
    # compiled, the shortcut does both in one call with the clock mappings: that call).
    mapped = readytick._mapped_compiled
    readytick._mapped_compiled = _timed(mapped, interp)  # type: ignore[assignment]
    try:
        return _pair_ticks(st, blocks, warm_ns, pairer, interp, feed)
    finally:
        readytick._mapped_compiled = mapped


def _pair_ticks(
    st: TickStreams,
    blocks: bool,
    warm_ns: int,
    pairer: Pairer,
    interp: list[int],
    feed: list[int],
) -> dict[str, float]:
    robot = pairer.robot
    robot._poses = _timed(robot._poses, interp)  # type: ignore[method-assign,assignment]
    buf = robot.buffer
    buf._locate = _timed(buf._locate, interp)  # type: ignore[method-assign,assignment]
    clk = pairer.sensor_clock(1)
    clk.feed_many = _timed(clk.feed_many, feed)  # type: ignore[method-assign,assignment]
    clk.feed = _timed(clk.feed, feed)  # type: ignore[method-assign,assignment]
    pi = np.searchsorted(st.arrive, st.ticks, side="right")
    ri = np.searchsorted(st.state_arrive, st.ticks, side="right")
    a = b = 0
    cpu = counted = 0
    n_interp = n_feed = 0
    for tick, pe, re in zip(st.ticks.tolist(), pi.tolist(), ri.tolist(), strict=True):
        pairer.add_robot_states(st.states[b:re])
        b = re
        block = _stream_block(st, a, pe)
        recs = [] if blocks else [block.profile(k) for k in range(pe - a)]
        interp[0] = feed[0] = 0
        t = time.thread_time_ns()
        if blocks and pe > a:
            pairer.add_block(block)
        for r in recs:
            pairer.add_profile(r)
        pairer.poll()
        if tick > T0 + warm_ns:
            cpu += time.thread_time_ns() - t
            n_interp += interp[0]
            n_feed += feed[0]
            counted += pe - a
        a = pe
    pairer.poll(pairer.latest_host_ns + S)
    if pairer.paired != st.arrive.shape[0]:
        raise RuntimeError(f"paired {pairer.paired} of {st.arrive.shape[0]}: {pairer.dropped}")
    return {
        "us": cpu / counted / 1e3,
        "robot_us": n_interp / counted / 1e3,
        "feed_us": n_feed / counted / 1e3,
    }


def figure_block_pairing(
    rate_hz: float = 5000.0, n_points: int = 2048, seconds: float = 2.0, runs: int = 5
) -> list[Figure]:
    """Pairing CPU per profile, 5 kHz x 2048 points in 10 ms ticks: blocks against records
    (medians of ``runs`` alternating runs; the machine is shared)."""
    st = make_tick_streams(rate_hz, n_points, seconds, 10 * MS, seed=11)
    got: dict[bool, list[dict[str, float]]] = {True: [], False: []}
    for _ in range(runs):
        for blocks in (True, False):
            got[blocks].append(pair_ticks(st, blocks))

    def med(blocks: bool, key: str) -> float:
        return float(np.median([g[key] for g in got[blocks]]))

    blk, rec = med(True, "us"), med(False, "us")
    label = f"blocks: {rate_hz / 1e3:g} kHz x {n_points}, 10 ms ticks"
    return [
        Figure(f"{label}, pairing CPU per profile (add_block + poll)", blk, "us", "<= 3", blk <= 3),
        Figure(f"{label}, same record by record (add_profile)", rec, "us", "", None),
        Figure(
            f"{label}, of which robot interpolation + FK (compiled: with the mappings)",
            med(True, "robot_us"),
            "us",
            "",
            None,
        ),
        Figure(f"{label}, of which sensor clock feed_many", med(True, "feed_us"), "us", "", None),
        Figure(f"{label}, records: sensor clock feed", med(False, "feed_us"), "us", "", None),
    ]


def tick_cpu_us(st: TickStreams, warm_ns: int = 500 * MS) -> float:
    """Thread CPU per 10 ms tick of everything the pairer does in it (the tick's robot states
    added at once, its profiles as one block, the poll with its batches built), after
    ``warm_ns``."""
    pairer = Pairer(pairer_config(SENSOR_LATENCY_NS))
    pi = np.searchsorted(st.arrive, st.ticks, side="right")
    ri = np.searchsorted(st.state_arrive, st.ticks, side="right")
    a = b = cpu = n = 0
    for tick, pe, re in zip(st.ticks.tolist(), pi.tolist(), ri.tolist(), strict=True):
        block = _stream_block(st, a, pe)
        t = time.thread_time_ns()
        pairer.add_robot_states(st.states[b:re])
        if pe > a:
            pairer.add_block(block)
        pairer.poll()
        if tick > T0 + warm_ns:
            cpu += time.thread_time_ns() - t
            n += 1
        a, b = pe, re
    return cpu / max(n, 1) / 1e3


def figure_tick_cost(rates: tuple[float, float] = (1000.0, 5000.0), runs: int = 5) -> list[Figure]:
    """The pairer's CPU per 10 ms tick at two rates (512-point profiles, medians of ``runs``
    alternating runs) split into a fixed part per tick and a part per profile (issue 21: at
    1-5 kHz the fixed part is most of the pairing)."""
    st = [make_tick_streams(r, 512, 2.0, 10 * MS, seed=12) for r in rates]
    got: list[list[float]] = [[], []]
    for _ in range(runs):
        for k in (0, 1):
            got[k].append(tick_cpu_us(st[k]))
    c1, c2 = (float(np.median(g)) for g in got)
    per_profile = (c2 - c1) / ((rates[1] - rates[0]) / 100.0)
    fixed = c1 - per_profile * rates[0] / 100.0
    label = "pairer per 10 ms tick"
    return [
        Figure(f"{label} at {rates[0] / 1e3:g} kHz (states + block + poll)", c1, "us", "", None),
        Figure(f"{label} at {rates[1] / 1e3:g} kHz", c2, "us", "", None),
        Figure(f"{label}: fixed part", fixed, "us", "", None),
        Figure(f"{label}: per profile", per_profile, "us", "", None),
    ]


def run(seed: int = 1) -> list[Figure]:
    figs, latency_ns = figure_latency(seed)
    return (
        figure_clock_and_pairing(seed, latency_ns)
        + figs
        + figure_throughput(seed)
        + figure_reset_and_wrap(seed, latency_ns)
        + figure_load_and_stalls(seed)
        + figure_block_pairing()
        + figure_tick_cost()
        + figure_feed_blocks()
        + figure_late_sender(seed=seed)
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--blocks-only", action="store_true", help="only the block pairing figures (issue 21)"
    )
    ap.add_argument(
        "--clock-only",
        action="store_true",
        help="only the clock feed and late-sender figures (issue 21)",
    )
    args = ap.parse_args(argv)
    if args.clock_only:
        figs = figure_feed_blocks() + figure_late_sender(seed=args.seed)
        return report("sync: clock feed, late sender (issue 21)", figs, json_out=args.json)
    if args.blocks_only:
        figs = figure_block_pairing() + figure_tick_cost()
        return report("sync: block pairing (issue 21)", figs, json_out=args.json)
    return report("sync (issue 5)", run(args.seed), json_out=args.json)


if __name__ == "__main__":
    sys.exit(main())
