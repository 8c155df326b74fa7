"""Large payloads through zenoh's shared memory (``[zenoh] shared_memory``).

zenoh copies a ``bytes``/``bytearray`` payload when it is put, then cuts it into 64 kB batches
and writes them to every subscriber's socket. A payload that already lives in a zenoh shared
memory buffer goes to a subscriber on the same host (with shared memory on its side too) as a
reference of a few bytes, and to any other subscriber as a copy, as before. So the daemon writes
each cloud batch into a buffer of its own pool once and puts that: at 10 kHz x 2048 points
(2.4 MB every 10 ms) the daemon's zenoh cost per profile goes from ~20 us to ~6 us
(docs/pipeline.md). The pool's buffers come back when every subscriber has dropped them; when
none is free (a subscriber on this host holding many batches, a pool too small) the batch is
put as plain bytes instead and counted in :attr:`ShmPayloads.fallbacks`.
"""

from __future__ import annotations

import logging
from typing import Any

import zenoh

log = logging.getLogger(__name__)

__all__ = ["ShmPayloads"]


class ShmPayloads:
    """A pool of ``pool_bytes`` of zenoh shared memory for the payloads of one publisher.

    :meth:`wrap` gives a payload to put: the bytes copied into a shared buffer, or the bytes
    themselves when the pool has no room (``fallbacks``). Raises ``RuntimeError`` when the
    pool cannot be made (no ``/dev/shm``, too small a one)."""

    def __init__(self, pool_bytes: int, min_bytes: int = 65536) -> None:
        if pool_bytes <= 0:
            raise ValueError(f"a shared memory pool needs a size, got {pool_bytes}")
        import zenoh.shm as zshm  # zenoh's shared memory API is marked unstable: kept here

        self._zshm = zshm
        try:
            self._provider = zshm.ShmProvider.default_backend(int(pool_bytes))
        except zenoh.ZError as exc:
            raise RuntimeError(
                f"cannot make a zenoh shared memory pool of {pool_bytes / 2**20:.0f} MiB "
                f"in /dev/shm: {exc}"
            ) from exc
        self._policy = zshm.GarbageCollect(zshm.JustAlloc(), zshm.JustAlloc())
        self.pool_bytes = int(pool_bytes)
        self.min_bytes = int(min_bytes)
        """Payloads smaller than this go as they are: a reference saves nothing on them."""
        self.shared = 0
        """Payloads put through shared memory."""
        self.fallbacks = 0
        """Payloads put as plain bytes because the pool had no free buffer."""

    def wrap(self, payload: bytes | bytearray) -> Any:
        """``payload`` in a shared buffer of the pool (a ``zenoh.shm.ZShmMut``, consumed by the
        put), or ``payload`` itself when it is small or the pool is full."""
        n = len(payload)
        if n < self.min_bytes:
            return payload
        try:
            buf = self._provider.alloc(n, self._policy)
        except zenoh.ZError:
            self.fallbacks += 1
            if self.fallbacks == 1 or self.fallbacks % 1000 == 0:
                log.warning(
                    "zenoh shared memory pool (%.0f MiB) full: %d batches put as plain bytes "
                    "so far (a subscriber on this host holding batches? [zenoh] shm_pool_mb)",
                    self.pool_bytes / 2**20,
                    self.fallbacks,
                )
            return payload
        buf[:] = payload  # the one copy: zenoh takes the buffer as it is
        self.shared += 1
        return buf

    def counters(self) -> dict[str, int]:
        return {"shared": self.shared, "fallbacks": self.fallbacks}
