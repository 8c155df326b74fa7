"""The pose notation of a UR teach pendant, ``p[x, y, z, rx, ry, rz]`` (metres, rotation vector in
radians): how wristscan shows a transform to an operator and reads one typed by an operator."""

from __future__ import annotations

import re

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["parse_ur_pose", "ur_pose_text"]


def ur_pose_text(pose: ArrayLike) -> str:
    """``p[x, y, z, rx, ry, rz]`` as typed on a UR teach pendant: metres to 10 um, radians to
    0.1 mrad."""
    p = np.asarray(pose, dtype=np.float64).reshape(6) + 0.0  # + 0.0 turns -0.0 into 0.0
    parts = [f"{v:.5f}" for v in p[:3]] + [f"{v:.4f}" for v in p[3:]]
    parts = [s[1:] if s.startswith("-") and float(s) == 0.0 else s for s in parts]
    return "p[" + ", ".join(parts) + "]"


_POSE_RE = re.compile(r"^\s*p?\s*\[(.*)\]\s*$")


def parse_ur_pose(text: str) -> NDArray[np.float64]:
    """``"p[x, y, z, rx, ry, rz]"`` as typed on a UR teach pendant (metres, rotation vector in
    radians; the ``p`` and the brackets are optional, commas or spaces separate) as a (6,) array,
    the inverse of :func:`ur_pose_text`. Raises ``ValueError`` with a one-line reason."""
    m = _POSE_RE.match(text)
    body = m.group(1) if m else text
    parts = [p for p in re.split(r"[,\s]+", body.strip()) if p]
    try:
        values = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise ValueError(f"not a UR pose p[x, y, z, rx, ry, rz]: {text!r}") from None
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ValueError(f"a UR pose needs 6 finite numbers (m, rad), got {text!r}")
    if np.linalg.norm(values[:3]) > 2.0:
        raise ValueError(f"pose translation {values[:3].tolist()} is over 2 m: metres expected")
    return values
