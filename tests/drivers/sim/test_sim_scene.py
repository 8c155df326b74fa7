"""Scene ray casting against closed-form intersections, mesh files, and the laser model."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import ArrayLike

from wristscan.calib import se3
from wristscan.drivers.sim.laser import LaserModel
from wristscan.drivers.sim.mesh import MeshFormatError, TriangleMesh, read_mesh
from wristscan.drivers.sim.primitives import Primitive
from wristscan.drivers.sim.scene import (
    Box,
    Cylinder,
    Plane,
    Scene,
    Sphere,
    demo_scene,
    sensor_looking_down,
)
from wristscan.drivers.sim.sensors import DEFAULT_SENSOR2FLANGE_POSE

RNG = np.random.default_rng(20260521)


def _random_pose() -> np.ndarray:
    return se3.make(se3.rotvec_to_matrix(RNG.normal(0, 1.0, 3)), RNG.uniform(-0.5, 0.5, 3))


def _cast(prim: Primitive, pose: np.ndarray, o_local: ArrayLike, d_local: ArrayLike) -> np.ndarray:
    """Rays defined in the primitive's frame, moved to the base frame, cast through a Scene."""
    scene = Scene([prim])
    t, hit = scene.raycast(se3.apply(pose, o_local), np.asarray(d_local) @ pose[:3, :3].T)
    assert np.array_equal(hit, np.isfinite(t))
    return t


def test_sphere_matches_closed_form() -> None:
    pose = _random_pose()
    R, D = 0.0127, 0.3
    b = np.linspace(-0.02, 0.02, 101)  # lateral offset of each ray from the centre
    o = np.column_stack([np.full_like(b, -D), b, np.zeros_like(b)])
    d = np.tile([1.0, 0.0, 0.0], (b.size, 1))
    t = _cast(Sphere(R, pose=pose), pose, o, d)
    inside = np.abs(b) < R
    np.testing.assert_allclose(t[inside], D - np.sqrt(R**2 - b[inside] ** 2), atol=1e-12)
    assert np.all(np.isinf(t[~inside]))
    # From inside the sphere the exit point is seen; rays pointing away from a sphere miss it.
    t_in, _ = Scene([Sphere(R, (0, 0, 0))]).raycast([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    t_away, _ = Scene([Sphere(R, (0, 0, 0))]).raycast([[0.0, 0.0, 0.1]], [[0.0, 0.0, 1.0]])
    assert t_in[0] == pytest.approx(R) and np.isinf(t_away[0])


def test_plane_infinite_and_finite() -> None:
    pose = _random_pose()
    h = 0.2
    ang = np.radians(np.linspace(-80, 80, 41))
    o = np.tile([0.0, 0.0, h], (ang.size, 1))
    d = np.column_stack([np.sin(ang), np.zeros_like(ang), -np.cos(ang)])
    t = _cast(Plane(pose), pose, o, d)
    np.testing.assert_allclose(t, h / np.cos(ang), rtol=1e-12)
    t_up = _cast(Plane(pose), pose, o, -d)
    assert np.all(np.isinf(t_up))  # the plane is behind these rays
    finite = _cast(Plane(pose, size=(0.2, 0.1)), pose, o, d)
    x_hit = h * np.tan(ang)
    inside = np.abs(x_hit) <= 0.1
    np.testing.assert_allclose(finite[inside], h / np.cos(ang[inside]), rtol=1e-12)
    assert np.all(np.isinf(finite[~inside]))


def test_box_faces_edges_and_inside() -> None:
    pose = _random_pose()
    box = Box((0.1, 0.06, 0.04), pose)
    o = np.array(
        [[-0.3, 0.0, 0.0], [0.0, 0.5, 0.01], [0.0, 0.0, -0.2], [0.0, 0.0, 0.0], [-0.3, 0.04, 0.0]]
    )
    d = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0]])
    t = _cast(box, pose, o, d)
    np.testing.assert_allclose(t[:4], [0.25, 0.47, 0.18, 0.02], atol=1e-12)
    assert np.isinf(t[4])  # passes beside the box (|y| = 0.04 > 0.03)
    # Diagonal rays at 45 degrees in X-Z: one enters the -X face at z = -0.01, the other
    # passes over the corner edge (x = -0.05, z = -0.02) on the outside.
    dd = np.array([[1.0, 0.0, 1.0], [1.0, 0.0, 1.0]]) / np.sqrt(2)
    t_diag = _cast(box, pose, np.array([[-0.15, 0.0, -0.11], [-0.15, 0.0, -0.07]]), dd)
    assert t_diag[0] == pytest.approx(np.sqrt(2) * 0.1) and np.isinf(t_diag[1])


def test_cylinder_side_caps_and_tube() -> None:
    pose = _random_pose()
    r, h = 0.01, 0.05
    b = np.linspace(-0.015, 0.015, 60)  # no ray exactly tangent
    o = np.column_stack([np.full_like(b, -0.2), b, np.full_like(b, 0.02)])
    d = np.tile([1.0, 0.0, 0.0], (b.size, 1))
    t = _cast(Cylinder(r, h, pose), pose, o, d)
    inside = np.abs(b) < r
    np.testing.assert_allclose(t[inside], 0.2 - np.sqrt(r**2 - b[inside] ** 2), atol=1e-12)
    assert np.all(np.isinf(t[~inside]))
    above = np.array([[0.003, 0.0, 0.3]])
    down = np.array([[0.0, 0.0, -1.0]])
    assert _cast(Cylinder(r, h, pose), pose, above, down)[0] == pytest.approx(0.25)
    assert np.isinf(_cast(Cylinder(r, h, pose, capped=False), pose, above, down)[0])
    # Beyond the height along the side: a miss.
    assert np.isinf(_cast(Cylinder(r, h, pose), pose, [[-0.2, 0.0, 0.06]], [[1.0, 0, 0]])[0])


def test_occlusion_takes_the_nearest_surface() -> None:
    ball = Sphere(0.0127, (0.0, 0.0, 0.05))
    scene = Scene([Plane(), ball, Cylinder(0.004, 0.05)])
    o = np.array([[0.0, 0.0, 0.3], [0.0, 0.003, 0.3], [0.05, 0.0, 0.3]])
    d = np.tile([0.0, 0.0, -1.0], (3, 1))
    t, hit = scene.raycast(o, d)
    assert hit.all()
    assert t[0] == pytest.approx(0.3 - 0.05 - 0.0127)
    assert t[1] == pytest.approx(0.25 - np.sqrt(0.0127**2 - 0.003**2))
    assert t[2] == pytest.approx(0.3)  # only the table out there
    # Rays from below the table towards the ball are blocked by the table.
    t_below, _ = scene.raycast([[0.0, 0.0, -0.1]], [[0.0, 0.0, 1.0]])
    assert t_below[0] == pytest.approx(0.1)


def test_table_mount_follows_the_table_angle() -> None:
    table = se3.make(se3.rot_x(0.01), (0.4, 0.2, 0.0))
    on_table = Box((0.05, 0.02, 0.03), se3.make(t=(0.08, 0.0, 0.05)), mount="table")
    scene = Scene([on_table], table_zero2base=table)
    theta = 0.7
    same_in_base = Scene([Box((0.05, 0.02, 0.03), scene.table2base(theta) @ on_table.pose)])
    o = RNG.uniform(-0.2, 0.2, (400, 3)) + np.array([0.45, 0.25, 0.3])
    d = (scene.table2base(theta)[:3, 3] + [0.06, 0.03, 0.05]) - o
    d = d + RNG.normal(0, 0.03, d.shape)
    t1, h1 = scene.raycast(o, d, theta)
    t2, h2 = same_in_base.raycast(o, d)
    assert h1.sum() > 50
    np.testing.assert_array_equal(h1, h2)
    np.testing.assert_allclose(t1[h1], t2[h2], atol=1e-12)
    # Per-ray angles: half the rays at theta, half at 0.
    angles = np.where(np.arange(400) < 200, theta, 0.0)
    t3, _ = scene.raycast(o, d, angles)
    np.testing.assert_allclose(t3[:200], t1[:200], atol=1e-12)


def _cube_triangles(half: float) -> np.ndarray:
    box = TriangleMesh.prism([(-half, -half), (half, -half), (half, half), (-half, half)], 2 * half)
    return box.vertices[box.faces]


def _write_meshes(tmp: Path, tris: np.ndarray) -> list[Path]:
    n = tris.shape[0]
    stl_bin = tmp / "cube.stl"
    rec = b"".join(
        struct.pack("<3f", 0, 0, 0) + struct.pack("<9f", *t.reshape(-1)) + b"\0\0" for t in tris
    )
    stl_bin.write_bytes(b"solid binary-but-says-solid".ljust(80, b" ") + struct.pack("<I", n) + rec)
    stl_txt = tmp / "cube_ascii.stl"
    lines = ["solid cube"]
    for t in tris:
        lines += ["facet normal 0 0 0", " outer loop"]
        lines += [f"  vertex {v[0]:.9e} {v[1]:.9e} {v[2]:.9e}" for v in t]
        lines += [" endloop", "endfacet"]
    stl_txt.write_text("\n".join([*lines, "endsolid cube"]) + "\n")
    verts = tris.reshape(-1, 3)
    faces = np.arange(3 * n).reshape(n, 3)
    ply_txt = tmp / "cube.ply"
    head = [
        "ply",
        "format ascii 1.0",
        "comment made by the test",
        f"element vertex {verts.shape[0]}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        f"element face {n}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    body = [f"{v[0]} {v[1]} {v[2]} 200" for v in verts] + [f"3 {a} {b} {c}" for a, b, c in faces]
    ply_txt.write_text("\n".join(head + body) + "\n")
    ply_bin = tmp / "cube_bin.ply"
    # Quads for two faces would need fans; keep triangles but use doubles and a u16 extra field.
    head_b = [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {verts.shape[0]}",
        "property double x",
        "property double y",
        "property double z",
        "property ushort flags",
        f"element face {n}",
        "property list uchar uint vertex_indices",
        "end_header",
    ]
    vb = b"".join(struct.pack("<3dH", *v, 1) for v in verts)
    fb = b"".join(struct.pack("<B3I", 3, *f) for f in faces)
    ply_bin.write_bytes(("\n".join(head_b) + "\n").encode() + vb + fb)
    return [stl_bin, stl_txt, ply_txt, ply_bin]


def test_meshes_from_files_match_the_box(tmp_path: Path) -> None:
    half = 0.02
    tris = _cube_triangles(half)
    pose = _random_pose()
    box = Scene([Box((2 * half,) * 3, pose)])
    o = se3.apply(pose, RNG.uniform(-0.1, 0.1, (300, 3)))
    d = se3.apply(pose, RNG.uniform(-0.04, 0.04, (300, 3))) - o
    t_box, h_box = box.raycast(o, d)
    assert 30 < h_box.sum() < 300
    for path in _write_meshes(tmp_path, tris):
        _, f = read_mesh(path)
        assert f.shape == (12, 3)
        mesh = TriangleMesh.from_file(path, scale=1.0, pose=pose)
        t, h = Scene([mesh]).raycast(o, d)
        np.testing.assert_array_equal(h, h_box, err_msg=path.name)
        np.testing.assert_allclose(t[h], t_box[h_box], atol=1e-6, err_msg=path.name)


def test_mesh_polygons_are_triangulated_and_bad_files_rejected(tmp_path: Path) -> None:
    quad = tmp_path / "quad.ply"
    quad.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    )
    v, f = read_mesh(quad)
    assert f.shape == (2, 3)
    t, hit = Scene([TriangleMesh(v, f)]).raycast([[0.9, 0.9, 1.0]], [[0.0, 0.0, -1.0]])
    assert hit[0] and t[0] == pytest.approx(1.0)
    for name, data in (
        ("junk.stl", b"not a mesh at all"),
        ("short.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"),
        ("trunc.stl", b"solid x\nfacet normal 0 0 0\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n"),
    ):
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(MeshFormatError):
            read_mesh(p)


def test_bundles_agree_with_plain_raycast() -> None:
    scene = demo_scene()
    lm = LaserModel(n_points=257, cache_size=0)
    centre = scene.table2base(0.4)[:3, 3]
    poses = np.stack(
        [
            sensor_looking_down(
                centre + np.array([0.03 * i - 0.06, 0.01, 0.05]), 0.1, yaw_rad=0.3 * i
            )
            @ se3.make(se3.rot_x(0.1 * i))
            for i in range(5)
        ]
    )
    angles = np.array([0.4, 0.5, 0.6, 0.7, 0.8])
    t_bundle = lm.ideal(poses, scene, angles)
    for p in range(5):
        o = se3.apply(poses[p], lm.origins)
        d = lm.dirs @ poses[p][:3, :3].T
        t, hit = scene.raycast(o, d, angles[p])
        near = hit & (t <= lm.z_max_m)  # beyond the reach the bundle may skip primitives
        np.testing.assert_allclose(t_bundle[p][near], t[near], atol=1e-12)
        assert np.all(np.isinf(t_bundle[p][~hit]))


def test_ball_profile_lies_on_the_sphere_where_truth_predicts() -> None:
    scene = demo_scene()
    ball = scene.find("ball")
    assert isinstance(ball, Sphere)
    s2f = se3.pose_to_matrix(DEFAULT_SENSOR2FLANGE_POSE)
    # A flange pose that puts the laser plane 4 mm beside the ball centre, slightly tilted.
    wanted = sensor_looking_down(ball.centre + np.array([0.004, 0.002, 0.0]), 0.095) @ se3.make(
        se3.rotvec_to_matrix([0.05, -0.08, 0.2])
    )
    flange2base = wanted @ se3.invert(s2f)
    sensor2base = flange2base @ s2f
    sigma = 20e-6
    lm = LaserModel(noise_std_m=sigma, rng=7)
    y, z, valid = lm.profile(sensor2base[None], scene)
    y, z, valid = y[0], z[0], valid[0]
    # Prediction: the laser plane (sensor x = 0) cuts the ball in a circle.
    c = se3.apply(se3.invert(sensor2base), ball.centre).reshape(3)
    rho = np.sqrt(ball.radius**2 - c[0] ** 2)
    expect = np.abs(y - c[1]) < rho
    z_pred = c[2] - np.sqrt(np.clip(rho**2 - (y - c[1]) ** 2, 0, None))
    edge = np.abs(np.abs(y - c[1]) - rho) < 1e-6
    np.testing.assert_array_equal(valid[~edge], expect[~edge])
    resid = z[valid] - z_pred[valid]
    assert abs(resid.mean()) < 3 * sigma / np.sqrt(valid.sum())
    assert resid.std() == pytest.approx(sigma, rel=0.1)
    assert np.max(np.abs(resid)) < 5 * sigma
    # In the base frame the points lie on the sphere.
    pts = se3.apply(sensor2base, np.column_stack([np.zeros(valid.sum()), y[valid], z[valid]]))
    r = np.linalg.norm(pts - ball.centre, axis=1)
    assert np.max(np.abs(r - ball.radius)) < 5 * sigma


def test_fan_geometry_ranges_to_a_plane() -> None:
    scene = Scene([Plane()])
    ang = np.radians(np.linspace(-60, 60, 121))
    lm = LaserModel(121, z_min_m=0.02, z_max_m=5.0, geometry="fan", angles_rad=ang)
    m = lm.measure(sensor_looking_down([0, 0, 0], 0.5)[None], scene)
    assert m.valid.all()
    np.testing.assert_allclose(m.t[0], 0.5 / np.cos(ang), rtol=1e-12)
    np.testing.assert_allclose(m.z[0], 0.5, rtol=1e-12)
    np.testing.assert_allclose(m.y[0], 0.5 * np.tan(ang), rtol=1e-12, atol=1e-15)


def test_dropouts_and_outliers_statistics() -> None:
    scene = Scene([Plane()])
    pose = np.repeat(sensor_looking_down([0, 0, 0], 0.1)[None], 50, axis=0)
    lm = LaserModel(dropout_prob=0.1, rng=3)
    m = lm.measure(pose, scene)
    assert (~m.valid).mean() == pytest.approx(0.1, abs=0.005)
    lm = LaserModel(outlier_prob=0.05, noise_std_m=10e-6, rng=4)
    m = lm.measure(pose, scene)
    assert m.valid.all()
    far = np.abs(m.z - 0.1) > 1e-3
    assert far.mean() == pytest.approx(0.05 * 0.98, abs=0.01)
    # Points out of the measuring range are invalid.
    m = LaserModel(rng=5).measure(sensor_looking_down([0, 0, 0], 0.2)[None], scene)
    assert not m.valid.any() and np.all(np.isnan(m.z))


def test_pose_cache_returns_identical_geometry() -> None:
    scene = demo_scene()
    lm = LaserModel(cache_size=4)
    pose = sensor_looking_down(scene.find("ball").pose[:3, 3], 0.1)
    poses = np.stack([pose, pose, pose @ se3.make(t=(0.001, 0, 0))])
    t = lm.ideal(poses, scene)
    assert len(lm._cache) == 2
    np.testing.assert_array_equal(t[0], t[1])
    assert not np.array_equal(np.isfinite(t[0]), np.isfinite(t[2])) or not np.allclose(
        t[0][np.isfinite(t[0])], t[2][np.isfinite(t[0])]
    )
