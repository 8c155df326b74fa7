"""``wristscan run``: the service that the cell PC runs under systemd.

Life cycle: validate the configuration and the calibration, open the devices, start the
pipeline, then tell systemd ``READY=1``; ping the watchdog while the pipeline makes progress;
``SIGHUP`` reloads configuration and calibration atomically (or keeps the old ones and logs why);
``SIGTERM``/``SIGINT`` drain the pipeline and exit 0. Signals only set flags: all the work happens
in the main thread.
"""

from __future__ import annotations

import gc
import logging
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session
from wristscan.daemon.config import Config, ConfigError, load_config
from wristscan.daemon.devices import Devices, make_devices, pairer_config, robot_model
from wristscan.daemon.io.calibfile import (
    Calibration,
    CalibrationFileError,
    RobotIdentity,
    SensorIdentity,
    identities,
    read_calibration,
)
from wristscan.daemon.service.notify import Notifier, Watchdog
from wristscan.daemon.service.pipeline import AlignmentSetup, Pipeline, PipelineSettings
from wristscan.daemon.sync.pairing import Pairer
from wristscan.drivers.base import DriverError

__all__ = ["Service", "StartupError", "load_setup", "run_service"]

log = logging.getLogger(__name__)


class StartupError(RuntimeError):
    """The service cannot start with this configuration (message says why)."""


def _identities(cfg: Config) -> tuple[RobotIdentity | None, SensorIdentity | None]:
    """The identities a calibration file must match, or (None, None) when the configuration
    does not check them."""
    return identities(cfg) if cfg.calibration.check_identity else (None, None)


def load_setup(cfg: Config, uncalibrated: bool = False) -> AlignmentSetup:
    """The alignment the configuration asks for; raises ``CalibrationFileError`` or
    ``StartupError`` with a message for the operator."""
    robot_id, sensor_id = _identities(cfg)
    c = cfg.calibration
    frame = cfg.pipeline.frame
    if c.file is None:
        if not uncalibrated:
            raise StartupError(
                "no calibration in force: set [calibration] file (wristscan calibrate sensor "
                "writes one), or start with --uncalibrated to publish with the sensor at the flange"
            )
        sensor2flange = np.eye(4)
        desc: dict[str, Any] = {"kind": "sensor2flange", "uncalibrated": True}
    else:
        calib = read_calibration(c.file, robot_id, sensor_id, kind="sensor2flange")
        sensor2flange = np.asarray(calib.transform, dtype=np.float64)
        desc = calib.to_dict()
    base2table = None
    offset = 0.0
    if frame != "base":
        if c.table_file is None:
            raise StartupError(f'pipeline.frame = "{frame}" needs [calibration] table_file')
        tcal: Calibration = read_calibration(c.table_file, robot_id, None, kind="table")
        base2table = np.asarray(tcal.transform, dtype=np.float64)
        offset = float(tcal.parameters.get("encoder_offset_rad", 0.0))
        desc = {"sensor2flange": desc, "table": tcal.to_dict()}
    return AlignmentSetup(
        sensor2flange=sensor2flange,
        frame=frame,
        base2table=base2table,
        encoder_offset_rad=offset,
        calibrated=c.file is not None,
        description=desc,
    )


def _ros2_class(cfg: Config) -> Any:
    """The ``[ros2]`` publisher class when enabled, else None; checked before anything opens."""
    if not cfg.ros2.enabled:
        return None
    try:
        from wristscan.daemon.cloud.ros2pub import Ros2Publisher
    except ImportError as exc:
        raise StartupError(
            f"[ros2] enabled needs the extra: pip install 'wristscan[ros2]' ({exc})"
        ) from exc
    return Ros2Publisher


class Service:
    """One running daemon: devices, pipeline, zenoh face; reloadable."""

    def __init__(self, config_path: Path, notifier: Notifier, uncalibrated: bool = False):
        self.config_path = config_path
        self.notifier = notifier
        self.uncalibrated = uncalibrated
        self.cfg: Config | None = None
        self.devices: Devices | None = None
        self.pipeline: Pipeline | None = None
        self.zenoh: DaemonZenoh | None = None
        self._session: Any = None
        self.ros2: Any = None
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._signal = threading.Event()
        self.reloads = 0
        self.reload_failures = 0

    # --- building blocks ----------------------------------------------------------------------
    def _start(self, cfg: Config, setup: AlignmentSetup) -> None:
        ros2_class = _ros2_class(cfg)
        devices = make_devices(cfg)
        devices.open()
        try:
            z = cfg.zenoh
            session = open_session(z.mode, z.connect, z.listen, z.multicast_scouting)
        except Exception:
            devices.close()
            raise
        face = DaemonZenoh(
            session,
            z.prefix,
            congestion=z.congestion_control,
            calibration=lambda: (
                dict(self.pipeline.setup.description or {}) if self.pipeline else {}
            ),
            stats=lambda: self.pipeline.stats() if self.pipeline else {},
        )
        if ros2_class is not None:
            self.ros2 = ros2_class(session, cfg.ros2, cfg.cell.name)
            self.ros2.publish_tf_static(setup.sensor2flange)
        pl = cfg.pipeline
        pcfg = pairer_config(cfg, robot_model(cfg, devices))
        pipeline = Pipeline(
            devices.sensor,
            devices.robot,
            Pairer(pcfg),
            setup,
            face.publish_cloud if self.ros2 is None else self.ros2.tee(face.publish_cloud),
            table=devices.table if pcfg.use_table else None,
            settings=PipelineSettings(
                batch_s=pl.batch_s,
                profile_queue=pl.profile_queue,
                status_period_s=z.status_period_s,
                publish_intensity=pl.publish_intensity,
                publish_profile_index=pl.publish_profile_index,
            ),
            publish_status=face.publish_status,
            publish_pose=face.publish_pose,
        )
        # What start-up built (modules, devices, sessions) lives as long as the service: out of
        # the collector's way, a full collection scans only what the pipeline makes.
        gc.freeze()
        pipeline.start()
        self.cfg, self.devices, self.pipeline = cfg, devices, pipeline
        self.zenoh, self._session = face, session

    def _calibration_json(self) -> dict[str, Any]:
        return dict(self.pipeline.setup.description or {}) if self.pipeline else {}

    def _shutdown(self, drain: bool = True) -> None:
        if self.pipeline is not None:
            self.pipeline.stop(drain=drain)
        if self.ros2 is not None:
            self.ros2.close()
            self.ros2 = None
        if self.zenoh is not None:
            self.zenoh.close()
        if self._session is not None:
            self._session.close()
        if self.devices is not None:
            self.devices.close()
        self.pipeline = self.zenoh = self.devices = self._session = None

    # --- signals --------------------------------------------------------------------------------
    def _on_signal(self, signum: int, _frame: Any) -> None:
        if signum == signal.SIGHUP:
            self._reload.set()
        else:
            self._stop.set()
        self._signal.set()

    def request_stop(self) -> None:
        self._stop.set()
        self._signal.set()

    # --- reload ---------------------------------------------------------------------------------
    def reload(self) -> bool:
        """Re-read configuration and calibration; True when the new ones are in force."""
        self.notifier.reloading("reloading configuration and calibration")
        try:
            new_cfg = load_config(self.config_path)
            new_setup = load_setup(new_cfg, self.uncalibrated)
        except (ConfigError, CalibrationFileError, StartupError) as exc:
            self.reload_failures += 1
            log.error("reload refused, keeping the configuration in force: %s", exc)
            self.notifier.ready(f"reload refused: {str(exc).splitlines()[0]}")
            return False
        old_cfg = self.cfg
        assert old_cfg is not None and self.pipeline is not None
        same_devices = all(
            getattr(old_cfg, k) == getattr(new_cfg, k)
            for k in ("robot", "sensor", "table", "sync", "pipeline", "zenoh", "ros2")
        )
        if same_devices:
            self.pipeline.set_setup(new_setup)  # one reference swap: atomic for the worker
            self.cfg = new_cfg
            if self.ros2 is not None:
                self.ros2.publish_tf_static(new_setup.sensor2flange)
        else:
            old_setup = self.pipeline.setup
            self._shutdown(drain=True)
            try:
                self._start(new_cfg, new_setup)
            except (DriverError, OSError, RuntimeError) as exc:
                log.error("new configuration failed to start (%s); restoring the old one", exc)
                self.reload_failures += 1
                self._start(old_cfg, old_setup)
                self.notifier.ready(f"reload failed: {exc}")
                return False
        self.reloads += 1
        log.info("configuration and calibration reloaded")
        self.notifier.ready("running (reloaded)")
        return True

    # --- main -----------------------------------------------------------------------------------
    def run(self) -> int:
        try:
            cfg = load_config(self.config_path)
            setup = load_setup(cfg, self.uncalibrated)
        except (ConfigError, CalibrationFileError, StartupError) as exc:
            log.error("%s", exc)
            return 2
        handlers = {
            s: signal.signal(s, self._on_signal)
            for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
        }
        try:
            self.notifier.status("opening devices")
            try:
                self._start(cfg, setup)
            except (DriverError, OSError, RuntimeError) as exc:
                log.error("cannot start: %s", exc)
                return 1
            assert self.pipeline is not None
            self.notifier.ready("running")
            log.info("wristscan running: publishing on %s/cloud", cfg.zenoh.prefix)
            with Watchdog(self.notifier, self._healthy):
                return self._loop()
        finally:
            self.notifier.stopping("stopping")
            self._shutdown(drain=True)
            for s, h in handlers.items():
                signal.signal(s, h)

    def _healthy(self) -> bool:
        return self.pipeline is not None and self.pipeline.healthy()

    def _loop(self) -> int:
        assert self.cfg is not None
        period = self.cfg.zenoh.status_period_s
        next_status = time.monotonic()
        while True:
            self._signal.wait(timeout=period)
            self._signal.clear()
            if self._stop.is_set():
                log.info("stop requested: draining")
                return 0
            if self._reload.is_set():
                self._reload.clear()
                self.reload()
            pl = self.pipeline
            if pl is None:
                return 1
            if pl.failure is not None:
                log.error("pipeline failed: %s", pl.failure)
                return 1
            if time.monotonic() >= next_status:
                next_status = time.monotonic() + period
                st = pl.stats()
                dropped = sum(st["dropped"].values())
                self.notifier.status(
                    f"running: {st['published']} profiles published, {dropped} dropped"
                )


def run_service(config_path: Path, uncalibrated: bool = False) -> int:
    """Run until SIGTERM/SIGINT; returns the process exit code."""
    with Notifier() as notifier:
        return Service(config_path, notifier, uncalibrated).run()
