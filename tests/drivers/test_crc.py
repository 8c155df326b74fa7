"""The LPF1 reader's CRC-32 (ISA-L's when installed) gives zlib's values."""

from __future__ import annotations

import zlib

import numpy as np

from wristscan.drivers import _crc


def test_crc32_is_zlibs_on_every_length_and_start() -> None:
    rng = np.random.default_rng(3)
    data = rng.integers(0, 256, 9000, dtype=np.uint8).tobytes()
    view = memoryview(data)
    for n in (0, 1, 3, 7, 64, 65, 4167, 4168, 8999):
        for start in (0, 0xFFFFFFFF, 0x2144DF1C):
            assert _crc.crc32(view[1 : 1 + n], start) == zlib.crc32(view[1 : 1 + n], start)
    # The residue the block reader tests: a message followed by its own CRC, little-endian.
    msg = data[:4200]
    assert _crc.crc32(msg + zlib.crc32(msg).to_bytes(4, "little")) == 0x2144DF1C


def test_the_test_install_has_the_fast_crc() -> None:
    # pyproject's test extra installs isal: the figures in docs/benchmarks.md assume it.
    assert _crc.fast
