"""The daemon's hot path in-process: CPU time per profile of each step, on the pipeline's own code.

A :class:`~wristscan.daemon.service.pipeline.Pipeline` is built as ``wristscan run`` builds it
(the real LPF1-over-UDP driver on a loopback socket, a :class:`Pairer`, the calibration) but
not started: this thread drives its tick itself. Each 10 ms tick of a ``rate_hz`` x
``n_points`` stream, the tick's LPF1 datagrams are sent to the driver's socket (not timed) and
the tick's 500 Hz robot states put in the worker's queue, then the worker's own steps run:
``_read_sensor_inline`` (receive + decode into blocks), ``_drain`` (states, admission, pairing
input), ``_poll`` and ``_emit`` (alignment straight into the WSC1 payload, the publish call: a
WSC1 header written as ``DaemonZenoh.publish_cloud`` does, no zenoh). The figures are the
worker's own CPU accounting by step (``stats()["worker_cpu_s"]``: thread CPU time), per profile.

Run alone: ``.venv/bin/python benchmarks/hot_path.py [--rate 10000] [--seconds 2]`` (target: the
total <= 15 us per 2048-point profile, issue 21); ``benchmarks/pipeline.py`` prints it too, and
``benchmarks/pipeline_ab.py COMMIT --hot-path`` compares it with a commit's.
"""

from __future__ import annotations

import argparse
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _report import Figure, report
from support import StandInRobot

MS = 1_000_000
WARMUP_S = 0.5
TARGET_US = 15.0
"""Issue 21: in-process hot path <= 15 us of CPU per 2048-point profile."""


def _datagrams(n_prof: int, n_points: int, t_exp: np.ndarray) -> list[bytes]:
    from wristscan.drivers import lpf1

    rng = np.random.default_rng(0)
    enc = lpf1.ProfileEncoder(1, lpf1.PointFormat.I16, x_uniform=(-0.025, 0.05 / (n_points - 1)))
    grams: list[bytes] = []
    for a in range(0, n_prof, 500):
        b = min(a + 500, n_prof)
        z = 0.1 + rng.normal(0.0, 20e-6, size=(b - a, n_points))
        msgs = enc.encode(np.arange(a, b), t_exp[a:b] + 2 * MS, z, np.ones(z.shape, bool))
        grams += [m[0] for m in msgs]
    return grams


def _publisher() -> Any:
    """The publish call without zenoh: the frame's header written, as publish_cloud does."""
    from wristscan.daemon.cloud import wsc1

    seq = [0]

    def publish(frame: Any, t_first: int, t_last: int, n_prof: int, frame_id: str, *_: Any) -> int:
        if not isinstance(frame, wsc1.Wsc1Frame):
            frame = wsc1.frame_of(frame, *_)
        frame.finish(
            seq=seq[0], t_first_ns=t_first, t_last_ns=t_last, n_profiles=n_prof, frame_id=frame_id
        )
        seq[0] += 1
        return seq[0] - 1

    return publish


def measure_hot_path(
    rate_hz: float = 5000.0, n_points: int = 2048, seconds: float = 2.5
) -> dict[str, float]:
    """CPU time per profile of each step of the worker (us) and the one-core capacity, over
    ``seconds`` of the stream after the first ``WARMUP_S``."""
    seconds += WARMUP_S
    from wristscan.calib import jit, se3
    from wristscan.daemon.service.pipeline import AlignmentSetup, Pipeline, PipelineSettings
    from wristscan.daemon.sync.pairing import Pairer, PairerConfig
    from wristscan.drivers.records import RobotState
    from wristscan.drivers.sensor_lpf1 import Lpf1UdpSensor

    jit.warm()  # as Pipeline.start does: compiled (or loaded) before the stream, not in it
    n_prof = int(rate_hz * seconds)
    t0 = time.monotonic_ns()
    t_exp = t0 + (np.arange(n_prof) * (1e9 / rate_hz)).astype(np.int64)
    grams = _datagrams(n_prof, n_points, t_exp)
    q = np.array([0.0, -1.2, 1.5, -1.9, -1.57, 0.0])
    r_t = np.arange(t0 - 50 * MS, int(t_exp[-1]) + 50 * MS, 2 * MS)
    s2f = se3.pose_to_matrix([0.06, 0.01, 0.2, 0.02, -0.015, 0.01])
    sensor = Lpf1UdpSensor(bind_host="127.0.0.1", port=0, recv_buffer_bytes=32 << 20)
    sensor.open()
    addr = sensor.local_address
    assert addr is not None
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    pipe = Pipeline(
        sensor,
        StandInRobot(),  # the states go into the worker's queue directly
        Pairer(PairerConfig(sensor_latency_ns=2 * MS)),
        AlignmentSetup(s2f),
        _publisher(),
        settings=PipelineSettings(shed_overload=False),
    )
    done: dict[str, Any] = {}

    def work() -> None:
        # The sensor's device clock = exposure + 2 ms; its arrival on the host clock is "now"
        # (kernel stamps): the fit sees a fixed delay, as from a real sensor.
        pi = ri = 0
        # The stream's times on the host clock from now on (the datagrams were made before):
        # the device clock is t0-based, the host's receipt and the robot's states follow it.
        shift = time.monotonic_ns() - t0
        warm = t0 + int(WARMUP_S * 1e9)
        for tick in range(t0, int(t_exp[-1]) + 30 * MS, 10 * MS):
            if "start" not in done and tick >= warm:  # the clock fits locked by now
                done["start"] = pipe._stats(latency=False)
            while time.monotonic_ns() < tick + shift - 5 * MS:  # the stream's own pace
                time.sleep(0.001)
            while pi < n_prof and t_exp[pi] + 2 * MS <= tick:
                tx.sendto(grams[pi], addr)
                pi += 1
            while ri < r_t.shape[0] and r_t[ri] + 300_000 <= tick:
                t = int(r_t[ri])
                state = RobotState((t - t0) * 1e-9 + 7200.0, t + shift + 300_000, q, np.zeros(6))
                pipe._robot_q.append(state)
                ri += 1
            pipe._read_sensor_inline()
            pipe._drain()
            batches = pipe._poll()
            for b in pipe.pairer.merge(batches) if len(batches) > 1 else batches:
                pipe._emit(b)
        done["stats"] = pipe._stats(latency=False)

    th = threading.Thread(target=work, name="hot-path")  # a worker thread, as in the daemon
    th.start()
    th.join()
    tx.close()
    sensor.close()
    st, st0 = done["stats"], done["start"]
    # Measured after WARMUP_S: the sensor clock fit locks within tenths of a second; before,
    # profiles are dropped (clock_unlocked) after their reading and pairing.
    received = int(st["received"]) - int(st0["received"])
    published = int(st["published"]) - int(st0["published"])
    if st["received"] != n_prof or published < received:
        raise RuntimeError(f"hot path published {published} of {received} profiles: {st}")
    cpu = {k: float(v) - float(st0["worker_cpu_s"][k]) for k, v in st["worker_cpu_s"].items()}
    out = {f"{k}_us": 1e6 * v / published for k, v in cpu.items()}
    out["total_us"] = sum(out.values())
    out["ns_per_point"] = 1e3 * out["total_us"] / n_points
    out["capacity_profiles_per_cpu_s"] = 1e6 / out["total_us"]
    return out


def figures(hot: dict[str, float], n_points: int) -> list[Figure]:
    """The hot path's figures (the total against its target for 2048 points)."""
    out = [
        Figure(f"hot path: {k.removesuffix('_us')} per profile", v, "us CPU", "-", None)
        for k, v in hot.items()
        if k.endswith("_us") and k != "total_us"
    ]
    total = hot["total_us"]
    target = TARGET_US * n_points / 2048
    out += [
        Figure("hot path: total per profile", total, "us CPU", f"<= {target:g}", total <= target),
        Figure("hot path: per point", hot["ns_per_point"], "ns CPU", "-", None),
        Figure(
            "hot path capacity (one core)", hot["capacity_profiles_per_cpu_s"], "1/s", "-", None
        ),
    ]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=10000.0, help="stream rate, Hz")
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--seconds", type=float, default=2.5, help="measured, after a 0.5 s warm-up")
    ap.add_argument("--runs", type=int, default=3, help="runs; the median is reported")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    runs = [measure_hot_path(args.rate, args.points, args.seconds) for _ in range(args.runs)]
    med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
    for r in runs:
        print(f"# run: { {k: round(v, 2) for k, v in r.items()} }")
    return report(
        f"hot path (issue 21), {args.rate / 1000:g} kHz x {args.points}, median of {args.runs}",
        figures(med, args.points),
        args.json,
    )


if __name__ == "__main__":
    sys.exit(main())
