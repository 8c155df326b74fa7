"""Clock-fit figures of benchmarks/sync.py for issue 21: the cost of feeding the sensor clock a
tick's records at once (``ClockMapper.feed_many``) against one at a time (``feed``), and the
fit under a sender that cannot keep its timing (records 5-50 ms late, spikes, bursts).

The late-sender streams come from ``tests/support.late_sender_arrivals`` (ground truth: the true
host instant of every stamp). See docs/sync.md for what each figure measures.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wristscan.daemon.sync.clockmap import ClockMapper

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
from _report import Figure
from support import late_sender_arrivals

IntArray = NDArray[np.int64]

MS = 1_000_000
S = 1_000_000_000


def gamma_stream(rate_hz: float, seconds: float, seed: int) -> tuple[IntArray, IntArray]:
    """Device stamps (+50 ppm) and arrivals (0.25 ms floor + gamma, sigma 0.1 ms, in order)."""
    rng = np.random.default_rng(seed)
    n = int(rate_hz * seconds)
    t = 100 * S + np.rint(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    dev = np.rint((t - 100 * S) / (1.0 + 50e-6)).astype(np.int64) + 777 * S
    delay = np.rint(250_000 + rng.gamma(2.0, 100_000 / np.sqrt(2.0), n)).astype(np.int64)
    return dev, np.maximum.accumulate(t + delay)


def _feed_ns(dev: IntArray, host: IntArray, block: int, warm: int) -> tuple[float, ClockMapper]:
    """Process CPU ns per arrival after the first ``warm`` arrivals (fed the same way, untimed)."""
    cm = ClockMapper()
    xs, ys = dev.tolist(), host.tolist()
    if block == 1:
        for x, y in zip(xs[:warm], ys[:warm], strict=True):
            cm.feed(x, y)
        t = time.process_time_ns()
        for x, y in zip(xs[warm:], ys[warm:], strict=True):
            cm.feed(x, y)
    else:
        for i in range(0, warm, block):
            cm.feed_many(dev[i : i + block], host[i : i + block])
        t = time.process_time_ns()
        for i in range(warm, dev.shape[0], block):
            cm.feed_many(dev[i : i + block], host[i : i + block])
    return (time.process_time_ns() - t) / (dev.shape[0] - warm), cm


def figure_feed_blocks(seconds: float = 6.0, runs: int = 3) -> list[Figure]:
    """ns of CPU per arrival: feed() one by one against feed_many() in ticks of 50 and 100
    records, at 5 and 10 kHz (medians of ``runs`` alternating runs: the machine is shared), and
    the largest difference of the lines they end with (they must be equal)."""
    figs = []
    for rate in (5000.0, 10_000.0):
        dev, host = gamma_stream(rate, seconds, seed=21)
        warm = int(rate)  # the first second (lock, first refits) untimed
        got: dict[int, list[float]] = {1: [], 50: [], 100: []}
        maps = {}
        for _ in range(runs):
            for block in got:
                ns, cm = _feed_ns(dev, host, block, warm)
                got[block].append(ns)
                maps[block] = cm.to_host(dev[-1000:])
        med = {b: float(np.median(v)) for b, v in got.items()}
        diff = max(float(np.max(np.abs(maps[b] - maps[1]))) for b in (50, 100))
        khz = f"{rate / 1e3:g} kHz"
        ratio = med[100] / med[1]
        figs += [
            Figure(f"clock feed: {khz}, feed() per arrival", med[1], "ns", "", None),
            Figure(f"clock feed: {khz}, feed_many() ticks of 50", med[50], "ns", "", None),
            Figure(f"clock feed: {khz}, feed_many() ticks of 100", med[100], "ns", "", None),
            Figure(f"clock feed: {khz}, ticks of 100 / feed()", ratio, "x", "<= 0.7", ratio <= 0.7),
            Figure(f"clock feed: {khz}, mapped difference", diff, "ns", "== 0", diff == 0),
        ]
    return figs


LATE_CASES = (
    # model, rate, first-lock target (s), what it is
    ("wakeups", 1000.0, 1.0, "sender waking every 0-45 ms, sending what is >= 5 ms old"),
    ("wakeups", 10_000.0, 1.0, "the same at 10 kHz"),
    ("jitter", 10_000.0, 1.0, "each record 5-50 ms late, queued behind later ones"),
    ("catch-up", 10_000.0, 3.0, "lag growing to 20-50 ms, then a burst"),
    ("overrun", 10_000.0, 4.5, "lag growing to 1 s over 2.5 s, then steady"),
    ("wander", 10_000.0, 2.0, "lag wandering over 5-50 ms"),
)


def late_sender_run(model: str, rate_hz: float, seconds: float, seed: int) -> dict[str, float]:
    """Feed tick by tick (10 ms), map each tick with the line known at its arrival."""
    dev, host, truth = late_sender_arrivals(seconds, rate_hz, model, seed=seed)
    cm = ClockMapper()
    err = np.full(dev.shape[0], np.nan)
    block = int(rate_hz // 100)
    for i in range(0, dev.shape[0], block):
        ep = int(cm.feed_many(dev[i : i + block], host[i : i + block])[-1])
        if cm.is_locked(ep):
            err[i : i + block] = cm.to_host(dev[i : i + block], ep) - truth[i : i + block]
    locked = ~np.isnan(err)
    first = int(np.argmax(locked)) if locked.any() else dev.shape[0] - 1
    ok = ~np.isnan(err[first:])
    e = err[first:][ok]
    # What the envelope can know: the smallest delay seen since the lock.
    excess = (e - np.minimum.accumulate((host - truth)[first:])[ok]) / MS
    st = cm.status()
    return {
        "first_lock_s": float(host[first] - host[0]) / S if locked.any() else float("inf"),
        "unlocked": float(np.count_nonzero(~locked[first:])),
        "resets": float(st["resets"]),
        "reanchors": float(st["reanchors"]),
        "floor_moves": float(st["floor_moves"]),
        "spread_ms": float(np.percentile(e, 99) - np.percentile(e, 1)) / MS if e.size else 0.0,
        "offset_ms": float(np.median(e)) / MS if e.size else float("nan"),
        "excess_p99_ms": float(np.percentile(excess, 99)) if e.size else float("nan"),
        "delay_min_ms": float(np.min(host - truth)) / MS,
        "uncertainty_us": float(st["uncertainty_us"]),
    }


def figure_late_sender(seconds: float = 20.0, seed: int = 1) -> list[Figure]:
    """Per delay model: first lock, arrivals unlocked after it (target 0), restarts (target 0),
    and the spread (p1 to p99) of mapped minus true instant: what the constant part of the
    delay, absorbed into the offset, leaves."""
    figs = []
    for model, rate, lock_s, _what in LATE_CASES:
        r = late_sender_run(model, rate, seconds, seed)
        r["lock_ok"] = r["first_lock_s"] <= lock_s
        tag = f"late sender: {model} {rate / 1e3:g} kHz"
        figs += [
            Figure(f"{tag}, first lock", r["first_lock_s"], "s", f"<= {lock_s:g}", r["lock_ok"]),
            Figure(
                f"{tag}, arrivals unlocked after it", r["unlocked"], "", "== 0", r["unlocked"] == 0
            ),
            Figure(f"{tag}, restarts", r["resets"], "", "== 0", r["resets"] == 0),
            Figure(f"{tag}, mapped - true, p1..p99 spread", r["spread_ms"], "ms", "", None),
            Figure(f"{tag}, mapped - true, median", r["offset_ms"], "ms", "", None),
            Figure(f"{tag}, smallest true delay", r["delay_min_ms"], "ms", "", None),
            Figure(
                f"{tag}, mapped - true - smallest delay since the lock, p99",
                r["excess_p99_ms"],
                "ms",
                "",
                None,
            ),
            Figure(f"{tag}, re-anchors", r["reanchors"], "", "", None),
            Figure(f"{tag}, floor moves before the lock", r["floor_moves"], "", "", None),
            Figure(f"{tag}, reported uncertainty at the end", r["uncertainty_us"], "us", "", None),
        ]
    return figs
