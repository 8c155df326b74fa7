"""Time series buffers that interpolate robot and table states at any instant, never beyond.

:class:`SampleBuffer` is the generic part: a bounded, preallocated series of ``(t_ns, values)``
with strictly increasing times, located and interpolated linearly for whole arrays of query
instants at once (``np.searchsorted``). A query is answered only when samples bracket it and lie
at most ``max_gap_ns`` apart; otherwise it gets a :class:`Reason` and no value (NaN):

* ``NOT_YET``: after the newest sample (the state may still arrive: wait),
* ``BEFORE_BUFFER``: before the oldest sample kept (never coming),
* ``GAP``: the bracketing samples are too far apart to interpolate between.

:class:`RobotStateBuffer` stores joint positions and the controller TCP pose and returns
``flange2base`` transforms: by default it interpolates the joints and runs forward kinematics
(``mode="joint"``), or it interpolates the controller TCP pose on SE(3) (``mode="tcp"``, needs the
TCP offset configured on the controller to get back to the flange). :class:`ScalarBuffer` serves
single channels such as the rotary table angle, optionally unwrapping a periodic value.

Times are integer ns on whatever clock the owner chooses (the pairer uses each device's own
clock, so interpolation does not depend on the clock fit); memory is fixed at construction.
"""

from __future__ import annotations

import itertools
import math
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3

__all__ = ["Reason", "RobotStateBuffer", "SampleBuffer", "ScalarBuffer"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
ReasonArray = NDArray[np.uint8]


class Reason(IntEnum):
    """Why a query instant got no value (``OK`` when it did)."""

    OK = 0
    NOT_YET = 1
    BEFORE_BUFFER = 2
    GAP = 3


class SampleBuffer:
    """Bounded series of ``(t_ns, values (width,))`` with strictly increasing ``t_ns``.

    Storage is two preallocated arrays of ``2 * capacity`` rows; the live window is a contiguous
    slice (searchsorted needs one), moved back to the front when it reaches the end, so appends
    cost O(width) amortised and memory never grows.
    """

    def __init__(self, width: int, capacity: int = 8192, max_gap_ns: int = 20_000_000) -> None:
        if width < 1 or capacity < 2 or max_gap_ns <= 0:
            raise ValueError("SampleBuffer: width >= 1, capacity >= 2 and max_gap_ns > 0 needed")
        self.width = int(width)
        self.capacity = int(capacity)
        self.max_gap_ns = int(max_gap_ns)
        self._t = np.zeros(2 * self.capacity, dtype=np.int64)
        self._v = np.zeros((2 * self.capacity, self.width), dtype=np.float64)
        self._i0 = 0
        self._i1 = 0
        self.n_rejected = 0
        """Appends refused because their time did not increase."""

    def __len__(self) -> int:
        return self._i1 - self._i0

    @property
    def times(self) -> IntArray:
        """Times of the samples held (a view; valid until the next append)."""
        return self._t[self._i0 : self._i1]

    @property
    def values(self) -> FloatArray:
        """Values of the samples held, ``(n, width)`` (a view; valid until the next append)."""
        return self._v[self._i0 : self._i1]

    @property
    def first_ns(self) -> int | None:
        return int(self._t[self._i0]) if self._i1 > self._i0 else None

    @property
    def last_ns(self) -> int | None:
        return int(self._t[self._i1 - 1]) if self._i1 > self._i0 else None

    def clear(self) -> None:
        self._i0 = self._i1 = 0

    def append(self, t_ns: int, values: ArrayLike) -> bool:
        """Add a sample; returns False (and counts it) when ``t_ns`` is not after the last one."""
        t = int(t_ns)
        i = self._slot(t)
        if i < 0:
            return False
        self._v[i] = values
        self._commit(i, t)
        return True

    def _slot(self, t: int) -> int:
        """The row a sample at ``t`` goes to (room made): write its values there, then
        :meth:`_commit` it; -1 (counted) when ``t`` is not after the last sample."""
        if self._i1 > self._i0 and t <= self._t[self._i1 - 1]:
            self.n_rejected += 1
            return -1
        if self._i1 == self._t.shape[0]:
            keep = min(self.capacity - 1, self._i1 - self._i0)
            self._t[:keep] = self._t[self._i1 - keep : self._i1]
            self._v[:keep] = self._v[self._i1 - keep : self._i1]
            self._i0, self._i1 = 0, keep
        return self._i1

    def _commit(self, i: int, t: int) -> None:
        """Add the sample whose values were written to row ``i`` (from :meth:`_slot`)."""
        self._t[i] = t
        self._i1 = i + 1
        if self._i1 - self._i0 > self.capacity:
            self._i0 += 1

    def _rows_for(self, ts: list[int]) -> slice | None:
        """:meth:`_slot` for samples ``ts`` at once: the rows to write their values to, then
        :meth:`_commit_many`; None (nothing counted) unless their times increase past the last
        sample and the rows are free without making room."""
        i, n = self._i1, len(ts)
        if i + n > self._t.shape[0] or not all(a < b for a, b in itertools.pairwise(ts)):
            return None
        if i > self._i0 and ts[0] <= self._t[i - 1]:
            return None
        return slice(i, i + n)

    def _commit_many(self, rows: slice, ts: list[int]) -> None:
        """:meth:`_commit` of the samples written to ``rows`` (from :meth:`_rows_for`)."""
        self._t[rows] = ts
        self._i1 = rows.stop
        self._i0 = max(self._i0, self._i1 - self.capacity)

    def locate(self, t_ns: ArrayLike) -> tuple[IntArray, FloatArray, ReasonArray]:
        """Bracket each query: index ``i`` into :attr:`times` with
        ``times[i] <= t <= times[i + 1]``, the fraction ``s`` in [0, 1] and the :class:`Reason`
        (``i`` and ``s`` are meaningless unless the reason is OK)."""
        i, s, reason, _ = self._locate(np.asarray(t_ns, dtype=np.int64))
        return i, s, reason

    def _locate(self, t: IntArray) -> tuple[IntArray, FloatArray, ReasonArray, bool]:
        """:meth:`locate`, and whether every reason is OK (few whole-array steps: the pairer
        calls it once per poll)."""
        T = self._t[self._i0 : self._i1]
        n = T.shape[0]
        if n < 2:
            reason = np.full(t.shape, Reason.NOT_YET, dtype=np.uint8)
            if n == 1:
                reason[t < T[0]] = Reason.BEFORE_BUFFER
            return np.zeros(t.shape, dtype=np.int64), np.zeros(t.shape), reason, False
        i = T.searchsorted(t, side="right")
        i -= 1
        np.minimum(i, n - 2, out=i)  # two ufuncs: np.clip costs several times more per call
        np.maximum(i, 0, out=i)
        t0 = T[i]
        dt = T[1:][i] - t0
        s = (t - t0) / dt  # both cast to float64
        reason = np.zeros(t.shape, dtype=np.uint8)
        if t.size == 0:
            return i, s, reason, True
        gap, early, late = dt.max() > self.max_gap_ns, t.min() < T[0], t.max() > T[-1]
        if gap:
            reason[dt > self.max_gap_ns] = Reason.GAP
        if early:
            reason[t < T[0]] = Reason.BEFORE_BUFFER
        if late:
            reason[t > T[-1]] = Reason.NOT_YET
        return i, s, reason, not (gap or early or late)

    def interpolate(self, t_ns: ArrayLike) -> tuple[FloatArray, ReasonArray]:
        """Linear interpolation of every column at ``t_ns`` ``(M,)``: values ``(M, width)`` (NaN
        rows where the reason is not OK) and reasons ``(M,)``."""
        i, s, reason = self.locate(t_ns)
        out = np.full((*i.shape, self.width), np.nan)
        ok = reason == Reason.OK
        if np.any(ok):
            V = self.values
            io, so = i[ok], s[ok][:, None]
            out[ok] = V[io] + (V[io + 1] - V[io]) * so
        return out, reason


class ScalarBuffer:
    """One interpolated channel (e.g. a rotary table angle in rad).

    With ``period`` (e.g. ``2 pi`` for a single-turn encoder) the value is unwrapped on append,
    so interpolation never crosses the wrap the long way round; results are then continuous
    (not reduced modulo the period).
    """

    def __init__(
        self, capacity: int = 4096, max_gap_ns: int = 200_000_000, period: float | None = None
    ) -> None:
        self._buf = SampleBuffer(1, capacity, max_gap_ns)
        self.period = period
        self._last: float | None = None

    def __len__(self) -> int:
        return len(self._buf)

    @property
    def buffer(self) -> SampleBuffer:
        return self._buf

    def clear(self) -> None:
        self._buf.clear()
        self._last = None

    def append(self, t_ns: int, value: float) -> bool:
        v = float(value)
        if self.period is not None and self._last is not None:
            v = self._last + math.remainder(v - self._last, self.period)
        ok = self._buf.append(t_ns, (v,))
        if ok:
            self._last = v
        return ok

    def interpolate(self, t_ns: ArrayLike) -> tuple[FloatArray, NDArray[np.bool_], ReasonArray]:
        """Values ``(M,)`` (NaN where not OK), ok mask ``(M,)`` and reasons ``(M,)``."""
        v, reason = self._buf.interpolate(t_ns)
        return v[..., 0], reason == Reason.OK, reason


class RobotStateBuffer:
    """Robot samples ``(t_ns, q (6,) rad, tcp_pose (6,) UR pose)`` interpolated to ``flange2base``.

    ``mode="joint"`` (default): joints interpolated linearly, then forward kinematics of
    ``model`` (a UR model name or :class:`~wristscan.calib.kinematics.DHParams`, ideally the
    robot's calibrated one). ``mode="tcp"``: geodesic interpolation of the controller TCP pose,
    then ``flange2base = tcp2base @ inv(tcp2flange)`` with ``tcp_offset`` the TCP set on the
    controller (UR pose ``p[x, y, z, rx, ry, rz]`` of the TCP in the flange frame; zero = flange).
    """

    def __init__(
        self,
        model: str | kinematics.DHParams = "UR5e",
        mode: str = "joint",
        capacity: int = 8192,
        max_gap_ns: int = 20_000_000,
        tcp_offset: ArrayLike | None = None,
    ) -> None:
        if mode not in ("joint", "tcp"):
            raise ValueError(f"RobotStateBuffer: mode must be 'joint' or 'tcp', not {mode!r}")
        self.mode = mode
        self.model = kinematics.get_model(model)
        offset = np.zeros(6) if tcp_offset is None else np.asarray(tcp_offset, dtype=np.float64)
        self._flange2tcp = se3.invert(se3.pose_to_matrix(offset))
        self._buf = SampleBuffer(12, capacity, max_gap_ns)

    def __len__(self) -> int:
        return len(self._buf)

    @property
    def buffer(self) -> SampleBuffer:
        return self._buf

    def clear(self) -> None:
        self._buf.clear()

    def append(self, t_ns: int, q: ArrayLike, tcp_pose: ArrayLike) -> bool:
        """Add a sample at ``t_ns``; False when its time does not increase (it is ignored)."""
        buf, t = self._buf, int(t_ns)
        i = buf._slot(t)
        if i < 0:
            return False
        row = buf._v[i]  # written in place: no temporary row
        row[:6] = q
        row[6:] = tcp_pose
        buf._commit(i, t)
        return True

    def append_many(self, ts: list[int], qs: list[FloatArray], poses: list[FloatArray]) -> bool:
        """:meth:`append` of samples whose times increase past the last one (a tick's), at once:
        True; False (nothing added) otherwise, or when they need the room made first."""
        buf = self._buf
        rows = buf._rows_for(ts)
        if rows is None:
            return False
        buf._v[rows, :6] = qs  # written in place, as append does
        buf._v[rows, 6:] = poses
        buf._commit_many(rows, ts)
        return True

    def interpolate(self, t_ns: ArrayLike) -> tuple[FloatArray, NDArray[np.bool_], ReasonArray]:
        """``flange2base`` ``(M, 4, 4)`` at each instant (NaN where not OK), ok mask ``(M,)`` and
        reasons ``(M,)``."""
        t = np.asarray(t_ns, dtype=np.int64)
        i, s, reason, all_ok = self._buf._locate(t)
        ok = reason == Reason.OK
        if all_ok:  # every instant covered: no mask, no NaN fill
            return self._poses(i, s), ok, reason
        out = np.full((*t.shape, 4, 4), np.nan)
        if ok.any():
            out[ok] = self._poses(i[ok], s[ok])
        return out, ok, reason

    def poses_if_covered(self, t_ns: ArrayLike) -> FloatArray | None:
        """``flange2base`` ``(M, 4, 4)`` at each instant when the samples cover every one of
        them (all reasons OK: the pairer's usual tick, no masks), else None."""
        i, s, _, all_ok = self._buf._locate(np.asarray(t_ns, dtype=np.int64))
        return self._poses(i, s) if all_ok else None

    def _poses(self, i: IntArray, s: FloatArray) -> FloatArray:
        """``flange2base`` between samples ``i`` and ``i + 1`` at fractions ``s``."""
        V = self._buf.values
        if self.mode == "joint":
            return kinematics.forward_between(self.model, V, i, s)
        T0 = se3.pose_to_matrix(V[i, 6:])
        T1 = se3.pose_to_matrix(V[i + 1, 6:])
        return np.asarray(se3.interpolate(T0, T1, s) @ self._flange2tcp)
