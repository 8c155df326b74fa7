"""ClockMapper.feed_many (vectorised blocks) against feed (one arrival at a time): same epochs,
same lines, same counters, on clean streams and on every discontinuity the mapper handles.

Tolerance: none. The blocks are cut where feed() would refit, so the refits see the same points
and the lines are equal to the last bit (checked with ``==`` on the line, the status and the
mapped times)."""

from __future__ import annotations

import numpy as np
import pytest
from support import late_sender_arrivals

from wristscan.daemon.sync.clockmap import ClockMapper

MS = 1_000_000
S = 1_000_000_000


def synth(seconds: float, rate_hz: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Device stamps (+50 ppm, 20 ms offset) and arrivals: gamma delays, 5 % spikes."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    t_true = 7 * S + np.rint(np.arange(n) * (S / rate_hz)).astype(np.int64)
    dev = np.rint((t_true - 20e6) / (1.0 + 50e-6)).astype(np.int64)
    delay = rng.gamma(2.0, 0.5e6, n)
    spike = rng.random(n) < 0.05
    delay[spike] += rng.uniform(5 * MS, 50 * MS, int(spike.sum()))
    return dev, t_true + np.rint(delay).astype(np.int64)


def streams() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {"clean 5 kHz": synth(3.0, 5000.0, 1)}
    dev, host = synth(4.0, 1000.0, 2)
    reboot = dev.copy()
    reboot[2000:] -= reboot[2000] - 123  # the device restarts its clock
    out["reboot"] = (reboot, host)
    jump = dev.copy()
    jump[2500:] += 10 * S
    out["forward jump"] = (jump, host)
    back = dev.copy()
    back[1500:] -= 5 * MS  # small step back: late arrivals for 0.5 s
    out["step back"] = (back, host)
    stall = dev.copy()
    stall[3000:3700] = stall[3000]  # device clock stopped for 0.7 s
    stall[3700:] -= stall[3700] - stall[3000] - MS
    out["stopped clock"] = (stall, host)
    order = np.argsort(host + np.where(np.arange(host.shape[0]) % 97 == 5, 3 * MS, 0))
    out["reordered"] = (dev[order], np.sort(host))
    burst = host.copy()
    burst[1000:1400] = burst[1400]  # a stall of 0.4 s read in a burst
    out["burst"] = (dev, burst)
    out["late sender"] = late_sender_arrivals(2.0, 10_000.0, "catch-up", seed=3)[:2]
    return out


RESETS = {"reboot": 1, "forward jump": 1, "step back": 1, "stopped clock": 1}


@pytest.mark.parametrize("name", list(streams()))
def test_feed_many_equals_feed_arrival_by_arrival(name: str) -> None:
    dev, host = streams()[name]
    one = ClockMapper()
    epochs_one = np.array(
        [one.feed(x, y) for x, y in zip(dev.tolist(), host.tolist(), strict=True)]
    )
    assert one.n_resets == RESETS.get(name, 0)  # the stream does exercise what it is named for
    for block in (50, 100, dev.shape[0]):
        many = ClockMapper()
        epochs = np.concatenate(
            [
                many.feed_many(dev[i : i + block], host[i : i + block])
                for i in range(0, dev.shape[0], block)
            ]
        )
        assert np.array_equal(epochs, epochs_one), (name, block)
        assert many.status() == one.status(), (name, block)
        assert many._line == one._line  # the same floating-point line: same refit points
        for e in np.unique(epochs_one).tolist():
            if one.is_locked(e):
                assert np.array_equal(many.to_host(dev, e), one.to_host(dev, e))


def test_feed_many_checks_its_input() -> None:
    cm = ClockMapper()
    with pytest.raises(ValueError, match="differ in length"):
        cm.feed_many([1, 2, 3], [1, 2])
    assert cm.feed_many([], []).shape == (0,)
