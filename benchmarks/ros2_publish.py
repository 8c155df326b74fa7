"""ROS 2 publication as the daemon does it (issue 19, section 1): the CPU that ``[ros2] enabled``
adds to a batch's publication, measured on real zenoh sessions on loopback.

For each batch, WSC1 alone (``DaemonZenoh.publish_cloud``: encode + put) against WSC1 followed
by the rmw_zenoh PointCloud2 (``Ros2Publisher.tee``: + CDR, attachment, put), alternated rounds,
medians; a subscriber session receives both keys. CPU is the publishing thread's
(``time.thread_time``: what the pipeline worker pays) and the whole process's
(``time.process_time``: also zenoh's own threads and the subscriber's callbacks), one
publication per 10 ms as the daemon's ticks come.

Target: ROS 2 publication adds <= 20 % to the daemon's CPU at 5 kHz x 2048, i.e. per 10 ms tick
(50 profiles x 2048 = 102 400 points) the added worker CPU over the daemon's >= 4.4 ms per tick
(44-51 % of a core, docs/pipeline.md).

    .venv/bin/python benchmarks/ros2_publish.py [--rounds 9]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
from _report import Figure, report
from support import free_tcp_port, own_loopback_host

from wristscan.daemon.cloud.ros2pub import Ros2Publisher
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session
from wristscan.daemon.config.ros2 import Ros2Config

DAEMON_TICK_CPU_MS = 4.4
PROFILE_POINTS = 2048
TICK_PROFILES = 50
T0 = 1_700_000_000_000_000_000


def _cpu(fn: Callable[[], object], calls: int, period_s: float = 0.010) -> tuple[float, float]:
    """(thread CPU, process CPU) per call, seconds; one call per ``period_s`` as the daemon's
    ticks come (back-to-back puts of megabytes fill zenoh's queue, and a put then waits for
    room, which a daemon publishing every 10 ms never meets)."""
    th = pr = 0.0
    nxt = time.monotonic()
    for _ in range(calls):
        nxt += period_s
        t0, p0 = time.thread_time(), time.process_time()
        fn()
        th += time.thread_time() - t0
        pr += time.process_time() - p0
        time.sleep(max(0.0, nxt - time.monotonic()))
    return th / calls, pr / calls


def measure(rounds: int) -> dict[str, float]:
    host = own_loopback_host()
    ep = f"tcp/{host}:{free_tcp_port(host)}"
    daemon_s = open_session(listen=[ep])
    peer = open_session(connect=[ep])
    got = [0]

    def count(_: object) -> None:
        got[0] += 1

    try:
        face = DaemonZenoh(daemon_s, "wristscan/bench")
        ros = Ros2Publisher(daemon_s, Ros2Config(enabled=True), "bench")
        subs = [
            peer.declare_subscriber("wristscan/bench/cloud", count),
            peer.declare_subscriber(ros.key_for("sensor_msgs/msg/PointCloud2", ros.topic), count),
        ]
        time.sleep(1.0)  # the subscriptions reach the publisher
        both = ros.tee(face.publish_cloud)
        rng = np.random.default_rng(0)
        out: dict[str, list[float]] = {}
        for n, calls in ((PROFILE_POINTS, 40), (PROFILE_POINTS * TICK_PROFILES, 20)):
            xyz = rng.normal(size=(n, 3)).astype(np.float32)
            inten = rng.integers(0, 256, n).astype(np.uint8)
            args = (xyz, T0, T0 + 10_000_000, n // PROFILE_POINTS, "base", inten, None)
            for _ in range(rounds):
                for name, fn in (("wsc1", face.publish_cloud), ("both", both)):
                    th, pr = _cpu(lambda fn=fn, a=args: fn(*a), calls)  # type: ignore[misc]
                    out.setdefault(f"{name}_thread_{n}", []).append(th)
                    out.setdefault(f"{name}_process_{n}", []).append(pr)
        for s in subs:
            s.undeclare()
        ros.close()
        face.close()
        if got[0] == 0:
            raise RuntimeError("the subscriber received nothing")
        return {k: statistics.median(v) for k, v in out.items()}
    finally:
        peer.close()
        daemon_s.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=9)
    args = ap.parse_args()
    m = measure(args.rounds)
    tick = PROFILE_POINTS * TICK_PROFILES
    figures: list[Figure] = []
    for n, label, scale, unit in (
        (PROFILE_POINTS, "2048 points", 1e6, "us"),
        (tick, "tick", 1e3, "ms"),
    ):
        for kind in ("thread", "process"):
            w, b = m[f"wsc1_{kind}_{n}"], m[f"both_{kind}_{n}"]
            figures.append(
                Figure(f"WSC1 publish, {label}, {kind} CPU", w * scale, unit, "info", None)
            )
            figures.append(
                Figure(f"WSC1 + PointCloud2, {label}, {kind} CPU", b * scale, unit, "info", None)
            )
    added_ms = (m[f"both_thread_{tick}"] - m[f"wsc1_thread_{tick}"]) * 1e3
    share = added_ms / DAEMON_TICK_CPU_MS
    added_proc = (m[f"both_process_{tick}"] - m[f"wsc1_process_{tick}"]) * 1e3
    figures += [
        Figure("added worker CPU per 5 kHz tick", added_ms, "ms", "info", None),
        Figure("ROS 2 publication added / daemon CPU", share * 100, "%", "<= 20 %", share <= 0.2),
        Figure(
            "same, whole process (zenoh threads, subscriber)",
            added_proc / DAEMON_TICK_CPU_MS * 100,
            "%",
            "info",
            None,
        ),
    ]
    return report("ROS 2 publication over rmw_zenoh (issue 19, section 1)", figures)


if __name__ == "__main__":
    sys.exit(main())
