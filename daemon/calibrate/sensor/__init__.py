"""``wristscan calibrate sensor``: the sensor-to-flange calibration as a procedure at the cell.

A tooling ball of known radius stands in the workspace; the operator jogs the robot so that the
laser line crosses the ball. Then, with motion enabled and confirmed (automatic mode):

a. **find** - the ball's arc in the live profiles is fitted with a circle (is it a ball of this
   radius?), then one sweep along the sensor X axis from ``-(R + margin)`` to ``+(R + margin)``
   (the paper's ball matching) gives the ball centre through the *nominal* sensor2flange;
b. **fov** - at the start orientation, the ball is placed at a ``n x n`` grid of field-of-view
   locations in the laser plane (lateral ``+-(FOV/2 - R - margin)``, depth across the measuring
   range) and swept along sensor X at each (Borangiu et al. 2009, sec. 1: ball matching). Step 1
   of the paper's solution (:func:`wristscan.calib.handeye.solve_orientation`) then gives the
   rotation of sensor2flange;
c. **orient** - the sensor orbits the ball: a balanced set of ``>= 6`` orientations tilted by
   ``>= 45`` degrees from the start orientation at evenly spread azimuths (paper sec. 3: at least
   45 degrees between tool Z axes, and a balanced set covering the orientations used later),
   each reached by a retreat along sensor -Z, a joint move and a linear approach, and swept along
   its sensor X. Unreachable orientations are replaced (more tilt, a roll about the sensor Z) or
   skipped, and the report says so. After two orientations the sensor origin is estimated (step
   2) and the remaining ones are aimed with it;
d. **solve** - the paper's two-step solution (:func:`~wristscan.calib.handeye.two_step`) and the
   joint refinement of all six parameters and the ball centre on every point of every sweep
   (:func:`~wristscan.calib.handeye.refine`, covariance including the robot's repeatability);
e. **validate** - leave-one-out over the orientations (the spread of the estimates), a check scan
   at an orientation that was not used (sphere fit of its points mapped with the new calibration:
   centre against the calibrated ball centre, radius against the known one; in automatic mode it
   is swept right after stage c, aimed with the estimate, so the robot does not wait for the
   solution), and the apparent sensor time offset from sweeps in both directions;
f. the calibration file is written (atomically; nothing is written when the procedure fails or
   is stopped, so the calibration in force stays) and a report.

Sweeps are recorded while the robot moves: every profile is paired with the robot state at its
exposure by the synchroniser (:class:`wristscan.daemon.procedure.acquisition.Acquisition`),
so a sweep gives hundreds of profiles, not one stop-and-go sample. Each location is swept
forwards and backwards:
an error in the configured sensor latency shifts the ball by ``speed * error`` along the travel,
in opposite directions for the two passes. Its size is measured (:class:`ApparentLatency`),
each pair is re-timed by its own offset before the final solution (:func:`compensate_timing`),
and a place whose passes still disagree with the solution is left out
(:func:`inconsistent_locations`).

Manual mode records each sweep while the operator moves the robot from the teach pendant (press
Enter to start and to stop); no motion is commanded.

Everything here is plain functions and classes, one module per stage: :mod:`.plan` (settings,
the places and orientations to visit), :mod:`.reach` (what the robot can reach), :mod:`.collect`
(moving the robot and recording sweeps), :mod:`.automatic` and :mod:`.manual` (the two modes),
:mod:`.sweeps` (recorded sweeps), :mod:`.solve` (the solution and the timing compensation),
:mod:`.validate` (leave-one-out, check scan), :mod:`.result` (the calibration file),
:mod:`.report` and :mod:`.procedure` (:class:`SensorCalibration` and :func:`run`, which ties them
to a configuration and is what the command line calls). This package re-exports their public
names. Units are SI throughout (metres, radians, seconds).
"""

from wristscan.daemon.calibrate.sensor.collect import RobotCell, SweepRecorder
from wristscan.daemon.calibrate.sensor.errors import CalibrationAborted, CalibrationFailed
from wristscan.daemon.calibrate.sensor.manual import Prompt
from wristscan.daemon.calibrate.sensor.plan import (
    UR_REPEATABILITY_ISO9283_M,
    OrientationPlan,
    Settings,
    default_nominal,
    fov_targets,
    iso9283_axis_sigma,
    orbit_pose,
    plan_orientations,
    settings_for,
    z_axis_angles_deg,
)
from wristscan.daemon.calibrate.sensor.procedure import SensorCalibration, run
from wristscan.daemon.calibrate.sensor.report import build_report
from wristscan.daemon.calibrate.sensor.result import (
    COVARIANCE_PARAMETERS,
    METHOD,
    SensorCalibrationResult,
    calibration_of,
)
from wristscan.daemon.calibrate.sensor.solve import (
    ApparentLatency,
    apparent_latency,
    compensate_timing,
    inconsistent_locations,
    inlier_masks,
    location_offsets,
    observed_robot_sigma,
    quick_refine,
    retime,
    solve,
)
from wristscan.daemon.calibrate.sensor.sweeps import (
    RecordedSweep,
    SweepStage,
    ball_coverage,
    reduce_sweep,
    split_round_trip,
)
from wristscan.daemon.calibrate.sensor.validate import (
    CheckScan,
    LeaveOneOut,
    check_scan_fit,
    leave_one_out,
)
from wristscan.daemon.procedure.progress import Progress, ProgressEvent

__all__ = [
    "COVARIANCE_PARAMETERS",
    "METHOD",
    "UR_REPEATABILITY_ISO9283_M",
    "ApparentLatency",
    "CalibrationAborted",
    "CalibrationFailed",
    "CheckScan",
    "LeaveOneOut",
    "OrientationPlan",
    "Progress",
    "ProgressEvent",
    "Prompt",
    "RecordedSweep",
    "RobotCell",
    "SensorCalibration",
    "SensorCalibrationResult",
    "Settings",
    "SweepRecorder",
    "SweepStage",
    "apparent_latency",
    "ball_coverage",
    "build_report",
    "calibration_of",
    "check_scan_fit",
    "compensate_timing",
    "default_nominal",
    "fov_targets",
    "inconsistent_locations",
    "inlier_masks",
    "iso9283_axis_sigma",
    "leave_one_out",
    "location_offsets",
    "observed_robot_sigma",
    "orbit_pose",
    "plan_orientations",
    "quick_refine",
    "reduce_sweep",
    "retime",
    "run",
    "settings_for",
    "solve",
    "split_round_trip",
    "z_axis_angles_deg",
]
