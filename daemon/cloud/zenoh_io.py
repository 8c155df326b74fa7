"""The daemon's zenoh face: the keys of the WSC1 contract (DESIGN.md). Sessions are opened by
:func:`open_session` (from :mod:`.session`: security settings, :class:`ZenohSetupError`).

| key | what |
|---|---|
| ``<prefix>/cloud`` | aligned point batches, WSC1, encoding ``application/octet-stream;wsc1`` |
| ``<prefix>/pose`` | the robot pose of every profile of each batch, WSP1 (``wsp1``), same ``seq`` |
| ``<prefix>/status`` | JSON health/status, published periodically |
| ``<prefix>/alive`` | liveliness token while the daemon runs |
| ``<prefix>/calibration`` | queryable: the calibration in force, JSON |
| ``<prefix>/stats`` | queryable: counters, JSON |
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
import zenoh
from numpy.typing import NDArray

from wristscan.daemon.cloud import wsc1, wsp1
from wristscan.daemon.cloud.session import ZenohSetupError, open_session, session_config
from wristscan.daemon.cloud.shm import ShmPayloads

__all__ = ["DaemonZenoh", "ZenohSetupError", "open_session", "session_config"]

log = logging.getLogger(__name__)

JsonFn = Callable[[], dict[str, Any]]


class DaemonZenoh:
    """Publisher, liveliness token and queryables of one daemon instance."""

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        congestion: Literal["drop", "block"] = "drop",
        calibration: JsonFn | None = None,
        stats: JsonFn | None = None,
        shm_pool_bytes: int = 0,
    ) -> None:
        """``shm_pool_bytes``: a zenoh shared memory pool of that size for the cloud batches
        (:class:`~wristscan.daemon.cloud.shm.ShmPayloads`; the session must have shared memory
        on); 0: none. A pool that cannot be made is logged and the batches go as plain bytes."""
        self.session = session
        self.prefix = prefix.rstrip("/")
        cc = zenoh.CongestionControl.DROP if congestion == "drop" else zenoh.CongestionControl.BLOCK
        self._cloud = session.declare_publisher(
            f"{self.prefix}/cloud",
            encoding=zenoh.Encoding(wsc1.ENCODING),
            congestion_control=cc,
        )
        self._pose = session.declare_publisher(
            f"{self.prefix}/pose", encoding=zenoh.Encoding(wsp1.ENCODING), congestion_control=cc
        )
        self._status = session.declare_publisher(
            f"{self.prefix}/status", encoding=zenoh.Encoding("application/json")
        )
        self._token = session.liveliness().declare_token(f"{self.prefix}/alive")
        self._calibration_fn = calibration or dict
        self._stats_fn = stats or dict
        self._queryables = [
            session.declare_queryable(
                f"{self.prefix}/calibration",
                self._answer(f"{self.prefix}/calibration", lambda: self._calibration_fn()),
            ),
            session.declare_queryable(
                f"{self.prefix}/stats",
                self._answer(f"{self.prefix}/stats", lambda: self._stats_fn()),
            ),
        ]
        self.seq = 0
        self.published = 0
        self._closed = False
        self.shm: ShmPayloads | None = None
        if shm_pool_bytes > 0:
            try:
                self.shm = ShmPayloads(shm_pool_bytes)
            except RuntimeError as exc:
                log.warning("%s; cloud batches go as plain bytes", exc)

    @staticmethod
    def _answer(key: str, fn: JsonFn) -> Callable[[zenoh.Query], None]:
        """Reply on the queryable's own key, so an asker with a wildcard (``wristscan/**/stats``,
        ``wristscan cells``) knows which daemon answered."""

        def on_query(query: zenoh.Query) -> None:
            try:
                body = json.dumps(fn())
            except Exception as exc:  # a bad reply must reach the asker, not kill zenoh's thread
                log.exception("query %s failed", query.key_expr)
                query.reply_err(json.dumps({"error": str(exc)}))
                return
            query.reply(key, body, encoding=zenoh.Encoding("application/json"))

        return on_query

    def set_sources(self, calibration: JsonFn | None = None, stats: JsonFn | None = None) -> None:
        """Swap what the queryables answer (after a reload)."""
        if calibration is not None:
            self._calibration_fn = calibration
        if stats is not None:
            self._stats_fn = stats

    def publish_cloud(
        self,
        xyz: NDArray[np.floating] | wsc1.Wsc1Frame,
        t_first_ns: int,
        t_last_ns: int,
        n_profiles: int,
        frame_id: str,
        intensity: NDArray[np.uint8] | None = None,
        profile_index: NDArray[np.integer] | None = None,
    ) -> int:
        """Publish one batch; returns its sequence number (consecutive: a gap means loss).

        ``xyz`` (N, 3) metres with the optional per-point blocks, or a :class:`wsc1.Wsc1Frame`
        the points (and its blocks) were written into: its header is written and its buffer
        put as it is (``intensity`` and ``profile_index`` must then be None: they are the
        frame's own)."""
        if isinstance(xyz, wsc1.Wsc1Frame):
            if intensity is not None or profile_index is not None:
                raise ValueError("with a Wsc1Frame, intensity and profile_index are its own")
            frame = xyz
        else:
            frame = wsc1.frame_of(xyz, intensity, profile_index)
        payload = frame.finish(
            seq=self.seq,
            t_first_ns=t_first_ns,
            t_last_ns=t_last_ns,
            n_profiles=n_profiles,
            frame_id=frame_id,
        )
        # zenoh copies a bytearray once; a shared buffer is passed on as it is
        self._cloud.put(payload if self.shm is None else self.shm.wrap(payload))
        self.seq += 1
        self.published += 1
        return self.seq - 1

    def publish_pose(
        self,
        seq: int,
        frame_id: str,
        t_ns: NDArray[np.integer],
        flange2base: NDArray[np.floating],
        sensor2frame: NDArray[np.floating],
    ) -> None:
        """The poses of batch ``seq``'s profiles (WSP1): exposure UTC ns (P,), flange in base and
        sensor in ``frame_id`` (P, 4, 4), metres."""
        self._pose.put(wsp1.encode(seq, frame_id, t_ns, flange2base, sensor2frame))

    def publish_status(self, status: dict[str, Any]) -> None:
        self._status.put(json.dumps(status))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for q in self._queryables:
            q.undeclare()
        self._token.undeclare()
        self._cloud.undeclare()
        self._pose.undeclare()
        self._status.undeclare()
