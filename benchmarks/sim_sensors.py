"""Emitted profiles per second of each simulated sensor against the rate asked (1, 5, 10 kHz).

Every sensor sends 2048-point profiles (SCIP: 2048 steps over 180 degrees) in standalone mode
(a still flange above the tooling ball) to a receiver in this process that reads the real
transport and counts what arrives. Targets: LPF1-UDP and RF627 >= 0.95 at 1 and 5 kHz; the other
figures are reported (TCP, pty and SCIP text encoding limit them; the Gocator is started on
its control channel and its data channel's Stamp messages are counted). Also reported: the
ray-casting cost with a moving pose (no cache), which bounds the rate of a sensor on a moving
robot.

Run: ``.venv/bin/python benchmarks/sim_sensors.py [--window 1.5] [--json out.json]``
"""

from __future__ import annotations

import argparse
import os
import selectors
import socket
import struct
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import Figure, report

from wristscan.drivers import gocator
from wristscan.drivers.sim.laser import LaserModel
from wristscan.drivers.sim.scene import demo_scene, sensor_looking_down
from wristscan.drivers.sim.sensors import KINDS, SensorSimConfig, SimulatedSensor

RATES_HZ = (1000.0, 5000.0, 10000.0)
TARGETED = {"lpf1-udp", "rf627-udp"}
N_POINTS = 2048


def _config(kind: str, rate: float, target: tuple[str, int] | None) -> SensorSimConfig:
    extra: dict[str, object] = {"rate_hz": rate, "n_points": N_POINTS, "heartbeat_s": 0.0}
    if kind.endswith("udp"):
        extra["target"] = target
    if kind.startswith("scip"):
        extra["scip_ares"] = 4096
    if kind == "gocator":
        extra["port"] = 0  # three free ports rather than the standard ones
    return SensorSimConfig.for_kind(kind, **extra)  # type: ignore[arg-type]


def _count(kind: str, sim: SimulatedSensor, udp: socket.socket | None, window_s: float,
           warmup_s: float) -> int:  # fmt: skip
    """Profiles that arrive within ``window_s`` after ``warmup_s``, read from the transport."""
    sel = selectors.DefaultSelector()
    stream: socket.socket | None = None
    fd: int | None = None
    if udp is not None:
        sel.register(udp, selectors.EVENT_READ)
    elif kind.endswith("tcp") or kind == "gocator":
        port = sim.endpoint["data_port" if kind == "gocator" else "port"]
        stream = socket.create_connection((sim.endpoint["host"], port), 5)
        stream.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        sel.register(stream, selectors.EVENT_READ)
    else:
        import termios
        import tty

        fd = os.open(sim.endpoint["port_path"], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        termios.tcflush(fd, termios.TCIFLUSH)
        sel.register(fd, selectors.EVENT_READ)
    if kind.startswith("scip"):
        cmd = f"MD0000{N_POINTS - 1:04d}00000\n".encode()
        if stream is not None:
            stream.sendall(cmd)
        else:
            assert fd is not None
            os.write(fd, cmd)
    control = None
    if kind == "gocator":  # Start on the control channel; count the Stamp headers
        control = socket.create_connection((sim.endpoint["host"], sim.endpoint["port"]), 5)
        control.sendall(gocator.encode_command(gocator.Cmd.START))
    stamp_head = struct.pack("<IHIH", 70, gocator.Msg.STAMP, 1, gocator.STAMP_SIZE)
    marker = {"lpf1-tcp": b"LPF1", "lpf1-serial": b"\x00", "gocator": stamp_head}.get(kind, b"\n\n")
    buf = bytearray(1 << 20)
    count = 0
    tail = b""
    t_start = time.monotonic() + warmup_s
    t_end = t_start + window_s
    try:
        while (now := time.monotonic()) < t_end:
            counting = now >= t_start
            for _key, _ in sel.select(0.05):
                if udp is not None:
                    while True:
                        try:
                            udp.recv_into(buf)
                        except BlockingIOError:
                            break
                        count += counting
                    continue
                try:
                    if stream is not None:
                        n = stream.recv_into(buf)
                    else:
                        assert fd is not None
                        n = os.readv(fd, [buf])
                except BlockingIOError:
                    continue
                data = tail + bytes(buf[:n])
                if counting:
                    count += data.count(marker)
                tail = data[-(len(marker) - 1) :] if len(marker) > 1 else b""
    finally:
        sel.close()
        if stream is not None:
            stream.close()
        if control is not None:
            control.close()
        if fd is not None:
            os.close(fd)
    return count


def measure_kind(kind: str, rate: float, window_s: float, warmup_s: float) -> tuple[float, dict]:
    udp = None
    target = None
    if kind.endswith("udp"):
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
        udp.bind(("127.0.0.1", 0))
        udp.setblocking(False)
        target = udp.getsockname()
    try:
        with SimulatedSensor(_config(kind, rate, target)) as sim:
            n = _count(kind, sim, udp, window_s, warmup_s)
            stats = sim.stats()
    finally:
        if udp is not None:
            udp.close()
    return n / (rate * window_s), stats


def raycast_rate(seconds: float = 1.0) -> float:
    """Profiles/s of LaserModel.measure on the demo scene with a new pose every profile."""
    scene = demo_scene()
    lm = LaserModel(N_POINTS, noise_std_m=20e-6, cache_size=0, rng=1)
    ball = scene.find("ball").pose[:3, 3]
    batch = 10
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        poses = np.stack(
            [sensor_looking_down(ball + np.array([1e-4 * (n + i) % 0.01, 0, 0]), 0.1)
             for i in range(batch)]
        )  # fmt: skip
        lm.measure(poses, scene)
        n += batch
    return n / (time.perf_counter() - t0)


def run(window_s: float = 1.5, warmup_s: float = 1.0, json_out: str | None = None) -> int:
    figures: list[Figure] = []
    for kind in KINDS:
        for rate in RATES_HZ:
            ratio, stats = measure_kind(kind, rate, window_s, warmup_s)
            targeted = kind in TARGETED and rate <= 5000
            name = f"{kind} {rate / 1000:g} kHz emitted/asked"
            target = ">= 0.95" if targeted else "report"
            figures.append(
                Figure(name, ratio, "ratio", target, ratio >= 0.95 if targeted else None)
            )
            if stats["overrun"] or stats["tx_overflow"]:
                print(f"  ({kind} {rate:g} Hz: overrun {stats['overrun']}, "
                      f"tx_overflow {stats['tx_overflow']})")  # fmt: skip
    figures.append(Figure("ray-cast, moving pose", raycast_rate(), "prof/s", "report", None))
    return report("simulated sensors: emitted profiles/s vs rate asked", figures, json_out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--window", type=float, default=1.5, help="counting window per figure (s)")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = ap.parse_args()
    return run(args.window, json_out=args.json)


if __name__ == "__main__":
    sys.exit(main())
