"""Cloud file formats and ROS 2 serialisation, side by side (issue 19, section 2).

1. Serialisation of a batch: ``sensor_msgs/msg/PointCloud2`` CDR (rosbags, through
   ``daemon/cloud/ros2msg.py``) against WSC1 encoding (``daemon/cloud/wsc1.py``), for a
   2048-point batch (one profile) and for the batch the daemon publishes at 5 kHz (one 10 ms
   tick: 50 profiles x 2048 points). Medians of alternated rounds.

   Target: ROS 2 publication adds <= 20 % to the daemon's CPU at 5 kHz x 2048. The daemon uses
   44-51 % of a core there (docs/pipeline.md, third session), i.e. >= 4.4 ms per 10 ms tick; its
   publish step (WSC1 encoding + zenoh put) 3.5-3.8 % of a core, i.e. <= 0.38 ms per tick. A
   second publication costs the CDR serialisation plus one more put of the same size (the
   publish step less the WSC1 encoding measured here): added = cdr + max(0, 0.38 ms - wsc1),
   and added / 4.4 ms must stay <= 20 %.

2. Writing throughput (points/s) of MCAP (streamed, LZ4 chunks) and E57 (pye57, one scan)
   against binary PLY (streamed), the same batches of 102 400 points of a scanned surface with
   intensity, into a temporary folder; and MCAP with zstd chunks (smaller, slower). Target:
   MCAP keeps up with the daemon, >= 10.24 M points/s (5 kHz x 2048), since ``wristscan
   record`` writes it while receiving; E57 is written once the recording ends (from its
   spool): reported against PLY, target >= 1 M points/s (a minute at 5 kHz written in <= 10
   min).

    .venv/bin/python benchmarks/formats.py [--rounds 7] [--points 2000000]
"""

from __future__ import annotations

import argparse
import ctypes
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import Figure, report

from wristscan.daemon.cloud import ros2msg, wsc1
from wristscan.daemon.io.e57_out import E57Writer
from wristscan.daemon.io.mcap_out import McapCloudWriter
from wristscan.daemon.io.ply import PlyStreamWriter

PROFILE_POINTS = 2048
TICK_PROFILES = 50  # 5 kHz in 10 ms ticks
DAEMON_TICK_CPU_MS = 4.4  # >= 44 % of a core per 10 ms tick at 5 kHz (docs/pipeline.md)
PUBLISH_STEP_MS = 0.38  # <= 3.8 % of a core per tick: WSC1 encoding + zenoh put
T0 = 1_700_000_000_000_000_000


def _steady_heap() -> bool:
    """Keep freed megabyte buffers in the heap (glibc ``mallopt``: no mmap per buffer, no trim),
    as ``MALLOC_MMAP_THRESHOLD_``/``MALLOC_TRIM_THRESHOLD_`` would for the daemon. Without it a
    1.6 MB buffer is page-faulted afresh on some calls and not on others, depending on what
    sits at the top of the heap, and the same encoding measures 0.1 or 3 ms from one process to
    the next. Returns False where there is no glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    ok = libc.mallopt(m_mmap_threshold, 64 << 20) == 1
    return ok and libc.mallopt(m_trim_threshold, 256 << 20) == 1


def _batch(n: int, seed: int) -> dict[str, np.ndarray]:
    """``n`` points of a scanned surface (profiles of 2048 points 0.1 mm apart, a gently
    curved face with 20 um noise: what compressors see in a recording), float64 as the
    pipeline aligns them, with intensity and profile indices."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    y = (k % PROFILE_POINTS) * (0.05 / PROFILE_POINTS) - 0.025
    x = k // PROFILE_POINTS * 1e-4 + (seed % 100) * 5e-3
    z = 0.1 + 1e-3 * np.sin(300.0 * y) + rng.normal(size=n) * 2e-5
    return {
        "xyz": np.stack([x, y, z], axis=1),
        "intensity": rng.integers(0, 256, n).astype(np.uint8),
        "profile_index": (np.arange(n) // PROFILE_POINTS).astype(np.uint32),
    }


def _time_per_call(fn: Callable[[], object], calls: int) -> float:
    fn()
    t = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - t) / calls


def serialisation(rounds: int) -> dict[str, float]:
    """Median seconds per call: WSC1 and CDR, one profile and one 5 kHz tick."""
    out: dict[str, list[float]] = {}
    for n, calls in ((PROFILE_POINTS, 400), (PROFILE_POINTS * TICK_PROFILES, 20)):
        b = _batch(n, n)
        profiles = max(1, n // PROFILE_POINTS)

        def enc_wsc1(b: dict[str, np.ndarray] = b, p: int = profiles) -> bytes:
            return wsc1.encode(
                b["xyz"],
                seq=1,
                t_first_ns=T0,
                t_last_ns=T0 + 10_000_000,
                n_profiles=p,
                intensity=b["intensity"],
                profile_index=b["profile_index"],
            )

        def enc_cdr(b: dict[str, np.ndarray] = b) -> bytearray:
            return ros2msg.cloud_cdr(b["xyz"], T0, "base", b["intensity"])

        for _ in range(rounds):
            for name, fn in (("wsc1", enc_wsc1), ("cdr", enc_cdr)):
                out.setdefault(f"{name}_{n}", []).append(_time_per_call(fn, calls))
    return {k: statistics.median(v) for k, v in out.items()}


def _write_ply(path: Path, batches: list[dict[str, np.ndarray]]) -> None:
    with PlyStreamWriter(path, has_intensity=True) as w:
        for b in batches:
            w.write(b["xyz"], intensity=b["intensity"])


def _write_mcap(path: Path, batches: list[dict[str, np.ndarray]]) -> None:
    with McapCloudWriter(path) as w:
        for k, b in enumerate(batches):
            w.write_cloud(b["xyz"], T0 + k * 10_000_000, "base", b["intensity"])


def _write_mcap_zstd(path: Path, batches: list[dict[str, np.ndarray]]) -> None:
    with McapCloudWriter(path, compression="zstd") as w:
        for k, b in enumerate(batches):
            w.write_cloud(b["xyz"], T0 + k * 10_000_000, "base", b["intensity"])


def _write_e57(path: Path, batches: list[dict[str, np.ndarray]]) -> None:
    xyz = np.concatenate([b["xyz"] for b in batches]).astype(np.float32)
    inten = np.concatenate([b["intensity"] for b in batches])
    with E57Writer(path) as w:
        w.add_scan(xyz, "bench", intensity=inten)


def throughput(rounds: int, points: int) -> tuple[dict[str, float], dict[str, int]]:
    """Median points/s writing each format, and the file sizes (bytes)."""
    n = PROFILE_POINTS * TICK_PROFILES
    batches = [_batch(n, 100 + k) for k in range(max(1, points // n))]
    total = n * len(batches)
    writers = {
        "ply": _write_ply,
        "mcap": _write_mcap,
        "mcap_zstd": _write_mcap_zstd,
        "e57": _write_e57,
    }
    rates: dict[str, list[float]] = {k: [] for k in writers}
    sizes: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(rounds):
            for name, fn in writers.items():
                path = Path(tmp) / f"bench.{name.split('_')[0]}"
                t = time.perf_counter()
                fn(path, batches)
                rates[name].append(total / (time.perf_counter() - t))
                sizes[name] = path.stat().st_size
                path.unlink()
    return {k: statistics.median(v) for k, v in rates.items()}, sizes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--points", type=int, default=2_048_000, help="points per file written")
    args = ap.parse_args()
    d = serialisation(args.rounds)  # the allocator as it comes
    steady = _steady_heap()
    s = serialisation(args.rounds)
    tick = PROFILE_POINTS * TICK_PROFILES
    one_w, one_c = s[f"wsc1_{PROFILE_POINTS}"], s[f"cdr_{PROFILE_POINTS}"]
    tick_w, tick_c = s[f"wsc1_{tick}"], s[f"cdr_{tick}"]
    added_ms = tick_c * 1e3 + max(0.0, PUBLISH_STEP_MS - tick_w * 1e3)
    share = added_ms / DAEMON_TICK_CPU_MS
    per_profile_share = (one_c * 1e3 * TICK_PROFILES) / DAEMON_TICK_CPU_MS
    rates, sizes = throughput(max(3, args.rounds // 2), args.points)
    mega = 1e6
    figures = [
        Figure("WSC1 encode, 2048 points", one_w * 1e6, "us", "info", None),
        Figure("PointCloud2 CDR, 2048 points", one_c * 1e6, "us", "info", None),
        Figure("CDR / WSC1, 2048 points", one_c / one_w, "x", "info", None),
        Figure("WSC1 encode, 5 kHz tick (102400 pts)", tick_w * 1e3, "ms", "info", None),
        Figure("PointCloud2 CDR, 5 kHz tick", tick_c * 1e3, "ms", "info", None),
        Figure("CDR / WSC1, 5 kHz tick", tick_c / tick_w, "x", "info", None),
        Figure("ROS 2 publication added / daemon CPU", share * 100, "%", "<= 20 %", share <= 0.2),
        Figure("heap kept (mallopt) for the figures above", float(steady), "", "info", None),
        Figure(
            "default heap: WSC1 / CDR, 5 kHz tick (ms)",
            d[f"wsc1_{tick}"] * 1e3,
            f"/ {d[f'cdr_{tick}'] * 1e3:.3g}",
            "info",
            None,
        ),
        Figure(
            "default heap: WSC1 / CDR, 2048 points (us)",
            d[f"wsc1_{PROFILE_POINTS}"] * 1e6,
            f"/ {d[f'cdr_{PROFILE_POINTS}'] * 1e6:.3g}",
            "info",
            None,
        ),
        Figure("same, one message per profile", per_profile_share * 100, "%", "info", None),
        Figure("PLY (binary, streamed) write", rates["ply"] / mega, "Mpt/s", "info", None),
        Figure(
            "MCAP (LZ4 chunks) write",
            rates["mcap"] / mega,
            "Mpt/s",
            ">= 10.24",
            rates["mcap"] >= 10.24e6,
        ),
        Figure("MCAP / PLY throughput", rates["mcap"] / rates["ply"], "x", "info", None),
        Figure("MCAP (zstd chunks) write", rates["mcap_zstd"] / mega, "Mpt/s", "info", None),
        Figure("E57 (pye57) write", rates["e57"] / mega, "Mpt/s", ">= 1", rates["e57"] >= 1e6),
        Figure("E57 / PLY throughput", rates["e57"] / rates["ply"], "x", "info", None),
        Figure("bytes per point PLY / MCAP / E57", 0.0, "", "info", None),
    ]
    n = max(1, args.points // tick) * tick
    figures[-1] = Figure(
        f"bytes/pt PLY {sizes['ply'] / n:.1f}, MCAP LZ4 {sizes['mcap'] / n:.1f}, "
        f"zstd {sizes['mcap_zstd'] / n:.1f}, E57",
        sizes["e57"] / n,
        "B",
        "info",
        None,
    )
    return report("cloud formats and ROS 2 serialisation (issue 19)", figures)


if __name__ == "__main__":
    sys.exit(main())
