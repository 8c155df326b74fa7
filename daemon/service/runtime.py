"""``wristscan run``: the service that the cell PC runs under systemd.

Life cycle: validate the configuration and the calibration, open the zenoh session (so that
``wristscan status`` sees the daemon from the start), open the devices, waiting for absent ones
with backoff (``[service] wait_for_devices_s``; STATUS says what it waits for, the watchdog is
pinged meanwhile), start the pipeline, then tell systemd ``READY=1``; ping the watchdog while the
pipeline makes progress; log device outages when they start and end; ``SIGHUP`` reloads
configuration and calibration (or keeps the old ones in force and logs why);
``SIGTERM``/``SIGINT`` drain the pipeline, log the final counters and exit 0. Signals only set
flags: all the work happens in the main thread.

A reload that changes devices or pipeline settings replaces the pipeline but keeps the zenoh
publisher (when ``[zenoh]`` does not change, the same session): the WSC1 sequence goes on without
a gap and the counters stay cumulative (``totals``). Every error at start-up or reload is one
line in the log, never a traceback.
"""

from __future__ import annotations

import gc
import logging
import signal
import threading
import time
from pathlib import Path
from typing import Any

from wristscan.daemon.cloud.scans import ScanServer
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh
from wristscan.daemon.config import Config, ConfigError, load_config
from wristscan.daemon.devices import Devices, make_devices, pairer_config, robot_model
from wristscan.daemon.io.archive import ScanArchive
from wristscan.daemon.io.calibfile import CalibrationFileError
from wristscan.daemon.service.changes import ALL_DEVICES, Changes, config_changes
from wristscan.daemon.service.heap import release_free_heap
from wristscan.daemon.service.notify import Notifier, Watchdog
from wristscan.daemon.service.outages import OutageMonitor
from wristscan.daemon.service.pipeline import AlignmentSetup, Pipeline, PipelineSettings
from wristscan.daemon.service.setup import (
    SETUP_ERRORS,
    StartupError,
    load_setup,
    one_line,
    open_daemon_session,
)
from wristscan.daemon.service.setup import ros2_class as _ros2_class
from wristscan.daemon.service.totals import CarriedCounters, counters_line
from wristscan.daemon.sync.pairing import Pairer

__all__ = ["Service", "StartupError", "load_setup", "one_line", "run_service"]

log = logging.getLogger(__name__)

_CHECK_S = 0.25
"""How often the main loop looks at the pipeline and the devices' outages."""
_TRIM_S = 5.0
"""The heap's free pages go back to the system this often."""
_LINGER_S = 0.2
"""Before a session that published is closed: zenoh's time to send what it has queued."""


class Service:
    """One running daemon: devices, pipeline, zenoh face; reloadable."""

    def __init__(self, config_path: Path, notifier: Notifier, uncalibrated: bool = False):
        self.config_path = config_path
        self.notifier = notifier
        self.uncalibrated = uncalibrated
        self.cfg: Config | None = None
        self.devices: Devices | None = None
        self.pipeline: Pipeline | None = None
        self.monitor: OutageMonitor | None = None
        self.zenoh: DaemonZenoh | None = None
        self._session: Any = None
        self.ros2: Any = None
        self.scans: ScanServer | None = None
        self.totals = CarriedCounters()
        self._outages: dict[str, dict[str, float]] = {}
        self._next_seq = 0
        self._phase = "starting"
        self._waiting: tuple[str, float, str] | None = None
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._signal = threading.Event()
        self._fatal: str | None = None
        self._declared: Config | None = None
        """The configuration the zenoh face was declared for."""
        self._ran = False
        self.reloads = 0
        self.reload_failures = 0

    # --- the zenoh side -------------------------------------------------------------------------
    def _declare(self, session: Any, cfg: Config, setup: AlignmentSetup) -> None:
        """The daemon's publishers and queryables (and ROS 2's) on ``session``; the WSC1
        sequence goes on from where the previous face left it."""
        z = cfg.zenoh
        ros2_class = _ros2_class(cfg)
        face = DaemonZenoh(
            session, z.prefix, congestion=z.congestion_control,
            calibration=self._calibration_json, stats=self.stats,
            shm_pool_bytes=z.shm_pool_mb * 2**20 if z.shared_memory else 0,
        )  # fmt: skip
        face.seq = face.published = self._next_seq
        try:
            ros2 = (
                None
                if ros2_class is None
                else ros2_class(session, cfg.ros2, cfg.cell.name, face.shm)
            )
        except BaseException:
            face.close()
            raise
        self._session, self.zenoh, self.ros2 = session, face, ros2
        self._declared = cfg
        self._serve_scans(cfg)
        if ros2 is not None:
            ros2.publish_tf_static(setup.sensor2flange)

    def _serve_scans(self, cfg: Config) -> None:
        """``<prefix>/scans``: the scan archive of ``[archive]`` (when enabled) on the network."""
        if self.scans is not None:
            self.scans.close()
            self.scans = None
        a = cfg.archive
        if a.enabled and self._session is not None:
            archive = ScanArchive(a.root, keep=a.keep, max_bytes=a.max_bytes)
            self.scans = ScanServer(self._session, cfg.zenoh.prefix, archive)

    def _undeclare(self, close_session: bool) -> None:
        if self.scans is not None:
            self.scans.close()
            self.scans = None
        if self.ros2 is not None:
            self.ros2.close()
            self.ros2 = None
        if self.zenoh is not None:
            self._next_seq = self.zenoh.seq
            self.zenoh.close()
            self.zenoh = None
        if close_session and self._session is not None:
            time.sleep(_LINGER_S)
            self._session.close()
            self._session = None

    # --- counters and status ------------------------------------------------------------------
    def _calibration_json(self) -> dict[str, Any]:
        return dict(self.pipeline.setup.description or {}) if self.pipeline else {}

    def _outage_summary(self) -> dict[str, dict[str, float]]:
        out = {k: dict(v) for k, v in self._outages.items()}
        if self.monitor is not None:
            for kind, s in self.monitor.summary().items():
                o = out.setdefault(kind, {"count": 0, "total_s": 0.0})
                o["count"] += s["count"]
                o["total_s"] = round(o["total_s"] + s["total_s"], 3)
        return out

    def stats(self) -> dict[str, Any]:
        """Counters since the service started (cumulative over reloads), JSON-friendly."""
        pl = self.pipeline
        st = self.totals.merge(pl.stats()) if pl is not None else self.totals.snapshot()
        st.update(
            state=self._state(), reloads=self.reloads, reload_failures=self.reload_failures,
            outages=self._outage_summary(),
        )  # fmt: skip
        shm = None if self.zenoh is None else self.zenoh.shm
        if shm is not None:
            st["shared_memory"] = shm.counters()
        return st

    def _state(self) -> str:
        if self._phase != "running":
            return self._phase
        return "degraded" if self.monitor is not None and self.monitor.degraded else "running"

    def _degraded(self) -> list[str]:
        if self._waiting is not None:
            kind, since, error = self._waiting
            return [f"waiting for {kind} for {time.monotonic() - since:.0f} s ({error})"]
        return list(self.monitor.degraded) if self.monitor is not None else []

    def _status_json(self, status: dict[str, Any]) -> dict[str, Any]:
        """The pipeline's status message with cumulative counters and what is degraded."""
        out = self.totals.merge(status)
        out["state"] = status["state"] if status.get("state") == "failed" else self._state()
        out["degraded"] = self._degraded()
        return out

    def _publish_status(self, status: dict[str, Any]) -> None:
        face = self.zenoh
        if face is not None:
            face.publish_status(self._status_json(status))

    def _status_line(self) -> str:
        st = self.stats()
        text = f"{st['published']} profiles published, {sum(st['dropped'].values())} dropped"
        degraded = self._degraded()
        return f"degraded: {'; '.join(degraded)}; {text}" if degraded else f"running: {text}"

    # --- devices and pipeline -----------------------------------------------------------------
    def _start_pipeline(self, cfg: Config, devices: Devices, setup: AlignmentSetup) -> None:
        face = self.zenoh
        assert face is not None
        z, pl = cfg.zenoh, cfg.pipeline
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
                batch_queue=pl.batch_queue,
                status_period_s=z.status_period_s,
                publish_intensity=pl.publish_intensity,
                publish_profile_index=pl.publish_profile_index,
                shed_overload=pl.shed_overload,
                overload_lag_s=pl.overload_lag_s,
            ),
            publish_status=self._publish_status,
            publish_pose=face.publish_pose,
        )
        # What start-up built (modules, devices, sessions) lives as long as the service: out of
        # the collector's way, a full collection scans only what the pipeline makes.
        gc.freeze()
        monitored: dict[str, Any] = {"sensor": devices.sensor, "robot": devices.robot}
        if pcfg.use_table and devices.table is not None:  # a table nobody reads delivers nothing
            monitored["table"] = devices.table
        self.monitor = OutageMonitor(monitored, cfg.service.outage_after_s)
        pipeline.start()
        self.cfg, self.devices, self.pipeline = cfg, devices, pipeline

    def _stop_pipeline(self, replaced: frozenset[str], why: str, drain: bool = True) -> None:
        """Drain and stop the pipeline (everything it holds is published), keep its counters
        (those of the devices in ``replaced`` too)."""
        pl = self.pipeline
        if pl is None:
            return
        pl.stop(drain=drain)
        self.totals.carry(pl.stats(), replaced)
        if self.monitor is not None:
            self.monitor.close(why)
            self._outages = self._outage_summary()
            self.monitor = None
        self.pipeline = None

    def _on_wait(self, kind: str, waited_s: float, error: str) -> None:
        """While a device is waited for: STATUS, the status message, more start time."""
        self._waiting = (kind, time.monotonic() - waited_s, error)
        text = self._degraded()[0]
        self.notifier.status(text)
        assert self.cfg is not None
        self.notifier.extend_timeout(self.cfg.service.retry_max_s + 30.0)
        if self.zenoh is not None:
            self.zenoh.publish_status(
                {
                    "state": "waiting", "healthy": False, "waiting_for": kind,
                    "waiting_s": round(waited_s, 1), "error": error, "degraded": [text],
                    "time_utc_ns": time.time_ns(),
                }
            )  # fmt: skip

    def _open_devices(self, cfg: Config, wait_s: float) -> Devices | None:
        """The devices of ``cfg``, open (waiting up to ``wait_s``); None when stopped."""
        s = cfg.service
        devices = make_devices(cfg)
        try:
            ok = devices.open_waiting(
                wait_s, self._stop, retry_initial_s=s.retry_initial_s,
                retry_max_s=s.retry_max_s, on_wait=self._on_wait,
            )  # fmt: skip
        finally:
            self._waiting = None
        return devices if ok else None

    # --- start, stop --------------------------------------------------------------------------
    def _start(self, cfg: Config, setup: AlignmentSetup) -> int | None:
        """zenoh, devices, pipeline; an exit code when the service cannot start."""
        self._phase = "waiting"
        try:
            session = open_daemon_session(cfg)
            try:
                self._declare(session, cfg, setup)
            except BaseException:
                session.close()
                raise
            self.cfg = cfg
            self.notifier.status("opening devices")
            devices = self._open_devices(cfg, cfg.service.wait_for_devices_s)
            if devices is None:
                log.info("stop requested while waiting for devices")
                return 0
            try:
                if cfg.calibration.check_identity:
                    # Again, now that the controller answers: its serial number is known.
                    setup = load_setup(cfg, self.uncalibrated)
                self._start_pipeline(cfg, devices, setup)
            except BaseException:
                devices.close()
                raise
        except (CalibrationFileError, StartupError) as exc:
            log.error("cannot start: %s", exc)
            return 2
        except SETUP_ERRORS as exc:
            log.error("cannot start: %s", one_line(exc))
            return 1
        self._phase = "running"
        self._ran = True
        return None

    def _shutdown(self, drain: bool = True) -> None:
        self._stop_pipeline(ALL_DEVICES, why="the service stops", drain=drain)
        self._undeclare(close_session=True)
        if self.devices is not None:
            self.devices.close()
            self.devices = None

    def _log_final(self) -> None:
        st = self.stats()
        outages = ", ".join(
            f"{k} {int(v['count'])} ({v['total_s']:.1f} s)"
            for k, v in st["outages"].items()
            if v["count"]
        )
        log.info(
            "final counters: %s; %d reloads (%d failed); outages: %s",
            counters_line(st),
            self.reloads,
            self.reload_failures,
            outages or "none",
        )

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
            _ros2_class(new_cfg)
        except (ConfigError, CalibrationFileError, StartupError) as exc:
            return self._reload_failed("reload refused", exc)
        old_cfg, pl = self.cfg, self.pipeline
        assert old_cfg is not None and pl is not None
        ch = config_changes(old_cfg, new_cfg)
        calib_changed = pl.setup.description != new_setup.description
        if not ch.pipeline:
            pl.set_setup(new_setup)  # one reference swap: atomic for the worker
            self.cfg = new_cfg
            if self.monitor is not None:
                self.monitor.after_ns = round(new_cfg.service.outage_after_s * 1e9)
            if self.ros2 is not None and calib_changed:
                self.ros2.publish_tf_static(new_setup.sensor2flange)
            if "archive" in ch.sections():
                self._serve_scans(new_cfg)
        else:
            self._phase = "reloading"
            try:
                self._rebuild(new_cfg, new_setup, ch)
            except SETUP_ERRORS as exc:
                self._restore(old_cfg, pl.setup)
                return self._reload_failed("reload failed", exc)
            finally:
                self._phase = "running"
        self.reloads += 1
        what = ch.describe() if ch.fields else "no configuration field"
        log.info(
            "reloaded: %s%s",
            what,
            "; calibration in force changed" if calib_changed else "; same calibration",
        )
        self.notifier.ready("running (reloaded)")
        return True

    def _reload_failed(self, what: str, exc: BaseException) -> bool:
        self.reload_failures += 1
        text = one_line(exc) if not isinstance(exc, ConfigError) else str(exc)
        log.error("%s, keeping the configuration in force: %s", what, text)
        self.notifier.ready(f"{what}: {text.splitlines()[0]}")
        return False

    def _rebuild(self, cfg: Config, setup: AlignmentSetup, ch: Changes) -> None:
        """Replace the pipeline (and the devices, the zenoh face or session that change).
        What can fail without touching the running service is tried first: a new session on
        other endpoints, the new drivers built. On an exception the old pipeline may be gone:
        the caller restores it."""
        assert self.cfg is not None
        overlap = set(cfg.zenoh.listen) & set(self.cfg.zenoh.listen)
        new_session = open_daemon_session(cfg) if ch.session and not overlap else None
        try:
            built = make_devices(cfg) if ch.device_kinds else None
            self._stop_pipeline(replaced=ch.device_kinds, why="reload")
            devices = self._swap_devices(built, ch.device_kinds)
            if ch.face or ch.ros2:
                self._undeclare(close_session=ch.session)
                session = new_session or self._session or open_daemon_session(cfg)
                new_session = session if session is not self._session else None
                self._declare(session, cfg, setup)  # on a failure the new session is closed
                new_session = None
            elif "archive" in ch.sections():
                self._serve_scans(cfg)
            self._start_pipeline(cfg, devices, setup)
        except BaseException:
            if new_session is not None:
                new_session.close()
            if self.pipeline is None and self.devices is not None:
                self.devices.close()  # the restore opens the old ones afresh
                self.devices = None
            raise

    def _swap_devices(self, built: Devices | None, kinds: frozenset[str]) -> Devices:
        """The devices of the new configuration: those of ``kinds`` from ``built`` (opened
        here, the old ones closed first: they may hold the same port), the others kept open."""
        old = self.devices
        assert old is not None
        if built is None:
            return old
        for kind in kinds:
            d = getattr(old, kind)
            if d is not None:
                d.close()
        mixed = Devices(
            sensor=built.sensor if "sensor" in kinds else old.sensor,
            robot=built.robot if "robot" in kinds else old.robot,
            table=built.table if "table" in kinds else old.table,
        )
        self.devices = mixed  # closed as one on a failure below
        for kind in kinds:
            d = getattr(mixed, kind)
            if d is not None:
                d.open()
        return mixed

    def _restore(self, cfg: Config, setup: AlignmentSetup) -> None:
        """Bring the old configuration back after a failed reload (whatever is missing of it)."""
        try:
            if self.pipeline is not None:
                return
            declared = self._declared
            if self.zenoh is not None and declared is not None:
                ch = config_changes(declared, cfg)
                if ch.face or ch.ros2:  # the new configuration's face was up already
                    self._undeclare(close_session=ch.session)
                elif "archive" in ch.sections():
                    self._serve_scans(cfg)
            if self.zenoh is None:
                if self._session is None:
                    self._session = open_daemon_session(cfg)
                self._declare(self._session, cfg, setup)
            devices = self.devices
            if devices is None:
                devices = self._open_devices(cfg, cfg.service.wait_for_devices_s)
                if devices is None:
                    return  # stop requested meanwhile
            self._start_pipeline(cfg, devices, setup)
        except SETUP_ERRORS as exc:
            self._fatal = (
                f"cannot restore the configuration in force after a reload: {one_line(exc)}"
            )

    # --- main -----------------------------------------------------------------------------------
    def run(self) -> int:
        try:
            cfg = load_config(self.config_path)
            # The controller may not be up yet: its serial number is checked once it answers.
            setup = load_setup(cfg, self.uncalibrated, ask_controller=False)
        except (ConfigError, CalibrationFileError, StartupError) as exc:
            log.error("%s", exc)
            return 2
        handlers = {
            s: signal.signal(s, self._on_signal)
            for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
        }
        try:
            with Watchdog(self.notifier, self._healthy):
                code = self._start(cfg, setup)
                if code is not None:
                    return code
                self.notifier.ready("running")
                log.info("wristscan running: publishing on %s/cloud", cfg.zenoh.prefix)
                return self._loop()
        finally:
            self.notifier.stopping("stopping")
            self._phase = "stopping"
            self._shutdown()
            if self._ran:
                self._log_final()
            for s, h in handlers.items():
                signal.signal(s, h)

    def _healthy(self) -> bool:
        if self._phase in ("waiting", "reloading", "starting"):
            return True  # the main thread is busy opening things, not stuck
        return self.pipeline is not None and self.pipeline.healthy()

    def _loop(self) -> int:
        assert self.cfg is not None
        next_status = next_trim = time.monotonic()
        shown = 0
        while True:
            self._signal.wait(timeout=_CHECK_S)
            self._signal.clear()
            if time.monotonic() >= next_trim:  # the RSS as what the daemon uses (service/heap.py)
                next_trim = time.monotonic() + _TRIM_S
                release_free_heap()
            if self._stop.is_set():
                log.info("stop requested: draining")
                return 0
            if self._reload.is_set():
                self._reload.clear()
                self.reload()
                if self._stop.is_set():
                    continue
            pl, monitor = self.pipeline, self.monitor
            if self._fatal is not None or pl is None or monitor is None:
                log.error("%s", self._fatal or "no pipeline running")
                return 1
            if pl.failure is not None:
                log.error("pipeline failed: %s", one_line(pl.failure))
                return 1
            degraded = monitor.check()
            if time.monotonic() >= next_status or len(degraded) != shown:
                next_status = time.monotonic() + self.cfg.zenoh.status_period_s
                shown = len(degraded)
                self.notifier.status(self._status_line())


def run_service(config_path: Path, uncalibrated: bool = False) -> int:
    """Run until SIGTERM/SIGINT; returns the process exit code."""
    with Notifier() as notifier:
        return Service(config_path, notifier, uncalibrated).run()
