"""Simulated cells set up for the procedures, and their ground truth: what the tests, the
benchmarks and ``wristscan demo`` run the calibration and teaching procedures on.

Production code never imports this module (it imports the simulator); the procedures take the
cell's configuration like any other.

* :func:`table_ball_cell`, :func:`table_truth`: a tooling ball on a post on the rotary table
  (``calibrate table`` and ``calibrate latency``).
* :func:`cell_with_scene`: a cell with a scene of ``wristscan.drivers.sim.scenes_apps`` (the
  teaching procedures) and the arm placed over it; :func:`write_truth_calibration` writes the
  cell's true sensor2flange as the calibration in force.
* :func:`pairing_truth_tap`, :func:`truth_offset_s`, :func:`truth_latency_parts`: the latency
  that ``calibrate latency`` should find, from the simulator's truth (its exposure-to-stamp
  delay) and the measured link delays, independently of the synchroniser.
* :func:`jog_to_ball`: the arm of a running cell placed as an operator starts ``calibrate
  sensor`` (the laser line across the scene's ball).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.calib.table import base2table_from
from wristscan.daemon.calibrate.latency import LatencyResult
from wristscan.daemon.config import Config, SimConfig
from wristscan.daemon.procedure.acquisition import Acquisition
from wristscan.daemon.simcell.cell import cell_spec, write_truth_calibrations
from wristscan.daemon.sync.batch import PairedBatch
from wristscan.drivers.records import RobotState
from wristscan.drivers.sim.cell import CellSpec, SimulatedCell
from wristscan.drivers.sim.scene import Cylinder, Scene, Sphere, demo_scene
from wristscan.drivers.sim.scenes_apps import start_q_for_sensor

__all__ = [
    "cell_with_scene",
    "jog_to_ball",
    "pairing_truth_tap",
    "table_ball_cell",
    "table_truth",
    "truth_latency_parts",
    "truth_offset_s",
    "write_truth_calibration",
]


def table_ball_cell(
    cfg: Config,
    *,
    ball_on_table_m: Sequence[float] = (0.10, 0.0),
    ball_height_m: float = 0.06,
    start_above: str | Sequence[float] | None = None,
    standoff_m: float = 0.10,
    **sensor_overrides: Any,
) -> CellSpec:
    """The simulated cell of ``cfg`` with a tooling ball on a post on the rotary table.

    The demo scene without its part, plus a platter (0.15 m radius, 0.03 m high), a post and a
    ball of ``[sim.scene] ball_radius_m`` at ``ball_on_table_m`` (table frame, m) with its centre
    ``ball_height_m`` above the platter. Primitive names: ``table_ball``, ``table_post`` (and the
    demo's ``ball`` on its post on the base).

    ``start_above``: the arm starts with the sensor ``standoff_m`` above this point (a base-frame
    point, or the name of a primitive: ``"table_ball"``, ``"ball"``), in the orientation of the
    configured start joints, as an operator would have placed it.
    """

    spec = cell_spec(cfg, **sensor_overrides)
    sim = cfg.sim or SimConfig()
    radius = sim.scene.ball_radius_m
    scene = demo_scene(
        ball_radius_m=radius,
        ball_centre=sim.scene.ball_centre_m,
        table_zero2base=sim.truth.table_zero2base(),
        with_part=False,
    )
    platter_h = 0.03
    bx, by = float(ball_on_table_m[0]), float(ball_on_table_m[1])
    scene.add(Cylinder(0.15, platter_h, mount="table", name="platter"))
    post_h = ball_height_m - 0.8 * radius
    scene.add(
        Cylinder(0.004, post_h, se3.make(t=(bx, by, platter_h)), mount="table", name="table_post")
    )
    scene.add(Sphere(radius, (bx, by, platter_h + ball_height_m), mount="table", name="table_ball"))
    if start_above is not None:
        if isinstance(start_above, str):
            target = se3.translation(scene.prim2base(scene.find(start_above), 0.0))
        else:
            target = np.asarray(start_above, dtype=np.float64)
        ctl = spec.controller
        s2f = spec.sensor.sensor2flange_matrix()
        q0 = np.asarray(ctl.initial_q, dtype=np.float64)
        R = (kinematics.forward(ctl.model, q0) @ s2f)[:3, :3]
        s2b = se3.make(R, target - standoff_m * R[:, 2])
        q = kinematics.inverse_nearest(ctl.model, s2b @ se3.invert(s2f), q0)
        spec = dataclasses.replace(
            spec, controller=dataclasses.replace(ctl, initial_q=tuple(float(v) for v in q))
        )
    return dataclasses.replace(spec, scene=scene)


def table_truth(spec: CellSpec, angle_rad: float = 0.0) -> dict[str, Any]:
    """Ground truth of a :func:`table_ball_cell` cell: the axis, its tilt, the ball centre at
    ``angle_rad`` and the encoder offset in the gauge of
    :func:`wristscan.calib.table.fit_table_axis`."""

    assert spec.scene is not None
    scene = spec.scene
    z2b = scene.table_zero2base
    direction = z2b[:3, 2]
    point = z2b[:3, 3]
    ball = scene.find("table_ball")
    centre0 = se3.translation(scene.prim2base(ball, 0.0))
    b2t = base2table_from(direction, point)
    local = b2t[:3, :3] @ centre0 + b2t[:3, 3]
    return {
        "axis_direction": direction.tolist(),
        "axis_point_m": point.tolist(),
        "tilt_deg": math.degrees(math.acos(min(1.0, abs(float(direction[2]))))),
        "ball_centre_m": se3.translation(scene.prim2base(ball, angle_rad)).tolist(),
        "ball_centre0_m": centre0.tolist(),
        "encoder_offset_rad": math.atan2(float(local[1]), float(local[0])),
    }


def cell_with_scene(
    cfg: Config, scene: Scene, sensor2base_start: ArrayLike, **sensor_overrides: Any
) -> CellSpec:
    """The simulated cell of ``cfg`` with ``scene`` (:mod:`wristscan.drivers.sim.scenes_apps`)
    and the arm placed so that the sensor starts at ``sensor2base_start`` (a ``CellSpec``)."""
    spec = cell_spec(cfg, **sensor_overrides)
    ctl = spec.controller
    q = start_q_for_sensor(
        ctl.model, sensor2base_start, spec.sensor.sensor2flange_matrix(), ctl.initial_q
    )
    ctl = dataclasses.replace(ctl, initial_q=tuple(float(v) for v in q))
    return dataclasses.replace(spec, controller=ctl, scene=scene)


def write_truth_calibration(cfg: Config, spec: CellSpec) -> Path:
    """Write the simulated cell's true sensor2flange as the calibration file of ``cfg`` (as
    ``wristscan demo`` does), so that a procedure runs with a perfect calibration."""
    if cfg.calibration.file is None:
        raise ValueError(f"{cfg.source}: [calibration] file is not set")
    truth = {"sensor2flange": spec.sensor.sensor2flange_matrix()}
    return write_truth_calibrations(cfg, truth, method="ground truth of the simulated cell")[0]


def pairing_truth_tap(
    cfg: Config, sensor_info: dict[str, Any], controller_start_ns: int
) -> Acquisition:
    """An :class:`~wristscan.daemon.procedure.acquisition.Acquisition` on the simulated cell that
    also records what the latency ``calibrate latency`` should find, from the simulator's ground
    truth and the drivers' receipt stamps, independently of the synchroniser (its clock fits and
    pairing are never read):

    * every profile paired: its true exposure instant (the sensor's ``t0_ns + k * period_ns``,
      ``k`` = frame counter + ``counter_base``) and its receipt stamp;
    * every robot state the driver hands over: its true instant (``controller_start_ns`` plus
      its controller timestamp) and its receipt stamp.

    The synchroniser maps each device time onto the host clock through the smallest delay of
    its stream (docs/sync.md), so the latency that pairs each profile with the robot pose of its
    true exposure is the simulator's exposure-to-stamp delay plus the smallest delay from that
    stamp to the profile's receipt, less the smallest delay of the robot stream, plus the
    configured ``[sync] robot_latency_s``. :func:`truth_latency_parts` gives the parts,
    :func:`truth_offset_s` the sum. ``sensor_info`` is ``SimulatedSensor.info()``;
    ``controller_start_ns`` the host time of controller time 0.
    """
    return _TruthTap(cfg, sensor_info, controller_start_ns)


class _TruthTap(Acquisition):
    """The acquisition of :func:`pairing_truth_tap`."""

    def __init__(self, cfg: Config, sensor_info: dict[str, Any], controller_start_ns: int) -> None:
        super().__init__(cfg)
        self.t0_ns = int(sensor_info["t0_ns"])
        self.period_ns = float(sensor_info["period_ns"])
        self.counter_base = int(sensor_info["counter_base"])
        self.stamp_delay_ns = int(sensor_info["stamp_delay_ns"])
        self.controller_start_ns = int(controller_start_ns)
        self.robot_latency_s = float(cfg.sync.robot_latency_s)
        self.sensor_delays: list[NDArray[np.int64]] = []
        self.robot_rows: list[tuple[float, int]] = []
        robot = self.devices.robot
        read = robot.read
        rows = self.robot_rows

        def tapped(timeout: float | None = None) -> RobotState | None:
            state = read(timeout)
            if state is not None:
                rows.append((state.controller_time_s, state.host_time_ns))
            return state

        robot.read = tapped  # type: ignore[method-assign]

    def _offer(self, batch: PairedBatch) -> None:
        if batch.arrival_ns is not None:
            k = np.asarray(batch.frame_counter, dtype=np.int64) + self.counter_base
            # The simulator's own arithmetic for its exposure instants (truncated ns).
            exposure = self.t0_ns + (k * self.period_ns).astype(np.int64)
            stamp = exposure + self.stamp_delay_ns
            self.sensor_delays.append(np.asarray(batch.arrival_ns, dtype=np.int64) - stamp)
        super()._offer(batch)


def truth_latency_parts(acq: Acquisition) -> dict[str, float]:
    """The parts of the true latency from an acquisition of :func:`pairing_truth_tap` (s):
    ``stamp_delay_s`` (the simulator's exposure to device stamp), ``sensor_link_s`` (the
    smallest delay from that stamp to a profile's receipt), ``robot_link_s`` (the smallest delay
    from a robot state's true instant to its receipt), ``robot_latency_s`` (configured),
    ``latency_s`` (stamp delay + sensor link - robot link + robot latency), and the numbers of
    profiles and robot states they come from. NaN without data."""
    nan = float("nan")
    if not isinstance(acq, _TruthTap):
        return dict.fromkeys(
            ("stamp_delay_s", "sensor_link_s", "robot_link_s", "robot_latency_s", "latency_s"),
            nan,
        ) | {"profiles": 0.0, "robot_states": 0.0}
    delays = [d for d in acq.sensor_delays if d.size]
    sensor_link = float(min(int(d.min()) for d in delays)) * 1e-9 if delays else nan
    robot_link = nan
    if acq.robot_rows:
        r = np.array(acq.robot_rows, dtype=np.float64)
        true_ns = acq.controller_start_ns + np.rint(r[:, 0] * 1e9)
        robot_link = float(np.min(r[:, 1] - true_ns)) * 1e-9
    stamp = acq.stamp_delay_ns * 1e-9
    robot_latency = acq.robot_latency_s
    return {
        "stamp_delay_s": stamp,
        "sensor_link_s": sensor_link,
        "robot_link_s": robot_link,
        "robot_latency_s": robot_latency,
        "latency_s": stamp + sensor_link - robot_link + robot_latency,
        "profiles": float(sum(d.size for d in delays)),
        "robot_states": float(len(acq.robot_rows)),
    }


def truth_offset_s(acq: Acquisition, result: LatencyResult) -> float:
    """The latency (s) that ``result`` should have found, from an acquisition of
    :func:`pairing_truth_tap`: the simulator's exposure-to-stamp delay plus the measured link
    delays (:func:`truth_latency_parts`), over the whole acquisition. NaN without data or
    without sweeps in ``result``."""
    if not result.sweeps:
        return float("nan")
    return truth_latency_parts(acq)["latency_s"]


def jog_to_ball(cell: SimulatedCell, depth_m: float = 0.105) -> NDArray[np.float64]:
    """What the operator does before ``calibrate sensor``: the arm of the running ``cell`` set
    so that the laser line crosses the scene's ball, the sensor looking down from ``depth_m``
    above its centre. Returns the joints; ``RuntimeError`` when the simulated arm does not take
    them."""
    assert cell.controller is not None
    t = cell.truth()
    X = np.array(t["sensor2flange"])
    S = se3.make(se3.rot_x(np.pi) @ se3.rot_z(np.pi / 2), np.array(t["ball_centre_base_m"]))
    S[:3, 3] += [0.0, 0.0, depth_m]
    q = kinematics.inverse_nearest(
        cell.spec.controller.model, S @ se3.invert(X), np.radians([0, -90, 90, -90, -90, 0])
    )
    if not cell.controller.set_joint_positions(q.tolist()):
        raise RuntimeError("the simulated arm did not take the start pose")
    return np.asarray(q, dtype=np.float64)
