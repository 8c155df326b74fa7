"""What the tests and the benchmarks share: reference data and checks against the simulator's
truth, in one place (benchmarks put this folder on ``sys.path``; pytest does for the tests)."""

from __future__ import annotations

import contextlib
import math
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import kinematics as kin
from wristscan.drivers.base import Robot
from wristscan.drivers.records import Profile, RobotState

# KinematicsInfo of a real UR10e as printed in Universal_Robots_ROS2_Driver
# ur_calibration/doc/algorithm.rst (complete calibrated DH values, not deltas).
REAL_UR10E = kin.from_kinematics_info(
    theta=[-2.4147806894359e-07, 1.60233952386695, -1.68607190752171, 0.0837331147700119,
           -1.01260355871158e-07, 3.91986209186124e-08],
    a=[2.12234865571206e-05, 0.0193171326277006, -0.569251663611088, -4.61409023720934e-05,
       -6.39280053471802e-05, 0.0],
    d=[0.180539811714259, 439.140974079901, -446.027059806332, 7.0603368964236,
       0.119811341150314, 0.115670917257426],
    alpha=[1.57014608044242, 0.0013941666682559, 0.00693818880325995, 1.56998468543761,
           -1.57038520649543, 0.0],
    name="real UR10e",
)  # fmt: skip


def same_profile(a: Profile, b: Profile) -> bool:
    """Two profiles carry the same data (NaN where the other has NaN)."""

    def eq(x: Any, y: Any) -> bool:
        if x is None or y is None:
            return x is None and y is None
        return bool(np.array_equal(x, y, equal_nan=x.dtype.kind == "f"))

    return (
        (a.sensor_id, a.frame_counter, a.sensor_time_ns, a.encoder)
        == (b.sensor_id, b.frame_counter, b.sensor_time_ns, b.encoder)
        and eq(a.y, b.y)
        and eq(a.z, b.z)
        and eq(a.valid, b.valid)
        and eq(a.intensity, b.intensity)
    )


def surface(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """A smooth patch (m) with no symmetry: anisotropic paraboloid, cubic term, off-centre bump
    (registration has one right answer on it)."""
    bump = 0.005 * np.exp(-((x - 0.01) ** 2 + (y + 0.015) ** 2) / (2 * 0.01**2))
    return 3.0 * x**2 + 1.0 * y**2 + 2.0 * x**3 + bump


def sample_surface(
    rng: np.random.Generator, x_range: tuple[float, float], step: float
) -> NDArray[np.float64]:
    """Points of :func:`surface` on a jittered grid over ``x_range`` x (-0.04, 0.04) m."""
    gx, gy = np.meshgrid(np.arange(*x_range, step), np.arange(-0.04, 0.04, step))
    x = gx.ravel() + rng.uniform(-step / 3, step / 3, gx.size)
    y = gy.ravel() + rng.uniform(-step / 3, step / 3, gx.size)
    return np.column_stack([x, y, surface(x, y)])


def depth_errors(
    sweep: Any,
    scene: Any,
    sensor2flange: NDArray[np.float64],
    table_angle_rad: float | None,
    n_profiles: int = 30,
) -> NDArray[np.float64]:
    """Measured minus true depth (m) of about ``n_profiles`` profiles of a recorded ``sweep``
    (:class:`~wristscan.daemon.procedure.acquisition.Sweep`): each ray-cast in the simulator's
    true ``scene`` from the robot pose it was paired with. A timing or pose fault shows here
    before any registration can hide it. NaN where the true ray misses."""
    errors = []
    for k in range(0, sweep.n_profiles, max(1, sweep.n_profiles // n_profiles)):
        m = (sweep.profile_index == k) & sweep.valid
        y = sweep.y[m]
        origins = np.column_stack([np.zeros_like(y), y, np.zeros_like(y)])
        dirs = np.tile([0.0, 0.0, 1.0], (y.size, 1))
        t, _ = scene.raycast_bundles(
            (sweep.flange2base[k] @ sensor2flange)[None], origins, dirs, table_angle_rad
        )
        errors.append(sweep.z[m] - t[0])
    return np.concatenate(errors)


# ---------------------------------------------------------------------------------------------
# Loopback addresses and ports a test run owns (issue 16: two runs on one machine never collide)


def own_loopback_host() -> str:
    """A random loopback address ``127.a.b.c`` of this run's own (see
    :func:`~wristscan.drivers.sim.ur.controller.pick_free_loopback_host`): ports chosen on it by
    binding port 0 and releasing it stay free for this run, since no other run binds there."""
    from wristscan.drivers.sim.ur.controller import pick_free_loopback_host

    return pick_free_loopback_host()


def free_tcp_port(host: str) -> int:
    """A TCP port free now on ``host``; take ``host`` from :func:`own_loopback_host` (on a shared
    address such as 127.0.0.1 another process could take the port before the test binds it)."""
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class RefusingPort:
    """A TCP port on ``host`` that refuses connections while held: bound, never listening (the
    kernel answers a connect with a reset). Held rather than released, so no other process can
    start listening there meanwhile. A context manager; ``port`` is the port."""

    def __init__(self, host: str = "127.0.0.1") -> None:
        import socket

        self._sock = socket.socket()
        self._sock.bind((host, 0))
        self.host = host
        self.port = int(self._sock.getsockname()[1])

    def __enter__(self) -> RefusingPort:
        return self

    def __exit__(self, *exc: object) -> None:
        self._sock.close()


def tcp_peers_of_this_process() -> list[tuple[str, int]]:
    """The remote (address, port) of every connected IPv4 TCP socket this process holds (Linux:
    its file descriptors matched with ``/proc/self/net/tcp``). Shows which process a link runs
    in, whatever the load: a driver that keeps its links in child processes holds none."""
    import os
    import socket
    import struct

    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:  # closed meanwhile
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    peers = []
    with open("/proc/self/net/tcp", encoding="ascii") as f:
        next(f)  # header
        for line in f:
            fields = line.split()
            ip_hex, port_hex = fields[2].split(":")
            if fields[9] in inodes and int(port_hex, 16) != 0:
                ip = socket.inet_ntoa(struct.pack("<I", int(ip_hex, 16)))
                peers.append((ip, int(port_hex, 16)))
    return peers


UR5E_WORK_Q = np.array(
    [
        [0.3, -1.9, 1.9, -1.57, -1.57, 0.2],
        [-0.4, -1.5, 1.6, -1.9, -1.4, 1.0],
        [0.8, -2.2, 2.0, -1.2, -1.8, -0.6],
        [0.0, -1.2, 1.3, -2.2, -1.0, 0.4],
        [-0.9, -1.7, 2.3, -1.5, -2.0, 2.0],
        [1.2, -1.4, 1.1, -1.0, -1.6, -1.5],
    ]
)
"""UR5e joint positions (rad) in front of the robot, where a sensor on the flange would scan."""


def ur5e_working_q(n: int, seed: int) -> NDArray[np.float64]:
    """``n`` joint positions scattered (0.25 rad) around :data:`UR5E_WORK_Q`, seeded."""
    rng = np.random.default_rng(seed)
    base = UR5E_WORK_Q[rng.integers(0, len(UR5E_WORK_Q), n)]
    return np.asarray(base + rng.normal(0.0, 0.25, base.shape))


TRUE_POSES_ONLY: dict[str, float] = {"truth_wait_s": 1.5, "max_lag_s": 1.0}
"""Simulated-sensor settings (``start_cell(cfg, **TRUE_POSES_ONLY)``, or a scenario's sensor
overrides) for a test that compares what the cell measured with the simulator's truth. By default
the simulated sensor waits 50 ms for the controller's true pose of an exposure and then ray-casts
from the newest pose it has: on a loaded machine, where the controller process runs late, whole
stretches of a pass are then measured from stale poses (passes 10-75 um off the true part, ICP
corrections up to 70 um, with nothing wrong in wristscan). Waiting longer than the sensor may lag
(beyond which it skips exposures, as a real sensor with a full buffer does) makes every profile
the sensor sends true to its exposure; it only sends later."""


# --------------------------------------------------------------------------------------------
# A cloud against the simulator's true surface: signed distances and a rigid registration


def _box_sd(q: NDArray[np.float64], half: NDArray[np.float64]) -> NDArray[np.float64]:
    d = np.abs(q) - half
    return np.asarray(np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0))


def primitive_signed_distance(prim: Any, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Signed distance (m, positive outside) of points ``p`` (N, 3, in the primitive's mount
    frame) from the surface of a simulated ``Box``, ``Cylinder`` (capped, from local z = 0 up to
    its height), ``Sphere`` or convex ``TriangleMesh`` (the largest face-plane distance: exact
    inside and off the edges, which is what a measured point near a face needs)."""
    from wristscan.drivers.sim.mesh import TriangleMesh
    from wristscan.drivers.sim.scene import Box, Cylinder, Sphere

    q = p @ prim.mount2local[:3, :3].T + prim.mount2local[:3, 3]
    if isinstance(prim, Box):
        return _box_sd(q, np.asarray(prim.half))
    if isinstance(prim, Cylinder):
        r = np.hypot(q[:, 0], q[:, 1]) - prim.radius
        h = np.abs(q[:, 2] - 0.5 * prim.height) - 0.5 * prim.height
        d = np.stack([r, h], axis=1)
        return np.asarray(
            np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)
        )
    if isinstance(prim, Sphere):
        return np.asarray(np.linalg.norm(q, axis=1) - prim.radius)
    if isinstance(prim, TriangleMesh):
        v, f = prim.vertices, prim.faces
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        n = np.cross(b - a, c - a)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        n *= np.sign(np.einsum("ij,ij->i", n, a - v.mean(axis=0)))[:, None]  # outwards
        return np.asarray(np.einsum("pfj,fj->pf", q[:, None, :] - a[None], n).max(axis=1))
    raise TypeError(f"no signed distance for {type(prim).__name__}")


def part_signed_distance(scene: Any, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Signed distance (m) of part-frame points (the scene's table frame) from the union of the
    table-mounted primitives of the simulator's ``scene`` (the platter and the part)."""
    prims = [x for x in scene.primitives if x.mount == "table"]
    return np.asarray(np.min([primitive_signed_distance(x, p) for x in prims], axis=0))


def registration_to_truth(
    points: NDArray[np.float64],
    signed_distance: Any,
    *,
    rotation: bool = False,
    trim_m: float = 0.3e-3,
    max_points: int = 20_000,
    iterations: int = 4,
) -> dict[str, Any]:
    """How far ``points`` (N, 3) lie from the true surface whose signed distance function
    ``signed_distance(p) -> (N,)`` is given: the rigid motion that brings them onto it, by
    Gauss-Newton on the point-to-surface distances (the surface normals by central differences),
    about the cloud's centroid; a translation only unless ``rotation``. A registration against
    the truth, not between clouds. Points farther than ``trim_m`` from the surface, and then
    farther than 4 robust sigmas from it, are left out (a stray profile does not steer it); at
    most ``max_points`` of them are used (a fixed random subset).

    Returns ``shift_m`` (3,): how far the cloud lies from the truth at its centroid (its points
    minus where they belong); ``rotation_rad`` (3,) (its rotation vector about the centroid,
    zero without ``rotation``); ``rms_before_m`` and ``rms_after_m`` (RMS distance of the points
    used); ``n`` (points used); ``centre``."""
    p = np.asarray(points, dtype=np.float64)
    if p.shape[0] > max_points:
        p = p[np.random.default_rng(0).choice(p.shape[0], max_points, replace=False)]
    centre = p.mean(axis=0)
    p = p[np.abs(signed_distance(p)) < trim_m]
    if p.shape[0] < 100:
        raise ValueError(f"registration_to_truth: {p.shape[0]} points near the true surface")
    R, t = np.eye(3), np.zeros(3)
    keep = np.ones(p.shape[0], dtype=bool)
    rms_before = math.nan
    for it in range(iterations):
        q = (p - centre) @ R.T + centre + t
        d = signed_distance(q)
        sigma = 1.4826 * float(np.median(np.abs(d - np.median(d))))
        keep = np.abs(d - np.median(d)) < 4 * sigma
        if it == 0:
            rms_before = float(np.sqrt(np.mean(d[keep] ** 2)))
        q, d = q[keep], d[keep]
        g = np.stack(
            [(signed_distance(q + e) - signed_distance(q - e)) / 2e-6 for e in np.eye(3) * 1e-6],
            axis=1,
        )
        # The step: q -> q + w x (q - centre) + dt.
        J = np.concatenate([np.cross(q - centre, g), g], axis=1) if rotation else g
        step = np.linalg.lstsq(J, -d, rcond=1e-9)[0]
        w = step[:3] if rotation else np.zeros(3)
        dR = _rotvec_matrix(w)
        R, t = dR @ R, dR @ t + step[-3:]
    q = ((p - centre) @ R.T + centre + t)[keep]
    # The correction maps the cloud onto the truth; the cloud's error is its inverse.
    return {
        "shift_m": -(R.T @ t),
        "rotation_rad": -_matrix_rotvec(R),
        "rms_before_m": rms_before,
        "rms_after_m": float(np.sqrt(np.mean(signed_distance(q) ** 2))),
        "n": int(keep.sum()),
        "centre": centre,
    }


def _rotvec_matrix(w: NDArray[np.float64]) -> NDArray[np.float64]:
    angle = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if angle < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(angle) / angle * K + (1 - np.cos(angle)) / angle**2 * K @ K


def _matrix_rotvec(R: NDArray[np.float64]) -> NDArray[np.float64]:
    angle = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return np.zeros(3) if angle < 1e-12 else axis / (2 * np.sin(angle)) * angle


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) of a PNG file's bytes, after checking its signature and the CRC of its
    header chunk (a truncated or foreign file fails the asserts)."""
    import struct
    import zlib

    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG signature"
    length, kind = struct.unpack(">I4s", data[8:16])
    assert kind == b"IHDR" and length == 13, "no PNG header chunk"
    body = data[16 : 16 + length]
    (crc,) = struct.unpack(">I", data[16 + length : 20 + length])
    assert zlib.crc32(kind + body) == crc, "PNG header CRC mismatch"
    width, height = struct.unpack(">II", body[:8])
    return int(width), int(height)


# ---------------------------------------------------------------------------------------------
# TLS certificates for zenoh's tls/ endpoints (docs/security.md), made with the openssl command


def make_tls_files(folder: Path, host: str, client: bool = False) -> Path:
    """In a new ``folder``: a certificate authority (``ca.pem``, ``ca.key``), a server
    certificate for the IP address ``host`` signed by it (``server.pem``, ``server.key``) and,
    with ``client``, a client certificate for mutual TLS (``client.pem``, ``client.key``).
    Returns ``folder``."""
    import subprocess

    def openssl(*args: str | Path) -> None:
        subprocess.run(["openssl", *map(str, args)], check=True, capture_output=True)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"]
    folder.mkdir(parents=True)
    ca, ca_key = folder / "ca.pem", folder / "ca.key"
    openssl("req", "-x509", *ec, "-keyout", ca_key, "-out", ca, "-days", "2", "-subj", "/CN=CA")
    kinds = {"server": f"subjectAltName=IP:{host}\n"}
    if client:
        kinds["client"] = "extendedKeyUsage=clientAuth\n"
    for kind, extension in kinds.items():
        key, csr, ext = (folder / f"{kind}.{x}" for x in ("key", "csr", "cnf"))
        openssl("req", *ec, "-keyout", key, "-out", csr, "-subj", f"/CN=wristscan {kind}")
        ext.write_text(extension)
        signing = ["-CA", ca, "-CAkey", ca_key, "-CAcreateserial", "-days", "2"]
        openssl(
            "x509", "-req", "-in", csr, *signing, "-out", folder / f"{kind}.pem", "-extfile", ext
        )
    return folder


# ---------------------------------------------------------------------------------------------
# A short scan of the demo part


def demo_part_one_pass_plan() -> Any:
    """One pass over the demo part's top (a plan of ``generate_plan``, table at 0 deg, the
    sensor tilted 20 deg, 20 mm/s: 0.3 ms of timing error moves the points 6 um along it): what
    the end-to-end tests of another sensor or robot driver scan."""
    from wristscan.daemon.scan.plan_generate import generate_plan

    plan = generate_plan(
        (0.02, -0.01, 0.03),
        (0.06, 0.03, 0.09),
        fov_width_m=0.05,
        overlap=0.3,
        standoff_m=0.1,
        table_angles_deg=[0.0],
        tilts_deg=[20.0],
        depth_range_m=(0.05, 0.15),
        speed_m_s=0.02,
    )
    return plan.model_copy(update={"passes": plan.passes[:1]})


# ---------------------------------------------------------------------------------------------
# The daemon's zenoh face publishing on loopback, for the client commands' tests


@contextlib.contextmanager
def loopback_publisher(
    prefix: str, step: Callable[[Any, int], None], **face: Any
) -> Iterator[tuple[str, Any]]:
    """The daemon's own zenoh face (``DaemonZenoh(session, prefix, **face)``) listening on a
    loopback address of this run's own, ``step(face, k)`` called every 10 ms (k = 0, 1, ...) in
    a thread until the block ends; yields ``(endpoint, face)``. Everything is closed after."""
    import threading

    from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session

    host = own_loopback_host()
    endpoint = f"tcp/{host}:{free_tcp_port(host)}"
    session = open_session(listen=[endpoint])
    dz = DaemonZenoh(session, prefix, **face)
    stop = threading.Event()

    def publish() -> None:
        k = 0
        while not stop.is_set():
            step(dz, k)
            k += 1
            stop.wait(0.01)

    thread = threading.Thread(target=publish, name="test-publisher")
    thread.start()
    try:
        yield endpoint, dz
    finally:
        stop.set()
        thread.join()
        dz.close()
        session.close()


def late_sender_arrivals(
    seconds: float,
    rate_hz: float = 10_000.0,
    model: str = "jitter",
    seed: int = 0,
    drift: float = 30e-6,
    spikes_per_s: float = 0.5,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """A sensor whose records leave 5-50 ms after their stamp (issue 21): device stamps, host
    receive times and the true host instants of the stamps (ns), in arrival order.

    The device clock runs ``drift`` fast and starts 1000 s ahead. The sender's lag, by model:
    ``"wakeups"``: a sender waking every 0-45 ms (spikes: 100-300 ms) that sends the records at
    least 5 ms old (what ``SensorSimConfig.send_late_s`` does); ``"jitter"``: independent per
    record, uniform 5-50 ms; ``"catch-up"``: a sender falling behind (its lag grows by 0-30 % of
    the record period per record, from 5 ms) until it catches up at a random 20-50 ms;
    ``"wander"``: a lag wandering slowly over 5-50 ms; ``"overrun"``: a sender computing at 60 %
    of the rate, whose lag grows from 0 to 1 s and stays there (the issue's 20 kHz simulator).
    Then ``spikes_per_s`` spikes of a further 100-300 ms. One sender on one socket sends in
    order: a late record holds back those behind it, which then
    leave in a burst. The loopback adds 50 us + gamma jitter (mean 0.1 ms).
    """
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    period = 1e9 / rate_hz
    t_stamp = 7_000_000_000 + np.rint(np.arange(n) * period).astype(np.int64)
    dev = 1000 * 10**9 + np.rint((t_stamp - t_stamp[0]) * (1.0 + drift)).astype(np.int64)
    ms = 1e6
    if model == "wakeups":
        # A sender that wakes every uniform(0, 45) ms (a spike: 100-300 ms later) and sends the
        # records at least 5 ms old: each late by 5-50 ms, the oldest of a burst the most.
        gaps = rng.uniform(0.0, 45 * ms, n)
        spike = rng.random(n) < spikes_per_s * 0.0225
        gaps[spike] += rng.uniform(100 * ms, 300 * ms, int(spike.sum()))
        wakes = t_stamp[0] + np.cumsum(gaps)
        sent = wakes[np.searchsorted(wakes, t_stamp + 5 * ms)].astype(np.int64)
        host = sent + np.rint(50_000 + rng.gamma(2.0, 50_000.0, n)).astype(np.int64)
        return dev, np.maximum.accumulate(host), t_stamp
    if model == "jitter":
        lag = rng.uniform(5 * ms, 50 * ms, n)
    elif model == "catch-up":
        grow = period * rng.uniform(0.0, 0.3, n)
        lag = np.empty(n)
        now, limit = 5 * ms, rng.uniform(20 * ms, 50 * ms)
        for i in range(n):  # a short recursion (test data, not library code)
            now += grow[i]
            if now > limit:
                now, limit = 5 * ms, rng.uniform(20 * ms, 50 * ms)
            lag[i] = now
    elif model == "wander":
        walk = np.cumsum(rng.normal(0.0, 0.3 * ms * np.sqrt(1e4 / rate_hz), n))
        lag = 5 * ms + np.abs((walk % (90 * ms)) - 45 * ms)
    elif model == "overrun":
        # A simulator computing at 60 % of the rate: its lag grows from 0 until exposures are
        # skipped at 1 s (SensorSimConfig.max_lag_s), then stays there (saw-tooth of chunks).
        lag = np.minimum(0.4 * (t_stamp - t_stamp[0]), 1e9) + rng.uniform(0, 3.2 * ms, n)
    else:
        raise ValueError(f"unknown late-sender model {model!r}")
    spike = rng.random(n) < spikes_per_s / rate_hz
    lag[spike] += rng.uniform(100 * ms, 300 * ms, int(spike.sum()))
    sent = np.maximum.accumulate(t_stamp + np.rint(lag).astype(np.int64))
    host = sent + np.rint(50_000 + rng.gamma(2.0, 50_000.0, n)).astype(np.int64)
    return dev, np.maximum.accumulate(host), t_stamp


def wait_for(cond: Any, what: str, timeout: float = 30.0) -> None:
    """Poll ``cond()`` every 10 ms until it is true; fail with ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def publish_until(
    publish: Callable[[], object],
    arrived: Callable[[], bool],
    what: str,
    every_s: float = 0.2,
    timeout: float = 30.0,
) -> None:
    """``publish()`` every ``every_s`` until ``arrived()`` (polled every 10 ms: returns as soon
    as it is true); fail with ``what`` after ``timeout`` s. For a subscriber that may match the
    publisher only after its first samples went by."""
    deadline = time.monotonic() + timeout
    while not arrived():
        assert time.monotonic() < deadline, what
        publish()
        until = min(time.monotonic() + every_s, deadline)
        while not arrived() and time.monotonic() < until:
            time.sleep(0.01)


class StandInRobot(Robot):
    """A controller stand-in for pipeline tests: its link opens and closes, it cannot move, and
    it sends no state unless a subclass's ``_read_internal`` makes one (the arm still)."""

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _read_internal(self, timeout: float | None) -> RobotState | None:
        time.sleep(min(timeout if timeout is not None else 0.05, 0.05))
        return None

    def tcp_offset(self) -> NDArray[np.float64]:
        return np.zeros(6)

    def move_l(self, pose: Any, speed: float, accel: float, asynchronous: bool = False) -> None:
        raise NotImplementedError

    def move_j(self, q: Any, speed: float, accel: float, asynchronous: bool = False) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        pass


def udp_receiver(rcvbuf: int = 4 << 20, timeout_s: float = 2.0) -> socket.socket:
    """A UDP socket bound to a free port on 127.0.0.1, with a receive buffer and a timeout."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(timeout_s)
    return rx
