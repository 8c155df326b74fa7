"""The ``wristscan`` command line: one typer app, subcommands added per capability."""

from __future__ import annotations

import logging
from importlib.metadata import version

import typer

app = typer.Typer(
    name="wristscan",
    help="Wrist-mounted laser profile sensor: acquisition, calibration and simulation.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"wristscan {version('wristscan')}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log (-vv: debug)."),
    show_version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Print the version."
    ),
) -> None:
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def _register_commands() -> None:
    """Each verb module of ``daemon/cli/`` adds its subcommands through ``register(app)``.

    Discovery keeps this file free of a list every capability must edit; command modules import
    their heavy dependencies inside the command functions so ``wristscan --help`` stays fast.
    """
    import importlib
    import pkgutil

    from wristscan.daemon import cli

    for info in sorted(pkgutil.iter_modules(cli.__path__), key=lambda m: m.name):
        if not info.name.startswith("_") and info.name != "app":
            module = importlib.import_module(f"wristscan.daemon.cli.{info.name}")
            module.register(app)


_register_commands()


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    try:
        app(args=argv, prog_name="wristscan")
    except SystemExit as exc:  # typer/click end every run with SystemExit
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
