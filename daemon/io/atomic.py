"""The one way wristscan replaces a file: all of the new content or none of it.

Calibrations, reports, clouds, plans and scripts are read by other programs (the daemon at
SIGHUP, a robot program, a viewer) and written while the machine can lose power or fill its
disk. Every writer therefore goes through :func:`atomic_writer`: the content goes to a temporary
file in the target's folder, which is flushed, fsynced and renamed over the target, then the
folder is fsynced so that the rename itself survives a power cut. On any failure the temporary
file is removed and the target is left exactly as it was.

Mode policy (one for every file): a file that is replaced keeps its permissions (an operator who
made a calibration group-readable keeps it so); a new file gets what a plain ``open()`` would
give it, ``0o666`` less the process umask.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Self

__all__ = ["atomic_writer", "fsync_dir", "process_umask", "write_atomic"]

log = logging.getLogger(__name__)


def process_umask() -> int:
    """The process umask, read without changing it (``os.umask`` can only be read by setting it,
    which would race with other threads creating files)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def _mode_for(target: Path) -> int:
    try:
        return os.stat(target).st_mode & 0o777
    except FileNotFoundError:
        return 0o666 & ~process_umask()


def fsync_dir(directory: Path) -> None:
    """Make the rename durable. Some file systems refuse fsync on a folder: that only weakens
    durability after a power cut, so it is logged, not raised."""
    try:
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        log.warning("cannot open %s to fsync it: %s", directory, exc)
        return
    try:
        os.fsync(fd)
    except OSError as exc:
        log.warning("fsync of folder %s failed: %s", directory, exc)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike[str]) -> Iterator[IO[bytes]]:
    """A binary file to write the new content of ``path`` into. On a clean exit of the block it
    replaces ``path`` (flushed, fsynced, renamed, folder fsynced); on an exception the temporary
    file is removed and ``path`` is untouched."""
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    mode = _mode_for(target)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    try:
        os.fchmod(fd, mode)  # mkstemp makes the file private (0600)
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    fsync_dir(directory)


def write_atomic(path: str | os.PathLike[str], data: bytes | str) -> Path:
    """Replace ``path`` with ``data`` (text is written as UTF-8) through :func:`atomic_writer`;
    returns the path."""
    with atomic_writer(path) as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)
    return Path(path)


class CloseOrAbort:
    """A file writer as a context manager: the block ending normally closes it (the file lands),
    an exception aborts it (nothing lands, the exception goes on)."""

    def close(self) -> object:
        """Finish the file (what it returns is the writer's own: e.g. the path written)."""
        raise NotImplementedError

    def abort(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
