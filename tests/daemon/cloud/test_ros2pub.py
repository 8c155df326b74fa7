"""ROS 2 publication without ROS installed: rmw_zenoh's key, payload, attachment and liveliness
tokens over real zenoh sessions on loopback, checked against the layouts of rmw_zenoh's
sources (docs/ros2.md names the versions), and the CDR read back by rosbags.

The expected keys and bytes below are written out by hand from rmw_zenoh's
``liveliness_utils.cpp`` (``TopicInfo``, ``Entity``, ``qos_to_keyexpr``, ``mangle_name``) and
``attachment_helpers.cpp`` (``AttachmentData::serialize_to_zbytes``) with the zenoh-ext
serialisation format, never from the code under test."""

from __future__ import annotations

import gc
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import xxhash
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation
from support import publish_until, wait_for

from wristscan.calib import kinematics, se3
from wristscan.daemon.cloud import ros2msg, wsc1, wsp1
from wristscan.daemon.cloud.ros2pub import (
    Ros2Publisher,
    attachment,
    data_key,
    liveliness_key,
    type_hash_for,
)
from wristscan.daemon.cloud.zenoh_io import DaemonZenoh, open_session
from wristscan.daemon.config import ConfigError, load_config
from wristscan.daemon.config.loading import DEFAULT_CONFIG_RESOURCE, parse_config
from wristscan.daemon.config.ros2 import Ros2Config
from wristscan.daemon.io.calibfile import (
    Calibration,
    Residuals,
    RobotIdentity,
    SensorIdentity,
    write_calibration,
)
from wristscan.daemon.service.notify import Notifier
from wristscan.daemon.service.runtime import Service, StartupError, _ros2_class, load_setup
from wristscan.daemon.simcell.cell import dump_toml, free_sim_config, start_cell
from wristscan.drivers.sim.scene import sensor_looking_down

PC2_HASH = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
"""sensor_msgs/msg/PointCloud2 as ROS 2 Iron and later hash it (rosidl ``type_description``)."""
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
"""std_msgs/msg/String: the hash rmw_zenoh's own ``0/chatter/...`` examples carry."""
PC2_DDS = "sensor_msgs::msg::dds_::PointCloud2_"


def test_type_hash_is_what_rosbags_computes_per_distribution() -> None:
    for distro, store in (
        ("jazzy", Stores.ROS2_JAZZY),
        ("kilted", Stores.ROS2_KILTED),
        ("lyrical", Stores.ROS2_LYRICAL),
        ("rolling", Stores.ROS2_LYRICAL),
    ):
        ts = get_typestore(store)
        assert type_hash_for(ros2msg.POINTCLOUD2, distro) == ts.hash_rihs01(ros2msg.POINTCLOUD2)
        assert ts.hash_rihs01(ros2msg.POINTCLOUD2) == PC2_HASH
        assert ts.hash_rihs01("std_msgs/msg/String") == STRING_HASH
    # Humble's messages have no type hash: rmw_zenoh's humble branch puts a fixed word
    assert type_hash_for(ros2msg.POINTCLOUD2, "humble") == "TypeHashNotSupported"


def test_keys_and_attachment_match_rmw_zenoh_byte_for_byte() -> None:
    assert (
        data_key(0, "/wristscan/sim/cloud", ros2msg.POINTCLOUD2, PC2_HASH)
        == "0/wristscan/sim/cloud/sensor_msgs::msg::dds_::PointCloud2_/" + PC2_HASH
    )
    zid = "9a1b2c3d4e5f60718293a4b5c6d7e8f9"
    assert (
        liveliness_key(7, zid, 0, 0, "NN", "/", "wristscan")
        == "@ros2_lv/7/9a1b2c3d4e5f60718293a4b5c6d7e8f9/0/0/NN/%/%/wristscan"
    )
    assert liveliness_key(
        0, zid, 0, 1, "MP", "/cell", "wristscan", ("/a/b", PC2_DDS, PC2_HASH, "::,10:,:,:,,")
    ) == (
        "@ros2_lv/0/9a1b2c3d4e5f60718293a4b5c6d7e8f9/0/1/MP/%/%cell/wristscan/%a%b/"
        "sensor_msgs::msg::dds_::PointCloud2_/" + PC2_HASH + "/::,10:,:,:,,"
    )
    gid = bytes(range(0xA0, 0xB0))
    expected = bytes.fromhex(
        "0500000000000000"  # sequence_number int64 LE
        "01ca9a3b00000000"  # source_timestamp int64 LE: 1_000_000_001 = 0x3b9aca01
        "10"  # zenoh-ext sequence length (LEB128) of the 16-byte GID array
        "a0a1a2a3a4a5a6a7a8a9aaabacadaeaf"
    )
    assert attachment(5, 1_000_000_001, gid) == expected
    # zenoh's own deserialiser reads it as rmw_zenoh's (int64, int64, array<uint8_t, 16>)
    seq, stamp, got_gid = zenoh.ext.z_deserialize(
        tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes], zenoh.ZBytes(expected)
    )
    assert (seq, stamp, got_gid) == (5, 1_000_000_001, gid)
    with pytest.raises(ValueError, match="16 bytes"):
        attachment(1, 1, b"\x00" * 24)


def _config_text() -> str:
    root = Path(__file__).resolve().parents[3]
    return (root / "daemon" / DEFAULT_CONFIG_RESOURCE).read_text(encoding="utf-8")


def test_ros2_section() -> None:
    cfg = parse_config(_config_text() + "\n[ros2]\nenabled = true\ndomain_id = 3\n")
    r = cfg.ros2
    assert r.enabled and r.mode == "rmw_zenoh" and r.domain_id == 3 and not r.tf_static
    assert r.topic_for(cfg.cell.name) == f"/wristscan/{cfg.cell.name}/cloud"
    assert Ros2Config().topic_for("line-2.a") == "/wristscan/line_2_a/cloud"
    assert r.frame_id("part") == "part" and Ros2Config(base_frame="base_link").frame_id("base") == (
        "base_link"
    )
    assert parse_config(_config_text()).ros2.enabled is False
    # check-config's summary says where the clouds go in ROS 2 (only when enabled).
    assert f"/wristscan/{cfg.cell.name}/cloud (rmw_zenoh, domain 3)" in "\n".join(cfg.summary())
    assert not any(line.startswith("ros2") for line in parse_config(_config_text()).summary())
    with pytest.raises(ConfigError, match=r"ros2\.topic"):
        parse_config(_config_text() + '\n[ros2]\ntopic = "no/leading/slash"\n')
    with pytest.raises(ConfigError, match=r"ros2\.mode"):
        parse_config(_config_text() + '\n[ros2]\nmode = "dds"\n')


def test_rmw_zenoh_publication_reaches_a_plain_subscriber(endpoint: str) -> None:
    daemon_session = open_session(listen=[endpoint])
    peer = open_session(connect=[endpoint])
    try:
        face = DaemonZenoh(daemon_session, "wristscan/t")
        cfg = Ros2Config(enabled=True, domain_id=4, tf_static=True, base_frame="base_link")
        ros = Ros2Publisher(daemon_session, cfg, "t")
        zid = str(daemon_session.info.zid())
        key = f"4/wristscan/t/cloud/{PC2_DDS}/{PC2_HASH}"
        tf_hash = get_typestore(Stores.ROS2_JAZZY).hash_rihs01("tf2_msgs/msg/TFMessage")
        tf_key = f"4/tf_static/tf2_msgs::msg::dds_::TFMessage_/{tf_hash}"
        got: list[zenoh.Sample] = []
        wsc: list[zenoh.Sample] = []
        tf: list[zenoh.Sample] = []
        subs = [
            peer.declare_subscriber(key, got.append),
            peer.declare_subscriber("wristscan/t/cloud", wsc.append),
            peer.declare_subscriber(tf_key, tf.append),
        ]
        # the graph as rmw_zenoh's graph cache reads it: every token under @ros2_lv/<domain>
        tokens: set[str] = set()

        def graph() -> bool:
            tokens.update(str(r.ok.key_expr) for r in peer.liveliness().get("@ros2_lv/4/**"))
            return len(tokens) >= 3

        wait_for(graph, f"liveliness tokens never seen: {tokens}")
        assert tokens == {
            f"@ros2_lv/4/{zid}/0/0/NN/%/%/wristscan",
            f"@ros2_lv/4/{zid}/0/1/MP/%/%/wristscan/%wristscan%t%cloud/{PC2_DDS}/{PC2_HASH}"
            "/::,10:,:,:,,",
            f"@ros2_lv/4/{zid}/0/2/MP/%/%/wristscan/%tf_static/tf2_msgs::msg::dds_::TFMessage_/"
            f"{tf_hash}/:1:,1:,:,:,,",
        }
        assert set(ros.liveliness_keys) == tokens
        rng = np.random.default_rng(3)
        xyz = rng.normal(size=(2048, 3)).astype(np.float32)
        inten = rng.integers(0, 256, 2048).astype(np.uint8)
        publish = ros.tee(face.publish_cloud)
        t0 = 1_700_000_000_123_456_789
        t_pub = time.time_ns()

        publish_until(
            lambda: publish(xyz, t0, t0 + 5_000_000, 10, "base", inten, None),
            lambda: bool(got and wsc),
            "PointCloud2 never arrived on the rmw_zenoh key",
        )
        sample = got[0]
        assert str(sample.key_expr) == key
        msg = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(
            sample.payload.to_bytes(), ros2msg.POINTCLOUD2
        )
        assert sample.payload.to_bytes()[:4] == b"\x00\x01\x00\x00"  # CDR little endian
        assert (msg.height, msg.width, msg.point_step, msg.is_bigendian) == (1, 2048, 16, False)
        assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity"]
        assert msg.header.frame_id == "base_link"
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
        table = np.frombuffer(bytes(msg.data), "<f4").reshape(2048, 4)
        ref = wsc1.decode(wsc[0].payload.to_bytes())
        np.testing.assert_array_equal(table[:, :3], ref.xyz)
        assert ref.intensity is not None
        np.testing.assert_array_equal(table[:, 3], ref.intensity.astype(np.float32))
        assert ref.t_first_ns == t0
        assert sample.attachment is not None
        seq, stamp, gid = zenoh.ext.z_deserialize(
            tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes], sample.attachment
        )
        seqs = [
            zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes], s.attachment)[0]
            for s in got
            if s.attachment is not None
        ]
        assert seq >= 1 and seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
        assert t_pub <= stamp <= time.time_ns()
        # rmw_zenoh's GID: XXH3-128 of the publisher's liveliness key, low then high 64 bits LE
        cloud_token = next(t for t in tokens if "/0/1/MP/" in t)
        assert gid == xxhash.xxh3_128_intdigest(cloud_token.encode()).to_bytes(16, "little")
        assert gid == xxhash.xxh3_128(cloud_token.encode()).digest()[::-1]  # canonical is BE
        # /tf_static: the flange -> sensor transform, published at start-up (transient local)
        s2f = np.eye(4)
        s2f[:3, 3] = [0.01, -0.02, 0.15]
        ros.publish_tf_static(s2f, stamp_ns=5)
        wait_for(lambda: bool(tf), "/tf_static never arrived")
        tfm = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(
            tf[0].payload.to_bytes(), "tf2_msgs/msg/TFMessage"
        )
        (t,) = tfm.transforms
        assert (t.header.frame_id, t.child_frame_id) == ("flange", "wristscan_sensor")
        assert (t.transform.translation.x, t.transform.translation.z) == (0.01, 0.15)
        # a subscriber that comes later (RViz started after the daemon) still gets it, the way
        # rmw_zenoh's transient-local subscription asks: an advanced subscriber with history
        late: list[zenoh.Sample] = []
        late_sub = zenoh.ext.declare_advanced_subscriber(
            peer,
            tf_key,
            late.append,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        )
        wait_for(lambda: bool(late), "a late /tf_static subscriber got nothing")
        assert late[-1].payload.to_bytes() == tf[-1].payload.to_bytes()
        late_sub.undeclare()
        for s in subs:
            s.undeclare()
        ros.close()
        wait_for(
            lambda: not list(peer.liveliness().get("@ros2_lv/4/**")),
            "liveliness tokens outlived the publisher",
        )
        face.close()
    finally:
        peer.close()
        daemon_session.close()


def test_bridge_mode_key_is_the_topic(endpoint: str) -> None:
    daemon_session = open_session(listen=[endpoint])
    peer = open_session(connect=[endpoint])
    try:
        cfg = Ros2Config(enabled=True, mode="bridge", topic="/scan/cloud")
        ros = Ros2Publisher(daemon_session, cfg, "x")
        assert ros.liveliness_keys == []
        xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
        # nobody subscribes yet: nothing is serialised or sent
        assert ros.publish_cloud(xyz, 42, 43, 1, "part") == -1 and ros.unmatched == 1
        got: list[zenoh.Sample] = []
        sub = peer.declare_subscriber("scan/cloud", got.append)

        publish_until(
            lambda: ros.publish_cloud(xyz, 42, 43, 1, "part"),
            lambda: bool(got),
            "bridge-mode PointCloud2 never arrived",
        )
        assert got[0].attachment is None
        back = ros2msg.cdr_to_cloud(got[0].payload.to_bytes())
        np.testing.assert_array_equal(back.xyz, xyz)
        assert (back.stamp_ns, back.frame_id, back.intensity) == (42, "part", None)
        assert not list(peer.liveliness().get("@ros2_lv/**"))
        sub.undeclare()
        ros.close()
    finally:
        peer.close()
        daemon_session.close()


def test_tee_keeps_wsc1_going_when_ros_fails() -> None:
    calls: list[tuple[Any, ...]] = []

    class Broken(Ros2Publisher):
        def __init__(self) -> None:
            self.errors = 0

        def publish_cloud(self, *args: Any) -> int:
            raise RuntimeError("boom")

    broken = Broken()
    both = broken.tee(lambda *a: calls.append(a) or 7)
    assert both(np.zeros((1, 3)), 1, 2, 1, "base", None, None) == 7
    assert len(calls) == 1 and broken.errors == 1


def test_daemon_on_the_sim_cell_publishes_pointcloud2_and_tf_static(tmp_path: Path) -> None:
    """``[ros2] enabled`` in a running service on the simulated cell: every batch also arrives
    as PointCloud2 on the rmw_zenoh key, the same points as its WSC1 twin; ``/tf_static``
    carries the simulator's true sensor pose and follows a calibration reload."""
    doc = free_sim_config(
        {
            "calibration": {"file": "s2f.json"},
            "pipeline": {"publish_intensity": True},
            "ros2": {"enabled": True, "tf_static": True, "domain_id": 9},
        }
    )
    cfg_path = tmp_path / "cell.toml"
    cfg_path.write_text(dump_toml(doc))
    cfg = load_config(cfg_path)
    cell = start_cell(cfg)
    svc: Service | None = None
    peer: zenoh.Session | None = None
    try:
        truth = cell.truth()
        s2f = np.array(truth["sensor2flange"])
        ball = np.array(truth["ball_centre_base_m"])
        write_calibration(tmp_path / "s2f.json", _calibration(s2f, "truth"))
        # the sensor held 0.1 m above the tooling ball: every batch has points on it
        assert cell.controller is not None
        q0 = np.array(cell.controller.state()["q"])
        flange = sensor_looking_down(ball, 0.10) @ se3.invert(s2f)
        assert cell.controller.set_joint_positions(kinematics.inverse_nearest("UR5e", flange, q0))
        svc = Service(cfg_path, Notifier(unset_environment=False))
        svc._start(cfg, load_setup(cfg))
        peer = open_session(connect=[cfg.zenoh.listen[0]])
        topic = cfg.ros2.topic_for(cfg.cell.name)
        ros: dict[int, bytes] = {}
        wsc: dict[int, Any] = {}
        tf: list[bytes] = []
        poses: dict[int, wsp1.PoseBatch] = {}

        def on_ros(s: zenoh.Sample) -> None:
            ros[ros2msg.cdr_to_cloud(s.payload.to_bytes()).stamp_ns] = s.payload.to_bytes()

        def on_wsc(s: zenoh.Sample) -> None:
            c = wsc1.decode(s.payload.to_bytes())
            wsc[c.t_first_ns] = c

        def on_pose(s: zenoh.Sample) -> None:
            p = wsp1.decode(s.payload.to_bytes())
            poses[p.seq] = p

        tf_hash = get_typestore(Stores.ROS2_JAZZY).hash_rihs01("tf2_msgs/msg/TFMessage")
        subs = [
            peer.declare_subscriber(f"9/{topic[1:]}/{PC2_DDS}/{PC2_HASH}", on_ros),
            peer.declare_subscriber(f"{cfg.zenoh.prefix}/cloud", on_wsc),
            peer.declare_subscriber(f"{cfg.zenoh.prefix}/pose", on_pose),
            zenoh.ext.declare_advanced_subscriber(
                peer,
                f"9/tf_static/tf2_msgs::msg::dds_::TFMessage_/{tf_hash}",
                lambda s: tf.append(s.payload.to_bytes()),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            ),
        ]

        def full() -> list[int]:
            return [t for t in set(ros) & set(wsc) if wsc[t].n_points > 0 and wsc[t].seq in poses]

        wait_for(lambda: bool(full()) and bool(tf), "no PointCloud2 with points / no tf_static")
        stamp = min(full())
        back = ros2msg.cdr_to_cloud(ros[stamp])
        assert back.frame_id == "base"
        # on the true ball (the sensor's noise is tens of micrometres)
        dist = np.linalg.norm(back.xyz - ball, axis=1) - truth["ball_radius_m"]
        assert np.abs(dist).max() < 1e-3, np.abs(dist).max()
        np.testing.assert_array_equal(back.xyz, wsc[stamp].xyz)
        # <prefix>/pose: the batch's profiles' robot poses, the flange where the arm holds it
        # (the simulated robot's few-micrometre noise), the sensor where the calibration puts it
        pb, cloud = poses[wsc[stamp].seq], wsc[stamp]
        assert (pb.n_poses, pb.frame_id) == (cloud.n_profiles, "base")
        assert (pb.t_ns[0], pb.t_ns.max()) == (cloud.t_first_ns, cloud.t_last_ns)
        np.testing.assert_allclose(
            pb.flange2base, np.broadcast_to(flange, pb.flange2base.shape), atol=5e-5
        )
        np.testing.assert_allclose(pb.sensor2frame, pb.flange2base @ s2f, atol=1e-12)
        in_sensor = se3.apply(se3.invert(pb.sensor2frame[0]), back.xyz)  # the laser plane x = 0
        assert np.abs(in_sensor[:, 0]).max() < 1e-4, np.abs(in_sensor[:, 0]).max()
        # intensity travels when the sensor gives it (the simulated LPF1 gives none)
        assert (back.intensity is None) == (wsc[stamp].intensity is None)
        if back.intensity is not None:
            np.testing.assert_array_equal(back.intensity, wsc[stamp].intensity)

        def tf_matrix(raw: bytes) -> Any:
            (t,) = (
                get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(raw, ros2msg.TF_MESSAGE).transforms
            )
            q, p = t.transform.rotation, t.transform.translation
            m = np.eye(4)
            m[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            m[:3, 3] = [p.x, p.y, p.z]
            return m

        np.testing.assert_allclose(tf_matrix(tf[-1]), s2f, atol=1e-12)
        moved = s2f.copy()
        moved[2, 3] += 0.001
        write_calibration(tmp_path / "s2f.json", _calibration(moved, "second"))
        n = len(tf)
        assert svc.reload()
        wait_for(lambda: len(tf) > n, "/tf_static not published again after the reload")
        np.testing.assert_allclose(tf_matrix(tf[-1]), moved, atol=1e-12)
        for s in subs:
            s.undeclare()
    finally:
        if peer is not None:
            peer.close()
        if svc is not None:
            svc._shutdown(drain=False)
        gc.unfreeze()  # Service._start froze what start-up built: give the test process it back
        cell.stop()


def _calibration(transform: Any, method: str) -> Calibration:
    return Calibration(
        kind="sensor2flange",
        transform=transform,
        robot=RobotIdentity("UR5e"),
        sensor=SensorIdentity("lpf1-udp", "1"),
        method=method,
        residuals=Residuals(rms_m=0.0),
    )


def test_missing_extra_is_a_clear_startup_error(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = parse_config(_config_text() + "\n[ros2]\nenabled = true\n")
    monkeypatch.setitem(sys.modules, "wristscan.daemon.cloud.ros2pub", None)  # as if not there
    with pytest.raises(StartupError, match=r"pip install 'wristscan\[ros2\]'"):
        _ros2_class(cfg)
    assert _ros2_class(parse_config(_config_text())) is None
