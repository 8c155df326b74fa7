"""The sensor calibration's manual mode: each sweep is recorded while the operator moves the
robot from the teach pendant (Enter starts and stops the recording); the procedure commands no
motion. A sweep across the ball and back becomes a forward/backward pair.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from wristscan.calib import handeye, se3
from wristscan.daemon.calibrate.sensor.collect import MAX_GAP_R, SweepRecorder
from wristscan.daemon.calibrate.sensor.errors import CalibrationAborted, CalibrationFailed
from wristscan.daemon.calibrate.sensor.plan import OrientationPlan, fov_targets, rotation_between
from wristscan.daemon.calibrate.sensor.sweeps import (
    RecordedSweep,
    SweepStage,
    ball_coverage,
    relabel,
    split_round_trip,
)

__all__ = ["ManualCollection", "Prompt"]

FloatArray = NDArray[np.float64]

Prompt = Callable[[str], str]
"""Shows the operator a message and returns the answer (``input``)."""

_ORIENTATION_TOL_RAD = 2e-3


class ManualCollection:
    """Stages b (fov) and c (orient) and the check scan, each sweep made by the operator and
    recorded through ``recorder``; ``prompt`` asks the operator (``q``/``quit``/``abort``
    stops the procedure)."""

    estimate: FloatArray | None = None
    """No sensor2flange estimate comes out of manual collection."""

    def __init__(self, recorder: SweepRecorder, prompt: Prompt) -> None:
        self.rec = recorder
        self.s = recorder.s
        self.prompt = prompt

    def _ask(self, message: str) -> str:
        answer = self.prompt(message).strip().lower()
        if answer in ("q", "quit", "abort"):
            raise CalibrationAborted("stopped by the operator")
        return answer

    def _manual_sweep(
        self, stage: SweepStage, group: int, label: str, instruction: str
    ) -> list[RecordedSweep] | None:
        """Record one operator-driven sweep; None when the operator ends the stage. A sweep
        across the ball and back becomes a forward/backward pair. A recording without the ball,
        with gaps (profiles not paired), over less than the ball's radius or with its orientation
        changing is rejected and asked for again."""
        while True:
            answer = self._ask(
                f"{label}: {instruction} Press Enter to start recording ('done' ends this stage, "
                "'quit' aborts)."
            )
            if answer in ("d", "done", "s", "skip"):
                return None
            data, _ = self.rec.cell.record_while(
                lambda: self._ask(
                    "Recording: move the sensor along its X axis across the ball and back, at "
                    "constant orientation (there and back cancels a latency error), then press "
                    "Enter."
                )
            )
            legs = split_round_trip(data)
            loc = self.rec.next_location()
            out: list[RecordedSweep] = []
            why = ""
            for leg, direction in zip(legs, (1, -1) if len(legs) == 2 else (0,), strict=True):
                name = label if direction == 0 else f"{label} {'fwd' if direction > 0 else 'bwd'}"
                try:
                    rs = self.rec.reduce(leg, stage, group, loc, direction, name)
                except CalibrationFailed as exc:
                    why = str(exc).removeprefix(name + ": ")
                    break
                why = self._rejection(rs)
                if why:
                    break
                out.append(rs)
            if why:
                self.rec.say(stage, f"rejected: {why}; repeat it")
                continue
            return out

    def _rejection(self, rs: RecordedSweep) -> str:
        """Why a recorded pass cannot be used ("" when it can): the ball seen over too little
        of the travel or with gaps, or the orientation changed during it."""
        R = self.s.ball_radius_m
        span, gap = ball_coverage(rs)
        if span < R or gap > MAX_GAP_R * R:
            return (
                f"the ball was seen over {span * 1e3:.1f} mm of travel with a "
                f"{gap * 1e3:.1f} mm gap; sweep across the whole ball"
            )
        if self._constant_orientation(rs) > _ORIENTATION_TOL_RAD:
            return "the orientation changed during the sweep"
        return ""

    def _constant_orientation(self, rs: RecordedSweep) -> float:
        R = rs.sweep.flange2base[:, :3, :3]
        return float(np.max(se3.rotation_angle(np.swapaxes(R[:1], -1, -2) @ R)))

    def collect(self) -> tuple[list[RecordedSweep], list[OrientationPlan], FloatArray]:
        """The sweeps (FOV first, then the tilted ones), the orientations recorded and the flange
        pose of the first FOV sweep (the FOV stage's orientation)."""
        sweeps, ref = self._fov_stage()
        tilts, plans = self._orient_stage(ref)
        return [*sweeps, *tilts], plans, ref

    def _fov_stage(self) -> tuple[list[RecordedSweep], FloatArray]:
        h = self.s.sweep_half_m
        targets = fov_targets(self.s)
        sweeps: list[RecordedSweep] = []
        ref: FloatArray | None = None
        k = 0
        self.rec.say(
            "fov",
            "manual mode: move the robot from the teach pendant; keep one "
            "orientation for the whole field-of-view stage",
        )
        while k < len(targets):
            g = targets[k]
            label = f"fov {k + 1}/{len(targets)}"
            self.rec.say("fov", label, k + 1, len(targets))
            got = self._manual_sweep(
                "fov",
                0,
                label,
                f"place the ball at about y {g[1] * 1e3:+.0f} mm, z {g[2] * 1e3:.0f} mm in the "
                f"laser plane, then move {h * 1e3:.0f} mm back along the sensor X axis.",
            )
            if got is None:
                if k >= 3:
                    break
                self.rec.say("fov", "at least 3 field-of-view sweeps are needed")
                continue
            F = got[0].sweep.flange2base[0]
            if ref is not None and rotation_between(F, ref) > _ORIENTATION_TOL_RAD:
                self.rec.say(
                    "fov", "rejected: the orientation differs from the first sweep's; repeat it"
                )
                continue
            ref = F if ref is None else ref
            sweeps += [relabel(w, f"fov {k + 1}") for w in got]
            k += 1
        assert ref is not None
        return sweeps, ref

    def _orient_stage(self, ref: FloatArray) -> tuple[list[RecordedSweep], list[OrientationPlan]]:
        s = self.s
        tilts: list[RecordedSweep] = []
        plans: list[OrientationPlan] = []
        j = 0
        while j < s.n_orientations:
            label = f"orientation {j + 1}/{s.n_orientations}"
            self.rec.say("orient", label, j + 1, s.n_orientations)
            got = self._manual_sweep(
                "tilt",
                j + 1,
                label,
                f"tilt the sensor by at least {s.min_tilt_deg:.0f} deg from the previous "
                "orientations (spread the tilts around the ball), keep the ball in view and "
                f"move {s.sweep_half_m * 1e3:.0f} mm back along the sensor X axis.",
            )
            if got is None:
                if j >= 2:
                    break
                self.rec.say("orient", "at least 2 tilted orientations are needed")
                continue
            tilt = math.degrees(rotation_between(got[0].sweep.flange2base[0], ref))
            tilts += [relabel(w, f"orientation {j + 1}") for w in got]
            plans.append(OrientationPlan(f"orientation {j + 1}", float("nan"), tilt, 0.0))
            j += 1
        return tilts, plans

    def check(self, joint: handeye.HandEyeResult | None) -> list[RecordedSweep]:
        """The check scan at an orientation of the operator's choice ([] when skipped)."""
        del joint
        got = self._manual_sweep(
            "check",
            -1,
            "check scan",
            "choose an orientation not used so far, put the ball in view and move "
            f"{self.s.sweep_half_m * 1e3:.0f} mm back along the sensor X axis ('done' skips the "
            "check).",
        )
        return [] if got is None else got
