"""The report of a table calibration (``wristscan calibrate table --report``): the axis
parameters with their uncertainty, the ball centres, the circle-fit residuals split into
radial, tangential and axial parts, and the figures. Kept apart from the procedure
(:mod:`.table`) because only the CLI and the benchmarks read it, and it needs the report
machinery (and matplotlib for the figures) that the procedure does not.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from wristscan.daemon.calibrate.table import TableResult

__all__ = ["residual_components", "table_report"]

FloatArray = NDArray[np.float64]


def _fmt(value: float, sigma: float, unit: str) -> tuple[str, str, str]:
    """Value, one-sigma and unit for the report, in convenient units."""
    if unit == "m":
        return f"{value * 1e3:.4f}", f"{sigma * 1e3:.4f}", "mm"
    if unit == "rad":
        return f"{value:.6f}", f"{sigma:.6f}", "rad"
    if unit == "1":
        return f"{value:.7f}", f"{sigma:.7f}", ""
    return f"{value:.5f}", f"{sigma:.5f}", unit


def table_report(result: TableResult, subtitle: str = "") -> Any:
    """A :class:`~wristscan.daemon.io.report.Report` of ``result``: parameters with their
    uncertainty, the centres and the residuals (figures when matplotlib is there)."""
    from wristscan.daemon.io.report import Report, have_matplotlib

    a = result.axis
    rep = Report("Rotary table calibration", subtitle)
    rep.section(
        "Result",
        f"Axis from the ball centre measured at {a.n_angles} table angles "
        f"({result.sweeps} sweeps, {result.duration_s:.0f} s). The uncertainties are one sigma "
        "from the residuals of the circle fit (they include the robot's repeatability).",
    )
    rows = [[name, *_fmt(v, s, unit)] for name, v, s, unit in result.parameters()]
    rep.table(["parameter", "value", "1 sigma", "unit"], rows)
    rep.text(
        f"axis direction (base frame): [{a.direction[0]:.7f}, {a.direction[1]:.7f}, "
        f"{a.direction[2]:.7f}]\nbase2table:\n"
        + np.array2string(result.base2table, precision=6, suppress_small=True),
        preformatted=True,
    )
    rep.section(
        "Measurements",
        f"RMS distance between measured and modelled centres: {a.rms_m * 1e6:.1f} um. "
        "Residuals: radial (away from the axis), tangential (direction of turning), axial.",
    )
    res_local = residual_components(result)
    rows = []
    for m, th, r in zip(result.measurements, result.angles_rad, res_local, strict=True):
        rows.append(
            [
                f"{math.degrees(th):.3f}",
                *(f"{1e3 * v:.4f}" for v in m.centre),
                *(f"{1e6 * v:.1f}" for v in r),
                str(m.n_points),
                str(m.rescans),
            ]
        )
    rep.table(
        [
            "angle (deg)",
            "x (mm)",
            "y (mm)",
            "z (mm)",
            "radial (um)",
            "tangential (um)",
            "axial (um)",
            "points",
            "rescans",
        ],
        rows,
    )
    if have_matplotlib():
        _table_figures(rep, result, res_local)
    else:
        rep.text("(figures need matplotlib: pip install 'wristscan[plot]')")
    return rep


def residual_components(result: TableResult) -> FloatArray:
    """(k, 3) circle-fit residuals as radial (away from the axis), tangential (direction of
    turning) and axial components (m)."""
    a = result.axis
    res = a.residuals_m
    model = result.centres - res
    d = a.direction
    rel = model - a.point
    radial = rel - np.outer(rel @ d, d)
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    tangential = np.cross(d, radial)
    return np.stack(
        [np.sum(res * radial, axis=1), np.sum(res * tangential, axis=1), res @ d], axis=1
    )


def _table_figures(rep: Any, result: TableResult, res_local: FloatArray) -> None:
    from wristscan.daemon.io.report import new_figure

    a = result.axis
    b2t = a.base2table()
    C = result.centres
    local = C @ b2t[:3, :3].T + b2t[:3, 3]  # centres in the table frame (origin on the axis)
    fig, ax = new_figure(1, 2, figsize=(10.0, 4.4))
    t = np.linspace(0, 2 * np.pi, 361)
    ax[0].plot(1e3 * a.radius_m * np.cos(t), 1e3 * a.radius_m * np.sin(t), lw=0.8, label="fit")
    ax[0].plot(1e3 * local[:, 0], 1e3 * local[:, 1], "o", label="ball centres")
    for (px, py, _), th in zip(local, result.angles_rad, strict=True):
        ax[0].annotate(f"{math.degrees(th):.0f}", (1e3 * px, 1e3 * py), fontsize=7)
    ax[0].plot([0], [0], "+k", ms=10, label="axis")
    ax[0].set_aspect("equal")
    ax[0].set_xlabel("table X (mm)")
    ax[0].set_ylabel("table Y (mm)")
    ax[0].legend(fontsize=8)
    ax[0].set_title("Ball centres seen along the axis")
    deg = np.degrees(result.angles_rad)
    labels = ("radial", "tangential", "axial")
    for j in range(3):
        ax[1].plot(deg, 1e6 * res_local[:, j], "o-", label=labels[j])
    ax[1].axhline(0, color="k", lw=0.5)
    ax[1].set_xlabel("table angle (deg)")
    ax[1].set_ylabel("residual (um)")
    ax[1].legend(fontsize=8)
    ax[1].set_title("Circle-fit residuals")
    rep.figure(fig, "Ball centres in the table frame and the residuals of the circle fit")
