"""``wristscan run --config FILE``: the acquisition service."""

from __future__ import annotations

import typer

from wristscan.daemon.cli._common import CellConfigOpt


def register(app: typer.Typer) -> None:
    @app.command("run")
    def run(
        config: CellConfigOpt,
        uncalibrated: bool = typer.Option(
            False,
            "--uncalibrated",
            help="Start without a calibration file (points published with the sensor at the "
            "flange; the status says 'calibrated: false').",
        ),
    ) -> None:
        """Run the acquisition daemon until SIGTERM (systemd Type=notify service)."""
        import logging

        from wristscan.daemon.service.runtime import run_service

        if not logging.getLogger().handlers:
            logging.basicConfig(level=logging.INFO)
        if logging.getLogger().getEffectiveLevel() > logging.INFO:
            # The service's own life cycle (start, waiting for devices, reloads and what they
            # changed, the final counters) is logged at INFO; the drivers stay at the root level.
            for name in ("wristscan.daemon.service", "wristscan.daemon.devices"):
                logging.getLogger(name).setLevel(logging.INFO)
        code = run_service(config, uncalibrated=uncalibrated)
        raise typer.Exit(code)
