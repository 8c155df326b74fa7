"""Pair every profile with the robot (and table) state at its exposure instant.

Records come in any order from independent drivers. The :class:`Pairer`

1. maps each profile's sensor timestamp onto the host clock (:class:`ClockMapper` per sensor,
   unwrapping a wrapping counter first) and subtracts the configured sensor latency, which gives
   the exposure instant on the host clock;
2. maps that instant onto the robot controller's clock (the robot's own :class:`ClockMapper`,
   inverted) and interpolates the robot samples there (:class:`RobotStateBuffer`), and likewise
   for the rotary table when one is configured;
3. releases profiles whose states are covered on both sides, in :class:`PairedBatch` objects
   sorted by exposure time; a profile not covered yet waits (``max_wait_ns`` of host time after
   its receipt) and is then dropped, counted by reason. Nothing is ever paired with an
   extrapolated or guessed pose.

In **encoder mode** the profiles carry the count of an encoder that the robot also reports
(:meth:`Pairer.add_encoder_sample`, e.g. from an RTDE register, stamped with the controller
clock). The profile's count is looked up among the robot's ``(count, controller time)`` samples,
which puts the exposure directly on the controller clock: the sensor clock is not used. The
counter must increase monotonically while profiles are taken (a trigger counter or an axis moving
one way); samples that do not increase are ignored.

Profiles come as blocks (:meth:`Pairer.add_block`, the hot path: whole arrays, no Python step
per profile; kept as they are, see :mod:`.pending`, and released as views of them) or as
records (:meth:`Pairer.add_profile`); both give the same batches.
Counters: ``received == paired + sum(dropped.values()) + pending`` holds after every call.
Not thread-safe: one owner thread adds records and polls.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from wristscan.daemon.sync.batch import PairedBatch, concat_batches
from wristscan.daemon.sync.buffers import Reason, RobotStateBuffer, SampleBuffer, ScalarBuffer
from wristscan.daemon.sync.clockfeed import feed_lists
from wristscan.daemon.sync.clockmap import ClockMapper
from wristscan.daemon.sync.counters import CounterUnwrapper, unwrap_nearest
from wristscan.daemon.sync.pairconfig import PairerConfig
from wristscan.daemon.sync.pending import PendingProfiles
from wristscan.daemon.sync.readytick import poll_all_ready
from wristscan.drivers.records import Profile, ProfileBlock, RobotState, TableState

logger = logging.getLogger(__name__)

__all__ = ["DROP_REASONS", "Pairer", "PairerConfig"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

# Per-profile status codes inside poll(): 0 ready, 1.. waiting, 100.. dropped now.
_READY = 0
_W_CLOCK = 1
_W_ROBOT_CLOCK = 2
_W_ROBOT = 3
_W_TABLE_CLOCK = 4
_W_TABLE = 5
_W_ENCODER = 6
_D_FIRST = 100
_D_CLOCK = 100
_D_BEFORE = 101
_D_GAP = 102
_D_TABLE_BEFORE = 103
_D_TABLE_GAP = 104
_D_ENC_BEFORE = 105
_D_ENC_GAP = 106

_REASON_OF: dict[int, str] = {
    # A waiting profile that times out is dropped for what it was waiting for.
    _W_CLOCK: "clock_unlocked",
    _W_ROBOT_CLOCK: "robot_clock_unlocked",
    _W_ROBOT: "no_robot_state_timeout",
    _W_TABLE_CLOCK: "table_clock_unlocked",
    _W_TABLE: "no_table_state_timeout",
    _W_ENCODER: "no_encoder_sample_timeout",
    _D_CLOCK: "clock_unlocked",
    _D_BEFORE: "before_buffer",
    _D_GAP: "gap_too_large",
    _D_TABLE_BEFORE: "table_before_buffer",
    _D_TABLE_GAP: "table_gap_too_large",
    _D_ENC_BEFORE: "encoder_before_buffer",
    _D_ENC_GAP: "encoder_gap_too_large",
}


def _status_of(**codes: int) -> IntArray:
    """Lookup table ``Reason`` -> status code (``np.select`` costs ~0.3 ms a call: per poll)."""
    table = np.full(max(Reason) + 1, _READY, dtype=np.int64)
    for name, code in codes.items():
        table[Reason[name]] = code
    return table


_ROBOT_STATUS = _status_of(NOT_YET=_W_ROBOT, BEFORE_BUFFER=_D_BEFORE, GAP=_D_GAP)
_TABLE_STATUS = _status_of(NOT_YET=_W_TABLE, BEFORE_BUFFER=_D_TABLE_BEFORE, GAP=_D_TABLE_GAP)
_ENCODER_STATUS = _status_of(NOT_YET=_W_ENCODER, BEFORE_BUFFER=_D_ENC_BEFORE)
"""Encoder mode: a gap between counts is no reason by itself (the time gap is checked)."""

DROP_REASONS: tuple[str, ...] = (
    *sorted(set(_REASON_OF.values())),
    "no_encoder_count",
    "pending_overflow",
    "flushed",
)
"""Every reason a profile can be dropped for (keys of ``Pairer.dropped``)."""


class Pairer:
    """Pairs profiles with robot/table states; see the module docstring."""

    def __init__(self, config: PairerConfig | None = None) -> None:
        cfg = config or PairerConfig()
        self.config = cfg
        self._sensor_cfg = replace(cfg.sensor_clock, latency_ns=cfg.sensor_latency_ns)
        self._sensor_clocks: dict[int, ClockMapper] = {}
        self._sensor_unwrap: dict[int, CounterUnwrapper] = {}
        self.robot_clock = ClockMapper(
            replace(cfg.robot_clock, latency_ns=cfg.robot_latency_ns), name="robot clock"
        )
        self.table_clock = ClockMapper(
            replace(cfg.table_clock, latency_ns=cfg.table_latency_ns), name="table clock"
        )
        self.robot = RobotStateBuffer(
            cfg.robot_model,
            cfg.interpolation,
            cfg.robot_capacity,
            cfg.robot_max_gap_ns,
            tcp_offset=cfg.tcp_offset,
        )
        self.table = ScalarBuffer(cfg.table_capacity, cfg.table_max_gap_ns, cfg.table_period_rad)
        self._table_on_device_clock: bool | None = None
        # Encoder samples: key = unwrapped count, value = controller time (ns). The key gap is
        # meaningless, so the buffer's own gap check is off and poll() checks the time gap.
        self.encoder = SampleBuffer(1, cfg.encoder_capacity, max_gap_ns=1 << 62)
        self._enc_last: int | None = None
        # Pending profiles, in arrival order: their blocks and per-profile arrays.
        self._pending = PendingProfiles()
        self._now = -(1 << 62)
        self.received = 0
        self.paired = 0
        self.waiting_for_states = 0
        """Profiles the last :meth:`poll` left waiting only for robot or table states to arrive
        (their clocks locked): a worker may wait briefly for those instead of a whole tick."""
        self._need_ns: dict[str, int] = {}
        """Per state stream (``robot``, ``table``): the newest device time a waiting profile
        needs a sample at or after (see :meth:`states_cover_waiting`)."""
        self.dropped: dict[str, int] = dict.fromkeys(DROP_REASONS, 0)
        self.robot_states = 0
        self.table_states = 0
        self.encoder_samples = 0
        self.batches = 0

    # ------------------------------------------------------------------ input

    @property
    def pending(self) -> int:
        """Profiles waiting for the states they need."""
        return len(self._pending)

    @property
    def latest_host_ns(self) -> int:
        """Newest host receive time seen on any stream (the pairer's notion of now)."""
        return self._now

    def sensor_unwrapper(self, sensor_id: int) -> CounterUnwrapper | None:
        """The timestamp unwrapper of one sensor (None without ``sensor_time_modulus_ns``)."""
        return self._sensor_unwrap.get(sensor_id)

    def sensor_clock(self, sensor_id: int) -> ClockMapper:
        """The clock mapper of one sensor (created on first use)."""
        clk = self._sensor_clocks.get(sensor_id)
        if clk is None:
            clk = ClockMapper(self._sensor_cfg, name=f"sensor {sensor_id} clock")
            self._sensor_clocks[sensor_id] = clk
        return clk

    def _unwrapper(self, sid: int) -> CounterUnwrapper | None:
        modulus = self.config.sensor_time_modulus_ns
        if modulus is None:
            return None
        unw = self._sensor_unwrap.get(sid)
        if unw is None:
            unw = self._sensor_unwrap[sid] = CounterUnwrapper(modulus)
        return unw

    def add_block(self, block: ProfileBlock) -> None:
        """Queue a block of profiles: the same as :meth:`add_profile` for each row in order,
        vectorised. The block's arrays are kept (no copy) and batches view them: hand over
        arrays that are not reused afterwards."""
        P = block.n_profiles
        if P == 0:
            return
        self.received += P
        host = block.host_time_ns
        top = int(host.max())
        if top > self._now:
            self._now = top
        rows: IntArray | None = None
        key: tuple[int, int] | None = None
        if self.config.mode == "clock":
            sid = block.sensor_id
            s0 = int(sid[0])
            if (sid == s0).all():
                x, epoch = self._feed_sensor(s0, block.sensor_time_ns, host)
                e0, e1 = int(epoch[0]), int(epoch[-1])  # epochs never decrease
                key = (s0, e0) if e0 == e1 else None
            else:
                x = np.empty(P, dtype=np.int64)
                epoch = np.empty(P, dtype=np.int64)
                for s in np.unique(sid).tolist():
                    g = np.flatnonzero(sid == s)
                    x[g], epoch[g] = self._feed_sensor(s, block.sensor_time_ns[g], host[g])
        else:
            enc, ok = block.encoder, block.encoder_valid
            if enc is None:
                self.dropped["no_encoder_count"] += P
                return
            if ok is not None and not ok.all():
                rows = np.flatnonzero(ok)
                self.dropped["no_encoder_count"] += P - rows.shape[0]
                enc = enc[rows]
            x = enc.astype(np.int64)
            epoch = np.zeros(x.shape[0], dtype=np.int64)
        self._pending.add_block(block, rows, x, epoch, key)
        self._trim()

    def _feed_sensor(self, sid: int, t: IntArray, host: IntArray) -> tuple[IntArray, IntArray]:
        """Unwrapped sensor times and their clock epochs, in arrival order."""
        unw = self._unwrapper(sid)
        x = t if unw is None else unw.many(t, host)
        return x, self.sensor_clock(sid).feed_many(x, host)

    def _trim(self) -> None:
        excess = len(self._pending) - self.config.max_pending
        if excess > 0:
            self.dropped["pending_overflow"] += excess
            self._pending.drop_oldest(excess)

    def add_profile(self, profile: Profile) -> None:
        """Queue a profile; it is released by a later :meth:`poll`."""
        self.received += 1
        host = profile.host_time_ns
        if host > self._now:
            self._now = host
        sid = profile.sensor_id
        if self.config.mode == "clock":
            x = profile.sensor_time_ns
            unw = self._unwrapper(sid)
            if unw is not None:
                x = unw(x, host)
            epoch = self.sensor_clock(sid).feed(x, host)
        else:
            if profile.encoder is None:
                self.dropped["no_encoder_count"] += 1
                return
            x, epoch = int(profile.encoder), 0
        self._pending.add_record(profile, x, epoch)
        self._trim()

    def add_robot_state(self, state: RobotState) -> None:
        """Add one controller sample (any order relative to profiles)."""
        self.robot_states += 1
        x, host = round(state.controller_time_s * 1e9), state.host_time_ns
        if host > self._now:
            self._now = host
        self.robot_clock.feed(x, host)
        self._append_robot(x, state)

    def add_robot_states(self, states: Sequence[RobotState]) -> None:
        """:meth:`add_robot_state` for each sample (a tick's, in arrival order), the robot clock
        fed them at once (:func:`~.clockfeed.feed_lists`: the same fit, to the last bit)."""
        if not states:
            return
        self.robot_states += len(states)
        hosts = [s.host_time_ns for s in states]
        xs = [round(s.controller_time_s * 1e9) for s in states]
        self._now = max(self._now, *hosts)
        feed_lists(self.robot_clock, xs, hosts)
        if not self.robot.append_many(xs, [s.q for s in states], [s.tcp_pose for s in states]):
            for x, state in zip(xs, states, strict=True):
                self._append_robot(x, state)

    def _append_robot(self, x: int, state: RobotState) -> None:
        last = self.robot.buffer.last_ns
        if last is not None and x < last - self.config.robot_clock.reorder_tolerance_ns:
            # The controller restarted (a smaller step back is a reordered sample: refused).
            logger.warning("robot controller clock went back; robot buffer cleared")
            self.robot.clear()
            self.encoder.clear()
            self._enc_last = None
        self.robot.append(x, state.q, state.tcp_pose)

    def add_table_state(self, state: TableState) -> None:
        """Add one rotary-table reading (used when ``use_table``)."""
        self.table_states += 1
        host = state.host_time_ns
        if host > self._now:
            self._now = host
        on_device = state.device_time_ns is not None
        if self._table_on_device_clock is None:
            self._table_on_device_clock = on_device
        elif on_device != self._table_on_device_clock:
            raise ValueError("table states must all carry a device time, or none")
        if state.device_time_ns is not None:
            x = int(state.device_time_ns)
            self.table_clock.feed(x, host)
        else:
            x = host - self.config.table_latency_ns
        last = self.table.buffer.last_ns
        if last is not None and x < last - self.config.table_clock.reorder_tolerance_ns:
            self.table.clear()
        self.table.append(x, state.angle_rad)

    def add_encoder_sample(self, count: int, controller_time_s: float, host_time_ns: int) -> None:
        """Add one ``(encoder count, controller time)`` sample reported by the robot."""
        self.encoder_samples += 1
        if host_time_ns > self._now:
            self._now = host_time_ns
        c = int(count)
        modulus = self.config.encoder_modulus
        if modulus is not None and self._enc_last is not None:
            c = int(unwrap_nearest(c, self._enc_last, modulus))
        if self.encoder.append(c, (float(round(controller_time_s * 1e9)),)):
            self._enc_last = c

    # ------------------------------------------------------------------ output

    def poll(self, now_ns: int | None = None) -> list[PairedBatch]:
        """Release every pending profile that can be paired now; drop the hopeless and the
        timed-out ones. ``now_ns`` (host monotonic) defaults to the newest receipt seen."""
        pend = self._pending
        P = len(pend)
        if P == 0:
            return []
        pend.consolidate()
        fast = self._poll_all_ready()
        if fast is not None:
            return fast
        now = self._now if now_ns is None else max(int(now_ns), self._now)
        self._need_ns = {}
        host, x = pend.host, pend.x
        status = np.zeros(P, dtype=np.int64)
        exposure = np.zeros(P, dtype=np.int64)
        unc = np.zeros(P)
        F = np.full((P, 4, 4), np.nan)
        angle: FloatArray | None = np.full(P, np.nan) if self.config.use_table else None

        if self.config.mode == "clock":
            self._map_sensor_times(x, status, exposure, unc)
            self._pair_robot_clock(status, exposure, F)
        else:
            self._pair_encoder(x, status, exposure, F)
        if angle is not None:
            self._pair_table(status, exposure, angle)

        waiting = (status > _READY) & (status < _D_FIRST)
        states = status == _W_ROBOT
        if angle is not None:
            states |= status == _W_TABLE
        self.waiting_for_states = int(np.count_nonzero(states))
        late = waiting & (host < now - self.config.max_wait_ns)
        drop = status >= _D_FIRST
        drop |= late
        dropping = bool(drop.any())
        if dropping:
            codes, counts = np.unique(status[drop], return_counts=True)
            for code, cnt in zip(codes.tolist(), counts.tolist(), strict=True):
                self.dropped[_REASON_OF[code]] += cnt
        ready = np.flatnonzero(status == _READY)
        batches: list[PairedBatch] = []
        if ready.shape[0]:
            ready = ready[np.argsort(exposure[ready], kind="stable")]
            step = self.config.max_batch_profiles
            for k in range(0, ready.shape[0], step):
                sel = ready[k : k + step]
                batches.append(
                    self._batch(sel, exposure, unc, F, None if angle is None else angle[sel], host)
                )
            self.paired += int(ready.shape[0])
            self.batches += len(batches)
        if ready.shape[0] or dropping:
            self._pending.keep(np.flatnonzero(waiting ^ late))
        return batches

    def _poll_all_ready(self) -> list[PairedBatch] | None:
        """:meth:`poll` when every pending profile can be paired now (the usual tick): the same
        batches without the per-profile status arrays (:mod:`.readytick`); None otherwise."""
        return poll_all_ready(self)

    def merge(self, batches: list[PairedBatch]) -> list[PairedBatch]:
        """Consecutive batches joined (up to ``max_batch_profiles`` profiles each), in order."""
        out: list[PairedBatch] = []
        group: list[PairedBatch] = []
        n = 0
        for b in batches:
            if group and n + b.n_profiles > self.config.max_batch_profiles:
                out.append(concat_batches(group))
                group, n = [], 0
            group.append(b)
            n += b.n_profiles
        if group:
            out.append(concat_batches(group))
        return out

    def flush(self, now_ns: int | None = None) -> list[PairedBatch]:
        """Poll once more, then drop whatever still waits (reason ``flushed``)."""
        out = self.poll(now_ns)
        self.dropped["flushed"] += len(self._pending)
        self._pending.clear()
        return out

    # ------------------------------------------------------------------ steps

    def _map_sensor_times(
        self, x: IntArray, status: IntArray, exposure: IntArray, unc: FloatArray
    ) -> None:
        pend = self._pending
        groups: list[tuple[tuple[int, int], slice | IntArray]]
        one = pend.single_key()
        if one is not None:
            groups = [(one, slice(None))]
        else:
            sid, epoch = pend.sid, pend.epoch
            uniq = np.unique(np.stack([sid, epoch], axis=1), axis=0).tolist()
            pend.set_keys({(s, e) for s, e in uniq})
            groups = [((s, e), np.flatnonzero((sid == s) & (epoch == e))) for s, e in uniq]
        for (s, e), g in groups:
            clk = self._sensor_clocks[s]
            if clk.is_locked(e):
                exposure[g] = clk.to_host(x[g], e)
                unc[g] = clk.uncertainty_ns(x[g], e)
            elif e < clk.epoch:
                status[g] = _D_CLOCK  # an old epoch that never locked never will
            else:
                status[g] = _W_CLOCK

    def _robot_lookup(
        self, t_robot: IntArray, status: IntArray, m: slice | IntArray, F: FloatArray
    ) -> None:
        T, _, reason = self.robot.interpolate(t_robot)
        status[m] = _ROBOT_STATUS[reason]
        F[m] = T
        self._note_need("robot", t_robot, reason)

    def _pair_robot_clock(self, status: IntArray, exposure: IntArray, F: FloatArray) -> None:
        m: slice | IntArray = slice(None)
        if status.any():
            m = np.flatnonzero(status == _READY)
            if m.shape[0] == 0:
                return
        if not self.robot_clock.locked:
            status[m] = _W_ROBOT_CLOCK
            return
        self._robot_lookup(self.robot_clock.to_device(exposure[m]), status, m, F)

    def _pair_encoder(
        self, x: IntArray, status: IntArray, exposure: IntArray, F: FloatArray
    ) -> None:
        cfg = self.config
        count = x
        if cfg.encoder_modulus is not None and self._enc_last is not None:
            count = unwrap_nearest(x, self._enc_last, cfg.encoder_modulus)
        i, s, reason = self.encoder.locate(count)
        V = self.encoder.values[:, 0]
        st = _ENCODER_STATUS[reason]
        ok = st == _READY
        t_robot = np.zeros(x.shape[0], dtype=np.int64)
        if np.any(ok):
            v0, v1 = V[i[ok]], V[i[ok] + 1]
            st[ok] = np.where(v1 - v0 > cfg.encoder_max_gap_ns, _D_ENC_GAP, _READY)
            t_robot[ok] = np.rint(v0 + (v1 - v0) * s[ok]).astype(np.int64) - cfg.sensor_latency_ns
        status[:] = st
        m = np.flatnonzero(status == _READY)
        if m.shape[0] == 0:
            return
        if not self.robot_clock.locked:
            # Pairing would not need it, but the batch reports exposure on the host clock.
            status[m] = _W_ROBOT_CLOCK
            return
        exposure[m] = self.robot_clock.to_host(t_robot[m])
        self._robot_lookup(t_robot[m], status, m, F)

    def _pair_table(self, status: IntArray, exposure: IntArray, angle: FloatArray) -> None:
        m = np.flatnonzero(status == _READY)
        if m.shape[0] == 0:
            return
        if self._table_on_device_clock:
            if not self.table_clock.locked:
                status[m] = _W_TABLE_CLOCK
                return
            t = self.table_clock.to_device(exposure[m])
        else:
            t = exposure[m]
        v, _, reason = self.table.interpolate(t)
        status[m] = _TABLE_STATUS[reason]
        angle[m] = v
        self._note_need("table", t, reason)

    def _note_need(self, stream: str, t: IntArray, reason: NDArray[np.uint8]) -> None:
        later = reason == Reason.NOT_YET
        if later.any():
            self._need_ns[stream] = int(t[later].max())

    def states_cover_waiting(self) -> bool:
        """Whether the states added since the last :meth:`poll` reach every profile it left
        waiting for them: polling before would only repeat its work."""
        for stream, need in self._need_ns.items():
            last = (self.robot if stream == "robot" else self.table).buffer.last_ns
            if last is None or last < need:
                return False
        return True

    def _batch(
        self,
        sel: IntArray | slice,
        exposure: IntArray,
        unc: FloatArray,
        F: FloatArray,
        angle: FloatArray | None,
        host: IntArray,
    ) -> PairedBatch:
        g = self._pending.gather(sel)
        return PairedBatch(
            sensor_id=g.sensor_id,
            frame_counter=g.frame_counter,
            exposure_ns=exposure[sel],
            clock_uncertainty_ns=unc[sel],
            flange2base=F[sel],
            table_angle=angle,
            y=g.y,
            z=g.z,
            valid=g.valid,
            intensity=g.intensity,
            offsets=g.offsets,
            arrival_ns=host[sel],
            y_grid=g.y_grid,
            segments=g.segments,
            points_per_profile=g.points_per_profile,
        )

    # ------------------------------------------------------------------ health

    def stats(self) -> dict[str, object]:
        """Counters and clock health (JSON-friendly) for the stats/status topics."""
        out: dict[str, object] = {
            "received": self.received,
            "paired": self.paired,
            "pending": self.pending,
            "dropped": {k: v for k, v in self.dropped.items() if v},
            "batches": self.batches,
            "robot_states": self.robot_states,
            "robot_states_rejected": self.robot.buffer.n_rejected,
            "table_states": self.table_states,
            "encoder_samples": self.encoder_samples,
            "robot_clock": self.robot_clock.status(),
            "sensor_clocks": {sid: c.status() for sid, c in self._sensor_clocks.items()},
            "sensor_counter_wraps": {sid: u.n_wraps for sid, u in self._sensor_unwrap.items()},
        }
        if self.config.use_table and self._table_on_device_clock:
            out["table_clock"] = self.table_clock.status()
        return out
