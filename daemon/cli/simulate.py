"""``wristscan simulate ...``: offline simulations of the calibration methods.

``wristscan simulate tcp`` reruns the Monte Carlo study of Borangiu et al. 2009, section 3 (Fig. 4):
the standard deviation of the TCP error per axis against the tilt ``alpha`` between the poses, for
the paper's three-pose formula (Eq. 7) and for least squares on more poses, beside the analytic
prediction.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from wristscan.daemon.cli._common import EXIT_FAILED, EXIT_USAGE, check_number, fail, progress_bar

if TYPE_CHECKING:
    from wristscan.calib.montecarlo import StudyRow
_MAX_ALPHAS = 10_000
_MAX_TRIALS = 10_000_000
_MAX_POSES = 1000


def parse_alphas(text: str) -> list[float]:
    """Angles in degrees from ``"10:90:5"`` (start:stop:step, stop included), ``"45"`` or a comma
    list of both (``"20,45,60:90:10"``).  Raises ``ValueError`` with a one-line reason."""
    out: list[float] = []
    for item in text.split(","):
        parts = item.strip().split(":")
        try:
            nums = [float(p) for p in parts]
        except ValueError:
            raise ValueError(
                f"bad --alpha item {item.strip()!r}: use degrees as START:STOP:STEP "
                "(e.g. 10:90:5), a single angle, or a comma list of these"
            ) from None
        if not all(math.isfinite(v) for v in nums):
            raise ValueError(f"bad --alpha item {item.strip()!r}: angles must be finite")
        if len(nums) == 1:
            out.append(nums[0])
        elif len(nums) == 3:
            start, stop, step = nums
            if step <= 0 or stop < start:
                raise ValueError(
                    f"bad --alpha range {item.strip()!r}: need START <= STOP and STEP > 0"
                )
            count = math.floor((stop - start) / step + 1e-9) + 1
            if len(out) + count > _MAX_ALPHAS:
                raise ValueError(f"--alpha gives more than {_MAX_ALPHAS} angles")
            out.extend(round(start + k * step, 9) for k in range(count))
        else:
            raise ValueError(
                f"bad --alpha item {item.strip()!r}: a range is START:STOP:STEP (three numbers)"
            )
    bad = [a for a in out if not 0.0 < a < 180.0]
    if bad:
        raise ValueError(f"--alpha angles must be in (0, 180) degrees, got {bad[0]:g}")
    return out


def _table(rows: list[StudyRow], sigma_mm: float, trials: int) -> str:
    lines = [
        f"TCP Monte Carlo (Borangiu 2009 sec. 3): sigma {sigma_mm:g} mm per position axis, "
        f"{trials} trials per row, TCP (60, 10, 200) mm",
        "'three' = Eq. 7 on the paper's 3 poses; 'lstsq-nN' = least squares on N poses on a cone",
        "",
        f"{'alpha':>6}  {'method':<10}  {'Monte Carlo std (mm)':^26}  {'analytic std (mm)':^26}",
        f"{'deg':>6}  {'':<10}  {'x':>8} {'y':>8} {'z':>8}  {'x':>8} {'y':>8} {'z':>8}",
    ]
    for r in rows:
        mc = " ".join(f"{v:8.4f}" for v in r.std_mm)
        an = " ".join(f"{v:8.4f}" for v in r.analytic_std_mm)
        lines.append(f"{r.alpha_deg:6g}  {r.method:<10}  {mc}  {an}")
    return "\n".join(lines)


def _plot(rows: list[StudyRow], path: Path, sigma_mm: float, trials: int) -> None:
    """A figure like the paper's Fig. 4: std of the TCP error per axis against alpha."""
    # Figure + Agg canvas directly: no pyplot global state, no backend switching.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    methods = list(dict.fromkeys(r.method for r in rows))
    fig = Figure(figsize=(5.0 * len(methods), 4.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(methods), sharey=True, squeeze=False)[0]
    colours = ("tab:red", "tab:green", "tab:blue")
    dashes = ("-", "--", "-")  # x and y coincide for the symmetric pose sets: keep both visible
    for ax, method in zip(axes, methods, strict=True):
        sel = [r for r in rows if r.method == method]
        alpha = [r.alpha_deg for r in sel]
        for k, (axis, colour, ls) in enumerate(zip("xyz", colours, dashes, strict=True)):
            ax.plot(alpha, [r.std_mm[k] for r in sel], "o", ms=4, color=colour, label=f"{axis} MC")
            ax.plot(
                alpha,
                [r.analytic_std_mm[k] for r in sel],
                ls,
                color=colour,
                lw=1,
                label=f"{axis} analytic",
            )
        ax.axvline(45.0, color="grey", ls=":", lw=1)
        ax.set_yscale("log")
        ax.set_xlabel("alpha [deg]")
        ax.set_title(
            "Eq. 7, three poses" if method == "three" else f"least squares, {method[7:]} poses"
        )
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("std of TCP error [mm]")
    axes[0].legend(fontsize="small", ncols=2)
    fig.suptitle(f"TCP error vs tilt: sigma {sigma_mm:g} mm, {trials} trials per point")
    fig.savefig(path, dpi=120, format="png")


def tcp(
    alpha: Annotated[
        str,
        typer.Option(help="Tilt angles (deg): START:STOP:STEP, a value, or a comma list."),
    ] = "10:90:5",
    trials: Annotated[int, typer.Option(help="Monte Carlo trials per angle and method.")] = 200,
    sigma: Annotated[float, typer.Option(help="Position noise per axis, millimetres.")] = 0.1,
    poses: Annotated[
        int, typer.Option(help="Also run least squares on N poses on a cone (0: Eq. 7 only).")
    ] = 6,
    json_out: Annotated[
        bool, typer.Option("--json", help="Print one JSON document (a list of rows).")
    ] = False,
    plot: Annotated[Path | None, typer.Option(help="Write a PNG like the paper's Fig. 4.")] = None,
    seed: Annotated[int, typer.Option(help="Random seed (>= 0).")] = 0,
) -> None:
    """Monte Carlo study of the TCP estimators (paper section 3, Fig. 4)."""
    try:
        alphas = parse_alphas(alpha)
    except ValueError as exc:
        fail(str(exc), EXIT_USAGE)
    check_number("--trials", trials, ge=2, le=_MAX_TRIALS)
    check_number("--sigma", sigma, gt=0)
    if poses != 0:
        check_number("--poses", poses, ge=3, le=_MAX_POSES)
    check_number("--seed", seed, ge=0)
    if plot is not None:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            fail(
                "--plot needs matplotlib; install the extra: pip install 'wristscan[plot]'",
                EXIT_FAILED,
            )
        if plot.suffix.lower() != ".png" or plot.is_dir():
            fail(f"--plot takes a .png file name, got {str(plot)!r}", EXIT_USAGE)
        if not plot.parent.is_dir():
            fail(f"--plot: directory {str(plot.parent)!r} does not exist", EXIT_USAGE)

    import json

    from wristscan.calib import montecarlo

    sigma_m = sigma * 1e-3
    rows: list[StudyRow] = []
    progress = progress_bar(
        alphas, enabled=not json_out and sys.stderr.isatty(), desc="alpha", unit="angle"
    )
    try:
        for a in progress:  # one angle at a time for the progress bar; rows do not depend on it
            rows.extend(montecarlo.study([a], trials, sigma_m, poses or None, seed))
    except ValueError as exc:  # includes DegeneratePoses
        fail(str(exc), EXIT_USAGE)
    finally:
        progress.close()

    if json_out:
        typer.echo(json.dumps([r.as_dict() for r in rows]))
    else:
        typer.echo(_table(rows, sigma, trials))
    if plot is not None:
        try:
            _plot(rows, plot, sigma, trials)
        except OSError as exc:
            fail(f"--plot: cannot write {str(plot)!r}: {exc.strerror or exc}", EXIT_USAGE)
        if not json_out:
            typer.echo(f"plot written to {plot}")


def register(app: typer.Typer) -> None:
    """Add the ``simulate`` command group to the ``wristscan`` app."""
    simulate = typer.Typer(
        name="simulate",
        help="Offline simulations of the calibration methods.",
        no_args_is_help=True,
    )
    simulate.command("tcp")(tcp)
    app.add_typer(simulate, name="simulate")
