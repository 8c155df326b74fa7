"""A PNG preview of a point cloud: two views side by side (from above, and from the side along
the cloud's first axis), each point coloured by its height (z). ``wristscan demo`` writes one
next to its PLY so a newcomer has something to look at without a point-cloud viewer.

Drawing needs matplotlib, the ``plot`` extra; without it :func:`write_preview` raises
:class:`PreviewUnavailable` naming the extra. The file is written atomically.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wristscan.daemon.io.atomic import write_atomic

__all__ = ["MAX_POINTS", "PreviewUnavailable", "write_preview"]

MAX_POINTS = 200_000
"""Points drawn at most (an even subsample beyond): enough to look dense at preview size."""


class PreviewUnavailable(RuntimeError):
    """The preview cannot be drawn here (the ``plot`` extra is missing)."""


def _subsample(xyz: NDArray[np.float64], limit: int) -> NDArray[np.float64]:
    if xyz.shape[0] <= limit:
        return xyz
    step = int(np.ceil(xyz.shape[0] / limit))
    return xyz[::step]


def write_preview(
    path: Path,
    xyz: NDArray[np.floating],
    title: str = "",
    size_px: tuple[int, int] = (1200, 520),
) -> Path:
    """Draw ``xyz`` ((N, 3) metres) as a PNG of ``size_px`` (width, height) at ``path``; axes in
    millimetres. Raises :class:`PreviewUnavailable` without matplotlib, ``ValueError`` for an
    empty cloud."""
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise PreviewUnavailable(
            f"the PNG preview needs matplotlib: pip install 'wristscan[plot]' ({exc})"
        ) from exc
    pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] == 0:
        raise ValueError("no points to preview")
    mm = _subsample(pts, MAX_POINTS) * 1e3
    order = np.argsort(mm[:, 2])  # high points drawn last: the top view shows the top
    mm = mm[order]
    dpi = 100
    fig = Figure(figsize=(size_px[0] / dpi, size_px[1] / dpi), dpi=dpi)
    top, side = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.0, 1.25]})
    z_lo, z_hi = float(mm[:, 2].min()), float(mm[:, 2].max())
    kw = {"c": mm[:, 2], "s": 0.3, "cmap": "viridis", "vmin": z_lo, "vmax": max(z_hi, z_lo + 1e-3)}
    art = top.scatter(mm[:, 0], mm[:, 1], rasterized=True, linewidths=0, **kw)
    top.set_aspect("equal", adjustable="datalim")
    top.set(xlabel="x (mm)", ylabel="y (mm)", title="from above")
    side.scatter(mm[:, 0], mm[:, 2], rasterized=True, linewidths=0, **kw)
    side.set_aspect("equal", adjustable="datalim")
    side.set(xlabel="x (mm)", ylabel="z (mm)", title="from the side (along y)")
    fig.colorbar(art, ax=[top, side], label="height z (mm)", shrink=0.85)
    if title:
        fig.suptitle(title)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return write_atomic(path, buf.getvalue())
