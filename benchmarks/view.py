"""``wristscan view`` (issue 19, section 3): the CPU its rerun logging costs per point and
per batch, for two batch sizes a daemon publishes.

Batches of 2048 points (one profile per batch, the lightest daemon setting) and of 102 400 points
(a 10 ms tick at 5 kHz x 2048) are decoded from WSC1 and logged with ``LiveView.batch`` into a
``.rrd`` file (rerun's encoder and writer threads included: ``time.process_time``); medians of
the rounds.

Target: one viewer keeps up with a daemon at 1 kHz x 2048 points (2.05 M points/s) with every
point logged (``--stride 1``); faster daemons (5 kHz x 2048: 10 M points/s) need ``--stride``
(docs/view.md).

    .venv/bin/python benchmarks/view.py [--rounds 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import Figure, report

from wristscan.daemon.cloud import wsc1
from wristscan.daemon.view.live import LiveView, new_recording

TARGET_POINTS_S = 1000 * 2048
BATCHES = 100


def _payloads(n_points: int) -> list[bytes]:
    rng = np.random.default_rng(1)
    xyz = rng.uniform(-0.1, 0.1, (n_points, 3)).astype(np.float32)
    return [
        wsc1.encode(xyz, seq=i, t_first_ns=i * 10**7, t_last_ns=i * 10**7 + 1, n_profiles=50)
        for i in range(BATCHES)
    ]


def _round(payloads: list[bytes], path: Path) -> float:
    """CPU seconds per point: decoding + logging into a file."""
    n = sum(wsc1.decode(p).n_points for p in payloads)
    rec = new_recording()
    rec.save(path)
    live = LiveView(rec)
    t0 = time.process_time()
    for p in payloads:
        live.batch(wsc1.decode(p))
    rec.flush()
    rec.disconnect()
    logged = time.process_time() - t0
    return logged / n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    figures: list[Figure] = []
    with tempfile.TemporaryDirectory() as tmp:
        for n_points in (2048, 102_400):
            payloads = _payloads(n_points)
            log = [_round(payloads, Path(tmp) / f"r{k}.rrd") for k in range(args.rounds)]
            l_med = statistics.median(log)
            rate = 1.0 / l_med
            figures.append(
                Figure(
                    f"{n_points}-pt batches: view CPU per point", l_med * 1e9, "ns", "info", None
                )
            )
            figures.append(
                Figure(
                    f"{n_points}-pt batches: view CPU per batch",
                    l_med * n_points * 1e3,
                    "ms",
                    "info",
                    None,
                )
            )
            ok = rate >= TARGET_POINTS_S if n_points == 2048 else None
            target = f">= {TARGET_POINTS_S / 1e6:.2f} M" if ok is not None else "info"
            figures.append(Figure(f"{n_points}-pt batches: points/s", rate, "pt/s", target, ok))
    return report("wristscan view: rerun logging cost", figures, args.json)


if __name__ == "__main__":
    sys.exit(main())
