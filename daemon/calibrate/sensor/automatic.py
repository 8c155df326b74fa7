"""The sensor calibration's automatic mode: the procedure moves the robot (stages a to c and the
check scan of e in the package's doc).

:class:`AutomaticCollection` finds the ball from the operator's start pose, sweeps it at the
field-of-view locations, finds the sensor rotation (step 1), then orbits the ball at the
planned orientations, aiming each one better as the sensor origin becomes known (step 2 on the
sweeps so far); :meth:`~AutomaticCollection.check` sweeps once more at an orientation the
solution did not use.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye, se3, sphere
from wristscan.daemon.calibrate.sensor.collect import SweepRecorder
from wristscan.daemon.calibrate.sensor.errors import CalibrationFailed
from wristscan.daemon.calibrate.sensor.plan import (
    OrientationPlan,
    Settings,
    fov_targets,
    plan_orientations,
    rotation_between,
    tx,
    tz,
)
from wristscan.daemon.calibrate.sensor.reach import Reachability, SweepReach
from wristscan.daemon.calibrate.sensor.solve import centre_at_start, origin_estimate
from wristscan.daemon.calibrate.sensor.sweeps import RecordedSweep, near_ball

__all__ = ["AutomaticCollection"]

FloatArray = NDArray[np.float64]

_BAND_WIDE_M = 8e-3
"""Points farther than this from the predicted ball surface are dropped while the sensor origin
is still the nominal one (clutter: the post, the table)."""
_BAND_NARROW_M = 4e-3
"""... and farther than this once the sensor origin has been estimated (step 2)."""

_Collected = tuple[list[RecordedSweep], list[OrientationPlan], FloatArray]


@dataclass(frozen=True)
class _Aim:
    """Sweep poses around the ball, as flange poses, for an estimate ``Xe`` of sensor2flange and
    ``ball`` of the ball centre: orientations relative to the start flange pose ``F0``, the ball
    at the working depth, sweeps of ``+-sweep_half_m`` along sensor X."""

    s: Settings
    F0: FloatArray
    kin: Reachability

    def clearance(self, Xe: FloatArray) -> FloatArray:
        """The approach pose is the sweep start moved back along sensor -Z, as a flange motion."""
        return np.asarray(Xe @ tz(-self.s.clearance_m) @ se3.invert(Xe))

    def ends(
        self, p: OrientationPlan, Xe: FloatArray, ball: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Start and end flange poses of the sweep at orientation ``p``."""
        h = self.s.sweep_half_m
        inv = se3.invert(Xe)
        Sc = p.sensor2base(self.F0 @ Xe, ball, self.s.working_depth_m)
        return Sc @ tx(-h) @ inv, Sc @ tx(h) @ inv

    def hub(self, Xe: FloatArray, ball: FloatArray) -> FloatArray:
        """Above the ball at the start orientation, well back: joint moves that would leave the
        workspace box go through here."""
        depth = self.s.working_depth_m
        Rref = (self.F0 @ Xe)[:3, :3]
        S = se3.make(Rref, ball - Rref @ np.array([0.0, 0.0, depth + 2 * self.s.clearance_m]))
        return np.asarray(S @ se3.invert(Xe))

    def reachable(
        self, Xe: FloatArray, ball: FloatArray, seed: FloatArray
    ) -> Callable[[OrientationPlan], bool]:
        """Whether the sweep of an orientation can be made from the joints ``seed``."""
        via = self.hub(Xe, ball)
        clear = self.clearance(Xe)
        return lambda p: self.kin.sweep(*self.ends(p, Xe, ball), clear, seed, via) is not None


class AutomaticCollection:
    """Stages a (find), b (fov) and c (orient) with the robot moved by the procedure, planned
    with the ``nominal`` sensor2flange; after :meth:`collect`, ``estimate`` is the sensor2flange
    the last orientations were aimed with (a start for the solution)."""

    def __init__(self, recorder: SweepRecorder, nominal: FloatArray) -> None:
        self.rec = recorder
        self.cell = recorder.cell
        self.s = recorder.s
        self.nominal = nominal
        self.estimate: FloatArray | None = None
        self._ball: FloatArray | None = None
        self._reference = np.eye(4)
        self._reference_q: FloatArray | None = None

    def collect(self) -> _Collected:
        """The sweeps (FOV first, then the tilted ones), the orientations visited and the start
        flange pose (the FOV stage's orientation)."""
        s = self.s
        X = self.nominal
        q_start = self.cell.joints()
        ball, F0 = self._find(X)
        aim = _Aim(s, F0, self.cell.planner(q_start))
        plan = self._fov_plan(aim.kin, F0, X, ball)
        # A first look at the orientations with the nominal tool: fail before the long stage.
        pre, _ = plan_orientations(s, aim.reachable(X, ball, self.cell.joints()))
        if len(pre) < 2:
            raise CalibrationFailed(
                f"only {len(pre)} of {s.n_orientations} orientations around the ball are "
                "reachable: move the ball (or the robot's start pose) towards the middle of the "
                "workspace, or lower --tilt-deg"
            )
        total = len(plan) + len(pre)
        self.rec.say(
            "plan",
            f"{len(plan)} field-of-view locations and {len(pre)} orientations "
            f"({'both directions' if s.bidirectional else 'one direction'}, "
            f"{s.sweep_speed_m_s * 1e3:g} mm/s)",
        )
        sweeps = self._fov_stage(plan, X, ball, total)
        ori, Xe, ball = self._step_one(sweeps, X)
        tilt_sweeps, visited, Xe = self._orient_stage(aim, sweeps, ori, Xe, ball, len(plan), total)
        if len(visited) < 2:
            raise CalibrationFailed(
                f"only {len(visited)} orientations could be swept; at least 2 are needed"
            )
        self._reference = F0
        self._reference_q = q_start
        self.estimate = Xe
        self._ball = ball
        return [*sweeps, *tilt_sweeps], visited, F0

    # --- (a) find ----------------------------------------------------------------------------
    def _find(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(a): the ball in view? Its centre in base through ``X``; returns it and the start
        flange pose (the reference orientation)."""
        s = self.s
        R = s.ball_radius_m
        self.cell.check_safety()
        F0 = self.cell.flange2base()
        data = self.cell.record_for(0.3)
        ok = data.valid & np.isfinite(data.y) & np.isfinite(data.z)
        yz = np.column_stack([data.y[ok], data.z[ok]])
        if yz.shape[0] < 20:
            raise CalibrationFailed(
                "the sensor sees nothing: jog the robot so that the laser line crosses the ball "
                f"at {s.depth_min_m * 1e3:.0f}-{s.depth_max_m * 1e3:.0f} mm"
            )
        try:
            circle = sphere.fit_circle(yz[-20000:], radius=None, robust="tukey")
        except ValueError:
            circle = None
        if circle is None or circle.n_inliers < 20 or circle.radius > 1.1 * R:
            got = "no arc" if circle is None else f"an arc of radius {circle.radius * 1e3:.1f} mm"
            raise CalibrationFailed(
                f"the sensor sees {got}, not a ball of radius {R * 1e3:.2f} mm: jog the robot so "
                "that the laser line crosses the ball (or check --ball-radius-mm)"
            )
        if not circle.plausible:
            # Clutter beside a short arc (a box corner, the ball's stand) fits a wrong circle.
            raise CalibrationFailed(
                f"the arc in view is not the ball's ({circle.why}): jog the robot so that the "
                "laser line crosses the ball away from other objects"
            )
        self.rec.say(
            "find",
            f"ball arc in view: radius {circle.radius * 1e3:.2f} mm at y "
            f"{circle.centre[0] * 1e3:+.1f} mm, z {circle.centre[1] * 1e3:.1f} mm",
        )
        S0 = F0 @ X
        h = s.sweep_half_m
        invX = se3.invert(X)
        start, end = S0 @ tx(-h) @ invX, S0 @ tx(h) @ invX
        self.rec.say("find", f"sweep across the ball along sensor X (+-{h * 1e3:.1f} mm)")
        self.cell.move_l(start, s.travel_speed_m_s, s.travel_accel_m_s2)
        # The ball may sit up to R off the plane: this sweep may see only part of it.
        rs = self.rec.sweep(start, end, "find", 0, 0, 1, "find sweep", coverage=False)
        pts = handeye.sweep_points_at_start(rs.sweep, X[:3, :3])
        try:
            fit = sphere.fit_sphere(pts, radius=R, robust="tukey")
        except ValueError as exc:
            raise CalibrationFailed(
                f"the ball could not be fitted in the find sweep: {exc}"
            ) from None
        c = rs.sweep.flange2base[0] @ X @ np.append(fit.centre, 1.0)
        self.rec.say(
            "find", f"ball centre (nominal tool) at {np.round(c[:3] * 1e3, 1).tolist()} mm"
        )
        return np.asarray(c[:3]), F0

    # --- (b) field of view -------------------------------------------------------------------
    def _fov_plan(
        self, kin: Reachability, F0: FloatArray, X: FloatArray, ball: FloatArray
    ) -> list[tuple[FloatArray, FloatArray, FloatArray]]:
        """The field-of-view locations at the start orientation: (ball in the sensor frame,
        sweep start, sweep end); :class:`CalibrationFailed` when one is out of reach."""
        h = self.s.sweep_half_m
        Rref = (F0 @ X)[:3, :3]
        plan: list[tuple[FloatArray, FloatArray, FloatArray]] = []
        q = self.cell.joints()
        invX = se3.invert(X)
        for g in fov_targets(self.s):
            Sc = se3.make(Rref, ball - Rref @ g)
            start, end = Sc @ tx(-h) @ invX, Sc @ tx(h) @ invX
            q_at = kin.ik(start, q)
            q_end = None if q_at is None else kin.linear(start, end, q_at)
            if q_end is None:
                raise CalibrationFailed(
                    f"field-of-view location y {g[1] * 1e3:+.1f} mm, z {g[2] * 1e3:.1f} mm is out "
                    "of reach or outside the workspace box: jog the robot to a more central pose"
                )
            q = q_end
            plan.append((g, start, end))
        return plan

    def _fov_stage(
        self,
        plan: list[tuple[FloatArray, FloatArray, FloatArray]],
        X: FloatArray,
        ball: FloatArray,
        total: int,
    ) -> list[RecordedSweep]:
        """(b): every field-of-view location swept (both ways when bidirectional)."""
        s = self.s
        sweeps: list[RecordedSweep] = []
        keep = near_ball(X, ball, s.ball_radius_m, _BAND_WIDE_M)
        for k, (g, start, end) in enumerate(plan):
            loc = self.rec.next_location()
            name = f"fov {k + 1} (y {g[1] * 1e3:+.0f}, z {g[2] * 1e3:.0f} mm)"
            self.rec.say("fov", name, k + 1, total)
            self.cell.move_l(start, s.travel_speed_m_s, s.travel_accel_m_s2)
            sweeps.append(self.rec.sweep(start, end, "fov", 0, loc, 1, f"{name} fwd", keep))
            if s.bidirectional:
                sweeps.append(self.rec.sweep(end, start, "fov", 0, loc, -1, f"{name} bwd", keep))
        return sweeps

    def _step_one(
        self, sweeps: list[RecordedSweep], X: FloatArray
    ) -> tuple[handeye.OrientationSolution, FloatArray, FloatArray]:
        """Step 1 (ball matching) on the FOV sweeps: the solution, sensor2flange with its
        rotation and the nominal origin, and the ball centre in base through it."""
        try:
            # A few iterations are enough to aim the orientations; the solution comes later.
            ori = handeye.solve_orientation(
                [w.for_solver() for w in sweeps], self.s.ball_radius_m, max_iter=4
            )
        except (handeye.PoorlyConstrained, ValueError) as exc:
            raise CalibrationFailed(f"step 1 (ball matching) failed: {exc}") from None
        Xe = se3.make(ori.rotation, X[:3, 3])
        in_base = [
            w.for_solver().flange2base[0] @ Xe @ np.append(c, 1.0)
            for w, c in zip(sweeps, ori.centres_sensor, strict=True)
        ]
        ball = np.mean(np.array(in_base)[:, :3], axis=0)
        self.rec.wait_for_data(quiet=True)
        self.rec.say(
            "fov",
            f"sensor rotation found (step 1), {math.degrees(rotation_between(Xe, X)):.2f} deg "
            "from the nominal",
        )
        return ori, Xe, ball

    # --- (c) orientations around the ball ----------------------------------------------------
    def _orient_stage(
        self,
        aim: _Aim,
        fov_sweeps: list[RecordedSweep],
        ori: handeye.OrientationSolution,
        Xe: FloatArray,
        ball: FloatArray,
        n_fov: int,
        total: int,
    ) -> tuple[list[RecordedSweep], list[OrientationPlan], FloatArray]:
        """(c): the tilted orientations swept; returns their sweeps, the orientations visited
        and the sensor2flange estimate after the last one."""
        s = self.s
        S_now = self.cell.flange2base() @ Xe
        self.cell.move_l(
            S_now @ tz(-s.clearance_m) @ se3.invert(Xe), s.travel_speed_m_s, s.travel_accel_m_s2
        )
        plans, notes = plan_orientations(s, aim.reachable(Xe, ball, self.cell.joints()))
        for n in notes:
            self.rec.note("orient", n)
        centres = list(ori.centres_sensor)
        visited: list[OrientationPlan] = []
        tilt_sweeps: list[RecordedSweep] = []
        band = _BAND_WIDE_M
        for j, p in enumerate(plans):
            self.rec.say(
                "orient",
                f"{p.label}, tilt {p.tilt_deg:.0f} deg, roll {p.roll_deg:.0f} deg",
                n_fov + j + 1,
                total,
            )
            got = self._visit(aim, p, j + 1, Xe, ball, band)
            if got is None:
                continue
            tilt_sweeps += got
            visited.append(p)
            centres += [centre_at_start(w, ori.rotation, s.ball_radius_m) for w in got]
            if len(visited) >= 2:
                # Step 2 with what is there aims the remaining orientations better.
                est = origin_estimate([*fov_sweeps, *tilt_sweeps], ori.rotation, centres)
                if est is not None:
                    Xe = se3.make(ori.rotation, est[0])
                    ball = est[1]
                    band = _BAND_NARROW_M
                self.rec.wait_for_data(quiet=True)
        return tilt_sweeps, visited, Xe

    def _visit(
        self,
        aim: _Aim,
        p: OrientationPlan,
        group: int,
        Xe: FloatArray,
        ball: FloatArray,
        band: float,
    ) -> list[RecordedSweep] | None:
        """One orientation: reach it, sweep its places, retreat. None (and a note) when it is
        unreachable with the current estimate."""
        s = self.s
        start, end = aim.ends(p, Xe, ball)
        r = aim.kin.sweep(start, end, aim.clearance(Xe), self.cell.joints(), aim.hub(Xe, ball))
        if r is None:
            self.rec.note("orient", f"{p.label}: unreachable with the updated estimate; skipped")
            return None
        if r.via is not None:
            self.cell.move_j(r.via, s.joint_speed_rad_s, s.joint_accel_rad_s2)
        self.cell.move_j(r.approach, s.joint_speed_rad_s, s.joint_accel_rad_s2)
        self.cell.move_l(start, s.travel_speed_m_s, s.travel_accel_m_s2)
        keep = near_ball(Xe, ball, s.ball_radius_m, band)
        places = self._places(aim, (p, start, end), r, Xe, ball)
        out, last = self._sweep_places(places, group, keep)
        self.cell.move_l(last @ aim.clearance(Xe), s.travel_speed_m_s, s.travel_accel_m_s2)
        return out

    def _places(
        self,
        aim: _Aim,
        first: tuple[OrientationPlan, FloatArray, FloatArray],
        r: SweepReach,
        Xe: FloatArray,
        ball: FloatArray,
    ) -> list[tuple[OrientationPlan, FloatArray, FloatArray]]:
        """The places of the ball along the laser line at an orientation: ``first`` (plan, sweep
        start, sweep end; reached as ``r``) and, with two lateral places, the other end of the
        line when it can be reached from there."""
        p, start, _ = first
        places = [first]
        if self.s.lateral_places == 2:
            # The same orientation with the ball at the other end of the laser line: reached
            # by a lateral move at the sweep start, where the laser plane is clear of the ball.
            p2 = dataclasses.replace(p, lateral_m=-p.lateral_m)
            start2, end2 = aim.ends(p2, Xe, ball)
            q2 = aim.kin.linear(start, start2, r.start)
            if q2 is not None and aim.kin.linear(start2, end2, q2) is not None:
                places.append((p2, start2, end2))
            else:
                self.rec.note("orient", f"{p.label}: the second lateral place is unreachable")
        return places

    def _sweep_places(
        self,
        places: list[tuple[OrientationPlan, FloatArray, FloatArray]],
        group: int,
        keep: Callable[[handeye.Sweep], NDArray[np.bool_]],
    ) -> tuple[list[RecordedSweep], FloatArray]:
        """Sweep each place (the robot stands at the first one's start); returns the sweeps and
        the flange pose the robot ends at."""
        s = self.s
        out: list[RecordedSweep] = []
        last = places[0][1]
        for k, (pk, a, b) in enumerate(places):
            if k:
                self.cell.move_l(a, s.travel_speed_m_s, s.travel_accel_m_s2)
            loc = self.rec.next_location()
            name = f"{pk.label} y {pk.lateral_m * 1e3:+.0f} mm"
            out.append(self.rec.sweep(a, b, "tilt", group, loc, 1, f"{name} fwd", keep))
            last = b
            if s.bidirectional:
                out.append(self.rec.sweep(b, a, "tilt", group, loc, -1, f"{name} bwd", keep))
                last = a
            elif k + 1 < len(places):
                self.cell.move_l(a, s.travel_speed_m_s, s.travel_accel_m_s2)
                last = a
        return out, last

    # --- (e) check scan ----------------------------------------------------------------------
    def check(self, joint: handeye.HandEyeResult | None) -> list[RecordedSweep]:
        """(e) a sweep at an orientation the solution did not use, aimed with ``joint`` or (None)
        with the estimate the last orientations were aimed with: then it is swept before the
        solution is computed, and the robot does not wait for it."""
        s = self.s
        if joint is not None:
            X, ball = joint.sensor2flange, np.asarray(joint.ball_centre_base)
        elif self.estimate is not None and self._ball is not None:
            X, ball = self.estimate, self._ball
        else:
            return []
        F0 = self._reference
        kin = self.cell.planner(self._reference_q)
        inv = se3.invert(X)
        clear = X @ tz(-s.clearance_m) @ inv
        h = s.sweep_half_m
        for az, tilt, roll in ((30.0, 25.0, 45.0), (210.0, 25.0, 45.0), (90.0, 20.0, -45.0)):
            p = OrientationPlan(f"check (az {az:.0f} deg)", az, tilt, roll)
            Sc = p.sensor2base(F0 @ X, ball, s.working_depth_m)
            start, end = Sc @ tx(-h) @ inv, Sc @ tx(h) @ inv
            Rref = (F0 @ X)[:3, :3]
            via = (
                se3.make(
                    Rref, ball - Rref @ np.array([0.0, 0.0, s.working_depth_m + 2 * s.clearance_m])
                )
                @ inv
            )
            r = kin.sweep(start, end, clear, self.cell.joints(), via)
            if r is not None:
                break
        else:
            self.rec.note("check", "no reachable orientation for the check scan; skipped")
            return []
        self.rec.say("check", f"check scan: {p.label}, tilt {tilt:.0f} deg, roll {roll:.0f} deg")
        if r.via is not None:
            self.cell.move_j(r.via, s.joint_speed_rad_s, s.joint_accel_rad_s2)
        self.cell.move_j(r.approach, s.joint_speed_rad_s, s.joint_accel_rad_s2)
        self.cell.move_l(start, s.travel_speed_m_s, s.travel_accel_m_s2)
        keep = near_ball(X, ball, s.ball_radius_m, 3e-3)
        loc = self.rec.next_location()
        out = [self.rec.sweep(start, end, "check", -1, loc, 1, f"{p.label} fwd", keep)]
        last = end
        if s.bidirectional:
            out.append(self.rec.sweep(end, start, "check", -1, loc, -1, f"{p.label} bwd", keep))
            last = start
        self.cell.move_l(last @ clear, s.travel_speed_m_s, s.travel_accel_m_s2)
        return out
