"""``wristscan status``: the daemon's status, counters and liveliness over zenoh.

Also home of what ``status`` and ``record`` share: where the daemon is (prefix, endpoints, mode,
from a config file, the command line or the embedded default), waiting for its liveliness token,
and stopping cleanly on SIGINT/SIGTERM.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
import signal
import sys
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer

if TYPE_CHECKING:
    from wristscan.daemon.cloud.client import CloudClient
# ------------------------------------------------------------------------------ shared options

ConfigOpt = Annotated[
    Path | None,
    typer.Option(
        "--config",
        "-c",
        help="Daemon config file: prefix and endpoints come from its \\[zenoh] section.",
        show_default=False,
    ),
]
PrefixOpt = Annotated[
    str | None,
    typer.Option(
        "--prefix",
        help="zenoh key prefix of the daemon (default: from the config, else wristscan/sim).",
        show_default=False,
    ),
]
ConnectOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--connect",
        "-e",
        help="zenoh endpoint to reach the daemon, e.g. tcp/127.0.0.1:7447 (repeatable; "
        "default: the config's endpoints).",
        show_default=False,
    ),
]
ModeOpt = Annotated[
    str | None,
    typer.Option(
        "--mode", help="zenoh mode: peer, or client (through a router).", show_default=False
    ),
]
TimeoutOpt = Annotated[
    float,
    typer.Option("--timeout", min=0.1, help="Seconds to wait for the daemon to answer."),
]

_ANY_ADDRESS = re.compile(r"^(?P<proto>[a-z-]+)/(?P<host>0\.0\.0\.0|\[::\])(?P<rest>:.*)$")


@dataclass(frozen=True)
class Target:
    """Where a daemon is reached: its key prefix and how to open a zenoh session towards it."""

    prefix: str
    connect: tuple[str, ...]
    mode: Literal["peer", "client"]

    def describe(self) -> str:
        eps = ", ".join(self.connect) if self.connect else "no endpoints"
        return f"{self.prefix} ({self.mode}, {eps})"


def fail(message: str, code: int) -> typer.Exit:
    """Print a one-line error on stderr; ``raise fail(...)`` ends the command with ``code``."""
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code)


def _reachable(endpoint: str) -> str:
    """A daemon listening on every interface is reached on the loopback one from its host."""
    m = _ANY_ADDRESS.match(endpoint)
    if m is None:
        return endpoint
    host = "127.0.0.1" if m["host"] == "0.0.0.0" else "[::1]"
    return f"{m['proto']}/{host}{m['rest']}"


def _mode(value: str) -> Literal["peer", "client"]:
    if value == "peer":
        return "peer"
    if value == "client":
        return "client"
    raise fail(f"--mode must be 'peer' or 'client', got {value!r}", 2)


def _check_prefix(prefix: str) -> str:
    key = prefix.rstrip("/")
    if not key or any(c in key for c in "*$?# ") or "//" in key or key.startswith("/"):
        raise fail(f"--prefix must be a plain zenoh key such as wristscan/sim, got {prefix!r}", 2)
    return key


def resolve_target(
    config: Path | None, prefix: str | None, connect: list[str] | None, mode: str | None
) -> Target:
    """The daemon to talk to. A config file (or, without one, the embedded default config of the
    simulated cell) gives the prefix and endpoints; ``--prefix``, ``--connect``, ``--mode``
    override them. In peer mode we connect to the endpoints the daemon listens on."""
    if config is None and prefix is not None and connect:
        # Everything given: skip the config module (its import alone takes a second or more).
        return Target(_check_prefix(prefix), tuple(connect), _mode(mode or "peer"))

    from wristscan.daemon.config import ConfigError, load_config, load_default

    try:
        cfg = load_default() if config is None else load_config(config)
    except ConfigError as exc:
        for line in exc.problems:
            typer.echo(line, err=True)
        raise fail(f"{exc.source}: not usable", 2) from None
    z = cfg.zenoh
    chosen = _mode(mode if mode is not None else z.mode)
    if connect:
        endpoints = tuple(connect)
    else:
        listen = [_reachable(ep) for ep in z.listen] if z.mode == "peer" else []
        endpoints = tuple(dict.fromkeys([*z.connect, *listen]))
    if chosen == "client" and not endpoints:
        raise fail("client mode needs a router endpoint: give --connect", 2)
    return Target(_check_prefix(prefix if prefix is not None else z.prefix), endpoints, chosen)


def open_client(target: Target, capacity: int, subscribe: bool = True) -> CloudClient:
    """A :class:`CloudClient` towards ``target``; a bad endpoint is a user error (exit 2)."""
    import zenoh

    from wristscan.daemon.cloud.client import CloudClient

    try:
        return CloudClient(
            target.prefix,
            connect=list(target.connect),
            mode=target.mode,
            capacity=capacity,
            subscribe=subscribe,
        )
    except zenoh.ZError as exc:
        raise fail(f"cannot open a zenoh session ({target.describe()}): {exc}", 2) from None


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM while the block runs, so that a command can finish its
    work (close files) instead of dying mid-write. Previous handlers are restored after."""
    stop = threading.Event()

    def handler(signum: int, frame: FrameType | None) -> None:
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


def wait_alive(client: CloudClient, timeout: float, stop: threading.Event) -> bool:
    """Wait up to ``timeout`` s for the daemon's liveliness token (the session may still be
    connecting: a query then returns at once with nothing, hence the retries)."""
    deadline = time.monotonic() + timeout
    while not stop.is_set():
        remaining = deadline - time.monotonic()
        if client.alive(timeout=max(0.05, min(0.5, remaining))):
            return True
        if remaining <= 0:
            return False
        stop.wait(min(0.1, max(remaining, 0.0)))
    return False


# ------------------------------------------------------------------------------ formatting


def _value_text(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else str(value)
    if isinstance(value, str):
        return value
    return json.dumps(value, separators=(",", ":"))


def flatten(data: Mapping[str, Any], parent: str = "") -> list[tuple[str, str]]:
    """Nested mappings as ``(dotted.key, text)`` rows, in their order."""
    rows: list[tuple[str, str]] = []
    for key, value in data.items():
        name = f"{parent}.{key}" if parent else str(key)
        if isinstance(value, Mapping) and value:
            rows += flatten(value, name)
        elif isinstance(value, Mapping):
            rows.append((name, "-"))
        else:
            rows.append((name, _value_text(value)))
    return rows


def table(rows: list[tuple[str, str]], indent: str = "  ") -> list[str]:
    """Aligned ``key  value`` lines."""
    width = max((len(k) for k, _ in rows), default=0)
    return [f"{indent}{k.ljust(width)}  {v}" for k, v in rows]


def _count(value: Any) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def breakdown(stats: Mapping[str, Any]) -> str | None:
    """``received R = published P + dropped D (reason n, ...)`` when the counters allow it.

    The published-side term is whichever of ``published`` / ``paired`` (with ``pending`` when
    present) makes the sum add up; otherwise the shortfall is stated, because a mismatch is
    itself worth seeing.
    """
    received = _count(stats.get("received"))
    if received is None:
        return None
    raw_dropped = stats.get("dropped", 0)
    reasons: dict[str, int] = {}
    if isinstance(raw_dropped, Mapping):
        reasons = {str(k): v for k, v in raw_dropped.items() if _count(v) is not None}
        dropped = sum(reasons.values())
    else:
        dropped = _count(raw_dropped) or 0
    candidates: list[list[str]] = []
    for main in ("published", "paired"):
        if _count(stats.get(main)) is not None:
            if _count(stats.get("pending")) is not None:
                candidates.append([main, "pending"])
            candidates.append([main])
    if not candidates:
        return None
    chosen = next(
        (c for c in candidates if sum(stats[k] for k in c) + dropped == received), candidates[0]
    )
    terms = [f"{k} {stats[k]}" for k in chosen]
    drop = f"dropped {dropped}"
    if reasons:
        drop += " (" + ", ".join(f"{k} {v}" for k, v in reasons.items()) + ")"
    total = sum(stats[k] for k in chosen) + dropped
    text = f"received {received} = " + " + ".join([*terms, drop])
    if total != received:
        text += f"  [does not add up: {received - total:+d}]"
    return text


# ------------------------------------------------------------------------------ the command


class _StatusListener:
    """The latest message on ``<prefix>/status`` (JSON), with its host receive time."""

    def __init__(self, client: CloudClient) -> None:
        self._cond = threading.Condition()
        self._latest: tuple[int, dict[str, Any] | str] | None = None
        self._count = 0
        self._sub = client.session.declare_subscriber(f"{client.prefix}/status", self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        text = sample.payload.to_string()
        try:
            body: dict[str, Any] | str = json.loads(text)
            if not isinstance(body, dict):
                body = {"value": body}
        except ValueError:
            body = text
        with self._cond:
            self._latest = (time.monotonic_ns(), body)
            self._count += 1
            self._cond.notify_all()

    def wait_new(self, seen: int, timeout: float, stop: threading.Event) -> int:
        """Wait until more than ``seen`` messages arrived (or timeout/stop); the new count."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._count <= seen and not stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(min(remaining, 0.1))
            return self._count

    def latest(self) -> tuple[float, dict[str, Any] | str] | None:
        with self._cond:
            if self._latest is None:
                return None
            t, body = self._latest
        return (time.monotonic_ns() - t) * 1e-9, body

    def close(self) -> None:
        self._sub.undeclare()


def _snapshot(client: CloudClient, listener: _StatusListener, timeout: float) -> dict[str, Any]:
    alive = client.alive(timeout=min(timeout, 1.0))
    stats: dict[str, Any] | None = None
    stats_error: str | None = None
    try:
        stats = client.query("stats", timeout=timeout)
    except TimeoutError:
        stats_error = "no answer"
    except RuntimeError as exc:
        stats_error = str(exc)
    latest = listener.latest()
    snap: dict[str, Any] = {
        "prefix": client.prefix,
        "alive": alive,
        "status": latest[1] if latest else None,
        "status_age_s": round(latest[0], 3) if latest else None,
        "stats": stats,
    }
    if stats_error is not None:
        snap["stats_error"] = stats_error
    return snap


def _answered(snap: Mapping[str, Any]) -> bool:
    return bool(snap["alive"] or snap["status"] is not None or snap["stats"] is not None)


def render(snap: Mapping[str, Any], timeout: float) -> list[str]:
    """The human-readable report of one snapshot."""
    lines = [f"daemon   {snap['prefix']}", f"alive    {'yes' if snap['alive'] else 'no'}"]
    status = snap["status"]
    if status is None:
        lines.append(f"status   none received within {timeout:g} s")
    else:
        lines.append(f"status   (received {snap['status_age_s']:.1f} s ago)")
        if isinstance(status, dict):
            lines += table(flatten(status))
        else:
            lines.append(f"  not JSON: {str(status)[:200]!r}")
    stats = snap["stats"]
    if stats is None:
        lines.append(f"stats    {snap.get('stats_error', 'no answer')}")
    elif not stats:
        lines.append("stats    none reported")
    else:
        lines.append("stats")
        lines += table(flatten(stats))
        summary = breakdown(stats)
        if summary is not None:
            lines.append(f"  {summary}")
    return lines


def status(
    config: ConfigOpt = None,
    prefix: PrefixOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
    watch: Annotated[
        bool, typer.Option("--watch", "-w", help="Keep printing at every status message.")
    ] = False,
    timeout: TimeoutOpt = 3.0,
) -> None:
    """Show the daemon's status, counters and liveliness (exit 1 when no daemon answers)."""
    target = resolve_target(config, prefix, connect, mode)
    with stop_on_signals() as stop:
        client = open_client(target, capacity=1, subscribe=False)
        listener = None
        try:
            listener = _StatusListener(client)
            if not wait_alive(client, timeout, stop):
                if stop.is_set():
                    raise typer.Exit(130)
                # Liveliness may be blocked by an access policy while the topics still flow.
                if listener.wait_new(0, 0.5, stop) == 0:
                    raise fail(
                        f"no wristscan daemon answered on {target.describe()} within {timeout:g} s",
                        1,
                    )
            seen = listener.wait_new(0, timeout, stop)
            clear = watch and not as_json and sys.stdout.isatty()
            while True:
                snap = _snapshot(client, listener, timeout)
                if not watch and not _answered(snap):
                    raise fail(f"the daemon on {target.describe()} stopped answering", 1)
                if as_json:
                    typer.echo(json.dumps(snap))
                else:
                    if clear:
                        typer.echo("\x1b[H\x1b[J", nl=False)
                    typer.echo("\n".join(render(snap, timeout)))
                    if watch and not clear:
                        typer.echo("")
                if not watch or stop.is_set():
                    break
                seen = listener.wait_new(seen, max(timeout, 1.0), stop)
                if stop.is_set():
                    break
        finally:
            if listener is not None:
                listener.close()
            client.close()


def register(app: typer.Typer) -> None:
    app.command("status")(status)
