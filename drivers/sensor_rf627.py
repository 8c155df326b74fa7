"""Riftek RF627 driver: the profile stream the sensor sends by UDP to the host (port 50001).

Decoding is :func:`wristscan.drivers.rf627.decode` (one vectorised step per datagram). RF627
packets carry no checksum, so the driver adds two plausibility checks that catch damage in the
header (damage in the point data cannot be detected):

* the fields that stay constant in a stream (data type, flags, device type, serial number,
  protocol version, offsets, scaling, payload size) are locked on the first packet; a packet that
  differs is rejected as malformed, and two consecutive packets (the second one newer) that
  agree on new values re-lock (reconfiguration, another sensor taking over the port);
* the frame counter (``measure_count``) and the device clock (``system_time``) must advance
  together: ``|dt - dc * period| <= period / 2 + dc * period / 100`` with the period learnt from
  the stream. A packet failing it is held back; if the next, newer packet agrees with it (a
  device reboot or clock step) the driver restarts its bookkeeping from there, otherwise it was
  damage.

``read_blocks`` decodes the packets that pass both checks with certainty (the locked fields
equal, the counter and the clock agree for every period the learnt one can have become within
the pass) in blocks (:mod:`wristscan.drivers.rf627_block`); the others go one by one through
the same checks as ``read``, with the same counts.
"""

from __future__ import annotations

import logging
import statistics
from collections import deque
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers import _bpf, rf627, rf627_block
from wristscan.drivers._udp import Datagrams, UdpProfileSensor
from wristscan.drivers.records import Profile, ProfileBlock

__all__ = ["Rf627Sensor"]

log = logging.getLogger(__name__)

_MOD32 = 1 << 32


def _signed32(v: int) -> int:
    v %= _MOD32
    return v - _MOD32 if v >= _MOD32 // 2 else v


class Rf627Sensor(UdpProfileSensor):
    """RF627 profiles by UDP. ``sensor_host`` keeps datagrams from that address only;
    ``sensor_id`` (the serial number) keeps that sensor's profiles only."""

    kind: ClassVar[str] = "rf627-udp"
    time_unit_ns = 1
    """Nanoseconds per ``system_time`` tick (the simulated RF627 writes ns; check a device)."""

    def __init__(
        self,
        sensor_id: int | None = None,
        bind_host: str = "0.0.0.0",
        port: int = 50001,
        sensor_host: str | None = None,
        recv_buffer_bytes: int = 8 << 20,
    ) -> None:
        super().__init__(sensor_id, bind_host, port, sensor_host, recv_buffer_bytes)
        self.sensor_host = sensor_host
        self._signature: tuple[int, ...] | None = None
        self._candidate_sig: tuple[int, ...] | None = None
        self._candidate_count = 0
        self._ref: tuple[int, int] | None = None
        """(measure_count, system_time) of the last delivered packet."""
        self._steps: deque[int] = deque(maxlen=9)
        """Device-clock ticks of the latest one-frame steps (their median is the period)."""
        self._period: float | None = None
        self._held: tuple[int, int] | None = None
        """(measure_count, system_time) of a packet that failed the counter/clock check."""
        self._holds = 0

    def _reset_decoder(self) -> None:
        self._signature = self._candidate_sig = None
        self._ref = self._held = None
        self._forget_period()

    def _admission_program(self, fraction: float) -> list[_bpf.Instruction]:
        # Every datagram is a profile; measure_count at bytes 24-27 of the 64-byte header.
        return _bpf.counter_filter(fraction, 24, rf627.HEADER.size)

    def _forget_period(self) -> None:
        self._steps.clear()
        self._period = None
        self._holds = 0

    @staticmethod
    def _sig(h: rf627.RF627Header) -> tuple[int, ...]:
        return (
            h.data_type,
            h.flags,
            h.device_type,
            h.serial,
            h.proto_major,
            h.proto_minor,
            h.hardware_params_offset,
            h.data_offset,
            h.zmr,
            h.xemr,
            h.discrete_value,
            h.payload_size,
            h.bytes_per_point,
        )

    def _plausible(self, ref: tuple[int, int], count: int, stamp: int) -> bool:
        period = self._period
        if period is None:
            return True
        dc = _signed32(count - ref[0])
        dt = stamp - ref[1]
        return abs(dt - dc * period) <= 0.5 * period + 0.01 * abs(dc) * period

    def _on_datagram(self, frame: memoryview, host_time_ns: int) -> None:
        try:
            decoded = rf627.decode(frame, host_time_ns, self.time_unit_ns)
        except rf627.FrameError as exc:
            self._reject(str(exc))
            return
        h = decoded.header
        if self.expected_sensor_id is not None and h.serial != self.expected_sensor_id:
            self.stats["foreign"] += 1
            return
        sig = self._sig(h)
        if self._signature is None:
            self._signature = sig
        elif sig != self._signature:
            newer = 0 < _signed32(h.measure_count - self._candidate_count) < 1 << 16
            if sig != self._candidate_sig or not newer:
                # A copy of the same packet does not confirm it: a newer one must.
                self._candidate_sig, self._candidate_count = sig, h.measure_count
                self._reject("RF627 header fields differ from the stream's")
                return
            log.info("%s: stream parameters changed, re-locking", self.kind)
            self.stats["relocks"] += 1
            self._signature = sig
            self._restart("stream parameters changed")
            self._ref = self._held = None
            self._forget_period()
        self._candidate_sig = None
        count, stamp = h.measure_count, h.system_time
        ref = self._ref
        if ref is not None and not self._plausible(ref, count, stamp):
            held = self._held
            self._holds += 1
            if self._holds >= 3:
                # Nothing agrees with the learnt period any more: learn it again.
                self._restart("frame period changed")
                self._forget_period()
                ref = None
            elif (
                held is None
                or _signed32(count - held[0]) <= 0  # a copy of it confirms nothing
                or not self._plausible(held, count, stamp)
            ):
                self._held = (count, stamp)
                self._reject("RF627 frame counter and device clock disagree")
                return
            else:
                # Two packets agree with each other, not with the past: reboot or clock step.
                self._restart("frame counter or device clock jumped")
                ref = None
        self._held = None
        self._holds = 0
        if not self._deliver(decoded.profile, _MOD32):
            return
        if ref is not None and _signed32(count - ref[0]) == 1:
            self._steps.append(stamp - ref[1])
            if len(self._steps) >= 3:
                self._period = float(statistics.median(self._steps))
        self._ref = (count, stamp)

    def _on_datagrams(self, grams: Datagrams) -> list[ProfileBlock]:
        """Runs of packets that certainly pass the checks as blocks, the others one by one;
        the blocks in arrival order."""
        headers = rf627_block.read_headers(grams)
        out: list[ProfileBlock] = []
        records: list[Profile] = []
        ok: NDArray[np.bool_] | None = None
        locked: tuple[int, ...] | None = None
        i, k = 0, len(grams)
        while i < k:
            m, steps, last = 0, list[int](), (0, 0)
            if self._signature is not None and self._steady():
                if ok is None or locked != self._signature:
                    locked = self._signature
                    ok = rf627_block.matching(grams, headers, locked, self.expected_sensor_id)
                m, steps, last = self._certain_run(headers, ok, i)
            if m == 0:
                self._datagram_slow(grams, i, records)
                i += 1
                continue
            if records:
                out += ProfileBlock.from_profiles(records)
                records = []
            block = rf627_block.decode_rows(grams, headers, i, i + m, self.time_unit_ns)
            kept = self._deliver_block(block, _MOD32)
            if kept is not None:
                out.append(kept)
            self._advance(steps, last)
            i += m
        if records:
            out += ProfileBlock.from_profiles(records)
        self._log_raw(grams, k)
        return out

    def _steady(self) -> bool:
        """Locked, the period learnt, the last delivered packet the reference."""
        ref = self._ref
        return self._period is not None and ref is not None and self._last_counter == ref[0]

    def _certain_run(
        self, h: NDArray[Any], ok: NDArray[np.bool_], i: int
    ) -> tuple[int, list[int], tuple[int, int]]:
        """How many packets from ``i`` on pass every check whatever the learnt period becomes
        meanwhile (it stays between the least and the greatest one-frame step seen here or
        in its window) and
        continue the counter: the slow path would deliver each of them. With their one-frame
        clock steps and the last one's (counter, clock)."""
        assert self._ref is not None
        c = h["measure_count"][i:].astype(np.int64)
        t = h["system_time"][i:].astype(np.int64)
        dc = np.empty_like(c)
        dc[0] = c[0] - self._ref[0]
        np.subtract(c[1:], c[:-1], out=dc[1:])
        dc &= _MOD32 - 1
        dti = np.empty_like(t)
        dti[0] = t[0] - self._ref[1]
        np.subtract(t[1:], t[:-1], out=dti[1:])
        one = dc == 1
        ones = dti[one]
        lo = min(self._steps) if ones.size == 0 else min(min(self._steps), int(ones.min()))
        hi = max(self._steps) if ones.size == 0 else max(max(self._steps), int(ones.max()))
        # |dt - dc p| <= (0.5 + 0.01 dc) p for every period p in [lo, hi] (the condition is
        # convex in p: both ends suffice), i.e. hi (dc - tol) <= dt <= lo (dc + tol); a hair
        # inside, so that borderline packets go one by one.
        n = dc.astype(np.float64)
        k = 1.0 - 1e-9
        dt = dti.astype(np.float64)
        cond = ok[i:] & ((dc - 1).view(np.uint64) < np.uint64(1 << 30))
        cond &= dt >= hi * (n * (1.0 - 0.01 * k) - 0.5 * k)
        cond &= dt <= lo * (n * (1.0 + 0.01 * k) + 0.5 * k)
        if lo <= 0:
            cond[:] = False
        m = int(cond.shape[0]) if cond.all() else int(np.argmin(cond))
        if m == 0:
            return 0, [], self._ref
        return m, dti[:m][one[:m]].tolist(), (int(c[m - 1]), int(t[m - 1]))

    def _advance(self, steps: list[int], ref: tuple[int, int]) -> None:
        """The state the slow path leaves after delivering a certain run (its one-frame clock
        steps, the last packet's counter and clock)."""
        self._steps.extend(steps)
        if len(self._steps) >= 3:
            self._period = float(statistics.median(self._steps))
        self._ref = ref
        self._held = None
        self._holds = 0
        self._candidate_sig = None

    def _health_detail(self) -> dict[str, Any]:
        return {
            **super()._health_detail(),
            "period_ticks": self._period,
        }
