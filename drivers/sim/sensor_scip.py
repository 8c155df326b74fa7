"""The SCIP 2.0 side of a simulated Hokuyo-style range finder (TCP or a pty).

SCIP mapping
------------
The SCIP sensor is a scanning range finder whose scan plane is the laser plane: step ``i``
(``0 .. n_points-1``) looks along ``theta_i = 2 pi (i - AFRT) / ARES`` from sensor +Z towards
+Y (``AFRT = (n_points - 1) // 2``, the front step), so the point is
``(0, r sin theta, r cos theta)``. Ranges are millimetres; a step without a return in
``[scip_range_min_m, scip_range_max_m]`` reports 1 (an error code below DMIN, as URG sensors do).
A cluster reports the smallest valid range of its steps. The whole scan is taken at one instant.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers import scip
from wristscan.drivers.sim.clock import DeviceClock
from wristscan.drivers.sim.sensor_config import SensorSimConfig
from wristscan.drivers.sim.sensor_links import Link, StreamLink
from wristscan.drivers.sim.sensor_protocols import Batch, SensorProtocol

__all__ = ["ScipProtocol"]


class ScipProtocol(SensorProtocol):
    """The sensor side of SCIP 2.0: a small state machine plus the scan encoder."""

    def __init__(self, cfg: SensorSimConfig, link: Link, clock: DeviceClock) -> None:
        super().__init__(cfg, link, clock)
        assert isinstance(link, StreamLink)
        self.stream_link = link
        link.on_data = self.on_data
        link.on_connect = self.on_connect
        self.inbuf = bytearray()
        self.laser_on = False
        self.time_adjust = False
        self.stream: scip.Command | None = None
        self.stream_left = 0  # scans still to send; -1: endless
        self.stream_skip = 0
        self.singles: deque[scip.Command] = deque()
        self.amax = cfg.n_points - 1
        self.afrt = (cfg.n_points - 1) // 2

    def on_connect(self) -> None:
        self.inbuf.clear()
        self.stream = None
        self.singles.clear()

    def wants_exposures(self) -> bool:
        return self.link.connected and (self.stream is not None or bool(self.singles))

    def on_data(self, data: bytes) -> None:
        self.inbuf += data
        while True:
            i = self.inbuf.find(b"\n")
            if i < 0:
                if len(self.inbuf) > 4096:
                    self.inbuf.clear()
                return
            line = bytes(self.inbuf[:i]).rstrip(b"\r")
            del self.inbuf[: i + 1]
            if line:
                self.handle(line)

    def _reply(self, echo: bytes, status: bytes, lines: tuple[bytes, ...] = ()) -> None:
        self.stream_link.send_now(scip.make_reply(echo, status, lines))

    def _ms(self, device_ns: int) -> int:
        return (device_ns // 1_000_000) % scip.TIMESTAMP_MODULO_MS

    def handle(self, line: bytes) -> None:
        try:
            cmd = scip.parse_command(line)
        except scip.FrameError:
            self._reply(line, b"0E")
            return
        code = cmd.code
        cfg = self.cfg
        if code == "VV":
            self._reply(line, b"00", (
                scip.info_line("VEND", "wristscan simulator"),
                scip.info_line("PROD", cfg.scip_model),
                scip.info_line("FIRM", "1.0.0"),
                scip.info_line("PROT", "SCIP 2.0"),
                scip.info_line("SERI", f"H{cfg.sensor_id:07d}"),
            ))  # fmt: skip
        elif code == "PP":
            self._reply(line, b"00", (
                scip.info_line("MODL", cfg.scip_model),
                scip.info_line("DMIN", round(cfg.scip_range_min_m * 1000)),
                scip.info_line("DMAX", round(cfg.scip_range_max_m * 1000)),
                scip.info_line("ARES", cfg.scip_ares),
                scip.info_line("AMIN", 0),
                scip.info_line("AMAX", self.amax),
                scip.info_line("AFRT", self.afrt),
                scip.info_line("SCAN", round(cfg.rate_hz * 60)),
            ))  # fmt: skip
        elif code == "II":
            self._reply(line, b"00", (
                scip.info_line("MODL", cfg.scip_model),
                scip.info_line("LASR", "ON" if self.laser_on else "OFF"),
                scip.info_line("SCSP", f"{round(cfg.rate_hz * 60)}[rpm]"),
                scip.info_line("MESM", "Measuring by Normal Mode"),
                scip.info_line("SBPS", "Ethernet 100 [Mbps]" if cfg.transport == "tcp" else "USB"),
                scip.info_line("TIME", f"{self._ms(self.clock.now_ns()):06X}"),
                scip.info_line("STAT", "Stable 000 no error."),
            ))  # fmt: skip
        elif code == "%ST":
            state = "004" if self.stream else "002" if self.time_adjust else (
                "003" if self.laser_on else "000")  # fmt: skip
            self._reply(line, b"00", (scip.with_checksum(state.encode()),))
        elif code == "BM":
            status = b"02" if self.laser_on else b"00"
            self.laser_on = True
            self._reply(line, status)
        elif code == "QT":
            self.stream = None
            self.singles.clear()
            self.laser_on = False
            self._reply(line, b"00")
        elif code in ("RS", "RT"):
            self.stream = None
            self.singles.clear()
            self.laser_on = False
            self.time_adjust = False
            self.clock.reset(offset_ns=0)
            self._reply(line, b"00")
        elif code == "TM":
            self._time_adjust(cmd, line)
        elif code in scip.SCAN_COMMANDS:
            self._scan_command(cmd, line)
        else:
            self._reply(line, b"0E")

    def _time_adjust(self, cmd: scip.Command, line: bytes) -> None:
        if cmd.params == "0":
            status = b"02" if self.time_adjust else b"00"
            self.time_adjust = True
            self.stream = None
            self._reply(line, status)
        elif cmd.params == "1":
            if not self.time_adjust:
                self._reply(line, b"04")
                return
            ts = scip.encode_values([self._ms(self.clock.now_ns())], 4)
            self._reply(line, b"00", (scip.with_checksum(ts),))
        elif cmd.params == "2":
            status = b"00" if self.time_adjust else b"03"
            self.time_adjust = False
            self._reply(line, status)
        else:
            self._reply(line, b"01")

    def _scan_command(self, cmd: scip.Command, line: bytes) -> None:
        try:
            start, end, _, _, scans = cmd.scan_params()
        except scip.FrameError:
            self._reply(line, b"01")
            return
        if end > self.amax or start > self.amax:
            self._reply(line, b"04")
            return
        if end < start:
            self._reply(line, b"05")
            return
        if self.time_adjust:
            self._reply(line, b"0L")
            return
        if cmd.code.startswith("G"):
            if not self.laser_on:
                self._reply(line, b"10")
                return
            self.singles.append(cmd)
            return
        self.laser_on = True
        self.stream = cmd
        self.stream_left = scans if scans > 0 else -1
        self.stream_skip = 0
        self._reply(line, b"00")

    def _ranges(self, t_m: NDArray[np.float64], valid: NDArray[np.bool_], cmd: scip.Command,
                n_chars: int) -> NDArray[np.int64]:  # fmt: skip
        start, end, cluster, _, _ = cmd.scan_params()
        mm = np.where(valid, np.rint(t_m * 1000.0), np.inf)[start : end + 1]
        cluster = max(1, cluster)
        pad = (-mm.size) % cluster
        if pad:
            mm = np.concatenate([mm, np.full(pad, np.inf)])
        grouped = mm.reshape(-1, cluster).min(axis=1)
        limit = (1 << (6 * n_chars)) - 1
        return np.where(np.isfinite(grouped) & (grouped <= limit), grouped, 1).astype(np.int64)

    def _intensity(self, inten: NDArray[np.uint8] | None, cmd: scip.Command) -> NDArray[Any]:
        start, end, cluster, _, _ = cmd.scan_params()
        cluster = max(1, cluster)
        n = -(-(end + 1 - start) // cluster)
        if inten is None:
            return np.full(n, 1000, dtype=np.int64)
        sel = inten[start : end + 1].astype(np.int64) * 40  # u8 to a URG-like scale
        sel = np.concatenate([sel, np.zeros((-sel.size) % cluster, dtype=np.int64)])
        return np.asarray(sel.reshape(n, cluster).max(axis=1))

    def _block(self, cmd: scip.Command, echo: bytes, status: bytes, batch: Batch,
               p: int) -> bytes:  # fmt: skip
        _, n_chars, with_int = scip.SCAN_COMMANDS[cmd.code]
        ranges = self._ranges(batch.meas.t[p], batch.meas.valid[p], cmd, n_chars)
        inten = None
        if with_int:
            inten = self._intensity(None if batch.intensity is None else batch.intensity[p], cmd)
        ts = self._ms(int(batch.stamps_ns[p]))
        return scip.scan_reply(echo, status, ts, ranges, inten, n_chars)

    def encode(self, batch: Batch) -> list[list[bytes]]:
        out: list[list[bytes]] = []
        for p in range(batch.counters.size):
            units: list[bytes] = []
            if self.singles:
                cmd = self.singles.popleft()
                units.append(self._block(cmd, cmd.raw, b"00", batch, p))
            if self.stream is not None:
                cmd = self.stream
                interval = int(cmd.params[10:11])
                if self.stream_skip > 0:
                    self.stream_skip -= 1
                else:
                    self.stream_skip = interval
                    if self.stream_left > 0:
                        self.stream_left -= 1
                    remaining = max(self.stream_left, 0)
                    head = cmd.code.encode() + cmd.params[:11].encode() + b"%02d" % remaining
                    echo = head + (b";" + cmd.string.encode() if cmd.string else b"")
                    units.append(self._block(cmd, echo, b"99", batch, p))
                    if self.stream_left == 0:
                        self.stream = None
            out.append(units)
        return out

    def on_reboot(self) -> None:
        self.stream = None
        self.singles.clear()
        self.laser_on = False
        self.time_adjust = False
