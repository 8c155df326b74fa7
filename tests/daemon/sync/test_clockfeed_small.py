"""ClockMapper.feed_many on small blocks (a 1-5 kHz tick: the scalar path of
:mod:`wristscan.daemon.sync.clockfeed`) against feed, one arrival at a time: the same epochs,
lines, counters, recent arrivals and stored buckets, to the last bit."""

from __future__ import annotations

import numpy as np
import pytest
from test_clockfeed import streams

from wristscan.daemon.sync.clockmap import ClockMapper


def small_streams() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The streams of test_clockfeed, and one whose device times lie on an exact 1 ms grid
    (arrivals then fall exactly on a refit instant, as a sensor stamping in whole periods)."""
    out = streams()
    rng = np.random.default_rng(5)
    dev = 7_000_000_000 + np.arange(4000, dtype=np.int64) * 1_000_000
    host = np.rint(dev * (1.0 + 50e-6) + 20e6 + rng.gamma(2.0, 0.5e6, dev.shape[0]))
    out["exact grid"] = (dev, host.astype(np.int64))
    return out


@pytest.mark.parametrize("name", list(small_streams()))
def test_small_blocks_equal_feed_arrival_by_arrival(name: str) -> None:
    dev, host = small_streams()[name]
    one = ClockMapper()
    epochs_one = [one.feed(x, y) for x, y in zip(dev.tolist(), host.tolist(), strict=True)]
    for block in (7, 37):
        many = ClockMapper()
        epochs = np.concatenate(
            [
                many.feed_many(dev[i : i + block], host[i : i + block])
                for i in range(0, dev.shape[0], block)
            ]
        )
        assert epochs.tolist() == epochs_one, (name, block)
        assert many.status() == one.status(), (name, block)
        assert many._line == one._line, (name, block)
        assert list(many._recent) == list(one._recent)
        assert np.array_equal(many._bx[many._b0 : many._b1], one._bx[one._b0 : one._b1])
        assert np.array_equal(many._br[many._b0 : many._b1], one._br[one._b0 : one._b1])
