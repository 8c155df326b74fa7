"""What the verbs of the command line share: exit codes, the one way to fail, loading the
configuration, confirming robot motion, progress output and the options several verbs take.

Exit codes of every verb: 0 done, 1 aborted or failed (nothing written; the calibration in force
is unchanged), 2 usage or configuration error (nothing moved), 130 stopped by a signal before
anything was done.

Like the verb modules, this one imports nothing heavy at the top: ``wristscan --help`` stays
fast.
"""

from __future__ import annotations

import contextlib
import math
import signal
import sys
import threading
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Annotated, Any, NoReturn, overload

import typer

from wristscan.daemon.procedure.progress import Progress, ProgressEvent

if TYPE_CHECKING:
    from wristscan.daemon.config import Config

__all__ = [
    "EXIT_FAILED",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "CellConfigOpt",
    "QuietOpt",
    "StopSignal",
    "YesOpt",
    "check_number",
    "check_out_folder",
    "confirm_motion",
    "fail",
    "load_config_or_exit",
    "mm",
    "progress_bar",
    "progress_printer",
    "report_path",
    "stop_on_signals",
    "table",
]

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2
EXIT_INTERRUPTED = 130
"""SIGINT or SIGTERM while waiting for a daemon (the shell's code for a Ctrl-C)."""

# ------------------------------------------------------------------------------ shared options

CellConfigOpt = Annotated[Path, typer.Option("--config", "-c", help="Cell configuration (TOML).")]
YesOpt = Annotated[
    bool,
    typer.Option(
        "--yes", "-y", help="Confirm that the robot may move (needed without a terminal)."
    ),
]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="No progress lines.")]

# ------------------------------------------------------------------------------ failing


def fail(message: str, code: int = EXIT_FAILED) -> NoReturn:
    """One line on stderr and the exit code (no traceback)."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def _bounds_text(ge: float | None, gt: float | None, le: float | None, lt: float | None) -> str:
    parts = [
        f"{op} {b:g}" for op, b in ((">=", ge), (">", gt), ("<=", le), ("<", lt)) if b is not None
    ]
    return " and ".join(parts)


def check_number(
    option: str,
    value: float | Sequence[float] | None,
    *,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
) -> None:
    """Exit 2 with one line naming ``option`` unless ``value`` is a finite number within the
    bounds given (``ge`` >=, ``gt`` >, ``le`` <=, ``lt`` <); every item of a sequence (a tuple or
    repeated option) is checked, None (an option not given) passes. Every verb calls this for
    each of its number options before it reads a file or opens a device::

        check_number("--dwell-s", dwell_s, gt=0)  # error: --dwell-s: must be ... > 0 (got nan)
    """
    if value is None:
        return
    values = [value] if isinstance(value, int | float) else list(value)
    for v in values:
        ok = math.isfinite(v)
        ok = ok and (ge is None or v >= ge) and (gt is None or v > gt)
        ok = ok and (le is None or v <= le) and (lt is None or v < lt)
        if not ok:
            bounds = _bounds_text(ge, gt, le, lt)
            what = "a finite number" + (f" {bounds}" if bounds else "")
            fail(f"{option}: must be {what} (got {v:g})", EXIT_USAGE)


def load_config_or_exit(path: Path | None) -> Config:
    """The validated configuration (``None``: the embedded default of the simulated cell), or
    exit 2 with the loader's message."""
    from wristscan.daemon.config import ConfigError, load_config, load_default

    try:
        return load_default() if path is None else load_config(path)
    except ConfigError as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(EXIT_USAGE) from None


def confirm_motion(cfg: Config, yes: bool, what: str) -> None:
    """Refuse (exit 2) unless motion is enabled in ``cfg`` and confirmed: ``--yes``, or an answer
    at a terminal. Nothing has moved when this exits."""
    if not cfg.robot.motion_enabled:
        fail(
            f"motion is not enabled in {cfg.source}: set [robot] motion_enabled = true to let "
            "the procedure move the robot",
            EXIT_USAGE,
        )
    if yes:
        return
    if not sys.stdin.isatty():
        fail(f"{what} moves the robot: confirm with --yes (no terminal to ask)", EXIT_USAGE)
    r = cfg.robot
    typer.echo(
        f"{what} will move the robot at {r.host} (TCP speed up to {r.max_speed_m_s * 1e3:g} "
        f"mm/s, inside the workspace box {list(r.workspace_min_m)} .. "
        f"{list(r.workspace_max_m)} m). Keep the emergency stop at hand.",
        err=True,
    )
    if not typer.confirm("Start?", default=False, err=True):
        fail("not confirmed; nothing moved", EXIT_USAGE)


def check_out_folder(target: Path, option: str) -> None:
    """Exit 2 when the folder ``target`` is to be written in does not exist."""
    if not target.parent.is_dir():
        fail(f"{option}: folder {target.parent} does not exist", EXIT_USAGE)


def report_path(target: Path, report: Path | None) -> Path:
    """A procedure's report file: ``report``, or beside ``target`` as ``<stem>-report.html``;
    exit 2 unless it is .html or .md."""
    rep = report if report is not None else target.with_name(target.stem + "-report.html")
    if rep.suffix.lower() not in (".html", ".htm", ".md"):
        fail("--report: the name must end in .html or .md", EXIT_USAGE)
    return rep


# ------------------------------------------------------------------------------ units, output


@overload
def mm(value: float) -> float: ...
@overload
def mm(value: None) -> None: ...
def mm(value: float | None) -> float | None:
    """Millimetres (as options take them) to metres; None stays None."""
    return None if value is None else value * 1e-3


def progress_printer(quiet: bool = False, *, err: bool = True, elapsed: bool = False) -> Progress:
    """A procedure's :data:`~wristscan.daemon.procedure.progress.Progress`: one line per event
    (``[stage step/total] message``) on stderr (``err``) or stdout; with ``elapsed`` the seconds
    since the printer was made follow the count."""
    import time

    t0 = time.monotonic()

    def line(event: ProgressEvent) -> None:
        if quiet:
            return
        text = str(event)
        if elapsed:
            head, _, message = text.partition("] ")
            text = f"{head} {time.monotonic() - t0:5.1f} s] {message}"
        typer.echo(text, err=err)

    return line


def progress_bar(iterable: Iterable[Any] | None = None, *, enabled: bool, **options: Any) -> Any:
    """A tqdm progress bar on stderr, drawn only when ``enabled`` (``options`` go to tqdm).

    Without tqdm's monitor thread: it starts even for a disabled bar and outlives the command.
    """
    from tqdm import tqdm

    class _Bar(tqdm):
        monitor_interval = 0

    return _Bar(iterable, file=sys.stderr, disable=not enabled, **options)


def table(rows: list[tuple[str, str]], indent: str = "  ") -> list[str]:
    """Aligned ``key  value`` lines."""
    width = max((len(k) for k, _ in rows), default=0)
    return [f"{indent}{k.ljust(width)}  {v}" for k, v in rows]


# ------------------------------------------------------------------------------ signals


class StopSignal(threading.Event):
    """Set by SIGINT or SIGTERM; ``signal_name`` says which (empty until then)."""

    signal_name = ""


@contextlib.contextmanager
def stop_on_signals() -> Iterator[StopSignal]:
    """An event set by SIGINT or SIGTERM while the block runs, so that a command can finish its
    work (close files, stop what it started) instead of dying mid-write. Previous handlers are
    restored after."""
    stop = StopSignal()

    def handler(signum: int, frame: FrameType | None) -> None:
        stop.signal_name = signal.Signals(signum).name
        stop.set()

    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            # A SIGINT ignored on purpose (a background job of a shell, nohup) stays ignored.
            if sig == signal.SIGINT and signal.getsignal(sig) == signal.SIG_IGN:
                continue
            previous[sig] = signal.signal(sig, handler)
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
