"""Build the configured drivers and the pairer from a validated :class:`Config`."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from wristscan.calib import kinematics
from wristscan.daemon.config import Config, PluginSensorConfig
from wristscan.daemon.io.kinematics_file import read_kinematics
from wristscan.daemon.sync.clockconfig import ClockConfig
from wristscan.daemon.sync.pairing import PairerConfig
from wristscan.drivers import registry
from wristscan.drivers.base import (
    Backoff,
    Device,
    DriverError,
    DriverInitError,
    DriverNotAvailable,
    ProfileSensor,
    Robot,
    RotaryTable,
)

__all__ = [
    "Devices",
    "DevicesUnavailable",
    "WaitCallback",
    "make_devices",
    "pairer_config",
    "robot_model",
]

log = logging.getLogger(__name__)

T = TypeVar("T", bound=Device[Any])

WaitCallback = Callable[[str, float, str], None]
"""Called after each failed attempt while waiting: (device kind, seconds waited, error)."""


class DevicesUnavailable(DriverError):
    """A device could not be opened within the wait (the message names it and its last error)."""


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


@dataclass
class Devices:
    """The cell's devices, typed by the contracts the procedures and the pipeline rely on."""

    sensor: ProfileSensor
    robot: Robot
    table: RotaryTable | None

    def all(self) -> list[Device[Any]]:
        return [d for d in (self.sensor, self.robot, self.table) if d is not None]

    def open(self) -> None:
        """Open every device; on a failure close those already open and re-raise."""
        opened: list[Device[Any]] = []
        try:
            for d in self.all():
                d.open()
                opened.append(d)
        except BaseException:
            for d in reversed(opened):
                d.close()
            raise

    def open_waiting(
        self,
        wait_s: float,
        stop: threading.Event,
        *,
        retry_initial_s: float = 0.25,
        retry_max_s: float = 2.0,
        on_wait: WaitCallback | None = None,
    ) -> bool:
        """Open every device, retrying one that cannot be opened yet (refused, timed out, I/O
        error) with exponential backoff for at most ``wait_s`` seconds in all (0: one attempt).

        Devices already open stay open while a later one is waited for. Returns True when all
        are open, False when ``stop`` was set meanwhile (every device closed again). Raises
        :class:`DevicesUnavailable` naming the device and its last error when the wait is over,
        and re-raises at once what retrying cannot fix (a missing driver dependency, a bug)."""
        t0 = time.monotonic()
        deadline = t0 + wait_s
        try:
            for d in self.all():
                if not self._open_one(d, t0, deadline, stop, retry_initial_s, retry_max_s, on_wait):
                    self.close()
                    return False
        except BaseException:
            self.close()
            raise
        return True

    @staticmethod
    def _open_one(
        d: Device[Any],
        t0: float,
        deadline: float,
        stop: threading.Event,
        retry_initial_s: float,
        retry_max_s: float,
        on_wait: WaitCallback | None,
    ) -> bool:
        backoff = Backoff(retry_initial_s, retry_max_s)
        waited_from: float | None = None
        last = ""
        while not stop.is_set():
            try:
                d.open()
            except DriverNotAvailable:
                raise
            except DriverError as exc:
                error = _one_line(exc)
            else:
                if waited_from is not None:
                    log.info("%s open after waiting %.1f s", d.kind, time.monotonic() - waited_from)
                return True
            now = time.monotonic()
            if now >= deadline:
                waited = f" for {now - t0:.0f} s" if deadline > t0 else ""
                raise DevicesUnavailable(f"{d.kind} not available{waited}: {error}")
            if waited_from is None:
                waited_from = now
                log.warning(
                    "waiting for %s: %s (retrying for up to %.0f s more)",
                    d.kind,
                    error,
                    deadline - now,
                )
            elif error != last:
                log.info("still waiting for %s: %s", d.kind, error)
            last = error
            if on_wait is not None:
                on_wait(d.kind, now - waited_from, error)
            stop.wait(min(backoff.next_delay(), max(0.0, deadline - now)))
        return False

    def close(self) -> None:
        for d in reversed(self.all()):
            try:
                d.close()
            except DriverError as exc:  # closing must go on for the others
                log.warning("closing %s: %s", d.kind, exc)


def _driver_class(kind: registry.Kind, name: str, contract: type[T]) -> type[T]:
    """The driver class ``name`` of ``kind``, checked to implement ``contract`` (a plug-in that
    does not would fail later, in the middle of a procedure)."""
    cls = registry.load(kind, name)
    if not issubclass(cls, contract):
        raise DriverInitError(
            f"{kind[:-1]} driver {name!r} ({cls.__module__}.{cls.__qualname__}) is not a "
            f"{contract.__module__}.{contract.__qualname__}"
        )
    return cls


def _sensor_kwargs(cfg: Config) -> dict[str, Any]:
    s = cfg.sensor
    opts = s.options if isinstance(s, PluginSensorConfig) else s.options.model_dump()
    return {"sensor_id": s.sensor_id, **opts}


def make_devices(cfg: Config) -> Devices:
    """Instantiate (not open) the drivers named in ``cfg``."""
    # Constructors differ per driver; the config models name their keyword arguments.
    sensor_cls: Any = _driver_class("sensors", cfg.sensor.driver, ProfileSensor)
    sensor = sensor_cls(**_sensor_kwargs(cfg))
    r = cfg.robot
    robot_cls: Any = _driver_class("robots", r.driver, Robot)
    robot = robot_cls(
        host=r.host,
        frequency_hz=r.frequency_hz,
        motion_enabled=r.motion_enabled,
        max_speed_m_s=r.max_speed_m_s,
        max_accel_m_s2=r.max_accel_m_s2,
        max_joint_speed_rad_s=r.max_joint_speed_rad_s,
        max_joint_accel_rad_s2=r.max_joint_accel_rad_s2,
        workspace_min_m=r.workspace_min_m,
        workspace_max_m=r.workspace_max_m,
        model=r.model,
        read_kinematics=r.use_factory_kinematics,
        # Only the built-in UR driver has the choice; plug-ins get their own options.
        **({"receive_backend": r.receive_backend} if r.driver == "ur-rtde" else r.options),
    )
    table: RotaryTable | None = None
    t = cfg.table
    if t is not None and t.enabled:
        table_cls: Any = _driver_class("tables", t.driver, RotaryTable)
        if t.driver != "modbus":
            table = table_cls(**t.options)
        else:
            table = table_cls(
                transport=t.transport,
                host=t.host or "127.0.0.1",
                port=t.port,
                serial_port=t.serial_port or "",
                baudrate=t.baudrate,
                parity=t.parity,
                stopbits=t.stopbits,
                device_id=t.device_id,
                register_type=t.register_type,
                encoder_register=t.encoder_register,
                encoder_bits=t.encoder_bits,
                word_order=t.word_order,
                scale_rad_per_count=t.rad_per_count,
                offset_rad=t.offset_rad,
                status_register=t.status_register if t.status_register is not None else 2,
                target_register=t.target_register if t.target_register is not None else 10,
                command_register=t.command_register if t.command_register is not None else 12,
                speed_register=t.speed_register if t.speed_register is not None else 13,
                poll_hz=t.poll_hz,
                timeout_s=t.timeout_s,
            )
    return Devices(sensor=sensor, robot=robot, table=table)


def robot_model(cfg: Config, devices: Devices) -> str | kinematics.DHParams:
    """The kinematic model to pair with: the arm's kinematics identified with the probe when
    ``[robot] kinematics_file`` names them (a file that cannot be used raises
    :class:`~wristscan.daemon.io.kinematics_file.KinematicsFileError`, one line), else the
    robot's factory calibration when the configuration asks for it and the driver read it at
    ``open()``, else the nominal model."""
    if cfg.robot.kinematics_file is not None:
        return read_kinematics(cfg.robot.kinematics_file, cfg.robot.model).model
    if cfg.robot.use_factory_kinematics:
        model = devices.robot.kinematic_model()
        if model is not None:
            return model
    return cfg.robot.model


def pairer_config(cfg: Config, model: str | kinematics.DHParams | None = None) -> PairerConfig:
    """The synchroniser settings of ``cfg`` (``model``: calibrated kinematics when known)."""
    sy = cfg.sync
    window_ns = round(sy.clock_window_s * 1e9)
    clock = ClockConfig(window_ns=window_ns, max_uncertainty_ns=sy.clock_max_uncertainty_s * 1e9)
    return PairerConfig(
        mode=sy.pairing,
        robot_model=model or cfg.robot.model,
        interpolation=sy.interpolation,
        sensor_latency_ns=round(cfg.sensor.latency_s * 1e9),
        robot_latency_ns=round(sy.robot_latency_s * 1e9),
        table_latency_ns=round(sy.table_latency_s * 1e9),
        sensor_time_modulus_ns=cfg.sensor.time_modulus_ns,
        encoder_modulus=None if sy.encoder_bits is None else 1 << sy.encoder_bits,
        max_wait_ns=round(sy.max_wait_s * 1e9),
        robot_max_gap_ns=round(sy.max_gap_s * 1e9),
        use_table=cfg.table_enabled and cfg.pipeline.frame == "part",
        table_max_gap_ns=round(sy.table_max_gap_s * 1e9),
        sensor_clock=clock,
        robot_clock=clock,
        table_clock=clock,
    )
