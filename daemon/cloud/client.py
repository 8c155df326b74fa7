"""A small typed subscriber API for wristscan's clouds; import it from the stable public path
``wristscan.daemon.client``:

```python
from wristscan.daemon.client import CloudClient

with CloudClient("wristscan/sim", connect=["tcp/127.0.0.1:7447"]) as client:
    cloud = client.recv(timeout=1.0)      # wsc1.Cloud or None
    if cloud is not None:
        print(cloud.seq, cloud.xyz.shape)  # numpy (N, 3) float32, metres
```

Received payloads go into a ring of ``capacity`` batches: when the consumer is slower than the
daemon the oldest batches are dropped (and counted in ``dropped``), so memory stays bounded no
matter how slow the consumer is. Decoding happens in the consumer's thread, on ``recv``.

Security settings (TLS, user/password, access control) come from a zenoh JSON5 file:
``config_file``, else the per-user client config (``$WRISTSCAN_ZENOH_CONFIG``, else
``~/.config/wristscan/zenoh.json5`` when it exists; see ``docs/security.md``). A session that
cannot be opened raises :class:`ZenohSetupError` (one line).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import deque
from collections.abc import Iterator, Sequence
from typing import Any, Literal, Self

import zenoh

from wristscan.daemon.cloud import wsc1
from wristscan.daemon.cloud.session import ZenohSetupError, open_session, user_client_config

__all__ = ["CloudClient", "Wsc1Error", "ZenohSetupError"]

Wsc1Error = wsc1.Wsc1Error


class CloudClient:
    """Subscribe to ``<prefix>/cloud`` and query the daemon's status, stats and calibration."""

    def __init__(
        self,
        prefix: str,
        connect: Sequence[str] = (),
        listen: Sequence[str] = (),
        mode: Literal["peer", "client"] = "peer",
        capacity: int = 8,
        session: zenoh.Session | None = None,
        subscribe: bool = True,
        multicast_scouting: bool = False,
        config_file: str | os.PathLike[str] | None = None,
        shared_memory: bool = False,
        user_config: bool = True,
    ) -> None:
        """``subscribe`` False: only query/liveliness (no cloud traffic is pulled).
        ``config_file``: a zenoh JSON5 file with the security settings (None: the per-user
        client config when ``user_config``, else plain zenoh). ``shared_memory``: zenoh's
        shared memory between processes of one host (off: zenoh leaves its files in
        ``/dev/shm``)."""
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.prefix = prefix.rstrip("/")
        self._own_session = session is None
        if session is None:
            session = open_session(
                mode,
                connect,
                listen,
                multicast_scouting,
                config_file=(
                    config_file
                    if config_file is not None or not user_config
                    else user_client_config()
                ),
                shared_memory=shared_memory,
            )
        self.session = session
        self._ring: deque[bytes] = deque(maxlen=capacity)
        self._cond = threading.Condition()
        self.received = 0
        self.dropped = 0
        self.malformed = 0
        self._closed = False
        self._sub = (
            self.session.declare_subscriber(f"{self.prefix}/cloud", self._on_sample)
            if subscribe
            else None
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        with self._cond:
            if len(self._ring) == self._ring.maxlen:
                self.dropped += 1
            self._ring.append(data)
            self.received += 1
            self._cond.notify()

    def recv(self, timeout: float | None = None) -> wsc1.Cloud | None:
        """The oldest batch held, or ``None`` after ``timeout`` seconds. Malformed payloads are
        counted in ``malformed`` and skipped."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._cond:
                while not self._ring:
                    if self._closed:
                        return None
                    remaining = None if deadline is None else deadline - time.monotonic()
                    if remaining is not None and remaining <= 0:
                        return None
                    self._cond.wait(remaining)
                data = self._ring.popleft()
            try:
                return wsc1.decode(data)
            except wsc1.Wsc1Error:
                self.malformed += 1

    def __iter__(self) -> Iterator[wsc1.Cloud]:
        while not self._closed:
            cloud = self.recv(timeout=0.5)
            if cloud is not None:
                yield cloud

    def query(self, what: Literal["stats", "calibration"], timeout: float = 2.0) -> dict[str, Any]:
        """Ask the daemon's queryable; raises ``TimeoutError`` when no daemon answers."""
        for reply in self.session.get(f"{self.prefix}/{what}", timeout=timeout):
            if reply.ok is not None:
                result: dict[str, Any] = json.loads(reply.ok.payload.to_string())
                return result
            if reply.err is not None:
                raise RuntimeError(f"{what} query failed: {reply.err.payload.to_string()}")
        raise TimeoutError(f"no wristscan daemon answered on {self.prefix}/{what}")

    def alive(self, timeout: float = 2.0) -> bool:
        """True when the daemon's liveliness token is present."""
        replies = self.session.liveliness().get(f"{self.prefix}/alive", timeout=timeout)
        return any(r.ok is not None for r in replies)

    def close(self) -> None:
        if self._closed:
            return
        if self._sub is not None:
            self._sub.undeclare()
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._own_session:
            self.session.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
