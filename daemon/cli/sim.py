"""``wristscan sim``: run the simulated cell of a configuration until stopped."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from wristscan.daemon.cli._common import (
    EXIT_FAILED,
    check_number,
    fail,
    load_config_or_exit,
    stop_on_signals,
)


def _wait_for_stop(duration_s: float | None) -> str:
    """Block until SIGINT/SIGTERM or the duration; returns what ended the wait."""
    with stop_on_signals() as stop:
        stop.wait(duration_s)
    return stop.signal_name or "duration"


def register(app: typer.Typer) -> None:
    @app.command("sim")
    def sim(
        config: Path | None = typer.Option(
            None, "--config", "-c", help="Configuration file (default: the embedded sim.toml)."
        ),
        duration: float | None = typer.Option(
            None,
            "--duration",
            help="Stop after this many seconds (default: run until Ctrl-C or SIGTERM).",
        ),
        as_json: bool = typer.Option(False, "--json", help="Print endpoints and truth as JSON."),
    ) -> None:
        """Start the simulated cell (UR controller, sensor, rotary table) on loopback."""
        from wristscan.daemon.simcell.cell import start_cell

        check_number("--duration", duration, ge=0)
        cfg = load_config_or_exit(config)
        try:
            cell = start_cell(cfg)
        except (RuntimeError, OSError) as exc:
            fail(f"the simulated cell did not start: {exc}", EXIT_FAILED)
        try:
            info = {"endpoints": cell.endpoints(), "truth": cell.truth()}
            if as_json:
                typer.echo(json.dumps(info, indent=2))
            else:
                typer.echo(f"simulated cell '{cfg.cell.name}' running (Ctrl-C stops it)")
                for name, ep in info["endpoints"].items():
                    typer.echo(f"  {name:<7} {ep}")
                t = info["truth"]
                pose = ", ".join(f"{v:.5f}" for v in t["sensor2flange_ur_pose"])
                typer.echo(f"  truth   sensor2flange p[{pose}]")
                typer.echo(f"          sensor latency {t['sensor_latency_s'] * 1e3:.3f} ms")
                if "ball_centre_base_m" in t:
                    c = ", ".join(f"{v:.4f}" for v in t["ball_centre_base_m"])
                    typer.echo(
                        f"          ball centre [{c}] m, R {t['ball_radius_m'] * 1e3:.2f} mm"
                    )
            reason = _wait_for_stop(duration)
            typer.echo(f"stopping ({reason})", err=True)
        finally:
            cell.stop()
