"""The minimal URScript subset the simulated controller runs: the parser of its statements.

Minimal URScript programs
------------------------
A program sent to the script port that calls ``movel``, ``movep``, ``movej`` or ``set_tcp`` runs
those statements in order, one per line (literal arguments only: ``p[...]`` poses, ``[...]``
joint vectors, numbers, positional or ``a=``/``v=``/``t=``/``r=``): ``set_tcp(p[...])``,
``movej(q | p[...], a, v, t, r)`` (a pose target is solved for the joints nearest the current
ones), ``movel(p[...], a, v, t, r)``, ``movep(p[...], a, v, r)``, ``sleep(t)``. Consecutive
linear moves with a blend radius ``r > 0`` run as one :class:`~.motion.PolylinePath` at the
first move's speed and acceleration: the blends are approximated by passing through each
waypoint without stopping (no corner rounding). Other statements (``textmsg``, ``popup``,
assignments, control flow) are skipped with a log line. The program ends after the last
statement; a protective stop or an unreachable target stops it as on a robot.
``state()`` reports the active TCP (``tcp_offset``) and the true TCP pose (``tcp_pose_true``,
from the true joints) for tests.

Running the statements (one motion at a time, the blended runs, the end of the program) is the
controller's (:class:`~.program.ProgramHost`); this module only reads them.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass

__all__ = ["ScriptOp", "parse_script"]

log = logging.getLogger(__name__)

_MOTION_DEFAULTS = {
    "movel": {"a": 1.2, "v": 0.25, "t": 0.0, "r": 0.0},
    "movep": {"a": 1.2, "v": 0.25, "t": 0.0, "r": 0.0},
    "movej": {"a": 1.4, "v": 1.05, "t": 0.0, "r": 0.0},
}
_POSITIONAL = {"movel": "avtr", "movej": "avtr", "movep": "avr"}
_SCRIPT_STATEMENTS = frozenset({"movel", "movep", "movej", "set_tcp", "sleep"})
_CALL = re.compile(r"^\s*([A-Za-z_]\w*)\s*\((.*)\)\s*$")


@dataclass(frozen=True)
class ScriptOp:
    """One statement of a minimal URScript program (SI units)."""

    kind: str
    """``movel``, ``movep``, ``movej``, ``set_tcp`` or ``sleep``."""
    target: tuple[float, ...] = ()
    """Pose ``[x, y, z, rx, ry, rz]`` or joint vector (rad)."""
    is_pose: bool = False
    a: float = 0.0
    v: float = 0.0
    t: float = 0.0
    r: float = 0.0
    line: int = 0


def _split_args(text: str) -> list[str]:
    out: list[str] = []
    cur: list[str] = []
    depth = 0
    for ch in text:
        if ch in "[(":
            depth += 1
        elif ch in "])":
            depth -= 1
        if ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
        else:
            cur.append(ch)
    if "".join(cur).strip():
        out.append("".join(cur).strip())
    return out


def _literal(text: str) -> tuple[tuple[float, ...], bool] | float:
    t = text.strip()
    is_pose = t.startswith("p[")
    if is_pose:
        t = t[1:]
    if t.startswith("[") and t.endswith("]"):
        return tuple(float(v) for v in t[1:-1].split(",")), is_pose
    return float(t)


def parse_script(text: str) -> list[ScriptOp] | None:
    """The motion statements of a URScript program, or None when it has none (see the module
    docstring). Raises ValueError for a motion statement it cannot read."""
    ops: list[ScriptOp] = []
    for no, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        m = _CALL.match(line)
        if m is None or m.group(1) not in _SCRIPT_STATEMENTS:
            if line and not re.match(r"(def|sec)\s+\w+\s*\(|end$", line):
                log.debug("script line %d not simulated: %s", no, line[:80])
            continue
        name, args = m.group(1), _split_args(m.group(2))
        try:
            if name == "sleep":
                ops.append(ScriptOp("sleep", t=float(args[0]), line=no))
                continue
            first = _literal(args[0])
            if not isinstance(first, tuple) or len(first[0]) != 6:
                raise ValueError("the target must be a pose p[...] or 6 joint values")
            target, is_pose = first
            if name == "set_tcp":
                if not is_pose:
                    raise ValueError("set_tcp needs a pose p[...]")
                ops.append(ScriptOp("set_tcp", target, True, line=no))
                continue
            if name in ("movel", "movep") and not is_pose:
                raise ValueError(f"{name} needs a pose p[...]")
            values = dict(_MOTION_DEFAULTS[name])
            for i, arg in enumerate(args[1:]):
                if "=" in arg:
                    key, _, val = arg.partition("=")
                    key = key.strip()
                else:
                    key, val = _POSITIONAL[name][i], arg
                if key not in values:
                    raise ValueError(f"unknown argument {key!r}")
                v = _literal(val)
                if not isinstance(v, float):
                    raise ValueError(f"argument {key} must be a number")
                values[key] = v
            ops.append(ScriptOp(name, target, is_pose, line=no, **values))
        except (ValueError, IndexError) as e:
            raise ValueError(f"line {no}: {line[:60]}: {e}") from None
    return ops or None
