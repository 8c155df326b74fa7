"""``wristscan cells``: the live cells of a plant through its zenoh router (docs/plant.md).

Every daemon under ``--root`` (default ``wristscan``) that holds its liveliness token is listed
with its state and counters; ``--json`` prints one JSON document. Exit 1 when no cell answers.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

import typer

from wristscan.daemon.cli._common import (
    EXIT_FAILED,
    EXIT_USAGE,
    check_number,
    fail,
    stop_on_signals,
    table,
)
from wristscan.daemon.cli._remote import (
    ConfigOpt,
    ConnectOpt,
    ModeOpt,
    TimeoutOpt,
    open_client,
    resolve_target,
)


def _row(prefix: str, stats: dict[str, Any] | None, state: str) -> tuple[str, str]:
    if stats is None:
        return prefix, f"{state}; no counters answered"
    dropped = sum(int(n) for n in dict(stats.get("dropped", {})).values())
    return prefix, (
        f"{state}; {int(stats.get('published', 0))} profiles published, {dropped} dropped, "
        f"{int(stats.get('published_points', 0))} points"
    )


def cells(
    root: Annotated[
        str, typer.Option("--root", help="Key root the cells' prefixes share (wristscan/<cell>).")
    ] = "wristscan",
    config: ConfigOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
    timeout: TimeoutOpt = 3.0,
) -> None:
    """List the live cells (liveliness tokens under --root) with their state and counters."""
    check_number("--timeout", timeout, ge=0.1)
    if not root or any(c in root for c in "*$?# ") or root.startswith("/"):
        fail(f"--root must be a plain zenoh key such as 'wristscan', got {root!r}", EXIT_USAGE)
    target = resolve_target(config, root.rstrip("/") + "/cells", connect, mode)
    from wristscan.daemon.cloud.cells import list_cells

    with stop_on_signals():
        client = open_client(target, capacity=1, subscribe=False)
        try:
            found = list_cells(client.session, root, timeout_s=timeout, status_s=min(timeout, 1.5))
        finally:
            client.close()
    if as_json:
        doc = [{"prefix": c.prefix, "state": c.state, "stats": c.stats} for c in found]
        typer.echo(json.dumps(doc))
    elif found:
        typer.echo("\n".join(table([_row(c.prefix, c.stats, c.state) for c in found], indent="")))
    if not found:
        fail(f"no live cell under {root}/** on {target.describe()}", EXIT_FAILED)


def register(app: typer.Typer) -> None:
    app.command("cells")(cells)
