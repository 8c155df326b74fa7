"""Hokuyo SCIP 2.0 driver (serial or TCP): continuous scans turned into profiles.

After connecting, the driver stops any stream left running (``QT``), reads the version (``VV``,
the serial number becomes the sensor id) and the parameters (``PP``: AMIN, AMAX, AFRT, ARES,
DMIN, DMAX, SCAN), switches the laser on (``BM``) and starts an endless continuous scan
(``MD``, or ``ME`` with intensities); ``close`` sends ``QT``. Framing and value decoding are
:mod:`wristscan.drivers.scip` (vectorised, checksums verified).

Geometry (the same as the simulated sensor's): step ``i`` looks along
``theta_i = 2 pi (i - AFRT) / ARES`` from sensor +Z towards +Y, so a range ``r`` is the point
``(y, z) = (r sin theta, r cos theta)``; with clusters, the angle of a cluster's middle step.
Ranges below ``max(20 mm, DMIN)`` (URG error codes) or above DMAX are invalid (NaN).

Time and counters: SCIP has no frame counter. ``sensor_time_ns`` is the sensor's 24-bit
millisecond counter times 10^6, *not* unwrapped: it wraps every 4.66 h and the daemon unwraps it
(the SCIP sensor configuration has ``clock_bits = 24``, ``clock_tick_s = 1e-3``, which the
pairer's ``CounterUnwrapper`` uses). ``frame_counter`` is synthesised from that clock: it
advances by ``round(dt / scan period)`` between scans (period from PP's SCAN rpm), so lost scans
show as gaps and repeated scans as duplicates. After a reconnection, a clock that went back or
jumped further than the time spent away means the sensor restarted (no loss counted).
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import deque
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers import scip
from wristscan.drivers._stream import Chunk, LinkDown, StreamProfileSensor, Transport, open_url
from wristscan.drivers.base import DriverInitError
from wristscan.drivers.records import Profile

__all__ = ["ScipSensor"]

log = logging.getLogger(__name__)

_MOD = scip.TIMESTAMP_MODULO_MS
ERROR_CODE_LIMIT_MM = 20
"""Range values below this are error codes, not distances."""


class ScipSensor(StreamProfileSensor):
    """A Hokuyo scanning range finder as a profile sensor.

    ``url``: ``socket://host:port`` (Ethernet models, port 10940) or a serial device path.
    ``start_step``/``end_step`` default to the sensor's AMIN/AMAX; ``cluster`` groups that many
    steps into one value; ``intensity`` requests ME scans (intensity / ``intensity_scale``,
    clipped to 0..255, in ``Profile.intensity``).
    """

    kind: ClassVar[str] = "scip"
    silence_timeout_s = 1.0
    """No scan for max(this, 10 scan periods) drops the link and redoes the handshake."""
    reply_timeout_s = 1.0
    """Wait for each handshake reply."""
    intensity_scale = 40
    """Raw SCIP intensity units per step of the 8-bit ``Profile.intensity``."""

    def __init__(
        self,
        url: str,
        sensor_id: int | None = None,
        baudrate: int = 115200,
        intensity: bool = False,
        start_step: int | None = None,
        end_step: int | None = None,
        cluster: int = 1,
    ) -> None:
        if not url:
            raise DriverInitError("scip: url is empty")
        if baudrate <= 0:
            raise DriverInitError("scip: baudrate must be positive")
        if not 1 <= cluster <= 99:
            raise DriverInitError(f"scip: cluster {cluster} outside 1..99")
        for name, v in (("start_step", start_step), ("end_step", end_step)):
            if v is not None and not 0 <= v <= 9999:
                raise DriverInitError(f"scip: {name} {v} outside 0..9999")
        if start_step is not None and end_step is not None and end_step < start_step:
            raise DriverInitError("scip: end_step must be >= start_step")
        super().__init__(sensor_id)
        self.url, self.baudrate = url, int(baudrate)
        self.intensity = bool(intensity)
        self.start_step, self.end_step, self.cluster = start_step, end_step, int(cluster)
        self.version: dict[str, str] = {}
        """The sensor's VV reply (VEND, PROD, FIRM, PROT, SERI)."""
        self.parameters: dict[str, str] = {}
        """The sensor's PP reply (MODL, DMIN, DMAX, ARES, AMIN, AMAX, AFRT, SCAN)."""
        self.angles_rad: NDArray[np.float64] = np.empty(0)
        """Angle of each value of a scan (rad, from +Z towards +Y)."""
        self._cmd = b""
        self._sin: NDArray[np.float64] = np.empty(0)
        self._cos: NDArray[np.float64] = np.empty(0)
        self._rmin_mm = ERROR_CODE_LIMIT_MM
        self._rmax_mm = 1 << 18
        self._period_ms = 25.0
        self._device_id = 0
        self._decoder = scip.ReplyDecoder()
        self._replies: deque[tuple[scip.Reply, int]] = deque()
        self._handshaking = False
        self._new_link = True
        self._scan_ref: tuple[int, int, int] | None = None
        """(timestamp_ms, frame_counter, host_time_ns) of the last delivered scan."""

    # --- link -------------------------------------------------------------------------------
    def _connect(self) -> Transport:
        return open_url(self.url, self.baudrate)

    def _reset_decoder(self) -> None:
        self._decoder = scip.ReplyDecoder()
        self._replies.clear()
        self._new_link = True

    def _silence_limit_s(self) -> float:
        return max(self.silence_timeout_s, 10e-3 * self._period_ms)

    def _feed(self, data: Chunk, host_time_ns: int) -> None:
        dec = self._decoder
        bad0 = dec.bad_replies
        for reply in dec.feed(data):
            self._replies.append((reply, host_time_ns))
        for _ in range(dec.bad_replies - bad0):
            if self._handshaking:  # joined a stream mid-reply: not the sensor's fault
                self.stats["startup_discarded"] += 1
            else:
                self._reject("malformed SCIP reply block")

    def _command(self, transport: Transport, line: bytes) -> scip.Reply:
        """Send a command; its reply (other replies on the way are skipped and counted)."""
        transport.write(line + b"\n")
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            while self._replies:
                reply, _ = self._replies.popleft()
                if reply.echo == line:
                    return reply
                self.stats["stray_replies"] += 1
            left = deadline - time.monotonic()
            if left <= 0:
                raise LinkDown(f"{transport.description}: no reply to {line.decode()}")
            data = transport.read(min(left, 0.1))
            if data:
                self.counters.bytes += len(data)
                self._feed(data, time.monotonic_ns())

    def _start(self, transport: Transport) -> None:
        self._handshaking = True
        try:
            self._command(transport, b"QT")
            self.version = scip.decode_info(self._command(transport, b"VV"))
            self.parameters = scip.decode_info(self._command(transport, b"PP"))
            self._configure()
            bm = self._command(transport, b"BM")
            if bm.status not in (b"00", b"02"):
                raise DriverInitError(f"scip: BM (laser on) refused with status {bm.status!r}")
            ack = self._command(transport, self._cmd)
            if ack.status != b"00":
                raise DriverInitError(
                    f"scip: {self._cmd.decode()} refused with status {ack.status!r}"
                )
        except scip.FrameError as exc:
            raise LinkDown(f"{transport.description}: bad handshake reply: {exc}") from exc
        finally:
            self._handshaking = False
        self._valid()
        self._drain()  # scans that arrived together with the acknowledgement

    def _stop(self, transport: Transport) -> None:
        transport.write(b"QT\n")

    def _configure(self) -> None:
        pp = self.parameters
        try:
            amin, amax, afrt, ares = (int(pp[k]) for k in ("AMIN", "AMAX", "AFRT", "ARES"))
            dmin, dmax, rpm = (int(pp[k]) for k in ("DMIN", "DMAX", "SCAN"))
        except (KeyError, ValueError) as exc:
            raise DriverInitError(f"scip: PP reply lacks a usable {exc}") from exc
        if ares <= 0 or rpm <= 0:
            raise DriverInitError(f"scip: PP reports ARES {ares}, SCAN {rpm}")
        start = amin if self.start_step is None else self.start_step
        end = amax if self.end_step is None else self.end_step
        if not amin <= start <= end <= amax:
            raise DriverInitError(f"scip: steps {start}..{end} outside the sensor's {amin}..{amax}")
        c = self.cluster
        n = -(-(end - start + 1) // c)
        lo = start + np.arange(n) * c
        hi = np.minimum(lo + c - 1, end)
        self.angles_rad = 2.0 * np.pi * ((lo + hi) / 2.0 - afrt) / ares
        self._sin, self._cos = np.sin(self.angles_rad), np.cos(self.angles_rad)
        self._rmin_mm = max(ERROR_CODE_LIMIT_MM, dmin)
        self._rmax_mm = dmax
        self._period_ms = 60_000.0 / rpm
        code = "ME" if self.intensity else "MD"
        self._cmd = f"{code}{start:04d}{end:04d}{c:02d}000".encode()
        digits = re.sub(r"\D", "", self.version.get("SERI", ""))
        self._device_id = int(digits[-9:]) if digits else 0

    # --- scans ------------------------------------------------------------------------------
    def _consume(self, data: Chunk, host_time_ns: int) -> None:
        self._feed(data, host_time_ns)
        self._drain()

    def _drain(self) -> None:
        head = self._cmd[:13]
        while self._replies:
            reply, host_ns = self._replies.popleft()
            if reply.status == b"99" and len(reply.echo) == 15 and reply.echo[:13] == head:
                self._on_scan(reply, host_ns)
            elif reply.echo == self._cmd:
                self.stats["acks"] += 1
            else:
                # Nothing else is asked while streaming: a damaged echo or a foreign reply.
                self._reject(f"unexpected SCIP reply {reply.echo[:20]!r} {reply.status!r}")

    def _on_scan(self, reply: scip.Reply, host_time_ns: int) -> None:
        try:
            scan = scip.decode_scan(reply, 3, self.intensity)
        except scip.FrameError as exc:
            self._reject(str(exc))
            return
        r_mm = scan.ranges_mm
        if r_mm.size != self._sin.size:
            self._reject(f"SCIP scan of {r_mm.size} values, {self._sin.size} expected")
            return
        self._valid()
        valid = (r_mm >= self._rmin_mm) & (r_mm <= self._rmax_mm)
        r_m = r_mm.astype(np.float64) * 1e-3
        r_m[~valid] = np.nan
        intensity = None
        if scan.intensity is not None:
            intensity = np.minimum(scan.intensity // self.intensity_scale, 255).astype(np.uint8)
        ts = scan.timestamp_ms
        counter = self._counter(ts, host_time_ns)
        profile = Profile(
            sensor_id=self._device_id,
            frame_counter=counter,
            sensor_time_ns=ts * 1_000_000,
            host_time_ns=host_time_ns,
            y=r_m * self._sin,
            z=r_m * self._cos,
            valid=valid,
            intensity=intensity,
            encoder=None,
        )
        if self._deliver(profile):
            self._scan_ref = (ts, counter, host_time_ns)

    def _counter(self, ts_ms: int, host_time_ns: int) -> int:
        """Frame counter from the device clock (see the module docstring)."""
        ref = self._scan_ref
        new_link, self._new_link = self._new_link, False
        if ref is None:
            return 0
        d = (ts_ms - ref[0]) % _MOD
        if d >= _MOD // 2:
            d -= _MOD
        if new_link:
            away_ms = (host_time_ns - ref[2]) * 1e-6
            if d < 0 or d > away_ms + 1000.0:
                self._restart(f"the sensor clock went from {ref[0]} to {ts_ms} ms")
                return ref[1] + 1
        return ref[1] + math.floor(d / self._period_ms + 0.5)

    def _health_detail(self) -> dict[str, Any]:
        return {
            **super()._health_detail(),
            "model": self.parameters.get("MODL"),
            "serial": self.version.get("SERI"),
            "scan_period_s": self._period_ms * 1e-3,
            "command": self._cmd.decode(),
        }
