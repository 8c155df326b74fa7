"""``wristscan drivers``: every registered driver and whether it can load here."""

from __future__ import annotations

import json

import typer


def register(app: typer.Typer) -> None:
    @app.command("drivers")
    def drivers(
        as_json: bool = typer.Option(False, "--json", help="One JSON document instead of a table."),
    ) -> None:
        """List sensor, robot and table drivers (built-in and from entry points)."""
        from dataclasses import asdict

        from wristscan.drivers import registry

        infos = registry.describe()
        if as_json:
            typer.echo(json.dumps([asdict(i) for i in infos], indent=2))
            return
        for kind in registry.KINDS:
            typer.echo(f"{kind}:")
            for info in (i for i in infos if i.kind == kind):
                status = "ok" if info.loadable else f"unavailable: {info.reason}"
                typer.echo(f"  {info.name:<12} {info.description:<34} [{info.origin}] {status}")
