"""``wristscan record``: save the daemon's published clouds to a file whose extension names the
format (:mod:`wristscan.daemon.io.cloudfile`): PLY, NPZ, MCAP (extra ``mcap``: ROS 2 messages
for Foxglove) or E57 (extra ``e57``: one scan, for CloudCompare).

PLY, MCAP and E57 are streamed to disk (a long recording never sits in memory) and renamed into
place when the recording ends; NPZ keeps the batch structure (sequence numbers, times, profile
indices) and is assembled in memory. Either way the file appears complete under its name or not
at all, also when the recording is stopped with Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from wristscan.daemon.cli._common import (
    EXIT_USAGE,
    check_number,
    fail,
    progress_bar,
    stop_on_signals,
    table,
)
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
    import numpy as np
    from numpy.typing import NDArray

    from wristscan.daemon.cloud.client import CloudClient
    from wristscan.daemon.cloud.poses import PoseSubscriber
    from wristscan.daemon.cloud.wsc1 import Cloud
    from wristscan.daemon.cloud.wsp1 import PoseBatch
    from wristscan.daemon.io.cloudfile import BatchSink
    from wristscan.daemon.io.ply import PlyStreamWriter
RING_CAPACITY = 64
"""Batches the subscriber holds while the file is being written (then the oldest are lost)."""
_POSE_BACKLOG = 256
"""Pose messages kept while their batch has not arrived."""


@dataclass
class _Tally:
    points: int = 0
    batches: int = 0
    lost: int = 0
    """Batches missing between the sequence numbers received."""
    restarts: int = 0
    """Sequence numbers that went backwards (a daemon restart)."""
    last_seq: int | None = None
    frames: dict[str, int] = field(default_factory=dict)
    t_first_ns: int | None = None
    t_last_ns: int | None = None

    def count(self, cloud: Cloud) -> None:
        if self.last_seq is not None:
            if cloud.seq > self.last_seq:
                self.lost += cloud.seq - self.last_seq - 1
            else:
                self.restarts += 1
        self.last_seq = cloud.seq
        self.batches += 1
        self.frames[cloud.frame_id] = self.frames.get(cloud.frame_id, 0) + 1
        if self.t_first_ns is None:
            self.t_first_ns = cloud.t_first_ns
        self.t_last_ns = cloud.t_last_ns


def _point_times_s(cloud: Cloud, take: int, t0_ns: int) -> NDArray[np.float64]:
    """Exposure time of each point (s since ``t0_ns``): its profile's place between the first
    and last profile of the batch when the batch says which profile a point is from, else the
    batch's first profile."""
    import numpy as np

    t = np.full(take, float(cloud.t_first_ns - t0_ns) * 1e-9)
    if cloud.profile_index is not None and cloud.n_profiles > 1:
        span = float(cloud.t_last_ns - cloud.t_first_ns) * 1e-9
        t += span * cloud.profile_index[:take] / (cloud.n_profiles - 1)
    return t


class _PlySink:
    """Streams points into a :class:`PlyStreamWriter` opened at the first batch (which decides
    whether the file carries intensity); with ``time`` each point carries ``scalar_time``."""

    def __init__(self, path: Path, ascii: bool, prefix: str, time: bool = False) -> None:
        self.path = path
        self.ascii = ascii
        self.prefix = prefix
        self.time = time
        self.t0_ns = 0
        self.writer: PlyStreamWriter | None = None
        self.intensity_mismatch = 0

    def _open(self, has_intensity: bool) -> PlyStreamWriter:
        from wristscan.daemon.io.ply import PlyStreamWriter

        comments = ["wristscan record", f"source {self.prefix}/cloud", "units metres"]
        if self.time:
            comments.append(f"scalar_time seconds since t0_ns {self.t0_ns}")
        return PlyStreamWriter(
            self.path,
            has_intensity=has_intensity,
            binary=not self.ascii,
            comments=comments,
            scalars=("scalar_time",) if self.time else (),
        )

    def add(self, cloud: Cloud, take: int) -> None:
        import numpy as np

        if self.writer is None:
            self.t0_ns = cloud.t_first_ns
            self.writer = self._open(cloud.intensity is not None)
        intensity = None
        if self.writer.has_intensity:
            if cloud.intensity is None:
                self.intensity_mismatch += 1
                intensity = np.zeros(take, np.uint8)
            else:
                intensity = cloud.intensity[:take]
        elif cloud.intensity is not None:
            self.intensity_mismatch += 1
        scalars = {"scalar_time": _point_times_s(cloud, take, self.t0_ns)} if self.time else None
        self.writer.write(cloud.xyz[:take], intensity=intensity, scalars=scalars)

    def close(self, tally: _Tally) -> Path:
        writer = self.writer if self.writer is not None else self._open(False)
        frames = ",".join(tally.frames) or "none"
        writer.comments += [f"frame {frames}", f"batches {tally.batches} lost {tally.lost}"]
        if tally.t_first_ns is not None:
            writer.comments.append(f"t_first_ns {tally.t_first_ns} t_last_ns {tally.t_last_ns}")
        return writer.close()

    def abort(self) -> None:
        if self.writer is not None:
            self.writer.abort()


class _NpzSink:
    """Keeps the batches and writes one ``.npz`` with per-point and per-batch arrays."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.xyz: list[NDArray[np.float32]] = []
        self.intensity: list[NDArray[np.uint8] | None] = []
        self.profile_index: list[NDArray[np.uint32] | None] = []
        self.batch: list[tuple[int, int, int, int, int, str]] = []
        self.intensity_mismatch = 0

    def add(self, cloud: Cloud, take: int) -> None:
        # Copies: the decoded arrays are views into the received payload.
        self.xyz.append(cloud.xyz[:take].copy())
        self.intensity.append(None if cloud.intensity is None else cloud.intensity[:take].copy())
        self.profile_index.append(
            None if cloud.profile_index is None else cloud.profile_index[:take].copy()
        )
        self.batch.append(
            (cloud.seq, cloud.t_first_ns, cloud.t_last_ns, take, cloud.n_profiles, cloud.frame_id)
        )

    def arrays(self) -> dict[str, Any]:
        import numpy as np

        out: dict[str, Any] = {
            "xyz": np.concatenate(self.xyz) if self.xyz else np.zeros((0, 3), np.float32)
        }
        have = [a is not None for a in self.intensity]
        if have and any(have):
            self.intensity_mismatch = have.count(False)
            out["intensity"] = np.concatenate(
                [
                    a if a is not None else np.zeros(len(x), np.uint8)
                    for a, x in zip(self.intensity, self.xyz, strict=True)
                ]
            )
        if self.profile_index and all(a is not None for a in self.profile_index):
            out["profile_index"] = np.concatenate([a for a in self.profile_index if a is not None])
        cols = list(zip(*self.batch, strict=True)) if self.batch else [()] * 6
        out["seq"] = np.array(cols[0], np.uint64)
        out["t_first_ns"] = np.array(cols[1], np.int64)
        out["t_last_ns"] = np.array(cols[2], np.int64)
        out["n_points"] = np.array(cols[3], np.int64)
        out["n_profiles"] = np.array(cols[4], np.uint32)
        out["frame_id"] = np.array(cols[5], dtype="U16")
        return out

    def close(self, tally: _Tally) -> Path:
        import numpy as np

        from wristscan.daemon.io.ply import atomic_writer

        arrays = self.arrays()
        with atomic_writer(self.path) as f:
            np.savez(f, **arrays)
        return self.path

    def abort(self) -> None:
        self.xyz.clear()


class _BatchSinkAdapter:
    """A :class:`BatchSink` (MCAP, E57) fed with received clouds and, for MCAP, the robot
    poses of their profiles (``<prefix>/pose``): one flange and one sensor pose per batch
    recorded, written when both its cloud and its pose message have arrived."""

    def __init__(self, sink: BatchSink) -> None:
        self.sink = sink
        self.seqs: tuple[int, int] | None = None
        """The first and the last sequence number recorded."""
        self.pending: dict[int, PoseBatch] = {}
        self.poses = 0
        self.seq_written: int | None = None

    @property
    def takes_poses(self) -> bool:
        return self.sink.takes_poses

    def add_poses(self, batches: list[PoseBatch]) -> None:
        """Write the poses of recorded batches; keep those of batches still to come."""
        for b in batches:
            self.pending[b.seq] = b
        if self.seqs is None:
            return
        first, last = self.seqs
        for seq in sorted(self.pending):
            if seq > last:
                break
            b = self.pending.pop(seq)
            if seq >= first and b.n_poses:
                self.sink.add_pose(int(b.t_ns[0]), b.flange2base[0], b.sensor2frame[0], b.frame_id)
                self.poses += 1
                self.seq_written = seq
        while len(self.pending) > _POSE_BACKLOG:  # a daemon restarted: its numbers start over
            self.pending.pop(min(self.pending))

    def last_poses(self, poses: PoseSubscriber, wait_s: float = 0.5) -> None:
        """The pose of the last batch follows it on the wire: wait for it briefly."""
        deadline = time.monotonic() + wait_s
        while True:
            self.add_poses(poses.drain())
            if self.seqs is None or self.seq_written == self.seqs[1]:
                return
            if time.monotonic() > deadline:
                return
            time.sleep(0.02)

    @property
    def intensity_mismatch(self) -> int:
        return self.sink.intensity_mismatch

    def add(self, cloud: Cloud, take: int) -> None:
        from wristscan.daemon.io.cloudfile import Batch

        inten = None if cloud.intensity is None else cloud.intensity[:take]
        batch = Batch(cloud.xyz[:take], cloud.t_first_ns, cloud.t_last_ns, cloud.frame_id, inten)
        self.sink.add_batch(batch)
        first = cloud.seq if self.seqs is None or cloud.seq < self.seqs[0] else self.seqs[0]
        self.seqs = (first, cloud.seq)

    def close(self, tally: _Tally) -> Path:
        return self.sink.finish()

    def abort(self) -> None:
        self.sink.abort()


_Sink = _PlySink | _NpzSink | _BatchSinkAdapter


def _open_sink(out: Path, ascii: bool, prefix: str, time: bool) -> _Sink:
    from wristscan.daemon.io.cloudfile import cloud_format, open_batch_sink

    fmt = cloud_format(out)
    if fmt == "ply":
        return _PlySink(out, ascii, prefix, time)
    if fmt == "npz":
        return _NpzSink(out)
    return _BatchSinkAdapter(open_batch_sink(out, fmt, f"{prefix}/cloud"))


def _pose_subscriber(client: CloudClient, out: Path) -> PoseSubscriber | None:
    """The daemon's robot poses, for the format that records them (MCAP); subscribed with the
    clouds, so the batches waiting in the client's ring find their poses."""
    from wristscan.daemon.cloud.poses import PoseSubscriber
    from wristscan.daemon.io.cloudfile import cloud_format

    if cloud_format(out) != "mcap":
        return None

    return PoseSubscriber(client.session, client.prefix)


def _check_options(
    out: Path,
    ascii: bool,
    point_time: bool,
    force: bool,
    numbers: tuple[float | None, int | None, float],
) -> None:
    duration, points, timeout = numbers
    check_number("--duration", duration, gt=0)
    check_number("--points", points, ge=1)
    check_number("--timeout", timeout, ge=0.1)
    from wristscan.daemon.io.cloudfile import FORMATS, CloudFormatError, cloud_format

    if out.suffix.lower() not in FORMATS:
        fail(
            f"--out must end in .ply or .npz (or .mcap, .e57 with their extras), got {str(out)!r}",
            EXIT_USAGE,
        )
    try:
        cloud_format(out)
    except CloudFormatError as exc:
        fail(f"--out: {exc}", EXIT_USAGE)
    if ascii and out.suffix.lower() != ".ply":
        fail("--ascii applies to .ply output only", EXIT_USAGE)
    if point_time and out.suffix.lower() != ".ply":
        fail("--time applies to .ply output only (MCAP and E57 carry the batch times)", EXIT_USAGE)
    if out.is_dir():
        fail(f"--out {str(out)!r} is a folder", EXIT_USAGE)
    if not out.parent.is_dir():
        fail(f"the folder of --out does not exist: {str(out.parent)!r}", EXIT_USAGE)
    if out.exists() and not force:
        fail(f"--out {str(out)!r} exists; use --force to replace it", EXIT_USAGE)


def record(
    out: Annotated[
        Path,
        typer.Option(
            "--out",
            "-o",
            help="Output file; the extension names the format: .ply, .npz, .mcap, .e57.",
            show_default=False,
        ),
    ],
    config: ConfigOpt = None,
    prefix: PrefixOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    duration: Annotated[
        float | None,
        typer.Option("--duration", "-d", help="Stop after this many seconds."),
    ] = None,
    points: Annotated[
        int | None, typer.Option("--points", "-n", help="Stop after this many points (>= 1).")
    ] = None,
    ascii: Annotated[bool, typer.Option("--ascii", help="Write ASCII PLY (large, slow).")] = False,
    point_time: Annotated[
        bool,
        typer.Option(
            "--time",
            help="PLY: each point's exposure time as scalar_time (s since the first batch), "
            "which CloudCompare shows as the scalar field 'time'.",
        ),
    ] = False,
    force: Annotated[
        bool, typer.Option("--force", help="Replace --out when it exists (refused otherwise).")
    ] = False,
    timeout: TimeoutOpt = 5.0,
    progress: Annotated[
        bool | None,
        typer.Option(
            "--progress/--no-progress",
            help="Progress bar on stderr (default: when stderr is a terminal).",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Record the daemon's point clouds to a file until --duration, --points or Ctrl-C."""
    _check_options(out, ascii, point_time, force, (duration, points, timeout))
    target = resolve_target(config, prefix, connect, mode)
    with stop_on_signals() as stop:
        client = open_client(target, capacity=RING_CAPACITY)
        poses = _pose_subscriber(client, out)
        try:
            if not wait_alive(client, timeout, stop):
                no_answer(target, timeout, stop)
            typer.echo(f"recording {target.prefix}/cloud to {out} (Ctrl-C to stop)", err=True)
            sink = _open_sink(out, ascii, target.prefix, point_time)
            tally = _Tally()
            bar = progress_bar(
                total=points,
                enabled=sys.stderr.isatty() if progress is None else progress,
                unit="pt",
                unit_scale=True,
                mininterval=0.25,
                dynamic_ncols=True,
            )
            t0 = time.monotonic()
            try:
                reason = _receive(client, sink, tally, bar, stop, t0, duration, points, poses)
                elapsed = time.monotonic() - t0
                bar.close()
                if poses is not None and isinstance(sink, _BatchSinkAdapter):
                    sink.last_poses(poses)
                path = sink.close(tally)
            except BaseException:
                bar.close()
                sink.abort()
                raise
        finally:
            if poses is not None:
                poses.close()
            client.close()
    _summary(path, tally, client.dropped, client.malformed, elapsed, reason, sink)


def _receive(
    client: CloudClient,
    sink: _Sink,
    tally: _Tally,
    bar: Any,
    stop: threading.Event,
    t0: float,
    duration: float | None,
    points: int | None,
    poses: PoseSubscriber | None = None,
) -> str:
    """Write the clouds received into ``sink`` (and with ``poses`` their robot poses) until a
    limit or a signal; what ended it."""
    while not stop.is_set():
        if poses is not None and isinstance(sink, _BatchSinkAdapter):
            sink.add_poses(poses.drain())
        wait = 0.1
        if duration is not None:
            left = duration - (time.monotonic() - t0)
            if left <= 0:
                return "duration reached"
            wait = min(wait, left)
        cloud = client.recv(timeout=wait)
        if cloud is None:
            continue
        tally.count(cloud)
        take = cloud.n_points
        if points is not None:
            take = min(take, points - tally.points)
        sink.add(cloud, take)
        tally.points += take
        bar.set_postfix(batches=tally.batches, lost=tally.lost, refresh=False)
        bar.update(take)
        if points is not None and tally.points >= points:
            return "point limit reached"
    return "signal"


def _summary(
    path: Path,
    tally: _Tally,
    overflow: int,
    malformed: int,
    elapsed: float,
    reason: str,
    sink: _Sink,
) -> None:
    lost = f"{tally.lost} batches (seq gaps)"
    if overflow:
        lost += f", {overflow} of them dropped here: the recorder was too slow"
    rows = [
        ("file", str(path.resolve())),
        ("points", str(tally.points)),
        ("batches", str(tally.batches)),
        ("lost", lost),
        ("malformed", str(malformed)),
        ("frame", ", ".join(tally.frames) or "-"),
        *(
            [("poses", f"{sink.poses} (flange and sensor, one per batch)")]
            if isinstance(sink, _BatchSinkAdapter) and sink.takes_poses
            else []
        ),
        ("duration", f"{elapsed:.2f} s"),
        ("stopped", reason),
    ]
    typer.echo("\n".join(table(rows, indent="")))
    if tally.batches == 0:
        typer.echo("warning: no cloud was received; the file is empty", err=True)
    elif isinstance(sink, _BatchSinkAdapter) and sink.takes_poses and sink.poses == 0:
        typer.echo(
            "warning: no robot pose arrived on <prefix>/pose (a daemon before 0.2 publishes "
            "none); the file holds the clouds only",
            err=True,
        )
    if len(tally.frames) > 1:
        typer.echo(
            f"warning: batches came in several frames ({', '.join(tally.frames)}); "
            "the file mixes them",
            err=True,
        )
    if tally.restarts:
        typer.echo(
            f"warning: the sequence restarted {tally.restarts} time(s) (daemon restarted?)",
            err=True,
        )
    if sink.intensity_mismatch:
        typer.echo(
            f"warning: {sink.intensity_mismatch} batch(es) differed in carrying intensity "
            "(filled with 0 or left out)",
            err=True,
        )


def register(app: typer.Typer) -> None:
    app.command("record")(record)
