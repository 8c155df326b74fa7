"""Subscribe to a daemon's robot poses (``<prefix>/pose``, WSP1) beside its clouds.

```python
from wristscan.daemon.client import CloudClient
from wristscan.daemon.cloud.poses import PoseSubscriber

with CloudClient("wristscan/sim", connect=["tcp/127.0.0.1:7447"]) as client:
    poses = PoseSubscriber(client.session, client.prefix)
    for batch in poses.drain():           # wsp1.PoseBatch, oldest first
        print(batch.seq, batch.flange2base[-1][:3, 3])
```

A pose message follows its cloud batch on the same zenoh session (same ``seq``); the ring holds
at most ``capacity`` messages (the oldest are dropped and counted), so memory stays bounded.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Self

import zenoh

from wristscan.daemon.cloud import wsp1

__all__ = ["PoseSubscriber"]


class PoseSubscriber:
    """A bounded ring of the WSP1 messages received on ``<prefix>/pose``."""

    def __init__(self, session: zenoh.Session, prefix: str, capacity: int = 1024) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self._ring: deque[bytes] = deque(maxlen=capacity)
        self._lock = threading.Lock()
        self.received = 0
        self.dropped = 0
        self.malformed = 0
        self._sub: zenoh.Subscriber[None] | None = session.declare_subscriber(
            f"{prefix.rstrip('/')}/pose", self._on_sample
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        with self._lock:
            if len(self._ring) == self._ring.maxlen:
                self.dropped += 1
            self._ring.append(data)
            self.received += 1

    def drain(self) -> list[wsp1.PoseBatch]:
        """Every message held, decoded, oldest first (malformed ones counted and skipped)."""
        with self._lock:
            raw = list(self._ring)
            self._ring.clear()
        out = []
        for data in raw:
            try:
                out.append(wsp1.decode(data))
            except wsp1.Wsp1Error:
                self.malformed += 1
        return out

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
