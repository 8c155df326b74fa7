"""``wristscan check-config``: validate a config file (or the embedded default) and summarise it."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from wristscan.daemon.cli._common import EXIT_USAGE, fail


def check_config(
    file: Annotated[
        Path | None, typer.Argument(help="The TOML config file to check.", show_default=False)
    ] = None,
    default: Annotated[
        bool, typer.Option("--default", help="Check the embedded default (the simulated cell).")
    ] = False,
) -> None:
    """Validate a config file: print a summary (exit 0) or every problem, one per line (exit 2)."""
    from wristscan.daemon.config import ConfigError, load_config, load_default

    if (file is None) == (not default):
        fail("give a config FILE or --default (one of the two)", EXIT_USAGE)
    try:
        config = load_default() if file is None else load_config(file)
    except ConfigError as exc:
        for line in exc.problems:
            typer.echo(line, err=True)
        n = len(exc.problems)
        typer.echo(f"{exc.source}: {n} problem{'s' if n != 1 else ''}, not usable", err=True)
        raise typer.Exit(EXIT_USAGE) from None
    typer.echo(f"{config.source}: OK (schema_version {config.schema_version})")
    for line in config.summary():
        typer.echo(f"  {line}")


def register(app: typer.Typer) -> None:
    app.command("check-config")(check_config)
