"""``wristscan view``: watch a running daemon's clouds in rerun (extra ``view``): the live cloud,
the laser's and the flange's trails, the sensor's pose and the calibration in force
(:mod:`wristscan.daemon.view.live` says what is drawn and why). ``--record FILE.rrd`` saves the
recording to a file instead of spawning the viewer (headless use; open it later with
``rerun FILE.rrd``).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from wristscan.daemon.cli._common import EXIT_USAGE, check_number, fail, stop_on_signals, table
from wristscan.daemon.cli._remote import (
    ConfigOpt,
    ConnectOpt,
    ModeOpt,
    PrefixOpt,
    TimeoutOpt,
    no_answer,
    open_client,
    resolve_target,
    wait_alive,
)

if TYPE_CHECKING:
    from wristscan.daemon.cloud.client import CloudClient
    from wristscan.daemon.cloud.poses import PoseSubscriber
    from wristscan.daemon.view.live import LiveView

RING_CAPACITY = 64
"""Batches held while the viewer catches up (then the oldest are dropped and counted)."""


def _open_recording(record: Path | None) -> Any:
    from wristscan.daemon.view.live import ViewUnavailable, new_recording

    if record is not None:
        if record.suffix.lower() != ".rrd":
            fail(f"--record must name a .rrd file, not {record}", EXIT_USAGE)
        if not record.parent.exists():
            fail(f"folder {record.parent} does not exist", EXIT_USAGE)
    try:
        return new_recording()
    except ViewUnavailable as exc:
        fail(str(exc), EXIT_USAGE)


def _sink(rec: Any, record: Path | None) -> None:
    """Send the recording to ``record``, or to a rerun viewer spawned (or already running)."""
    if record is not None:
        rec.save(record)
    else:
        rec.spawn()


def _watch(
    client: CloudClient,
    live: LiveView,
    stop: threading.Event,
    seconds: float | None,
    poses: PoseSubscriber,
) -> str:
    """Log batches and robot poses until ``seconds`` or a signal; what ended it."""
    t0 = time.monotonic()
    while not stop.is_set():
        for batch in poses.drain():
            live.pose(batch)
        wait = 0.1
        if seconds is not None:
            left = seconds - (time.monotonic() - t0)
            if left <= 0:
                return "time reached"
            wait = min(wait, left)
        cloud = client.recv(timeout=wait)
        if cloud is not None:
            live.batch(cloud)
    return "signal"


def view(
    record: Annotated[
        Path | None,
        typer.Option(
            "--record",
            help="Save to this .rrd file instead of spawning the rerun viewer.",
            show_default=False,
        ),
    ] = None,
    seconds: Annotated[
        float | None,
        typer.Option(
            "--seconds", help="Stop after this many seconds (default: Ctrl-C).", show_default=False
        ),
    ] = None,
    stride: Annotated[
        int,
        typer.Option(
            "--stride", help="Log every N-th point of a batch (lighter on CPU and disk; >= 1)."
        ),
    ] = 1,
    config: ConfigOpt = None,
    prefix: PrefixOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    timeout: TimeoutOpt = 10.0,
) -> None:
    """Show a running daemon's live cloud, laser and flange trails, sensor pose and
    calibration in rerun (the viewer is spawned unless --record saves to a file)."""
    check_number("--seconds", seconds, gt=0)
    check_number("--stride", stride, ge=1)
    check_number("--timeout", timeout, ge=0.1)
    target = resolve_target(config, prefix, connect, mode)
    rec = _open_recording(record)
    from wristscan.daemon.cloud.poses import PoseSubscriber
    from wristscan.daemon.view.live import LiveView

    with stop_on_signals() as stop:
        client = open_client(target, capacity=RING_CAPACITY)
        poses = PoseSubscriber(client.session, client.prefix)
        try:
            if not wait_alive(client, timeout, stop):
                no_answer(target, timeout, stop)
            _sink(rec, record)
            live = LiveView(rec, stride=stride)
            try:
                has_sensor = live.calibration(client.query("calibration", timeout=timeout))
            except (TimeoutError, RuntimeError) as exc:
                typer.echo(f"warning: no calibration shown: {exc}", err=True)
                has_sensor = False
            where = f"to {record}" if record is not None else "in the rerun viewer"
            typer.echo(f"viewing {target.prefix}/cloud {where} (Ctrl-C to stop)", err=True)
            t0 = time.monotonic()
            reason = _watch(client, live, stop, seconds, poses)
            live.log_trail()
            elapsed = time.monotonic() - t0
        finally:
            poses.close()
            client.close()
            rec.flush()
            rec.disconnect()
    rows = [
        ("recording", str(record.resolve()) if record is not None else "rerun viewer"),
        ("points", str(live.points)),
        ("stride", f"every {stride}th point logged" if stride > 1 else "every point logged"),
        ("batches", str(live.batches)),
        ("poses", f"{live.poses} batches' robot poses"),
        ("dropped", f"{client.dropped} batches (the viewer was too slow)"),
        ("sensor", "calibration shown" if has_sensor else "no sensor transform"),
        ("duration", f"{elapsed:.2f} s"),
        ("stopped", reason),
    ]
    typer.echo("\n".join(table(rows, indent="")))
    if live.batches == 0:
        typer.echo("warning: no cloud was received", err=True)


def register(app: typer.Typer) -> None:
    app.command("view")(view)
