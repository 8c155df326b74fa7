"""Giving the heap's free memory back to the system, so that the daemon's RSS is what it uses.

glibc serves a large block (above ``M_MMAP_THRESHOLD``, 128 kB at first) with its own mapping
and unmaps it when freed, but raises that threshold up to 32 MB whenever such a block is
freed: from then on the hot path's megabyte arrays come from the heap, whose free pages stay
resident. The RSS then climbs in steps for minutes to a level that depends on the largest
backlog seen (benchmarks/faults.py ``--soak``: +12 % in 120 s, a plateau only after ~10 min)
and says little about what the daemon holds. Fixing the threshold keeps the RSS flat but maps
and faults in every array afresh (+40 % CPU on the hot path, measured); returning the free
pages every few seconds (``malloc_trim``) costs a fraction of a millisecond each time.
"""

from __future__ import annotations

import ctypes
import sys
from collections.abc import Callable

__all__ = ["release_free_heap"]


def _load() -> Callable[[int], int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None).malloc_trim  # glibc; musl has none
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


_malloc_trim = _load()


def release_free_heap() -> bool:
    """Return the free pages of every malloc arena to the system (glibc ``malloc_trim(0)``);
    False where the C library has no such call (nothing done)."""
    if _malloc_trim is None:
        return False
    _malloc_trim(0)
    return True
