"""CRC-32 (IEEE 802.3, zlib's) for the LPF1 frames: ISA-L's when installed, else zlib's.

Every LPF1 datagram is checked whole; at 10 kHz x 2048 points that is ~42 MB/s. zlib's table
CRC costs ~1.9 us per 4.2 KB datagram here, ISA-L's (carry-less multiply, ``isal``, extra
``fast``) ~0.2 us: the same values (``tests/drivers/test_crc.py``).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable

__all__ = ["crc32", "fast"]

crc32: Callable[..., int]
"""``crc32(data, start=0)``: zlib's signature and values."""

try:
    from isal.isal_zlib import crc32 as _isal_crc32
except ImportError:  # the core install: zlib's
    crc32 = zlib.crc32
    fast = False
    """ISA-L's CRC in use."""
else:
    crc32 = _isal_crc32
    fast = True
