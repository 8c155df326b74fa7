"""Replay a learned edge path with another tool (``wristscan teach replay``; Borangiu et al.
2009, section 5: "the robot can use the tool specific to the technological operation needed,
change the tool transformation matrix to the one for the physical tool, and replay the learned
path with high accuracy").

The learned path (:mod:`.edge`, its file :mod:`.edge_path`) is a list of edge points in the base
frame with the edge tangent and the surface normal at each. For a tool - a dispenser, a deburring
spindle, a torch, given by its tool transformation (the TCP as a UR pose in the flange frame) - each
point becomes a TCP pose:

* the tool's Z axis points into the surface (``-normal``), its X axis along the path;
* ``lead_rad`` tilts the tool about its Y axis (travel angle: positive leans the tool's tip
  back, so the tool pushes forward along the path), ``tilt_rad`` about the path (work angle);
* the tool tip sits ``offset_m`` off the edge along the normal (a dispensing gap).

Waypoints closer to the straight line between their neighbours than ``tolerance_m`` are dropped
(Douglas-Peucker on the positions, keeping every point where the orientation has turned by more
than ``angle_tolerance_rad`` since the last one kept). The rest are written as JSON and CSV, and
as a URScript program::

    def wristscan_replay():
      set_tcp(p[tool])
      movej(p[approach], a, v)        # joint move to approach_m above the first point
      movel(p[first], a, v)           # down along the normal
      movel(p[w_i], a, v, r=r_i)      # the path, blended (or movep)
      movel(p[retract], a, v)         # up along the normal
    end

Blend radii are ``min(blend_m, 0.45 x the shorter neighbouring segment)`` (UR refuses blends
that overlap), zero at the last point. :func:`run_program` sends the program to the robot's
script port (30003), follows it through the robot state stream and stops it (dashboard
``stop``) on Ctrl-C or a timeout.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import socket
import time
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wristscan.calib import kinematics, se3
from wristscan.daemon.config import Config
from wristscan.daemon.io.atomic import write_atomic
from wristscan.daemon.io.urpose import parse_ur_pose, ur_pose_text
from wristscan.daemon.procedure.errors import ProcedureError
from wristscan.daemon.procedure.progress import Progress, stage_reporter

if TYPE_CHECKING:
    from wristscan.daemon.teach.edge_path import LearnedPath
__all__ = [
    "ReplayError",
    "ReplayOptions",
    "ReplayPlan",
    "ToolDef",
    "dashboard_command",
    "load_tool",
    "plan_replay",
    "run_program",
    "send_script",
    "simplify",
    "tool_poses",
    "write_csv",
    "write_script",
    "write_waypoints",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

SCRIPT_PORT = 30003
DASHBOARD_PORT = 29999
WAYPOINTS_FORMAT = "wristscan-replay"


class ReplayError(ProcedureError):
    """The path cannot be replayed with this tool, or the run failed."""


# --------------------------------------------------------------------------------------------
# Tools and options


@dataclass(frozen=True)
class ToolDef:
    """A tool: its TCP in the flange frame (UR pose, m and rad) and its own replay settings."""

    name: str
    tcp: FloatArray
    settings: Mapping[str, Any] = field(default_factory=dict)


def load_tool(spec: str, tools_file: str | Path | None = None) -> ToolDef:
    """A tool from ``"p[...]"`` or from a name in a tools file (TOML ``[tools.<name>]`` with
    ``tcp = [x, y, z, rx, ry, rz]`` and optional :class:`ReplayOptions` fields). ValueError
    with a clear message otherwise."""
    if spec.strip().startswith(("p[", "[")):
        return ToolDef("tool", parse_ur_pose(spec))
    if tools_file is None:
        raise ValueError(f"--tool {spec!r} is not a UR pose p[...]; name a tool with --tools FILE")
    path = Path(tools_file)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"cannot read the tools file {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: {exc}") from None
    table = doc.get("tools", doc)
    if not isinstance(table, dict) or spec not in table or not isinstance(table[spec], dict):
        names = ", ".join(sorted(k for k, v in table.items() if isinstance(v, dict)))
        raise ValueError(f"{path}: no tool {spec!r} (tools: {names or 'none'})")
    entry = dict(table[spec])
    if "tcp" not in entry:
        raise ValueError(f"{path}: tool {spec!r} needs tcp = [x, y, z, rx, ry, rz]")
    tcp = parse_ur_pose(str(list(entry.pop("tcp"))))
    known = {f.name for f in fields(ReplayOptions)}
    unknown = sorted(set(entry) - known)
    if unknown:
        raise ValueError(f"{path}: tool {spec!r}: unknown setting(s) {', '.join(unknown)}")
    return ToolDef(spec, tcp, entry)


@dataclass(frozen=True)
class ReplayOptions:
    """How the path is replayed (SI units)."""

    offset_m: float = 0.0
    lead_rad: float = 0.0
    tilt_rad: float = 0.0
    speed_m_s: float = 0.02
    accel_m_s2: float = 0.5
    blend_m: float = 0.001
    tolerance_m: float = 2e-5
    angle_tolerance_rad: float = math.radians(1.0)
    approach_m: float = 0.02
    approach_speed_m_s: float = 0.05
    joint_speed_rad_s: float = 0.5
    joint_accel_rad_s2: float = 1.0
    move: str = "movel"

    def __post_init__(self) -> None:
        for name in ("speed_m_s", "accel_m_s2", "approach_speed_m_s", "joint_speed_rad_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        for name in ("blend_m", "tolerance_m", "approach_m", "angle_tolerance_rad"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        if abs(self.lead_rad) >= math.pi / 2 or abs(self.tilt_rad) >= math.pi / 2:
            raise ValueError("lead and tilt angles must be within +-90 degrees")
        if self.move not in ("movel", "movep"):
            raise ValueError("move must be movel or movep")

    @classmethod
    def from_tool(cls, tool: ToolDef, **overrides: Any) -> ReplayOptions:
        """Defaults, then the tool's settings, then ``overrides``."""
        kw: dict[str, Any] = {**dict(tool.settings), **overrides}
        try:
            return cls(**kw)
        except TypeError as exc:
            raise ValueError(str(exc)) from None


# --------------------------------------------------------------------------------------------
# Poses


def tool_poses(
    points: ArrayLike,
    tangents: ArrayLike,
    normals: ArrayLike,
    *,
    offset_m: float = 0.0,
    lead_rad: float = 0.0,
    tilt_rad: float = 0.0,
) -> FloatArray:
    """``tcp2base (K, 4, 4)`` of the tool along the path (see the module doc)."""
    P = np.asarray(points, dtype=np.float64)
    T = np.asarray(tangents, dtype=np.float64)
    N = np.asarray(normals, dtype=np.float64)
    z = -N / np.linalg.norm(N, axis=1, keepdims=True)
    x = T - np.einsum("ij,ij->i", T, z)[:, None] * z
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=-1)  # columns
    R = R @ se3.rot_x(tilt_rad) @ se3.rot_y(lead_rad)
    out = np.broadcast_to(np.eye(4), (P.shape[0], 4, 4)).copy()
    out[:, :3, :3] = R
    out[:, :3, 3] = P - offset_m * z
    return out


def simplify(poses: FloatArray, tolerance_m: float, angle_tolerance_rad: float) -> list[int]:
    """Indices of the waypoints kept (first and last always; module doc)."""
    n = poses.shape[0]
    if n <= 2 or tolerance_m <= 0:
        return list(range(n))
    P = poses[:, :3, 3]
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        ab = P[b] - P[a]
        L2 = float(ab @ ab)
        rel = P[a + 1 : b] - P[a]
        if L2 > 0:
            t = np.clip(rel @ ab / L2, 0.0, 1.0)
            dist = np.linalg.norm(rel - t[:, None] * ab, axis=1)
        else:
            dist = np.linalg.norm(rel, axis=1)
        k = int(np.argmax(dist))
        if float(dist[k]) > tolerance_m:
            m = a + 1 + k
            keep[m] = True
            stack += [(a, m), (m, b)]
    if angle_tolerance_rad > 0:
        last = 0
        for i in range(1, n):
            if keep[i]:
                last = i
                continue
            ang = se3.rotation_angle(poses[last, :3, :3].T @ poses[i, :3, :3])
            if float(ang) > angle_tolerance_rad:
                keep[i] = True
                last = i
    return [int(i) for i in np.flatnonzero(keep)]


@dataclass(frozen=True)
class ReplayPlan:
    """The tool poses to replay and the program that does it."""

    tool: FloatArray
    """(6,) TCP in the flange frame (UR pose)."""
    poses: FloatArray
    """(K, 4, 4) tcp2base of the waypoints kept."""
    normals: FloatArray
    """(K, 3) surface normals at the waypoints."""
    blends_m: FloatArray
    """(K,) blend radius at each waypoint."""
    edge_points: FloatArray
    """(K, 3) the learned edge points of the waypoints."""
    options: ReplayOptions
    n_path_points: int
    source: str = ""
    q: FloatArray | None = None
    """(K, 6) joint positions along the path when a robot model was known."""

    @property
    def ur_poses(self) -> FloatArray:
        return np.asarray(se3.matrix_to_pose(self.poses))

    def approach_pose(self, index: int) -> FloatArray:
        T = self.poses[index].copy()
        T[:3, 3] += self.options.approach_m * self.normals[index]
        return np.asarray(T)

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.poses[:, :3, 3], axis=0), axis=1).sum())

    def script(self, name: str = "wristscan_replay") -> str:
        o = self.options
        fmt = ur_pose_text
        lines = [
            f"def {name}():",
            f"  # wristscan teach replay: {self.poses.shape[0]} waypoints "
            f"({self.n_path_points} learned), {self.length_m * 1e3:.1f} mm",
            f"  # from {self.source or 'a learned path'}",
            f"  set_tcp({_pose_text(self.tool)})",
            f"  movej({_pose_text(se3.matrix_to_pose(self.approach_pose(0)))}, "
            f"a={o.joint_accel_rad_s2:g}, v={o.joint_speed_rad_s:g})",
            f"  movel({_pose_text(self.ur_poses[0])}, a={o.accel_m_s2:g}, "
            f"v={o.approach_speed_m_s:g})",
        ]
        for pose, r in zip(self.ur_poses[1:], self.blends_m[1:], strict=True):
            lines.append(
                f"  {o.move}({_pose_text(pose)}, a={o.accel_m_s2:g}, v={o.speed_m_s:g}, r={r:.6f})"
            )
        lines += [
            f"  movel({_pose_text(se3.matrix_to_pose(self.approach_pose(-1)))}, "
            f"a={o.accel_m_s2:g}, v={o.approach_speed_m_s:g})",
            "end",
            "",
        ]
        del fmt
        return "\n".join(lines)

    def summary_lines(self) -> list[str]:
        o = self.options
        return [
            f"replay        {self.poses.shape[0]} waypoints of {self.n_path_points} learned "
            f"points, {self.length_m * 1e3:.1f} mm at {o.speed_m_s * 1e3:g} mm/s ({o.move}, "
            f"blends up to {o.blend_m * 1e3:g} mm)",
            f"  tool        {ur_pose_text(self.tool)}; tip {o.offset_m * 1e3:g} mm off the "
            f"edge, lead {math.degrees(o.lead_rad):g} deg, tilt {math.degrees(o.tilt_rad):g} deg",
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": WAYPOINTS_FORMAT,
            "version": 1,
            "frame": "base",
            "source": self.source,
            "tool_ur_pose": self.tool.tolist(),
            "options": {k: getattr(self.options, k) for k in self.options.__dataclass_fields__},
            "waypoints": [
                {
                    "tcp_ur_pose": p.tolist(),
                    "edge_point_m": e.tolist(),
                    "normal": n.tolist(),
                    "blend_m": float(r),
                    **({"q_rad": self.q[i].tolist()} if self.q is not None else {}),
                }
                for i, (p, e, n, r) in enumerate(
                    zip(self.ur_poses, self.edge_points, self.normals, self.blends_m, strict=True)
                )
            ],
        }


def _pose_text(pose: ArrayLike) -> str:
    """A UR pose with micrometre resolution (ur_pose_text rounds to 10 um)."""
    p = np.asarray(pose, dtype=np.float64).reshape(6) + 0.0
    return "p[" + ", ".join(f"{v:.6f}" for v in p) + "]"


def _blends(P: FloatArray, blend_m: float) -> FloatArray:
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    r = np.zeros(P.shape[0])
    if P.shape[0] > 2:
        r[1:-1] = np.minimum(blend_m, 0.45 * np.minimum(seg[:-1], seg[1:]))
    return r


def plan_replay(
    path: LearnedPath,
    tool: ArrayLike,
    options: ReplayOptions | None = None,
    *,
    cfg: Config | None = None,
    model: str | kinematics.DHParams | None = None,
) -> ReplayPlan:
    """The waypoints of ``path`` for ``tool`` (UR pose of its TCP in the flange frame).

    With ``cfg`` (a run), the speeds must stay within its caps and every waypoint within its
    workspace box; with a robot model (``model``, else ``cfg``'s) every waypoint must be
    reachable and the joints must not flip between neighbours. :class:`ReplayError` otherwise.
    """
    o = options or ReplayOptions()
    tool6 = np.asarray(tool, dtype=np.float64).reshape(6)
    poses_all = tool_poses(
        path.points,
        path.tangents,
        path.normals,
        offset_m=o.offset_m,
        lead_rad=o.lead_rad,
        tilt_rad=o.tilt_rad,
    )
    idx = simplify(poses_all, o.tolerance_m, o.angle_tolerance_rad)
    poses = poses_all[idx]
    plan = ReplayPlan(
        tool=tool6,
        poses=poses,
        normals=np.asarray(path.normals[idx]),
        blends_m=_blends(poses[:, :3, 3], o.blend_m),
        edge_points=np.asarray(path.points[idx]),
        options=o,
        n_path_points=int(path.points.shape[0]),
        source=path.source,
    )
    if cfg is not None:
        r = cfg.robot
        if o.speed_m_s > r.max_speed_m_s or o.approach_speed_m_s > r.max_speed_m_s:
            raise ReplayError(
                f"speed {max(o.speed_m_s, o.approach_speed_m_s) * 1e3:g} mm/s exceeds the "
                f"configured limit {r.max_speed_m_s * 1e3:g} mm/s"
            )
        if o.accel_m_s2 > r.max_accel_m_s2:
            raise ReplayError(
                f"acceleration {o.accel_m_s2:g} m/s^2 exceeds the limit {r.max_accel_m_s2:g}"
            )
        if o.joint_speed_rad_s > r.max_joint_speed_rad_s:
            raise ReplayError("joint speed exceeds the configured limit")
        if r.workspace_min_m is not None and r.workspace_max_m is not None:
            lo = np.asarray(r.workspace_min_m, dtype=np.float64)
            hi = np.asarray(r.workspace_max_m, dtype=np.float64)
            pts = np.vstack(
                [poses[:, :3, 3], plan.approach_pose(0)[:3, 3], plan.approach_pose(-1)[:3, 3]]
            )
            out = np.any((pts < lo) | (pts > hi), axis=1)
            if np.any(out):
                raise ReplayError(
                    f"waypoint at {np.round(pts[int(np.argmax(out))], 4).tolist()} m is outside "
                    f"the workspace box {lo.tolist()} .. {hi.tolist()} m"
                )
        model = model or r.model
    if model is not None:
        plan = replace(plan, q=_joint_path(model, poses, tool6))
    return plan


def _joint_path(
    model: str | kinematics.DHParams, poses: FloatArray, tool6: FloatArray
) -> FloatArray:
    f2t = se3.invert(se3.pose_to_matrix(tool6))
    q_prev: FloatArray | None = None
    out = []
    for i, T in enumerate(poses):
        F = T @ f2t
        sols = kinematics.inverse(model, F)
        if sols.shape[0] == 0:
            raise ReplayError(
                f"waypoint {i} at {np.round(T[:3, 3], 4).tolist()} m is out of the robot's reach "
                "with this tool"
            )
        if q_prev is None:
            q = sols[0]
        else:
            q = kinematics.inverse_nearest(model, F, q_prev)
            if float(np.max(np.abs(q - q_prev))) > 0.5:
                raise ReplayError(
                    f"the joints flip between waypoints {i - 1} and {i} (a singularity or the "
                    "wrist's limit): the tool cannot follow the path continuously"
                )
        out.append(np.asarray(q))
        q_prev = np.asarray(q)
    return np.asarray(out)


# --------------------------------------------------------------------------------------------
# Files


def write_waypoints(path: str | Path, plan: ReplayPlan) -> Path:
    return write_atomic(path, json.dumps(plan.to_dict(), indent=1) + "\n")


def write_csv(path: str | Path, plan: ReplayPlan) -> Path:
    """One waypoint per row: the TCP pose (m, rad), the edge point (m), the normal, the blend."""
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            *("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"),
            *("edge_x_m", "edge_y_m", "edge_z_m", "normal_x", "normal_y", "normal_z", "blend_m"),
        ]
    )
    for p, e, n, r in zip(
        plan.ur_poses, plan.edge_points, plan.normals, plan.blends_m, strict=True
    ):
        w.writerow([f"{v:.7f}" for v in (*p, *e, *n)] + [f"{r:.6f}"])
    return write_atomic(path, buf.getvalue())


def write_script(path: str | Path, plan: ReplayPlan) -> Path:
    return write_atomic(path, plan.script())


# --------------------------------------------------------------------------------------------
# Running on the robot


def send_script(host: str, text: str, port: int = SCRIPT_PORT, timeout_s: float = 5.0) -> None:
    """Send a URScript program to the controller's script port."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as s:
            s.sendall(text.encode("utf-8"))
    except OSError as exc:
        raise ReplayError(f"cannot send the program to {host}:{port}: {exc}") from None


def dashboard_command(
    host: str, command: str, port: int = DASHBOARD_PORT, timeout_s: float = 5.0
) -> str:
    """One dashboard server command (``stop``, ``programState`` ...); its reply line."""
    with socket.create_connection((host, port), timeout=timeout_s) as s:
        f = s.makefile("rwb")
        f.readline()  # welcome
        f.write((command + "\n").encode())
        f.flush()
        return f.readline().decode("utf-8", errors="replace").strip()


def run_program(
    cfg: Config,
    plan: ReplayPlan,
    *,
    timeout_s: float = 600.0,
    start_timeout_s: float = 10.0,
    progress: Progress | None = None,
) -> str:
    """Run the plan's program on the robot of ``cfg`` (motion must be enabled; the caller has
    confirmed): send it, wait until it has run, and return a one-line outcome. Stops the
    program and raises :class:`ReplayError` on a protective stop, a timeout or Ctrl-C."""
    from wristscan.daemon.devices import make_devices
    from wristscan.daemon.procedure.acquisition import open_retrying
    from wristscan.drivers.base import DriverError

    if not cfg.robot.motion_enabled:
        raise ReplayError(f"{cfg.source}: [robot] motion_enabled is false: the replay moves it")
    report = stage_reporter(progress, "replay")
    host = cfg.robot.host
    try:
        robot = open_retrying(lambda: make_devices(cfg).robot, attempts=3)
    except DriverError as exc:
        raise ReplayError(f"cannot connect to the robot: {exc}") from None
    text = plan.script()
    t0 = time.monotonic()
    try:
        state = robot.read(timeout=5.0)
        if state is None:
            raise ReplayError("the robot sends no state")
        if state.protective_stop:
            raise ReplayError("the robot is in a protective stop: clear it first")
        report(0, 2, "sending the program")
        send_script(host, text)
        started = False
        deadline = time.monotonic() + start_timeout_s
        while True:
            s = robot.read(timeout=0.5)
            now = time.monotonic()
            if s is not None:
                if s.protective_stop:
                    raise ReplayError("protective stop during the replay")
                if s.program_running and not started:
                    started = True
                    report(1, 2, "running")
                    deadline = now + timeout_s
                elif started and not s.program_running:
                    break
            if now > deadline:
                what = "did not finish" if started else "did not start"
                _stop_program(host)
                raise ReplayError(f"the program {what} within the time allowed; stopped")
    except KeyboardInterrupt:
        _stop_program(host)
        raise ReplayError("interrupted: the program was stopped") from None
    finally:
        robot.close()
    report(2, 2, "done")
    return (
        f"{plan.poses.shape[0]} waypoints, {plan.length_m * 1e3:.1f} mm in "
        f"{time.monotonic() - t0:.1f} s"
    )


def _stop_program(host: str) -> None:
    try:
        dashboard_command(host, "stop")
    except OSError as exc:
        log.warning("could not stop the program through the dashboard: %s", exc)
