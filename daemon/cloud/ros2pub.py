"""The daemon as a ROS 2 publisher (``[ros2]``, docs/ros2.md): each batch also leaves as a
``sensor_msgs/msg/PointCloud2`` in CDR, on the same zenoh session as WSC1.

``rmw_zenoh`` mode speaks rmw_zenoh_cpp's wire contract (Humble 0.1.2+, Jazzy 0.2.4+, Kilted
0.6.x, Lyrical 0.10.x, Rolling up to 0.12; ``docs/design.md`` and
``src/detail/liveliness_utils.cpp`` / ``attachment_helpers.cpp`` of ros2/rmw_zenoh):

- data key ``<domain_id>/<topic without leading slash>/<DDS type name>/<type hash>``, e.g.
  ``0/wristscan/sim/cloud/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_9198...``; Humble, whose
  messages carry no type hash, puts ``TypeHashNotSupported``;
- payload: CDR with its 4-byte encapsulation header;
- attachment (zenoh-ext serialisation): sequence number int64 LE (from 1), source timestamp int64
  LE (UTC ns at publication), publisher GID as a sequence (LEB128 length ``0x10``, 16 bytes);
- liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<kind>/<enclave>/<namespace>/<node>``
  for the node (``NN``) and, with ``/<topic>/<type>/<hash>/<qos>`` appended, for each publisher
  (``MP``); every ``/`` inside a part is ``%``, QoS as rmw_zenoh's ``qos_to_keyexpr`` writes it
  against its defaults (reliable, volatile, keep last 42).

``bridge`` mode is what zenoh-bridge-ros2dds routes to DDS: key = topic name without its
leading slash, CDR payload, no attachment or tokens (the bridge makes its own).
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import xxhash
import zenoh
from numpy.typing import NDArray
from rosbags.typesys import Stores

from wristscan.daemon.cloud import ros2msg
from wristscan.daemon.cloud.shm import ShmPayloads
from wristscan.daemon.cloud.wsc1 import Wsc1Frame

if TYPE_CHECKING:  # the cloud room imports no configuration at run time
    from wristscan.daemon.config.ros2 import Ros2Config

__all__ = [
    "ADMIN_SPACE",
    "CLOUD_QOS",
    "TF_STATIC_QOS",
    "Ros2Publisher",
    "attachment",
    "data_key",
    "dds_type_name",
    "liveliness_key",
    "mangle",
    "type_hash_for",
]

log = logging.getLogger(__name__)

ADMIN_SPACE = "@ros2_lv"
CLOUD_QOS = "::,10:,:,:,,"
"""Reliable, volatile, keep last 10 (rclcpp's default profile): only the depth differs from
rmw_zenoh's default, so only it is written."""
TF_STATIC_QOS = ":1:,1:,:,:,,"
"""Transient local (1), keep last 1: what tf2's static broadcaster declares."""
_STORES = {
    "humble": Stores.ROS2_HUMBLE,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
    "lyrical": Stores.ROS2_LYRICAL,
    "rolling": Stores.ROS2_LYRICAL,
}
_GID_SIZE = 16
"""``RMW_GID_STORAGE_SIZE`` since Iron (rmw_zenoh uses 16 bytes on Humble too)."""


def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/PointCloud2`` -> ``sensor_msgs::msg::dds_::PointCloud2_``."""
    *ns, name = typename.split("/")
    return "::".join([*ns, "dds_", f"{name}_"])


def type_hash_for(typename: str, distro: str) -> str:
    """The type hash part of the key: RIHS01 from rosbags' store of ``distro``; Humble's
    rmw_zenoh writes ``TypeHashNotSupported``."""
    if distro == "humble":
        return "TypeHashNotSupported"
    return ros2msg.type_hash(typename, _STORES[distro])


def data_key(domain_id: int, topic: str, typename: str, type_hash: str) -> str:
    """rmw_zenoh's data key of a topic."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(typename)}/{type_hash}"


def mangle(name: str) -> str:
    """A name as one key chunk: ``/`` becomes ``%`` (so ``/`` alone is ``%``)."""
    return name.replace("/", "%")


def liveliness_key(
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    kind: str,
    namespace: str,
    node: str,
    topic: tuple[str, str, str, str] | None = None,
    enclave: str = "/",
) -> str:
    """rmw_zenoh's liveliness token key; ``topic`` is (name, DDS type, type hash, QoS)."""
    parts = [ADMIN_SPACE, str(domain_id), zid, str(node_id), str(entity_id), kind]
    parts += [mangle(enclave), mangle(namespace), mangle(node)]
    if topic is not None:
        name, typ, thash, qos = topic
        parts += [mangle(name), mangle(typ), mangle(thash), qos]
    return "/".join(parts)


def attachment(seq: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment rmw_zenoh subscribers read: int64 seq, int64 timestamp, GID sequence."""
    if len(gid) != _GID_SIZE:
        raise ValueError(f"a GID is {_GID_SIZE} bytes, got {len(gid)}")
    return struct.pack("<qqB", seq, source_timestamp_ns, _GID_SIZE) + gid


def gid_of(token_key: str) -> bytes:
    """The publisher's GID as rmw_zenoh makes it (``liveliness_utils.cpp``, ``Entity``): XXH3-128
    (seed 0) of the entity's whole liveliness key, its low 64 bits then its high 64 bits, each
    little-endian; so ``ros2 topic info -v`` and the attachment name the same publisher."""
    return int(xxhash.xxh3_128_intdigest(token_key.encode())).to_bytes(_GID_SIZE, "little")


class _Endpoint:
    """One rmw_zenoh publisher: its zenoh publisher, liveliness token, GID and sequence."""

    def __init__(self, pub: Any, token_key: str, gid: bytes) -> None:
        self.pub, self.token_key, self.gid = pub, token_key, gid
        self.seq = 1
        self.shm: ShmPayloads | None = None
        """The daemon's shared memory pool, when ``[zenoh] shared_memory`` is on."""

    def put(self, payload: bytes | bytearray, rmw: bool) -> None:
        att = attachment(self.seq, time.time_ns(), self.gid) if rmw else None
        if self.shm is not None:
            payload = self.shm.wrap(payload)
        self.pub.put(payload, attachment=att)  # no bytes() copy: a megabyte less per tick
        self.seq += 1


class Ros2Publisher:
    """PointCloud2 (and ``/tf_static``) publication on an open zenoh session."""

    def __init__(
        self,
        session: zenoh.Session,
        cfg: Ros2Config,
        cell_name: str,
        shm: ShmPayloads | None = None,
    ) -> None:
        """``shm``: the pool the PointCloud2 payloads are written into (the WSC1 face's)."""
        self.session = session
        self.cfg = cfg
        self.topic = cfg.topic_for(cell_name)
        self.rmw = cfg.mode == "rmw_zenoh"
        self.zid = str(session.info.zid())
        self.published = 0
        self.unmatched = 0
        """Batches not serialised because no subscriber matched."""
        self.errors = 0
        self._lock = threading.Lock()
        self._tokens: list[Any] = []
        self.node_key = liveliness_key(
            cfg.domain_id, self.zid, 0, 0, "NN", cfg.namespace, cfg.node_name
        )
        if self.rmw:
            self._tokens.append(session.liveliness().declare_token(self.node_key))
        self.cloud = self._endpoint(ros2msg.POINTCLOUD2, self.topic, 1, CLOUD_QOS)
        self.cloud.shm = shm
        self.tf: _Endpoint | None = None
        if cfg.tf_static:
            self.tf = self._endpoint(ros2msg.TF_MESSAGE, "/tf_static", 2, TF_STATIC_QOS)

    def key_for(self, typename: str, topic: str) -> str:
        """The data key of ``topic`` in this mode."""
        if not self.rmw:
            return topic.strip("/")
        return data_key(
            self.cfg.domain_id, topic, typename, type_hash_for(typename, self.cfg.distro)
        )

    def _endpoint(self, typename: str, topic: str, entity_id: int, qos: str) -> _Endpoint:
        key = self.key_for(typename, topic)
        cfg = self.cfg
        token_key = liveliness_key(
            cfg.domain_id,
            self.zid,
            0,
            entity_id,
            "MP",
            cfg.namespace,
            cfg.node_name,
            (topic, dds_type_name(typename), type_hash_for(typename, cfg.distro), qos),
        )
        if qos == TF_STATIC_QOS:
            # reliable + transient local as rmw_zenoh declares it: a cache of the last sample
            # that late subscribers (RViz started later) query, detection of this publisher,
            # sporadic heartbeats (500 ms) for sample-miss detection (which also spares the
            # session the timestamping a cache would otherwise need)
            pub: Any = zenoh.ext.declare_advanced_publisher(
                self.session,
                key,
                cache=zenoh.ext.CacheConfig(max_samples=1),
                publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    heartbeat=None, sporadic_heartbeat=0.5
                ),
            )
        else:
            pub = self.session.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.DROP,
                reliability=zenoh.Reliability.RELIABLE,
            )
        if self.rmw:
            self._tokens.append(self.session.liveliness().declare_token(token_key))
        return _Endpoint(pub, token_key, gid_of(token_key))

    @property
    def liveliness_keys(self) -> list[str]:
        """The tokens declared (rmw_zenoh mode): node, cloud publisher, ``/tf_static``."""
        if not self.rmw:
            return []
        return [self.node_key, self.cloud.token_key] + ([self.tf.token_key] if self.tf else [])

    def publish_cloud(
        self,
        xyz: NDArray[np.floating] | Wsc1Frame,
        t_first_ns: int,
        t_last_ns: int,
        n_profiles: int,
        frame_id: str,
        intensity: NDArray[np.integer] | None = None,
        profile_index: NDArray[np.integer] | None = None,
    ) -> int:
        """Publish one batch as PointCloud2 (``DaemonZenoh.publish_cloud``'s signature, ``xyz``
        an array or a :class:`Wsc1Frame` whose points and intensities are taken; the stamp is
        the batch's first exposure); returns the ROS sequence number used, or -1 when no
        subscriber matches (nothing is serialised then: no cost while nobody listens)."""
        if not self.cloud.pub.matching_status.matching:
            self.unmatched += 1
            return -1
        if isinstance(xyz, Wsc1Frame):
            intensity = xyz.intensity if intensity is None else intensity
            xyz = xyz.xyz
        payload = ros2msg.cloud_cdr(xyz, t_first_ns, self.cfg.frame_id(frame_id), intensity)
        with self._lock:
            seq = self.cloud.seq
            self.cloud.put(payload, self.rmw)
            self.published += 1
        return seq

    def tee(self, publish: Callable[..., int]) -> Callable[..., int]:
        """``publish`` (WSC1) followed by this PointCloud2; a ROS failure is logged and counted,
        never stops the WSC1 stream. Returns what ``publish`` returns. The arguments go to both
        as they are: with a :class:`Wsc1Frame` the PointCloud2 is built from ``frame.xyz``."""

        def both(*args: Any) -> int:
            seq = publish(*args)
            try:
                self.publish_cloud(*args)
            except Exception:
                self.errors += 1
                if self.errors == 1 or self.errors % 1000 == 0:
                    log.exception("ROS 2 publication failed (%d so far)", self.errors)
            return seq

        return both

    def publish_tf_static(self, sensor2flange: NDArray[np.floating], stamp_ns: int = 0) -> bool:
        """Publish the sensor frame in the flange frame on ``/tf_static`` (when configured);
        True if published."""
        if self.tf is None:
            return False
        payload = ros2msg.tf_cdr(
            sensor2flange, stamp_ns or time.time_ns(), self.cfg.flange_frame, self.cfg.sensor_frame
        )
        with self._lock:
            self.tf.put(payload, self.rmw)
        return True

    def close(self) -> None:
        for token in self._tokens:
            token.undeclare()
        self._tokens.clear()
        for ep in (self.cloud, self.tf):
            if ep is not None:
                ep.pub.undeclare()
