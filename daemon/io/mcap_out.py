"""MCAP recordings that Foxglove (and ``ros2 bag``'s MCAP storage) play: extra ``mcap``.

Profile ``ros2``; every message is CDR (:mod:`wristscan.daemon.cloud.ros2msg`) under a
``ros2msg`` schema holding the message definition text:

- ``/wristscan/cloud``: ``sensor_msgs/msg/PointCloud2``, one per batch (record) or pass (scan);
- ``/wristscan/flange_pose``: ``geometry_msgs/msg/PoseStamped`` of the flange in the base frame,
  one per batch when the robot pose is known;
- ``/wristscan/sensor_pose``: ``PoseStamped`` of the sensor in the frame of the clouds (a scan:
  the trail of the sensor, drawn with the clouds in one display frame).

A message's log and publish times are its header stamp (the exposure time), so the file plays
on the timeline of the acquisition. Messages are streamed into compressed chunks of 1 MiB, so
memory stays bounded on long recordings; LZ4 by default (it keeps up with the daemon at 5 kHz,
benchmarks/formats.py: zstd packs a scanned surface a quarter tighter at half the speed),
``compression="zstd"`` or ``"none"`` on request; Foxglove reads all three. The file is written
through :func:`atomic_writer`: it appears complete under its name when
:meth:`McapCloudWriter.close` returns, or not at all.
"""

from __future__ import annotations

import os
from contextlib import AbstractContextManager
from pathlib import Path
from typing import IO, Literal, cast

import numpy as np
from mcap.writer import CompressionType, Writer
from numpy.typing import NDArray

from wristscan.daemon.cloud import ros2msg
from wristscan.daemon.io.atomic import CloseOrAbort, atomic_writer

__all__ = ["CLOUD_TOPIC", "POSE_TOPIC", "SENSOR_POSE_TOPIC", "McapCloudWriter"]

CLOUD_TOPIC = "/wristscan/cloud"
POSE_TOPIC = "/wristscan/flange_pose"
SENSOR_POSE_TOPIC = "/wristscan/sensor_pose"
_COMPRESSION = {
    "lz4": CompressionType.LZ4,
    "zstd": CompressionType.ZSTD,
    "none": CompressionType.NONE,
}


class _Abort(Exception):
    """Thrown into the atomic writer to make it drop the temporary file."""


class McapCloudWriter(CloseOrAbort):
    """Stream clouds (and robot poses) into an MCAP file; see the module doc."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        cloud_topic: str = CLOUD_TOPIC,
        pose_topic: str = POSE_TOPIC,
        metadata: dict[str, str] | None = None,
        compression: Literal["lz4", "zstd", "none"] = "lz4",
    ) -> None:
        self.path = Path(path)
        self.n_points = 0
        self.n_clouds = 0
        self.n_poses = 0
        self._pose_topic = pose_topic
        self._pose_channels: dict[str, int] = {}
        self._pose_seq: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._closed = False
        self._atomic: AbstractContextManager[IO[bytes]] = atomic_writer(self.path)
        f = self._atomic.__enter__()
        try:
            self._writer = Writer(f, compression=_COMPRESSION[compression])
            self._writer.start(profile="ros2", library="wristscan")
            if metadata:
                self._writer.add_metadata("wristscan", dict(metadata))
            self._cloud = self._channel(cloud_topic, ros2msg.POINTCLOUD2)
        except BaseException:
            self.abort()
            raise

    def _channel(self, topic: str, typename: str) -> int:
        schema = self._schemas.get(typename)
        if schema is None:
            schema = self._writer.register_schema(
                name=typename,
                encoding="ros2msg",
                data=ros2msg.message_definition(typename).encode("utf-8"),
            )
            self._schemas[typename] = schema
        return self._writer.register_channel(topic, message_encoding="cdr", schema_id=schema)

    @property
    def closed(self) -> bool:
        return self._closed

    def write_cloud(
        self,
        xyz: NDArray[np.floating],
        stamp_ns: int,
        frame_id: str,
        intensity: NDArray[np.integer] | NDArray[np.floating] | None = None,
    ) -> None:
        """One ``PointCloud2`` of ``xyz`` (N, 3) metres stamped ``stamp_ns`` (UTC ns)."""
        if self._closed:
            raise ValueError(f"{self.path}: writer is closed")
        # bytes-like: the writer copies it into its chunk (typed bytes, takes any buffer)
        data = cast(bytes, ros2msg.cloud_cdr(xyz, stamp_ns, frame_id, intensity))
        self._writer.add_message(self._cloud, int(stamp_ns), data, int(stamp_ns), self.n_clouds)
        self.n_clouds += 1
        self.n_points += int(np.shape(xyz)[0])

    def write_pose(
        self,
        transform: NDArray[np.floating],
        stamp_ns: int,
        frame_id: str = "base",
        topic: str | None = None,
    ) -> None:
        """One ``PoseStamped`` of ``transform`` (4x4, e.g. flange in base) at ``stamp_ns`` on
        ``topic`` (the flange pose topic unless told; a channel per topic)."""
        if self._closed:
            raise ValueError(f"{self.path}: writer is closed")
        topic = topic or self._pose_topic
        if topic not in self._pose_channels:
            self._pose_channels[topic] = self._channel(topic, ros2msg.POSE_STAMPED)
            self._pose_seq[topic] = 0
        data = ros2msg.pose_cdr(transform, stamp_ns, frame_id)
        seq = self._pose_seq[topic]
        self._writer.add_message(
            self._pose_channels[topic], int(stamp_ns), data, int(stamp_ns), seq
        )
        self._pose_seq[topic] = seq + 1
        self.n_poses += 1

    def close(self) -> Path:
        """Write the summary and put the file in place; returns its path. On failure nothing is
        left behind and the error propagates."""
        if self._closed:
            return self.path
        try:
            self._writer.finish()
        except BaseException:
            self.abort()
            raise
        self._closed = True
        self._atomic.__exit__(None, None, None)
        return self.path

    def abort(self) -> None:
        """Drop everything written so far; nothing appears under ``path``."""
        if self._closed:
            return
        self._closed = True
        exc = _Abort()
        self._atomic.__exit__(_Abort, exc, None)
