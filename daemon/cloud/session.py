"""Every zenoh session wristscan opens (the daemon's, ``CloudClient``'s, the CLI's) gets its
configuration from :func:`session_config`: the mode, endpoints, scouting and shared memory of
wristscan's settings over an optional zenoh JSON5 file holding the security settings (TLS
certificates, user/password, access control; see ``docs/security.md``).

- The daemon's file is ``[zenoh] config_file``.
- A client's file (``wristscan status``, ``record``, ``view``, ``CloudClient``) is the per-user
  client config: the file named by ``$WRISTSCAN_ZENOH_CONFIG`` (set but empty: none), else
  ``~/.config/wristscan/zenoh.json5`` when it exists (:func:`user_client_config`).

Relative file paths inside a zenoh config file (certificates, keys, the password dictionary)
are taken relative to that file's folder. A session that cannot be opened raises
:class:`ZenohSetupError`, one line naming the endpoints or the file; no message and no log line
ever shows the configuration itself (it may hold a password).
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import zenoh

__all__ = [
    "CLIENT_CONFIG_ENV",
    "FILE_KEYS",
    "USER_CLIENT_CONFIG",
    "ZenohSetupError",
    "check_config_file",
    "load_config_file",
    "open_session",
    "session_config",
    "user_client_config",
    "zenoh_reason",
]

log = logging.getLogger(__name__)

Mode = Literal["peer", "client", "router"]

CLIENT_CONFIG_ENV = "WRISTSCAN_ZENOH_CONFIG"
"""Environment variable naming a client's zenoh config file (set but empty: none)."""
USER_CLIENT_CONFIG = "~/.config/wristscan/zenoh.json5"
"""The per-user client config, used when it exists and ``$WRISTSCAN_ZENOH_CONFIG`` is unset."""

FILE_KEYS = (
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/connect_certificate",
    "transport/link/tls/connect_private_key",
    "transport/auth/usrpwd/dictionary_file",
    "transport/auth/pubkey/public_key_file",
    "transport/auth/pubkey/private_key_file",
    "transport/auth/pubkey/known_keys_file",
)
"""The keys of a zenoh config that name files (resolved against the config file's folder)."""

_SOURCE_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_PARSE_AT = re.compile(r"-->\s*(\d+):(\d+)")
_PARSE_WHY = re.compile(r"^\s*=\s*(.+)$", re.MULTILINE)
_SERDE_MSG = re.compile(r'msg:\s*"(?P<msg>[^"]*?)(?:, expected one of[^"]*)?"')
_SERDE_AT = re.compile(r"line:\s*(\d+),\s*column:\s*(\d+)")


class ZenohSetupError(RuntimeError):
    """A zenoh session could not be opened or configured: an endpoint that cannot be bound or
    reached, a zenoh config file missing, unreadable or invalid, a certificate or password file
    zenoh refused. The message is one line naming the endpoints or the file (never the
    configuration's content); the zenoh error, when there is one, is the ``__cause__``."""


def zenoh_reason(exc: BaseException) -> str:
    """zenoh's message on one line, without the Rust source locations it carries."""
    text = _SOURCE_LOCATION.sub("", str(exc))
    return " ".join(text.split()).rstrip(".") or type(exc).__name__


def _parse_reason(exc: BaseException) -> str:
    """Where and why a JSON5 file failed to parse, without echoing its lines (they may hold a
    password)."""
    text = _SOURCE_LOCATION.sub("", str(exc))
    at, why = _PARSE_AT.search(text), _PARSE_WHY.search(text)
    if at is not None:
        reason = why.group(1).strip() if why is not None else "syntax error"
        return f"line {at.group(1)} column {at.group(2)}: {reason}"
    msg, at = _SERDE_MSG.search(text), _SERDE_AT.search(text)
    if msg is not None:
        where = f"line {at.group(1)} column {at.group(2)}: " if at is not None else ""
        return f"{where}{msg.group('msg')}"
    return zenoh_reason(exc)


def load_config_file(path: str | os.PathLike[str]) -> zenoh.Config:
    """A zenoh JSON5 config file, its relative file paths resolved against its folder (``~``
    expanded); raises :class:`ZenohSetupError` naming the file when it is missing, unreadable
    or invalid."""
    file = Path(path).expanduser()
    try:
        with file.open("rb"):
            pass
    except OSError as exc:
        raise ZenohSetupError(f"zenoh config {file}: {exc.strerror or exc}") from exc
    try:
        conf = zenoh.Config.from_file(str(file))
    except zenoh.ZError as exc:
        raise ZenohSetupError(f"zenoh config {file}: {_parse_reason(exc)}") from exc
    folder = file.resolve().parent
    for key in FILE_KEYS:
        value = json.loads(conf.get_json(key))
        if isinstance(value, str) and value:
            resolved = folder / Path(value).expanduser()  # an absolute path stays as it is
            if str(resolved) != value:
                conf.insert_json5(key, json.dumps(str(resolved)))
    return conf


def check_config_file(path: str | os.PathLike[str], tls_listen: bool = False) -> list[str]:
    """What stops a zenoh config file from working, one line each (empty: none found): the file
    missing, unreadable or invalid, a file it names (certificate, key, password dictionary)
    missing or unreadable, passwords (the file's own, the dictionary) everyone may read, and
    with ``tls_listen`` a TLS listener without its certificate and key."""
    try:
        conf = load_config_file(path)
    except ZenohSetupError as exc:
        return [str(exc)]
    problems = []
    password = json.loads(conf.get_json("transport/auth/usrpwd/password"))
    if isinstance(password, str) and Path(path).expanduser().stat().st_mode & 0o004:
        problems.append("holds a password and every user may read it (chmod o-r)")
    for key in FILE_KEYS:
        value = json.loads(conf.get_json(key))
        if isinstance(value, str) and value:
            try:
                with open(value, "rb") as file:
                    mode = os.fstat(file.fileno()).st_mode
            except OSError as exc:
                problems.append(f"{key} {value}: {exc.strerror or exc}")
                continue
            if (
                key.endswith(("dictionary_file", "private_key", "private_key_file"))
                and mode & 0o004
            ):
                problems.append(f"{key} {value}: every user may read it (chmod o-r)")
    if tls_listen:
        for key in FILE_KEYS[1:3]:
            if not isinstance(json.loads(conf.get_json(key)), str):
                problems.append(f"a tls/ or quic/ listen endpoint needs {key}")
    return problems


def user_client_config() -> Path | None:
    """The zenoh config file of a client run by this user: ``$WRISTSCAN_ZENOH_CONFIG`` when set
    (empty: none), else ``~/.config/wristscan/zenoh.json5`` when it exists, else ``None``."""
    named = os.environ.get(CLIENT_CONFIG_ENV)
    if named is not None:
        return Path(named).expanduser() if named.strip() else None
    default = Path(USER_CLIENT_CONFIG).expanduser()
    return default if default.is_file() else None


def _explicit_list(conf: zenoh.Config, key: str) -> bool:
    """True when the file set ``key`` to a list (zenoh's default is a per-mode table)."""
    return isinstance(json.loads(conf.get_json(key)), list)


def session_config(
    mode: Mode = "peer",
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    multicast_scouting: bool = False,
    *,
    config_file: str | os.PathLike[str] | None = None,
    shared_memory: bool = False,
) -> zenoh.Config:
    """The configuration of every wristscan zenoh session: ``config_file`` (a zenoh JSON5
    file: TLS, user/password, access control, tuning) under wristscan's settings. The mode,
    multicast scouting and shared memory are always wristscan's; an endpoint list wristscan
    leaves empty keeps the file's list when the file sets one. Multicast scouting stays off
    unless asked for, so a cell PC never talks to whatever else is on the plant network by
    accident. Shared memory is off by default: zenoh leaves its segment files in ``/dev/shm``
    after the process ends."""
    conf = zenoh.Config() if config_file is None else load_config_file(config_file)
    try:
        conf.insert_json5("mode", json.dumps(mode))
        if connect or config_file is None or not _explicit_list(conf, "connect/endpoints"):
            conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if mode != "client" and (
            listen or config_file is None or not _explicit_list(conf, "listen/endpoints")
        ):
            conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(shared_memory))
    except zenoh.ZError as exc:
        raise ZenohSetupError(f"bad zenoh setting: {zenoh_reason(exc)}") from exc
    return conf


def _describe(mode: Mode, connect: Sequence[str], listen: Sequence[str], file: object) -> str:
    parts: list[str] = [mode]
    if listen:
        parts.append("listen " + ", ".join(listen))
    if connect:
        parts.append("connect " + ", ".join(connect))
    if file is not None:
        parts.append(f"zenoh config {file}")
    return "; ".join(parts)


def open_session(
    mode: Mode = "peer",
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    multicast_scouting: bool = False,
    *,
    config_file: str | os.PathLike[str] | None = None,
    shared_memory: bool = False,
) -> zenoh.Session:
    """Open a zenoh session configured by :func:`session_config`; raises
    :class:`ZenohSetupError` (one line: the endpoints, the file and zenoh's reason) when an
    endpoint cannot be bound, a client finds no router, or zenoh refuses a certificate or
    password file."""
    conf = session_config(
        mode,
        connect,
        listen,
        multicast_scouting,
        config_file=config_file,
        shared_memory=shared_memory,
    )
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        where = _describe(mode, connect, listen, config_file)
        reason = zenoh_reason(exc)
        raise ZenohSetupError(f"cannot open a zenoh session ({where}): {reason}") from exc
    log.debug("zenoh session %s opened (%s)", session.zid(), _describe(mode, connect, listen, None))
    return session
