"""``wristscan demo``: the simulated cell, the daemon and a multi-pass scan, in one command."""

from __future__ import annotations

from pathlib import Path

import typer

from wristscan.daemon.cli._common import EXIT_FAILED, EXIT_USAGE, fail


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        out: Path = typer.Option(
            Path("scan.ply"),
            "--out",
            "-o",
            help="Merged cloud (PLY); a PNG preview is written next to it.",
        ),
        voxel_mm: float = typer.Option(
            0.5, "--voxel-mm", min=0.01, help="Voxel size of the merged cloud (mm)."
        ),
        sensor: str = typer.Option(
            "lpf1",
            "--sensor",
            help="The sensor pair: lpf1 (LPF1 over UDP), rf627 (Riftek RF627) or gocator "
            "(LMI Gocator Protocol), each with its simulated counterpart.",
        ),
    ) -> None:
        """Scan the demo part on the simulated cell and write the merged cloud."""
        import time

        from wristscan.daemon.simcell.demo import SENSORS, run_demo

        if sensor not in SENSORS:
            fail(f"--sensor must be one of {', '.join(SENSORS)}, not {sensor!r}", EXIT_USAGE)
        if out.suffix.lower() != ".ply":
            fail(f"--out must name a .ply file, not {out}", EXIT_USAGE)
        if not out.parent.exists():
            fail(f"folder {out.parent} does not exist", EXIT_USAGE)
        t0 = time.monotonic()
        try:
            res = run_demo(
                out,
                voxel_m=voxel_mm * 1e-3,
                progress=lambda m: typer.echo(f"- {m}"),
                sensor=sensor,
            )
        except RuntimeError as exc:
            fail(str(exc), EXIT_FAILED)
        st = res.stats
        typer.echo("")
        typer.echo(f"wrote {res.out} ({res.points_written} points, {voxel_mm:g} mm voxels)")
        typer.echo(
            f"{res.passes} passes at 2 table angles: {res.points_received} points in "
            f"{res.batches} batches from the daemon ({res.lost_batches} batches lost)"
        )
        dropped = sum(st.get("dropped", {}).values())
        typer.echo(
            f"daemon: {st.get('received', 0)} profiles received, {st.get('published', 0)} "
            f"published, {dropped} dropped {st.get('dropped', {})}"
        )
        typer.echo(
            f"part top face in the merged cloud: {res.top_height_m * 1e3:.3f} mm above the table "
            f"(true 70.000 mm), flat to {res.top_flatness_m * 1e6:.1f} um RMS"
        )
        if res.preview is not None:
            typer.echo(f"preview: {res.preview} (from above and from the side, coloured by height)")
        else:
            typer.echo(f"preview skipped: {res.preview_skipped}")
        typer.echo(
            f"done in {time.monotonic() - t0:.0f} s; open {res.out} in MeshLab or CloudCompare"
        )
