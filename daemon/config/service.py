"""The sections about how the daemon runs: ``[sync]`` (pairing profiles with robot states),
``[pipeline]`` (batching and what is published), ``[zenoh]`` (the network) and
``[calibration]`` (the calibration files in force).

Relative paths (calibration files, an extra zenoh config) are resolved against the folder of the
config file, passed as ``base_dir`` in the validation context.
"""

from __future__ import annotations

import os
import re
import socket
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from wristscan.daemon.config.values import (
    Bool,
    Float,
    Int,
    Str,
    StrictModel,
    cross_field,
    render_value,
)

__all__ = ["CalibrationConfig", "PipelineConfig", "SyncConfig", "ZenohConfig"]

_ENDPOINT_NET = re.compile(
    r"^(tcp|udp|tls|quic|ws)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+):(\d{1,5})(#\S*)?$"
)
_ENDPOINT_OTHER = re.compile(r"^(unixsock-stream|serial)/\S+$")


def _bind_problem(host: str) -> str | None:
    """Why a listener could not be bound on ``host`` (it does not resolve, or is no address of
    this machine), or None. Binds port 0 only: the configured port may be the running daemon's."""
    name = host[1:-1] if host.startswith("[") else host
    try:
        infos = socket.getaddrinfo(name, 0, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        return f"the host {host!r} does not resolve ({getattr(exc, 'strerror', None) or exc})"
    family, _, _, _, address = infos[0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            sock.bind(address)
    except OSError as exc:
        return f"cannot listen on {host!r}: {exc.strerror or exc} (not an address of this host?)"
    return None


def _resolve_path(value: str | None, info: ValidationInfo) -> Path | None:
    if value is None:
        return None
    path = Path(os.path.expanduser(value))
    base = (info.context or {}).get("base_dir")
    if not path.is_absolute() and base is not None:
        path = Path(base) / path
    return Path(os.path.normpath(path))


class SyncConfig(StrictModel):
    interpolation: Literal["joint", "tcp"] = "joint"
    """``joint``: interpolate joint positions then forward kinematics; ``tcp``: the TCP pose."""
    pairing: Literal["clock", "encoder"] = "clock"
    """Pair profiles to robot states by time (clock) or by the sensor's encoder input."""
    max_gap_s: Annotated[Float, Field(gt=0, le=1.0)] = 0.020
    """Largest spacing of the two robot samples a profile is interpolated between."""
    table_max_gap_s: Annotated[Float, Field(gt=0, le=10.0)] = 0.200
    max_wait_s: Annotated[Float, Field(gt=0, le=10.0)] = 0.200
    """How long a profile may wait for the robot states after it before it is dropped."""
    clock_window_s: Annotated[Float, Field(gt=0, le=3600)] = 30.0
    """Sliding window of the device-to-host clock fit."""
    clock_max_uncertainty_s: Annotated[Float, Field(gt=0, le=0.1)] = 200e-6
    """A clock mapping is trusted while its uncertainty stays below this."""
    robot_latency_s: Annotated[Float, Field(ge=0, le=1.0)] = 0.0
    table_latency_s: Annotated[Float, Field(ge=0, le=1.0)] = 0.0
    encoder_bits: Annotated[Int, Field(ge=8, le=64)] | None = None
    """Width of the sensor's encoder counter (None: does not wrap)."""


class PipelineConfig(StrictModel):
    batch_s: Annotated[Float, Field(gt=0, le=1.0)] = 0.010
    """Profiles are aligned and published in batches of this length."""
    profile_queue: Annotated[Int, Field(ge=16, le=1_000_000)] = 4096
    """Profiles waiting for pairing at most (the oldest are dropped beyond)."""
    batch_queue: Annotated[Int, Field(ge=1, le=1024)] = 8
    """Aligned batches waiting for publication at most."""
    frame: Literal["base", "table", "part"] = "base"
    """Frame of the published points; ``table`` and ``part`` need a ``[table]``."""
    publish_raw_profiles: Bool = False
    publish_robot_state: Bool = False
    publish_intensity: Bool = False
    publish_profile_index: Bool = False
    shed_overload: Bool = True
    """When profiles arrive faster than the daemon can process them, shed whole profiles evenly
    (counted as ``overload``) and keep publishing near capacity, instead of falling behind
    (docs/pipeline.md, "Overload")."""
    overload_lag_s: Annotated[Float, Field(gt=0.0, le=10.0)] = 0.1
    """Shedding starts when the oldest profile waiting for admission is older than this."""


class ZenohConfig(StrictModel):
    mode: Literal["peer", "client"] = "peer"
    connect: list[Str] = Field(default_factory=list)
    """Endpoints to connect to, e.g. ``tcp/192.168.1.10:7447``."""
    listen: list[Str] = Field(default_factory=list)
    multicast_scouting: Bool = False
    """Off by default: on a cell network the endpoints are known and scouting crosses cells."""
    prefix: Str = ""
    """Key prefix (default ``wristscan/<cell.name>``)."""
    congestion_control: Literal["drop", "block"] = "drop"
    """``drop``: a slow network loses batches (seq gaps) rather than stalling acquisition."""
    status_period_s: Annotated[Float, Field(gt=0, le=3600)] = 1.0
    config_file: Str | None = None
    """An extra zenoh JSON5 config merged under these settings (TLS, authentication, ACL; see
    ``docs/security.md``). Loading only resolves the path (a client reading this config on
    another machine has no such file); :meth:`problems` checks it for ``check-config`` and
    ``run``."""
    shared_memory: Bool = False
    """zenoh's shared memory towards subscribers on this host: the cloud batches are written
    into a pool of ``shm_pool_mb`` and passed by reference (a third of zenoh's cost at 10 kHz,
    docs/pipeline.md); zenoh leaves small segment files in ``/dev/shm`` when the daemon exits
    (docs/security.md)."""
    shm_pool_mb: Annotated[Int, Field(ge=4, le=4096)] = 64
    """Size of the shared memory pool of the cloud batches (MiB): a batch whose subscribers on
    this host still hold the pool's buffers goes as plain bytes (counted)."""

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for i, ep in enumerate(v):
            m = _ENDPOINT_NET.match(ep)
            if m is not None:
                if not 1 <= int(m.group(3)) <= 65535:
                    raise ValueError(f"item {i}: port out of range in {ep!r}")
            elif not _ENDPOINT_OTHER.match(ep):
                raise ValueError(
                    f"item {i}: not a zenoh endpoint {ep!r} (expected e.g. 'tcp/127.0.0.1:7447')"
                )
        return v

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, v: str) -> str:
        chunks = v.split("/")
        if not v or any(not c for c in chunks) or re.search(r"[*$?#\s]", v):
            raise ValueError(
                "not a plain zenoh key: non-empty chunks separated by '/', no wildcards "
                "('*', '$'), '?', '#' or spaces"
            )
        return v

    @field_validator("config_file")
    @classmethod
    def _config_file(cls, v: str | None, info: ValidationInfo) -> str | None:
        path = _resolve_path(v, info)
        return None if path is None else str(path)

    @model_validator(mode="after")
    def _client_needs_router(self) -> ZenohConfig:
        if self.mode == "client" and not self.connect:
            raise cross_field(
                "connect", 'mode = "client" needs at least one endpoint to connect to'
            )
        return self

    @model_validator(mode="after")
    def _tls_needs_a_certificate(self) -> ZenohConfig:
        if self.config_file is None and any(self._tls_listen()):
            raise cross_field(
                "config_file",
                "a tls/ or quic/ listen endpoint needs a config_file with the certificate and key "
                "(docs/security.md)",
            )
        return self

    def _tls_listen(self) -> list[bool]:
        return [ep.startswith(("tls/", "quic/")) for ep in self.listen]

    def problems(self) -> list[str]:
        """What stops the daemon's zenoh session on this machine, known without opening it, one
        line each (``zenoh.<key>: ...``; empty: nothing): a listen host that does not resolve or
        is no address of this host (port 0 is bound, not the configured port: the running
        daemon may hold it); a zenoh config file missing, unreadable or invalid, a file it names
        missing, a password, dictionary or private key everyone may read, a TLS listener without
        certificate and key."""
        out = []
        for i, ep in enumerate(self.listen):
            m = _ENDPOINT_NET.match(ep)
            problem = None if m is None else _bind_problem(m.group(2))
            if problem is not None:
                out.append(f"zenoh.listen: item {i}: {problem}")
        if self.config_file is not None:
            from wristscan.daemon.cloud.session import check_config_file

            found = check_config_file(self.config_file, tls_listen=any(self._tls_listen()))
            out += [f"zenoh.config_file: {p}" for p in found]
        return out


class CalibrationConfig(StrictModel):
    file: Path | None = None
    """The sensor2flange calibration (JSON, see :mod:`wristscan.daemon.io.calibfile`); relative
    paths are resolved against the config file's folder. None: no calibration yet."""
    table_file: Path | None = None
    """The rotary-table calibration (``kind = "table"``)."""
    check_identity: Bool = True
    """Refuse a calibration made for another robot or sensor."""

    @field_validator("file", "table_file", mode="before")
    @classmethod
    def _paths(cls, v: Any, info: ValidationInfo) -> Any:
        if isinstance(v, str):
            if not v:
                raise ValueError("must not be empty (leave the key out for none)")
            return _resolve_path(v, info)
        if v is None or isinstance(v, Path):
            return v
        raise ValueError(f"must be a path string (got {render_value(v)})")
