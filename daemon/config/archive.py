"""The ``[archive]`` section: where finished scans are kept and for how long (docs/plant.md).

``wristscan scan`` copies each finished job's merged cloud and report into ``dir``; the oldest
jobs go beyond ``keep`` jobs or ``max_mb``; the running daemon serves them on
``<prefix>/scans``. ``dir`` empty (the default) is the daemon's state directory:
``$STATE_DIRECTORY/scans`` under systemd (``/var/lib/wristscan/scans``), else
``~/.local/state/wristscan/scans``; a relative ``dir`` is taken from the config file's folder.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

from pydantic import Field, ValidationInfo, field_validator

from wristscan.daemon.config.values import Bool, Float, Str, StrictModel

__all__ = ["ArchiveConfig", "default_archive_root"]


def default_archive_root() -> Path:
    state = os.environ.get("STATE_DIRECTORY")
    if state:
        return Path(state.split(":")[0]) / "scans"
    return Path.home() / ".local" / "state" / "wristscan" / "scans"


class ArchiveConfig(StrictModel):
    enabled: Bool = True
    """Keep finished scans and serve them; off: neither."""
    dir: Str = ""
    """The archive folder; empty: the state directory's ``scans`` (see the module doc)."""
    keep: Annotated[int, Field(ge=1, le=100_000)] = 100
    """At most this many jobs (the oldest go first)."""
    max_mb: Annotated[Float, Field(gt=0, le=10_000_000)] = 2000.0
    """At most this many megabytes (10**6 bytes) of files; the newest job is always kept."""

    @field_validator("dir")
    @classmethod
    def _dir(cls, v: str, info: ValidationInfo) -> str:
        if not v:
            return v
        path = Path(os.path.expanduser(v))
        base = (info.context or {}).get("base_dir")
        if not path.is_absolute() and base is not None:
            path = Path(base) / path
        return os.path.normpath(path)

    @property
    def root(self) -> Path:
        return Path(self.dir) if self.dir else default_archive_root()

    @property
    def max_bytes(self) -> int:
        return int(self.max_mb * 1e6)
