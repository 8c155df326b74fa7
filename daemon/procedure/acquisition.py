"""Acquisition for procedures (calibration, teaching, scan jobs): the configured devices and the
synchroniser, recording paired profiles while the robot moves.

```python
with Acquisition(cfg) as acq:
    acq.robot.move_l(start, speed, accel)
    with acq.record() as rec:
        acq.robot.move_l(end, speed, accel)          # a sweep: profiles are paired on the fly
    sweep = rec.result()                            # y, z, valid, profile_index, flange2base ...
```

Recording stops at the end of the block, after the profiles exposed inside it have been paired
(the synchroniser waits for the robot states that bracket them).

The procedures open it with :func:`open_retrying` (a device that does not answer in time is
tried again) and move inside :func:`wristscan.daemon.procedure.motion.guarded_motion`, which
stops the robot (and the table) when anything goes wrong.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from wristscan.daemon.config import Config
from wristscan.daemon.devices import Devices, make_devices, pairer_config, robot_model
from wristscan.daemon.procedure.errors import ProcedureError
from wristscan.daemon.service.pipeline import AlignmentSetup, Pipeline, PipelineSettings
from wristscan.daemon.sync.batch import PairedBatch
from wristscan.daemon.sync.pairing import Pairer
from wristscan.drivers.base import Robot, RotaryTable

__all__ = ["Acquisition", "Recording", "Sweep", "open_retrying"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sweep:
    """Profiles recorded during one block: per profile ``(P,)``, per point ``(N,)``."""

    y: NDArray[np.float64]
    z: NDArray[np.float64]
    valid: NDArray[np.bool_]
    profile_index: NDArray[np.int64]
    flange2base: NDArray[np.float64]
    exposure_ns: NDArray[np.int64]
    table_angle: NDArray[np.float64] | None

    @property
    def n_profiles(self) -> int:
        return int(self.exposure_ns.shape[0])

    def points_sensor(self) -> NDArray[np.float64]:
        """Valid points as (M, 3) sensor-frame coordinates (x = 0)."""
        m = self.valid
        return np.column_stack([np.zeros(int(m.sum())), self.y[m], self.z[m]])


class Recording:
    """Collects the paired batches whose profiles were exposed within ``[t_start, t_stop]``."""

    def __init__(self, t_start_ns: int) -> None:
        self.t_start_ns = t_start_ns
        self.t_stop_ns: int | None = None
        self._batches: list[PairedBatch] = []
        self._lock = threading.Lock()
        self._covered = threading.Condition(self._lock)
        self._latest_ns = 0

    def offer(self, batch: PairedBatch) -> None:
        with self._lock:
            self._batches.append(batch)
            self._latest_ns = max(self._latest_ns, int(batch.exposure_ns.max()))
            self._covered.notify_all()

    def wait_covered(self, timeout_s: float) -> bool:
        """Wait until a profile exposed after ``t_stop`` was paired (so every earlier one was)."""
        assert self.t_stop_ns is not None
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._latest_ns < self.t_stop_ns:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._covered.wait(left)
        return True

    def result(self) -> Sweep:
        with self._lock:
            batches = list(self._batches)
        t0, t1 = self.t_start_ns, self.t_stop_ns or np.iinfo(np.int64).max
        ys, zs, vs, idx, poses, times, angles = [], [], [], [], [], [], []
        base = 0
        for b in batches:
            keep = (b.exposure_ns >= t0) & (b.exposure_ns <= t1)
            if not keep.any():
                continue
            sel = np.flatnonzero(keep)
            remap = np.full(b.n_profiles, -1, dtype=np.int64)
            remap[sel] = np.arange(sel.size) + base
            pts = keep[b.profile_index]
            ys.append(b.y[pts])
            zs.append(b.z[pts])
            vs.append(b.valid[pts])
            idx.append(remap[b.profile_index[pts]])
            poses.append(b.flange2base[sel])
            times.append(b.exposure_ns[sel])
            if b.table_angle is not None:
                angles.append(b.table_angle[sel])
            base += sel.size
        if not times:
            empty = np.zeros(0)
            return Sweep(
                empty,
                empty,
                empty.astype(bool),
                empty.astype(np.int64),
                np.zeros((0, 4, 4)),
                empty.astype(np.int64),
                None,
            )
        return Sweep(
            y=np.concatenate(ys),
            z=np.concatenate(zs),
            valid=np.concatenate(vs),
            profile_index=np.concatenate(idx),
            flange2base=np.concatenate(poses),
            exposure_ns=np.concatenate(times),
            table_angle=np.concatenate(angles) if len(angles) == len(times) else None,
        )


class Acquisition:
    """Open devices and a recording pipeline (nothing is published)."""

    def __init__(self, cfg: Config, devices: Devices | None = None) -> None:
        self.cfg = cfg
        self.devices = devices or make_devices(cfg)
        self._recordings: list[Recording] = []
        self._lock = threading.Lock()
        self._pipeline: Pipeline | None = None
        self._open = False

    @property
    def pipeline(self) -> Pipeline:
        """The recording pipeline (exists once the acquisition is open)."""
        if self._pipeline is None:
            raise RuntimeError("the acquisition is not open")
        return self._pipeline

    @property
    def robot(self) -> Robot:
        """The robot driver (motion commands: ``move_l``, ``move_j``, ``stop``...)."""
        return self.devices.robot

    @property
    def table(self) -> RotaryTable | None:
        """The rotary table; None when the configuration has none."""
        return self.devices.table

    def require_table(self, needed_for: str) -> RotaryTable:
        """The rotary table; :class:`ProcedureError` naming ``needed_for`` when there is none."""
        if self.devices.table is None:
            raise ProcedureError(f"{self.cfg.source}: no [table] is configured: {needed_for}")
        return self.devices.table

    def _offer(self, batch: PairedBatch) -> None:
        with self._lock:
            recs = list(self._recordings)
        for r in recs:
            r.offer(batch)

    def open(self) -> Acquisition:
        if not self._open:
            self.devices.open()
            # The pairer needs the kinematic model, which the robot driver may read at open().
            pcfg = pairer_config(self.cfg, robot_model(self.cfg, self.devices))
            self._pipeline = Pipeline(
                self.devices.sensor,
                self.devices.robot,
                Pairer(pcfg),
                AlignmentSetup(sensor2flange=np.eye(4), calibrated=False),
                None,
                table=self.devices.table if pcfg.use_table else None,
                settings=PipelineSettings(batch_s=self.cfg.pipeline.batch_s),
                on_batch=self._offer,
            )
            self._pipeline.start()
            self._open = True
        return self

    def close(self) -> None:
        if self._open:
            self._open = False
            self.pipeline.stop(drain=False)
            self._pipeline = None
            self.devices.close()

    def __enter__(self) -> Acquisition:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def record(self, settle_timeout_s: float = 2.0) -> Iterator[Recording]:
        """Record the profiles exposed while the block runs."""
        rec = Recording(time.monotonic_ns())
        with self._lock:
            self._recordings.append(rec)
        try:
            yield rec
            rec.t_stop_ns = time.monotonic_ns()
            if not rec.wait_covered(settle_timeout_s):
                log.warning("recording: profiles at the end of the block were not all paired")
        finally:
            if rec.t_stop_ns is None:
                rec.t_stop_ns = time.monotonic_ns()
            with self._lock:
                self._recordings.remove(rec)

    def stats(self) -> dict[str, Any]:
        return self.pipeline.stats()

    def stop_motion(self, table: bool = True) -> None:
        """Stop the robot and, with ``table``, the table, as after a failure: a stop that fails
        is logged, not raised (the other device must still be stopped, and the error that led
        here matters more)."""
        stops: list[tuple[str, Callable[[], None]]] = [("robot", self.robot.stop)]
        if table and self.table is not None:
            stops.append(("table", self.table.stop))
        for name, stop in stops:
            try:
                stop()
            except Exception as exc:
                log.warning("stopping the %s after an abort: %s", name, exc)


class _Openable(Protocol):
    def open(self) -> Any: ...


_D = TypeVar("_D", bound=_Openable)


def open_retrying(make: Callable[[], _D], attempts: int = 1) -> _D:
    """``make()`` (an :class:`Acquisition`, a device), opened. When a device does not answer in
    time (``DriverTimeout``: a controller busy starting up) a new one is made and tried again,
    ``attempts`` times in all; the last timeout and any other error propagate."""
    from wristscan.drivers.base import DriverTimeout

    for attempt in range(1, max(1, attempts) + 1):
        obj = make()
        try:
            obj.open()
            return obj
        except DriverTimeout as exc:
            if attempt >= attempts:
                raise
            log.warning("%s; trying again", exc)
    raise AssertionError("unreachable")
