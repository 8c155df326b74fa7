"""The acquisition pipeline: sensor driver -> synchroniser -> alignment -> zenoh, in batches.

Threads:

* one reader per device (sensor, robot, table) that blocks on the driver's ``read`` and puts
  records into a bounded queue (a full queue drops the record and counts it by reason), except
  for devices whose records are stamped on receipt (the UDP sensors, the UR robot), which the
  worker reads itself at each tick;
* one worker that, every ``batch_s``, drains the queues into the :class:`Pairer`, aligns the
  paired batches with the calibration in force (vectorised, Eq. 1) and publishes WSC1 batches.

Counters always add up: ``received = published + dropped (by reason) + pending``. Device errors
never kill the pipeline (drivers reconnect by themselves); an unexpected exception in a thread
marks the pipeline failed, which the service turns into a non-zero exit (systemd restarts it).
"""

from __future__ import annotations

import gc
import logging
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import align, jit
from wristscan.daemon.cloud import wsc1
from wristscan.daemon.service.instruments import STEPS, LatencyWindow, StepCpu
from wristscan.daemon.service.overload import KernelAdmission, Shedder, spread_rows, take_rows
from wristscan.daemon.service.publisher import Outgoing, Publisher
from wristscan.daemon.service.readers import InlineReader, Reader, name_os_thread
from wristscan.daemon.service.settings import AlignmentSetup, PipelineSettings
from wristscan.daemon.sync.batch import PairedBatch
from wristscan.daemon.sync.pairing import Pairer
from wristscan.drivers.base import Device, DriverError, ProfileSensor
from wristscan.drivers.records import Profile, ProfileBlock, RobotState, TableState

PosePublisher = Callable[
    [int, str, NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]], None
]
"""(seq, frame, exposure UTC ns (P,), flange2base (P, 4, 4), sensor2frame (P, 4, 4))."""

__all__ = ["AlignmentSetup", "Pipeline", "PipelineSettings"]

log = logging.getLogger(__name__)

_SLOW_TICK_NS = 50_000_000
"""A tick longer than this (five batch periods at the default) is counted and logged."""


class Pipeline:
    """Wire devices, the pairer and the publisher together; start/stop, counters, health."""

    def __init__(
        self,
        sensor: ProfileSensor,
        robot: Device[RobotState],
        pairer: Pairer,
        setup: AlignmentSetup,
        publish: Callable[..., int] | None,
        table: Device[TableState] | None = None,
        settings: PipelineSettings | None = None,
        publish_status: Callable[[dict[str, Any]], None] | None = None,
        on_batch: Callable[[PairedBatch], None] | None = None,
        publish_pose: PosePublisher | None = None,
    ) -> None:
        """``publish`` receives aligned batches (``DaemonZenoh.publish_cloud``'s signature) and
        returns their sequence number; ``publish_pose`` the robot pose of each of their profiles
        (``DaemonZenoh.publish_pose``); ``on_batch`` receives every paired batch before
        alignment (calibration procedures record them). Any may be None."""
        self.settings = settings or PipelineSettings()
        self.sensor, self.robot, self.table = sensor, robot, table
        self.pairer = pairer
        self._setup = setup
        self._publish = publish
        self._publish_status = publish_status
        self._publish_pose = publish_pose
        self._inline_failing = 0
        self._on_batch = on_batch
        s = self.settings
        self._profiles: deque[Profile] = deque()
        self._blocks: list[ProfileBlock] = []
        """Blocks read inline since the last tick's admission, and their profile count."""
        self._blocks_n = 0
        self._rate_in = 0.0
        """Profiles per second read over the last ticks (sets the read-ahead pace)."""
        self.shedder = Shedder(max_lag_s=s.overload_lag_s)
        self._robot_q: deque[RobotState] = deque()
        self._table_q: deque[TableState] = deque()
        self.dropped: Counter[str] = Counter()
        self.published_profiles = 0
        self.published_points = 0
        self.published_batches = 0
        self._publishing = 0
        """Profiles handed to the publishing thread whose put has not returned yet."""
        self._payloads: deque[bytearray] = deque(maxlen=s.batch_queue + 2)
        """Recent WSC1 payloads, written over again once nobody holds them."""
        self._publisher = Publisher(self._put, self._published, self._fail, s.batch_queue)
        self.robot_states_dropped = 0
        self._lock = threading.Lock()
        # Held by the worker while it drains, pairs and publishes one tick, and by stats(): the
        # counters it reads then add up exactly (no profile is half-way between two of them).
        self._tick_lock = threading.Lock()
        self._stop = threading.Event()
        self._states_arrived = threading.Event()
        self._failure: BaseException | None = None
        self._last_progress_ns = time.monotonic_ns()
        self._utc_offset_ns = time.time_ns() - time.monotonic_ns()
        self._sensor_stamped = sensor.stamped_on_receipt
        self.inline_sensor = self._sensor_stamped if s.inline_sensor is None else s.inline_sensor
        self._kernel = KernelAdmission(sensor, s.shed_overload and self.inline_sensor)
        self.read_errors: Counter[str] = Counter()
        """Driver errors met while reading inline, by device (the drivers reconnect)."""
        self.inline_robot: InlineReader[RobotState] | None = None
        self._readers = self._make_readers()
        self._worker = threading.Thread(target=self._work, name="pipeline-worker", daemon=True)
        self._started = False
        self._saved_switch_interval: float | None = None
        self.latency = LatencyWindow()
        self.gc_pauses: Counter[int] = Counter()
        """Garbage collections per generation that held every thread for more than 20 ms."""
        self.slow_ticks = 0
        """Ticks that took over ``_SLOW_TICK_NS`` from start to the last publish."""
        self.state_waited_s = 0.0
        """Wall time the worker spent at ticks waiting for the states of received profiles."""
        self._cpu = {step: StepCpu() for step in STEPS}
        """The worker's CPU time by step: reading the sensor, pairing, aligning; publishing is
        the publishing thread's."""
        self._cpu["publish"] = self._publisher.cpu
        self.tick_ms_max = 0.0
        self._gc_t0 = 0
        self._tick_ns = 0

    def _make_readers(self) -> list[Reader[Any]]:
        """A reader thread per device: the robot and the sensor unless the worker reads them
        itself (``inline_robot`` made here), the table if any. State readers wake the worker's
        wait for states."""
        s = self.settings
        readers: list[Reader[Any]] = []
        inline = self.robot.stamped_on_receipt if s.inline_robot is None else s.inline_robot
        if inline:
            self.inline_robot = InlineReader(
                "robot", self.robot, self._robot_q, s.state_queue, self._drop_state
            )
        if not self.inline_sensor:
            readers.append(
                Reader(
                    "sensor",
                    self.sensor,
                    self._profiles,
                    s.profile_queue,
                    self._drop_profile,
                    self._fail,
                )
            )
        states: list[tuple[str, Device[Any], deque[Any]]] = []
        if self.inline_robot is None:
            states.append(("robot", self.robot, self._robot_q))
        if self.table is not None:
            states.append(("table", self.table, self._table_q))
        for name, device, sink in states:
            readers.append(
                Reader(
                    name,
                    device,
                    sink,
                    s.state_queue,
                    self._drop_state,
                    self._fail,
                    self._states_arrived,
                )
            )
        return readers

    # --- counters and health ----------------------------------------------------------------
    def _drop_profile(self) -> None:
        with self._lock:
            self.dropped["queue_full"] += 1

    def _drop_state(self) -> None:
        with self._lock:
            self.robot_states_dropped += 1

    def _fail(self, exc: BaseException) -> None:
        self._failure = exc
        self._stop.set()

    @property
    def failure(self) -> BaseException | None:
        return self._failure

    def healthy(self, stall_s: float = 2.0) -> bool:
        """False when the worker has not made progress for ``stall_s`` (the watchdog then
        withholds its ping) or a thread failed."""
        if self._failure is not None:
            return False
        return (time.monotonic_ns() - self._last_progress_ns) < stall_s * 1e9

    def stats(self) -> dict[str, Any]:
        """Counters (JSON-friendly). ``received == published + sum(dropped) + pending``, exactly:
        ``received`` counts the profiles the sensor reader handed to the pipeline (the driver's
        own count, in ``sensor``, may be ahead by the one record the reader holds)."""
        return self._stats(latency=True)

    def _stats(self, latency: bool) -> dict[str, Any]:
        with self._tick_lock:
            p = self.pairer.stats()
            queued = len(self._profiles) + self._blocks_n
            overload = {**self.shedder.status(), "kernel_fraction": self._kernel.fraction}
            with self._lock:
                dropped = dict(self.dropped)
                published = self.published_profiles
                points, batches = self.published_points, self.published_batches
                publishing = self._publishing
        for reason, n in dict(p["dropped"]).items():  # type: ignore[call-overload]
            dropped[reason] = dropped.get(reason, 0) + int(n)
        # Shed before the pairer (queue_full, overload): received by the pipeline all the same.
        received = (
            int(p["received"])  # type: ignore[call-overload]
            + queued
            + dropped.get("queue_full", 0)
            + dropped.get("overload", 0)
        )
        # Paired (in the pairer's received), handed to the publishing thread, not put yet.
        pending = int(p["pending"]) + queued + publishing  # type: ignore[call-overload]
        return {
            "received": received,
            "published": published,
            "dropped": dropped,
            "pending": pending,
            "published_points": points,
            "published_batches": batches,
            "robot_states": self.robot.counters.received,
            "robot_states_dropped": self.robot_states_dropped,
            "sensor": self.sensor.health().counters.as_dict(),
            "robot": self.robot.health().counters.as_dict(),
            "table": None if self.table is None else self.table.health().counters.as_dict(),
            "pairing": p,
            "latency_ms": self.latency.summary() if latency else {},
            "read_errors": dict(self.read_errors),
            "gc_pauses_over_20ms": dict(self.gc_pauses),
            "slow_ticks": self.slow_ticks,
            "state_waited_s": round(self.state_waited_s, 4),
            "worker_cpu_s": {k: round(c.ns * 1e-9, 4) for k, c in self._cpu.items()},
            "tick_ms_max": round(self.tick_ms_max, 3),
            "overload": overload,
        }

    def status(self) -> dict[str, Any]:
        st = self._stats(latency=False)  # the worker publishes this: no percentiles to sort
        devices: dict[str, Device[Any]] = {"sensor": self.sensor, "robot": self.robot}
        if self.table is not None:
            devices["table"] = self.table
        setup = self._setup
        return {
            "state": "failed" if self._failure else ("running" if self._started else "stopped"),
            "healthy": self.healthy(),
            "calibrated": setup.calibrated,
            "frame": setup.frame,
            "devices": {k: d.health().state.value for k, d in devices.items()},
            "received": st["received"],
            "published": st["published"],
            "dropped": st["dropped"],
            "pending": st["pending"],
            "time_utc_ns": time.time_ns(),
        }

    # --- calibration --------------------------------------------------------------------------
    def set_setup(self, setup: AlignmentSetup) -> None:
        """Swap the calibration in force; the next batch uses it (one reference assignment)."""
        self._setup = setup

    @property
    def setup(self) -> AlignmentSetup:
        return self._setup

    # --- life cycle -----------------------------------------------------------------------------
    def _on_gc(self, phase: str, info: dict[str, int]) -> None:
        # A collection holds the GIL: every thread of the pipeline waits for it.
        if phase == "start":
            self._gc_t0 = time.monotonic_ns()
            return
        pause_ns = time.monotonic_ns() - self._gc_t0
        if pause_ns > 20_000_000:
            self.gc_pauses[info.get("generation", -1)] += 1
            log.warning(
                "garbage collection (generation %d) held the pipeline for %.0f ms",
                info.get("generation", -1),
                pause_ns * 1e-6,
            )

    def start(self) -> None:
        # The compiled alignment made ready now, not on the first batch (numba: ~0.3-0.6 s).
        took = jit.warm()
        if took:
            log.debug("hot-path kernels warmed in %.2f s", took)
        gc.callbacks.append(self._on_gc)
        interval = self.settings.gil_switch_interval_s
        if interval is not None and not self._sensor_stamped:
            self._saved_switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(min(interval, self._saved_switch_interval))
        self._started = True
        for r in self._readers:
            r.start()
        if self._publish is not None:
            self._publisher.start()
        self._worker.start()

    def stop(self, drain: bool = True, timeout_s: float = 5.0) -> None:
        """Stop reading; with ``drain`` the worker publishes what it holds before ending.
        Profiles that still lack robot states then are dropped and counted (``shutdown``)."""
        if not self._started:
            return
        for r in self._readers:
            r.stop()
        for r in self._readers:
            r.join(timeout_s)
        self._drain_on_stop = drain
        self._stop.set()
        self._worker.join(timeout_s)
        self._publisher.stop(timeout_s)
        self._started = False
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
        if self._saved_switch_interval is not None:
            sys.setswitchinterval(self._saved_switch_interval)
            self._saved_switch_interval = None

    # --- worker ---------------------------------------------------------------------------------
    def _read_sensor_inline(self) -> None:
        """Everything the sensor driver holds now (inline mode), as blocks for the next tick."""
        if not self.inline_sensor:
            return
        limit = self.settings.profile_queue
        n0 = self._blocks_n
        with self._cpu["read"]:
            # Bounded: a flood cannot keep the worker here forever (the rest waits in the
            # socket buffer for the next step).
            while self._blocks_n - n0 < 4 * limit:
                try:
                    blocks = self.sensor.read_blocks(limit)
                except DriverError as exc:
                    # The driver reconnects by itself; the next step tries again. A UDP sensor
                    # can fail 100 times a second: the first of a run warns, the rest debug.
                    self.read_errors[self.sensor.kind] += 1
                    self._inline_failing += 1
                    level = logging.WARNING if self._inline_failing == 1 else logging.DEBUG
                    log.log(level, "%s: %s", self.sensor.kind, exc)
                    break
                if not blocks:
                    break
                self._inline_failing = 0
                n = sum(b.n_profiles for b in blocks)
                self._blocks.extend(blocks)
                self._blocks_n += n
                if n < limit:
                    break

    def _admit(self) -> None:
        """This tick's profiles into the pairer, shedding what the worker cannot process."""
        blocks, self._blocks = self._blocks, []
        n_in, self._blocks_n = self._blocks_n, 0
        # The arrival rate (profiles/s) over the last ticks, for the read-ahead's pace.
        self._rate_in += 0.3 * (n_in / self._period() - self._rate_in)
        records = self._profiles
        if records:
            taken = [records.popleft() for _ in range(len(records))]
            blocks += ProfileBlock.from_profiles(taken)
            n_in += len(taken)
        kernel = self._kernel.shed_since()  # shed before reading (counter gaps)
        keep = n_in
        if not n_in:
            self.shedder.admit(kernel, time.monotonic_ns(), None, 0)
        elif self.settings.shed_overload:
            oldest = min(int(b.host_time_ns[0]) for b in blocks)
            now, period = time.monotonic_ns(), self._period()
            keep = self.shedder.admit(n_in + kernel, now, oldest, n_in, period)
        self._kernel.steer(self.shedder)
        if keep < n_in or kernel:
            with self._lock:
                self.dropped["overload"] += n_in - keep + kernel
        if keep < n_in:
            blocks = take_rows(blocks, spread_rows(n_in, keep))
        for b in blocks:
            self.pairer.add_block(b)

    def _drain(self, profiles_too: bool = True) -> None:
        pairer = self.pairer
        # States first: the profiles admitted after them find their robot samples in place.
        # Only what is there now: later arrivals wait for the next tick.
        self._states_arrived.clear()
        robot, table = self._robot_q, self._table_q
        if self.inline_robot is not None:
            with self._cpu["read"]:
                self.inline_robot.pump()
        with self._cpu["pair"]:
            if robot:
                pairer.add_robot_states([robot.popleft() for _ in range(len(robot))])
            for _ in range(len(table)):
                pairer.add_table_state(table.popleft())
            if profiles_too:
                self._admit()

    def _states_wait(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for new states: from the robot read inline, else from the
        reader threads; True when some arrived."""
        if self.inline_robot is None:
            return self._states_arrived.wait(timeout_s)
        with self._cpu["read"]:
            return self.inline_robot.pump(timeout_s) > 0 or self._states_arrived.is_set()

    def _poll(self) -> list[PairedBatch]:
        with self._cpu["pair"]:
            return self.pairer.poll()

    def _pair(self, stopping: bool) -> list[PairedBatch]:
        """This tick's batches: pair what arrived, then wait up to ``state_wait_s`` for the
        states that received profiles still need (not while stopping)."""
        self._read_sensor_inline()
        self._drain()
        batches = self._poll()
        t0 = time.monotonic()
        deadline = t0 + self.settings.state_wait_s
        unpolled = False
        while self.pairer.waiting_for_states and not stopping:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._states_wait(remaining):
                break
            self._drain(profiles_too=False)
            # Poll once the states reach every waiting profile, not at each state (a poll
            # costs the same for one profile as for fifty).
            unpolled = not self.pairer.states_cover_waiting()
            if not unpolled:
                batches.extend(self._poll())
        if unpolled:
            batches.extend(self._poll())  # what the states that came in time do cover
        waited = time.monotonic() - t0
        self.state_waited_s += waited
        return self.pairer.merge(batches) if len(batches) > 1 else batches

    def _emit(self, batch: PairedBatch) -> None:
        if self._on_batch is not None:
            self._on_batch(batch)
        if self._publish is None:
            with self._lock:
                self.published_batches += 1
                self.published_profiles += batch.n_profiles
            return
        setup = self._setup
        frame = setup.frame
        s = self.settings
        with self._cpu["align"]:
            poses = align.sensor_poses(
                batch.flange2base,
                setup.sensor2flange,
                base2table=setup.base2table if frame != "base" else None,
                table_angle_rad=batch.table_angle if frame == "part" else None,
                encoder_offset_rad=setup.encoder_offset_rad,
                frame=frame,  # type: ignore[arg-type]
                checked=False,  # kinematics and a calibration checked when loaded
            )
            # Every point in float32 straight into the WSC1 payload, segment by segment (the
            # profiles' rows as they arrived: nothing concatenated first).
            groups = [(g.y, g.points, g.valid, g.intensity) for g in batch.segments()]
            cloud = wsc1.aligned_frame_of(
                groups,
                poses,
                intensity=s.publish_intensity and all(g[3] is not None for g in groups),
                profile_index=s.publish_profile_index,
                reuse=self._free_payload(),
            )
            if not any(b is cloud.buffer for b in self._payloads):
                self._payloads.append(cloud.buffer)
        item = Outgoing(
            cloud,
            int(batch.exposure_ns.min()) + self._utc_offset_ns,
            int(batch.exposure_ns.max()) + self._utc_offset_ns,
            batch.n_profiles,
            cloud.n_points,
            frame,
            batch.exposure_ns,
            batch.flange2base,
            poses,
            batch.arrival_ns,
            self._tick_ns,
        )
        with self._lock:
            self._publishing += batch.n_profiles
        self._publisher.submit(item)

    def _free_payload(self) -> bytearray | None:
        """A recent payload nobody holds any more (zenoh copied it when it was put): zeroing
        and mapping a new one cost ~2 us per profile. None: all in use."""
        for buf in self._payloads:
            if sys.getrefcount(buf) <= 3:  # the deque, this loop and getrefcount's argument
                return buf
        return None

    def _put(self, item: Outgoing) -> None:
        """The publishing thread's work: the cloud, then its profiles' poses."""
        assert self._publish is not None
        seq = self._publish(
            item.cloud, item.t_first_ns, item.t_last_ns, item.n_profiles, item.frame, None, None
        )
        if self._publish_pose is not None:
            t_ns = item.exposure_ns.astype(np.int64) + self._utc_offset_ns
            self._publish_pose(seq, item.frame, t_ns, item.flange2base, item.sensor2frame)

    def _published(self, item: Outgoing) -> None:
        if item.arrival_ns is not None:
            self.latency.add(item.exposure_ns, item.arrival_ns, item.tick_ns, time.monotonic_ns())
        item.cloud = None  # the payload is free for the next batch
        with self._lock:
            self._publishing -= item.n_profiles
            self.published_batches += 1
            self.published_profiles += item.n_profiles
            self.published_points += item.n_points

    def _period(self) -> float:
        """The tick period (s): ``batch_s``; while an admission rate is in force, half the lag
        bound instead, so that the worker pays its cost per tick less often (the latency is
        bounded by the lag then, not by the tick)."""
        s = self.settings
        return max(s.batch_s, 0.5 * s.overload_lag_s) if self.shedder.limiting else s.batch_s

    def _wait_for_tick(self, tick: float) -> bool:
        """Sleep until the monotonic time ``tick``, reading ahead meanwhile (not while an
        admission rate is in force: the socket holds a tick); True to stop."""
        step = 0.0 if self.shedder.limiting else self.settings.read_ahead_s
        if step > 0 and self._rate_in > 0:
            step = max(step, self.settings.read_ahead_profiles / self._rate_in)
        while True:
            now = time.monotonic()
            if step <= 0 or tick - now <= step:
                return self._stop.wait(max(0.0, tick - now))
            if self._stop.wait(step):
                return True
            with self._tick_lock:
                self._read_sensor_inline()

    def _note_tick(
        self, t0: int, t1: int, t2: int, cpu_ns: int, batches: list[PairedBatch]
    ) -> None:
        """Keep the longest tick; log a slow one with where its time went (its own CPU time
        against the wall time tells waiting for a CPU or a lock from working)."""
        ms = (t2 - t0) * 1e-6
        self.tick_ms_max = max(self.tick_ms_max, ms)
        if t2 - t0 > _SLOW_TICK_NS:
            self.slow_ticks += 1
            log.warning(
                "slow tick: %.0f ms for %d profiles in %d batches (reading and pairing %.0f ms, "
                "aligning and publishing %.0f ms; the worker's CPU time %.0f ms)",
                ms,
                sum(b.n_profiles for b in batches),
                len(batches),
                (t1 - t0) * 1e-6,
                (t2 - t1) * 1e-6,
                cpu_ns * 1e-6,
            )

    def _work(self) -> None:
        name_os_thread(self._worker.name)
        next_status = time.monotonic() + self.settings.status_period_s
        next_tick = time.monotonic() + self._period()
        try:
            while True:
                # Ticks on a fixed schedule (the work of a tick does not stretch the period,
                # which would add to every profile's latency); missed ticks are not made up.
                stopping = self._wait_for_tick(next_tick)
                next_tick = max(next_tick + self._period(), time.monotonic())
                with self._tick_lock:
                    self._tick_ns = t0 = time.monotonic_ns()
                    cpu0 = time.thread_time_ns()
                    batches = self._pair(stopping)
                    if stopping:
                        if getattr(self, "_drain_on_stop", True):
                            batches.extend(self.pairer.flush())
                    t1 = time.monotonic_ns()
                    for b in batches:
                        self._emit(b)
                self._last_progress_ns = t2 = time.monotonic_ns()
                self._note_tick(t0, t1, t2, time.thread_time_ns() - cpu0, batches)
                if self._publish_status is not None and time.monotonic() >= next_status:
                    next_status += self.settings.status_period_s
                    self._publish_status(self.status())
                if stopping:
                    return
        except BaseException as exc:
            log.exception("pipeline worker failed")
            self._failure = exc
