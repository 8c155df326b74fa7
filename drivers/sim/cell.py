"""The whole simulated cell: UR controller, rotary table and profile sensor, each in its own
process, sharing the ground truth of motion through :class:`~.truth.TruthRing` segments.

``SimulatedCell`` is a context manager: entering starts every process and waits until each
listens; leaving (or :meth:`stop`) ends every process it started and removes the shared memory,
also when start-up fails half way.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematic_errors as kerr
from wristscan.calib import kinematics, se3
from wristscan.drivers.sim.scene import Scene, demo_scene
from wristscan.drivers.sim.sensors import SensorSimConfig, SimulatedSensor
from wristscan.drivers.sim.table import SimulatedTable, TableSimConfig
from wristscan.drivers.sim.truth import TruthRing
from wristscan.drivers.sim.ur.controller import ControllerConfig, SimulatedController

__all__ = ["CellSpec", "SimulatedCell"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CellSpec:
    """What to start. ``table`` None: no rotary table (objects mounted on it stay at angle 0)."""

    controller: ControllerConfig = field(default_factory=ControllerConfig)
    sensor: SensorSimConfig = field(default_factory=SensorSimConfig)
    table: TableSimConfig | None = field(default_factory=TableSimConfig)
    scene: Scene | None = None
    """None: :func:`~.scene.demo_scene`."""


class SimulatedCell:
    def __init__(self, spec: CellSpec | None = None) -> None:
        self.spec = spec or CellSpec()
        ctrl, sensor = self.spec.controller, self.spec.sensor
        if ctrl.kinematic_errors is not None and kinematics.get_model(
            sensor.robot_model
        ) == kinematics.get_model(ctrl.model):
            # The sensor sees the scene from where the flange really is: the arm's true model.
            true: dict[str, Any] = {"robot_model": ctrl.true_model}
            self.spec = dataclasses.replace(self.spec, sensor=dataclasses.replace(sensor, **true))
        self.scene = self.spec.scene or demo_scene()
        self.robot_ring: TruthRing | None = None
        self.table_ring: TruthRing | None = None
        self.controller: SimulatedController | None = None
        self.table: SimulatedTable | None = None
        self.sensor: SimulatedSensor | None = None

    def start(self) -> SimulatedCell:
        try:
            self.robot_ring = TruthRing.create(width=6)
            # The three processes start side by side (each ~0.6-0.8 s of imports), then each is
            # waited for: the sensor reads the others' truth rings, not their sockets.
            self.controller = SimulatedController(self.spec.controller, self.robot_ring.name)
            self.controller.spawn()
            if self.spec.table is not None:
                self.table_ring = TruthRing.create(width=1)
                self.table = SimulatedTable(self.spec.table, self.table_ring.name).spawn()
            self.sensor = SimulatedSensor(
                self.spec.sensor,
                self.scene,
                robot_ring=self.robot_ring.name,
                table_ring=self.table_ring.name if self.table_ring is not None else None,
            ).spawn()
            self.controller.wait_ready(60.0)
            if self.table is not None:
                self.table.wait_ready()
            self.sensor.wait_ready()
        except BaseException:
            self.stop()
            raise
        log.info("simulated cell started: %s", self.endpoints())
        return self

    def stop(self) -> None:
        for part in (self.sensor, self.table, self.controller):
            if part is not None:
                part.stop()
        self.sensor = self.table = self.controller = None
        for ring in (self.robot_ring, self.table_ring):
            if ring is not None:
                ring.close()
                ring.unlink()
        self.robot_ring = self.table_ring = None

    def __enter__(self) -> SimulatedCell:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- what tests and operators need to know ---------------------------------------------
    def endpoints(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.controller is not None:
            out["robot"] = {
                "host": self.controller.host,
                "rtde": 30004,
                "dashboard": 29999,
                "script": 30003,
                "frequency_hz": self.controller.frequency_hz,
            }
        if self.table is not None:
            out["table"] = dict(self.table.endpoint)
        if self.sensor is not None:
            out["sensor"] = {"kind": self.spec.sensor.kind, **self.sensor.endpoint}
        return out

    def _robot_truth(self) -> dict[str, Any]:
        """The arm's kinematics: true, reported (factory calibration) and nominal models as
        :func:`~wristscan.calib.kinematic_errors.model_dict` (``model_from_dict`` reads them
        back), and the sizes of its errors."""
        c = self.spec.controller
        e = c.kinematic_errors
        return {
            "robot_model_nominal": kerr.model_dict(kinematics.get_model(c.model)),
            "robot_model_true": kerr.model_dict(c.true_model),
            "robot_model_reported": kerr.model_dict(c.reported_model),
            "robot_kinematic_errors": None if e is None else dataclasses.asdict(e),
            "robot_kinematic_seed": c.kinematic_seed,
            "robot_factory_calibration": c.factory_calibration if e is not None else "exact",
            "robot_joint_noise_rad": c.joint_noise_rad,
        }

    def true_flange2base(self, t_ns: ArrayLike) -> NDArray[np.float64]:
        """Where the flange really was at host instants ``t_ns`` (``time.monotonic_ns()``, e.g.
        the exposure instants of profiles): the arm's true model at the true joints of the truth
        ring, ``(M, 4, 4)``; NaN rotation and position where the ring does not cover an instant."""
        if self.robot_ring is None:
            raise RuntimeError("the cell is not running")
        q = self.robot_ring.sample(np.asarray(t_ns, dtype=np.int64))
        return kinematics.forward(self.spec.controller.true_model, q)

    def truth(self) -> dict[str, Any]:
        """Ground truth in SI units: the values calibration should recover."""
        s = self.spec.sensor
        s2f = s.sensor2flange_matrix()
        out: dict[str, Any] = {
            "sensor2flange": s2f.tolist(),
            "sensor2flange_ur_pose": se3.matrix_to_pose(s2f).tolist(),
            "sensor_latency_s": s.latency_s if s.stamp_delay_s is None else s.stamp_delay_s,
            "sensor_clock_offset_ns": s.clock_offset_ns,
            "sensor_clock_drift_ppm": s.clock_drift_ppm,
            "robot_repeatability_m": self.spec.controller.repeatability_m,
            **self._robot_truth(),
        }
        try:
            ball = self.scene.find("ball")
            out["ball_centre_base_m"] = se3.translation(self.scene.prim2base(ball)).tolist()
            out["ball_radius_m"] = float(getattr(ball, "radius", np.nan))
        except KeyError:
            pass
        if self.table is not None:
            t2b = self.scene.table2base(0.0)
            out["table_zero2base"] = np.asarray(t2b).tolist()
            out["table_axis_direction"] = np.asarray(t2b)[:3, 2].tolist()
            out["table_axis_point_m"] = np.asarray(t2b)[:3, 3].tolist()
        return out
