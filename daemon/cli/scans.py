"""``wristscan scans``: a cell's scan archive over the network (docs/plant.md).

``wristscan scans list`` prints the finished scans a running daemon keeps; ``wristscan scans
fetch JOB --out DIR`` copies one job's files (merged cloud, job report, manifest) into ``DIR``,
each written atomically. Exit 1 when no daemon answers or it holds no such job.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
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
    PrefixOpt,
    TimeoutOpt,
    open_client,
    resolve_target,
)

scans_app = typer.Typer(
    help="Finished scans a running daemon keeps: list them, fetch one.", no_args_is_help=True
)


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e5 else f"{n} B"


def _row(m: dict[str, Any]) -> tuple[str, str]:
    files = dict(m.get("files", {}))
    when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(float(m.get("created_utc", 0))))
    total = sum(int(s) for s in files.values())
    return str(m.get("job", "?")), f"{when}, {len(files)} files, {_size(total)}"


@scans_app.command("list")
def list_cmd(
    config: ConfigOpt = None,
    prefix: PrefixOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
    timeout: TimeoutOpt = 5.0,
) -> None:
    """List the scans the daemon keeps, oldest first."""
    from wristscan.daemon.cloud.scans import fetch_jobs

    check_number("--timeout", timeout, ge=0.1)
    target = resolve_target(config, prefix, connect, mode)
    with stop_on_signals():
        client = open_client(target, capacity=1, subscribe=False)
        try:
            jobs = fetch_jobs(client.session, target.prefix, timeout)
        except (TimeoutError, LookupError) as exc:
            fail(f"no scan archive answered on {target.prefix}/scans: {exc}", EXIT_FAILED)
        finally:
            client.close()
    if as_json:
        typer.echo(json.dumps(jobs))
    elif jobs:
        typer.echo("\n".join(table([_row(m) for m in jobs], indent="")))
    else:
        typer.echo(f"{target.prefix}: no scan kept yet", err=True)


@scans_app.command("fetch")
def fetch_cmd(
    job: Annotated[str, typer.Argument(help="The job name, as `scans list` prints it.")],
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Folder to copy the job's files into.")
    ] = Path("."),
    config: ConfigOpt = None,
    prefix: PrefixOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    timeout: TimeoutOpt = 30.0,
) -> None:
    """Copy one scan's files (merged cloud, job report, manifest) into --out."""
    from wristscan.daemon.cloud.scans import fetch_file, fetch_manifest
    from wristscan.daemon.io.archive import ArchiveError, check_name
    from wristscan.daemon.io.atomic import atomic_writer

    check_number("--timeout", timeout, ge=0.1)
    try:
        check_name(job)
    except ArchiveError as exc:
        fail(str(exc), EXIT_USAGE)
    if not out.is_dir():
        fail(f"--out must be an existing folder, got {str(out)!r}", EXIT_USAGE)
    target = resolve_target(config, prefix, connect, mode)
    written: list[Path] = []
    with stop_on_signals():
        client = open_client(target, capacity=1, subscribe=False)
        try:
            manifest = fetch_manifest(client.session, target.prefix, job, timeout)
            for name in manifest.get("files", {}):
                data = fetch_file(client.session, target.prefix, job, name, timeout)
                with atomic_writer(out / name) as f:
                    f.write(data)
                written.append(out / name)
            with atomic_writer(out / "manifest.json") as f:
                f.write(json.dumps(manifest, indent=1).encode())
            written.append(out / "manifest.json")
        except (TimeoutError, LookupError) as exc:
            fail(f"{target.prefix}/scans/{job}: {exc}", EXIT_FAILED)
        finally:
            client.close()
    typer.echo("\n".join(table([(p.name, str(p.resolve())) for p in written], indent="")))


def register(app: typer.Typer) -> None:
    app.add_typer(scans_app, name="scans")
