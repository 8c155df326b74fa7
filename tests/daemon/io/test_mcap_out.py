"""MCAP recordings read back by the mcap ROS 2 decoder (what Foxglove uses) and by rosbags."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from wristscan.daemon.cloud import ros2msg
from wristscan.daemon.io.mcap_out import CLOUD_TOPIC, POSE_TOPIC, McapCloudWriter

T0 = 1_700_000_000_123_456_789


def _batches(n_batches: int = 4, n: int = 257) -> list[dict]:
    rng = np.random.default_rng(7)
    out = []
    for k in range(n_batches):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.5).as_matrix()
        pose[:3, 3] = rng.normal(size=3) * 0.3
        out.append(
            {
                "xyz": rng.normal(size=(n + k, 3)).astype(np.float32),
                "intensity": rng.integers(0, 256, n + k).astype(np.uint8),
                "stamp": T0 + k * 4_000_000,
                "pose": pose,
            }
        )
    return out


def _cloud_points(msg: object) -> tuple[np.ndarray, np.ndarray | None]:
    """Points of a decoded PointCloud2 read the way a ROS 2 user would: by the field table."""
    fields = {f.name: f for f in msg.fields}  # type: ignore[attr-defined]
    n = msg.width * msg.height  # type: ignore[attr-defined]
    step = msg.point_step  # type: ignore[attr-defined]
    raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(n, step)  # type: ignore[attr-defined]

    def col(name: str) -> np.ndarray:
        assert fields[name].datatype == 7 and fields[name].count == 1  # FLOAT32
        o = fields[name].offset
        return raw[:, o : o + 4].copy().view("<f4").ravel()

    xyz = np.stack([col("x"), col("y"), col("z")], axis=1)
    return xyz, (col("intensity") if "intensity" in fields else None)


def test_clouds_and_poses_read_back_by_the_ros2_decoder(tmp_path: Path) -> None:
    batches = _batches()
    path = tmp_path / "rec.mcap"
    with McapCloudWriter(path, metadata={"source": "test"}) as w:
        for i, b in enumerate(batches):
            # the first batch without intensity: the field is left out of that message
            w.write_cloud(b["xyz"], b["stamp"], "base", None if i == 0 else b["intensity"])
            w.write_pose(b["pose"], b["stamp"])
    assert os.listdir(tmp_path) == ["rec.mcap"]
    clouds, poses = [], []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema is not None and schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            if channel.topic == CLOUD_TOPIC:
                assert schema.name == "sensor_msgs/msg/PointCloud2"
                clouds.append((message, decoded))
            else:
                assert channel.topic == POSE_TOPIC
                assert schema.name == "geometry_msgs/msg/PoseStamped"
                poses.append((message, decoded))
    assert len(clouds) == len(poses) == len(batches)
    for i, (b, (message, msg)) in enumerate(zip(batches, clouds, strict=True)):
        xyz, inten = _cloud_points(msg)
        np.testing.assert_array_equal(xyz, b["xyz"])
        if i == 0:
            assert inten is None
        else:
            np.testing.assert_array_equal(inten, b["intensity"].astype(np.float32))
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == b["stamp"]
        assert msg.header.frame_id == "base"
        assert msg.is_bigendian is False and msg.height == 1
        assert message.log_time == message.publish_time == b["stamp"]
    for b, (_, msg) in zip(batches, poses, strict=True):
        p, q = msg.pose.position, msg.pose.orientation
        np.testing.assert_allclose([p.x, p.y, p.z], b["pose"][:3, 3], atol=1e-12)
        rot = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        np.testing.assert_allclose(rot, b["pose"][:3, :3], atol=1e-12)
        assert msg.header.frame_id == "base"
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == b["stamp"]


def test_rosbags_deserialises_the_recorded_cdr(tmp_path: Path) -> None:
    """Another deserialiser (rosbags, Humble's type store) reads the same bytes."""
    batches = _batches(2)
    path = tmp_path / "rec.mcap"
    with McapCloudWriter(path) as w:
        for b in batches:
            w.write_cloud(b["xyz"], b["stamp"], "part", b["intensity"])
    humble = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "rb") as f:
        msgs = [m for _, _, m in make_reader(f).iter_messages(topics=[CLOUD_TOPIC])]
    assert len(msgs) == 2
    for b, m in zip(batches, msgs, strict=True):
        assert m.data[:4] == b"\x00\x01\x00\x00"  # CDR little endian encapsulation
        msg = humble.deserialize_cdr(m.data, "sensor_msgs/msg/PointCloud2")
        xyz, inten = _cloud_points(msg)
        np.testing.assert_array_equal(xyz, b["xyz"])
        np.testing.assert_array_equal(inten, b["intensity"])
        assert msg.header.frame_id == "part"
        got = ros2msg.cdr_to_cloud(m.data)
        assert got.stamp_ns == b["stamp"]


def test_abort_leaves_nothing(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with pytest.raises(RuntimeError), McapCloudWriter(path) as w:
        w.write_cloud(np.zeros((3, 3), np.float32), T0, "base")
        raise RuntimeError("stopped")
    assert os.listdir(tmp_path) == []


def test_schema_is_the_ros2_message_definition() -> None:
    text = ros2msg.message_definition(ros2msg.POINTCLOUD2)
    assert text.startswith("std_msgs/Header header\n")
    assert "MSG: sensor_msgs/PointField" in text and "MSG: builtin_interfaces/Time" in text
    # the type hash ROS 2 Jazzy and Kilted compute (rmw_zenoh puts it in the key expression)
    expected = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
    for store in (Stores.ROS2_JAZZY, Stores.ROS2_KILTED):
        assert ros2msg.type_hash(ros2msg.POINTCLOUD2, store) == expected
