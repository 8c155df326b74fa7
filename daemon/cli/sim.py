"""``wristscan sim``: run the simulated cell of a configuration until stopped."""

from __future__ import annotations

import json
import signal
import threading
from pathlib import Path
from typing import Any

import typer


def _wait_for_stop(duration_s: float | None) -> str:
    """Block until SIGINT/SIGTERM or the duration; returns what ended the wait."""
    stop = threading.Event()
    why = {"reason": "duration"}

    def on_signal(signum: int, _frame: Any) -> None:
        why["reason"] = signal.Signals(signum).name
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        stop.wait(duration_s)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    return why["reason"]


def register(app: typer.Typer) -> None:
    @app.command("sim")
    def sim(
        config: Path | None = typer.Option(
            None, "--config", "-c", help="Configuration file (default: the embedded sim.toml)."
        ),
        duration: float | None = typer.Option(
            None,
            "--duration",
            min=0.0,
            help="Stop after this many seconds (default: run until Ctrl-C or SIGTERM).",
        ),
        as_json: bool = typer.Option(False, "--json", help="Print endpoints and truth as JSON."),
    ) -> None:
        """Start the simulated cell (UR controller, sensor, rotary table) on loopback."""
        from wristscan.daemon.config import ConfigError, load_config, load_default
        from wristscan.daemon.simcell.cell import start_cell

        try:
            cfg = load_config(config) if config is not None else load_default()
        except ConfigError as exc:
            typer.echo(str(exc), err=True)
            raise typer.Exit(2) from None
        try:
            cell = start_cell(cfg)
        except (RuntimeError, OSError) as exc:
            typer.echo(f"error: the simulated cell did not start: {exc}", err=True)
            raise typer.Exit(1) from None
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
