"""``wristscan status``: the daemon's status, counters and liveliness over zenoh."""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any

import typer

from wristscan.daemon.cli._common import EXIT_FAILED, check_number, fail, stop_on_signals, table
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


def state_text(status: Any) -> str | None:
    """``degraded: no profiles for 3 s``, ``waiting: waiting for robot for 12 s (...)``,
    ``running``: the daemon's state and what is degraded, from its status message."""
    if not isinstance(status, Mapping) or "state" not in status:
        return None
    degraded = status.get("degraded")
    if isinstance(degraded, list) and degraded:
        return f"{status['state']}: " + "; ".join(str(d) for d in degraded)
    return str(status["state"])


def render(snap: Mapping[str, Any], timeout: float) -> list[str]:
    """The human-readable report of one snapshot."""
    lines = [f"daemon   {snap['prefix']}", f"alive    {'yes' if snap['alive'] else 'no'}"]
    status = snap["status"]
    state = state_text(status)
    if state is not None:
        lines.append(f"state    {state}")
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
    check_number("--timeout", timeout, ge=0.1)
    target = resolve_target(config, prefix, connect, mode)
    with stop_on_signals() as stop:
        client = open_client(target, capacity=1, subscribe=False)
        listener = None
        try:
            listener = _StatusListener(client)
            # Liveliness may be blocked by an access policy while the topics still flow.
            if not wait_alive(client, timeout, stop) and (
                stop.is_set() or listener.wait_new(0, 0.5, stop) == 0
            ):
                no_answer(target, timeout, stop)
            seen = listener.wait_new(0, timeout, stop)
            clear = watch and not as_json and sys.stdout.isatty()
            while True:
                snap = _snapshot(client, listener, timeout)
                if not watch and not _answered(snap):
                    fail(f"the daemon on {target.describe()} stopped answering", EXIT_FAILED)
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
