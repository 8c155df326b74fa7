"""The one-way wire formats of the simulated sensors: LPF1 and RF627 profile senders.

A protocol turns a batch of exposures into wire units (what faults apply to, one by one) and
may talk on its own (LPF1's HELLO and heartbeats). The SCIP conversation is in
:mod:`.sensor_scip`; the sensor loop that drives them in :mod:`.sensors`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.drivers import lpf1, rf627
from wristscan.drivers.sim.clock import DeviceClock
from wristscan.drivers.sim.laser import Measurement
from wristscan.drivers.sim.sensor_config import SensorSimConfig
from wristscan.drivers.sim.sensor_links import Link, StreamLink

__all__ = ["Batch", "Lpf1Protocol", "Rf627Protocol", "SensorProtocol"]


@dataclass
class Batch:
    """Exposures computed together."""

    counters: NDArray[np.int64]
    t_exp_ns: NDArray[np.int64]
    stamps_ns: NDArray[np.int64]
    meas: Measurement
    encoder: NDArray[np.int64] | None
    intensity: NDArray[np.uint8] | None


class SensorProtocol:
    def __init__(self, cfg: SensorSimConfig, link: Link, clock: DeviceClock) -> None:
        self.cfg = cfg
        self.link = link
        self.clock = clock

    def wants_exposures(self) -> bool:
        return self.link.connected

    def encode(self, batch: Batch) -> list[list[bytes]]:
        """Wire units per profile (faults are applied to each unit)."""
        raise NotImplementedError

    def periodic(self, now_ns: int, counter: int) -> None:
        pass

    def on_reboot(self) -> None:
        pass


class Lpf1Protocol(SensorProtocol):
    def __init__(self, cfg: SensorSimConfig, link: Link, clock: DeviceClock) -> None:
        super().__init__(cfg, link, clock)
        fmt = {
            "i16": lpf1.PointFormat.I16,
            "i32": lpf1.PointFormat.I32,
            "f32": lpf1.PointFormat.F32,
        }
        step = 2 * cfg.half_width_m / max(1, cfg.n_points - 1)
        self.encoder = lpf1.ProfileEncoder(
            cfg.sensor_id,
            fmt[cfg.lpf1_point_format],
            z_scale_nm=cfg.lpf1_z_scale_nm,
            z_offset_um=cfg.lpf1_z_offset_um,
            x_uniform=(-cfg.half_width_m, step),
            intensity=cfg.intensity,
            max_message_bytes=cfg.max_datagram if cfg.transport == "udp" else None,
        )
        self.serial = cfg.transport == "serial"
        self.last_counter = 0
        self.next_heartbeat_ns = 0
        if isinstance(link, StreamLink):
            link.on_connect = self.hello

    def _frame(self, msg: bytes) -> bytes:
        return lpf1.cobs_frame(msg) if self.serial else msg

    def hello(self) -> None:
        info = {
            "model": "wristscan-sim",
            "kind": self.cfg.kind,
            "n_points": self.cfg.n_points,
            "rate_hz": self.cfg.rate_hz,
            "z_range_m": [self.cfg.z_min_m, self.cfg.z_max_m],
        }
        msg = lpf1.encode_control(
            lpf1.MsgType.HELLO, self.cfg.sensor_id, self.last_counter, self.clock.now_ns(), info
        )
        self.link.send(self._frame(msg))

    def encode(self, batch: Batch) -> list[list[bytes]]:
        msgs = self.encoder.encode(
            batch.counters,
            batch.stamps_ns,
            batch.meas.z,
            batch.meas.valid,
            intensity=batch.intensity,
            encoder=batch.encoder,
        )
        self.last_counter = int(batch.counters[-1])
        if self.serial:
            return [[lpf1.cobs_frame(m) for m in frags] for frags in msgs]
        return msgs

    def periodic(self, now_ns: int, counter: int) -> None:
        if self.cfg.heartbeat_s <= 0 or now_ns < self.next_heartbeat_ns:
            return
        self.next_heartbeat_ns = now_ns + int(self.cfg.heartbeat_s * 1e9)
        if self.link.connected:
            msg = lpf1.encode_control(
                lpf1.MsgType.HEARTBEAT, self.cfg.sensor_id, self.last_counter, self.clock.now_ns()
            )
            self.link.send(self._frame(msg))

    def on_reboot(self) -> None:
        self.last_counter = 0
        if self.cfg.transport != "tcp":
            self.hello()


class Rf627Protocol(SensorProtocol):
    def __init__(self, cfg: SensorSimConfig, link: Link, clock: DeviceClock) -> None:
        super().__init__(cfg, link, clock)
        self.encoder = rf627.RF627Encoder(cfg.sensor_id, intensity=cfg.intensity)

    def encode(self, batch: Batch) -> list[list[bytes]]:
        grams = self.encoder.encode(
            batch.counters,
            batch.stamps_ns,
            batch.meas.y,
            batch.meas.z,
            batch.meas.valid,
            intensity=batch.intensity,
            step_count=batch.encoder,
        )
        return [[g] for g in grams]

    def on_reboot(self) -> None:
        self.encoder.packet_count = 0
