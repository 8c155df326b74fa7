"""The slope search's shortcuts (``envelope.support_slope``): the warm start's pruning against
both ends of its bracket, the search going on in Python floats once a few points are left, the
bracket's ends shared by the searches of one fit. Each must give the slope of the plain numpy
search, to the last bit; checked on real windows, with warm guesses near and off the edge."""

from __future__ import annotations

import numpy as np
import pytest
from test_clockfeed import synth

from wristscan.daemon.sync import envelope
from wristscan.daemon.sync.clockmap import ClockMapper


def _windows() -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Bucket minima of a 3 s and a 20 s stream (1 kHz, gamma delays, 5 % spikes), and the
    fitted drift of each."""
    out = []
    for seconds, seed in ((3.0, 1), (20.0, 2)):
        dev, host = synth(seconds, 1000.0, seed)
        cm = ClockMapper()
        cm.feed_many(dev, host)
        X, R = cm._points()
        out.append((X, R, cm.drift))
    return out


def test_shortcuts_give_the_plain_search_slope(monkeypatch: pytest.MonkeyPatch) -> None:
    cases = []
    for X, R, drift in _windows():
        span = float(X.max() - X.min())
        for f in np.linspace(0.05, 0.95, 19):
            x_e = float(X.min() + f * span)
            for guess in (None, drift, drift + 1.5e-6, drift - 3e-6):
                for half in (slice(None), slice(0, None, 2)):
                    cases.append((X[half], R[half], x_e, guess))
    searched = [0]
    search_lists = envelope._search_lists

    def counted(*args: object) -> float:
        searched[0] += 1
        return search_lists(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(envelope, "_search_lists", counted)
    fast = []
    for X, R, x_e, guess in cases:
        ends = None if guess is None else envelope.warm_ends(X, R, -1e-3, 1e-3, guess)
        fast.append(envelope.support_slope(X, R, x_e, -1e-3, 1e-3, guess, None, ends))
    assert searched[0] > len(cases) // 4  # the Python floats path does run
    monkeypatch.setattr(envelope, "_FEW_POINTS", -1)  # numpy all along, no shared ends
    plain = [envelope.support_slope(X, R, x_e, -1e-3, 1e-3, g) for X, R, x_e, g in cases]
    assert fast == plain
