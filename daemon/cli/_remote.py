"""Reaching a running daemon over zenoh, for the verbs that talk to one (``status``,
``record``): where it is (prefix, endpoints, mode, from a config file, the command line or the
embedded default), opening a client, and waiting for its liveliness token (exit 130 when a
signal, see :func:`._common.stop_on_signals`, ended the wait).

The security settings of the client session (TLS, user/password) come from the per-user client
config: ``$WRISTSCAN_ZENOH_CONFIG``, else ``~/.config/wristscan/zenoh.json5`` (see
:func:`wristscan.daemon.cloud.session.user_client_config` and ``docs/security.md``).
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, NoReturn

import typer

from wristscan.daemon.cli._common import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE, fail

if TYPE_CHECKING:
    from wristscan.daemon.cloud.client import CloudClient

__all__ = [
    "ConfigOpt",
    "ConnectOpt",
    "ModeOpt",
    "PrefixOpt",
    "Target",
    "TimeoutOpt",
    "no_answer",
    "open_client",
    "resolve_target",
    "wait_alive",
]

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
    typer.Option("--timeout", help="Seconds to wait for the daemon to answer (>= 0.1)."),
]

_ANY_ADDRESS = re.compile(r"^(?P<proto>[a-z-]+)/(?P<host>0\.0\.0\.0|\[::\])(?P<rest>:.*)$")


@dataclass(frozen=True)
class Target:
    """Where a daemon is reached: its key prefix and how to open a zenoh session towards it."""

    prefix: str
    connect: tuple[str, ...]
    mode: Literal["peer", "client"]
    zenoh_config: Path | None = None
    """The client's zenoh config file (security settings), None: plain zenoh."""

    def describe(self) -> str:
        eps = ", ".join(self.connect) if self.connect else "no endpoints"
        extra = f", zenoh config {self.zenoh_config}" if self.zenoh_config is not None else ""
        return f"{self.prefix} ({self.mode}, {eps}{extra})"


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
    fail(f"--mode must be 'peer' or 'client', got {value!r}", EXIT_USAGE)


def _check_prefix(prefix: str) -> str:
    key = prefix.rstrip("/")
    if not key or any(c in key for c in "*$?# ") or "//" in key or key.startswith("/"):
        fail(
            f"--prefix must be a plain zenoh key such as wristscan/sim, got {prefix!r}", EXIT_USAGE
        )
    return key


def resolve_target(
    config: Path | None, prefix: str | None, connect: list[str] | None, mode: str | None
) -> Target:
    """The daemon to talk to. A config file (or, without one, the embedded default config of the
    simulated cell) gives the prefix and endpoints; ``--prefix``, ``--connect``, ``--mode``
    override them. In peer mode we connect to the endpoints the daemon listens on. The client's
    security settings are the per-user client config, if any."""
    from wristscan.daemon.cloud.session import user_client_config

    zconf = user_client_config()
    if config is None and prefix is not None and connect:
        # Everything given: skip the config module (its import alone takes a second or more).
        return Target(_check_prefix(prefix), tuple(connect), _mode(mode or "peer"), zconf)

    from wristscan.daemon.config import ConfigError, load_config, load_default

    try:
        cfg = load_default() if config is None else load_config(config)
    except ConfigError as exc:
        for line in exc.problems:
            typer.echo(line, err=True)
        fail(f"{exc.source}: not usable", EXIT_USAGE)
    z = cfg.zenoh
    chosen = _mode(mode if mode is not None else z.mode)
    if connect:
        endpoints = tuple(connect)
    else:
        listen = [_reachable(ep) for ep in z.listen] if z.mode == "peer" else []
        endpoints = tuple(dict.fromkeys([*z.connect, *listen]))
    if chosen == "client" and not endpoints:
        fail("client mode needs a router endpoint: give --connect", EXIT_USAGE)
    key = _check_prefix(prefix if prefix is not None else z.prefix)
    return Target(key, endpoints, chosen, zconf)


def open_client(target: Target, capacity: int, subscribe: bool = True) -> CloudClient:
    """A :class:`CloudClient` towards ``target``; a bad endpoint or zenoh config file is a user
    error (exit 2, one line)."""
    import zenoh

    from wristscan.daemon.cloud.client import CloudClient
    from wristscan.daemon.cloud.session import ZenohSetupError, zenoh_reason

    try:
        return CloudClient(
            target.prefix,
            connect=list(target.connect),
            mode=target.mode,
            capacity=capacity,
            subscribe=subscribe,
            config_file=target.zenoh_config,
        )
    except ZenohSetupError as exc:
        fail(str(exc), EXIT_USAGE)
    except zenoh.ZError as exc:
        fail(f"zenoh refused ({target.describe()}): {zenoh_reason(exc)}", EXIT_USAGE)


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


def no_answer(target: Target, timeout: float, stop: threading.Event) -> NoReturn:
    """End a command whose daemon did not answer: exit 130 when a signal stopped the wait,
    else 1 with the reason."""
    if stop.is_set():
        raise typer.Exit(EXIT_INTERRUPTED)
    fail(f"no wristscan daemon answered on {target.describe()} within {timeout:g} s", EXIT_FAILED)
