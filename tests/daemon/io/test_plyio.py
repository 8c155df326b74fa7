"""PLY files: exact header text, binary/ASCII round trips, streaming, atomicity."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest

from wristscan.daemon.io import ply as plyio


def _cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    # Values over many magnitudes, so that ASCII formatting must really round-trip float32.
    xyz = (rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-6, 4, size=(n, 1))).astype(np.float32)
    normals = rng.normal(size=(n, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    intensity = rng.integers(0, 256, size=n).astype(np.uint8)
    return xyz, normals, intensity


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
@pytest.mark.parametrize("with_normals", [False, True], ids=["xyz", "normals"])
@pytest.mark.parametrize("with_intensity", [False, True], ids=["nointensity", "intensity"])
def test_round_trip(tmp_path: Path, binary: bool, with_normals: bool, with_intensity: bool) -> None:
    xyz, normals, intensity = _cloud(1000)
    path = tmp_path / "c.ply"
    plyio.write_ply(
        path,
        xyz,
        normals=normals if with_normals else None,
        intensity=intensity if with_intensity else None,
        binary=binary,
    )
    got = plyio.read_ply(path)
    expected_keys = {"xyz"}
    expected_keys |= {"normals"} if with_normals else set()
    expected_keys |= {"intensity"} if with_intensity else set()
    assert set(got) == expected_keys
    assert got["xyz"].dtype == np.float32
    np.testing.assert_array_equal(got["xyz"], xyz)
    if with_normals:
        np.testing.assert_array_equal(got["normals"], normals)
    if with_intensity:
        assert got["intensity"].dtype == np.uint8
        np.testing.assert_array_equal(got["intensity"], intensity)
    assert os.listdir(tmp_path) == ["c.ply"]


def test_binary_header_is_exactly_what_meshlab_and_cloudcompare_read(tmp_path: Path) -> None:
    xyz, normals, intensity = _cloud(3)
    path = tmp_path / "c.ply"
    plyio.write_ply(path, xyz, normals, intensity, comments=["frame base"])
    raw = path.read_bytes()
    header = (
        b"ply\n"
        b"format binary_little_endian 1.0\n"
        b"comment frame base\n"
        b"element vertex 3\n"
        b"property float x\n"
        b"property float y\n"
        b"property float z\n"
        b"property float nx\n"
        b"property float ny\n"
        b"property float nz\n"
        b"property uchar intensity\n"
        b"end_header\n"
    )
    assert raw[: len(header)] == header
    body = raw[len(header) :]
    assert len(body) == 3 * (12 + 12 + 1)  # packed records, no padding
    rec = np.frombuffer(
        body,
        dtype=[("p", "<f4", 3), ("n", "<f4", 3), ("i", "u1")],
    )
    np.testing.assert_array_equal(rec["p"], xyz)
    np.testing.assert_array_equal(rec["n"], normals)
    np.testing.assert_array_equal(rec["i"], intensity)


def test_ascii_layout(tmp_path: Path) -> None:
    path = tmp_path / "c.ply"
    plyio.write_ply(
        path,
        np.array([[0.5, -1.25, 3.0], [1e-7, 2.0, 0.1]], np.float32),
        intensity=np.array([0, 255], np.uint8),
        binary=False,
    )
    assert path.read_text().splitlines() == [
        "ply",
        "format ascii 1.0",
        "element vertex 2",
        "property float x",
        "property float y",
        "property float z",
        "property uchar intensity",
        "end_header",
        "0.5 -1.25 3 0",
        "1.00000001e-07 2 0.100000001 255",
    ]


def test_float_intensity_for_meshlab(tmp_path: Path) -> None:
    xyz, _, intensity = _cloud(50)
    path = tmp_path / "c.ply"
    plyio.write_ply(path, xyz, intensity=intensity, intensity_float=True)
    assert b"property float intensity\n" in path.read_bytes()[:200]
    got = plyio.read_ply(path)["intensity"]
    assert got.dtype == np.float32 and got.min() >= 0.0 and got.max() <= 1.0
    np.testing.assert_array_equal(np.rint(got * 255).astype(np.uint8), intensity)


def test_stream_writer_equals_one_shot(tmp_path: Path) -> None:
    xyz, _, intensity = _cloud(2500)
    for binary in (True, False):
        one = tmp_path / f"one{binary}.ply"
        plyio.write_ply(one, xyz, intensity=intensity, binary=binary, comments=["c"])
        streamed = tmp_path / f"stream{binary}.ply"
        with plyio.PlyStreamWriter(
            streamed, has_intensity=True, binary=binary, comments=["c"]
        ) as w:
            for lo in range(0, 2500, 700):  # uneven chunks
                w.write(xyz[lo : lo + 700], intensity=intensity[lo : lo + 700])
            w.write(np.zeros((0, 3)), intensity=np.zeros(0, np.uint8))
            assert not streamed.exists(), "nothing under the final name before close"
        assert w.n_points == 2500 and w.closed
        assert streamed.read_bytes() == one.read_bytes()
    assert sorted(os.listdir(tmp_path)) == sorted(
        ["oneTrue.ply", "streamTrue.ply", "oneFalse.ply", "streamFalse.ply"]
    )


def test_exception_mid_stream_leaves_no_file_and_no_temp(tmp_path: Path) -> None:
    xyz, _, _ = _cloud(100)
    path = tmp_path / "c.ply"
    with pytest.raises(RuntimeError, match="sensor unplugged"):
        with plyio.PlyStreamWriter(path) as w:
            w.write(xyz)
            assert len(os.listdir(tmp_path)) == 1  # the temporary body file
            raise RuntimeError("sensor unplugged")
    assert os.listdir(tmp_path) == []
    with pytest.raises(ValueError, match="closed"):
        w.write(xyz)


def test_failed_write_keeps_the_previous_file(tmp_path: Path) -> None:
    xyz, _, _ = _cloud(10)
    path = tmp_path / "c.ply"
    plyio.write_ply(path, xyz)
    before = path.read_bytes()
    w = plyio.PlyStreamWriter(path, has_intensity=True)
    w.write(xyz, intensity=np.ones(10, np.uint8))
    with pytest.raises(ValueError, match="intensity"):
        w.write(xyz)  # this file declares intensity
    w.abort()
    assert path.read_bytes() == before
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        plyio.write_ply(path, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="uint8"):
        plyio.write_ply(path, xyz, intensity=np.ones(10))
    with pytest.raises(ValueError, match="one line"):
        plyio.write_ply(path, xyz, comments=["two\nlines"])
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["c.ply"]


def test_file_mode_follows_umask(tmp_path: Path) -> None:
    path = tmp_path / "c.ply"
    plyio.write_ply(path, np.zeros((1, 3)))
    mask = os.umask(0o022)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask


def test_empty_cloud(tmp_path: Path) -> None:
    for binary in (True, False):
        path = tmp_path / f"e{binary}.ply"
        with plyio.PlyStreamWriter(path, binary=binary):
            pass
        assert b"element vertex 0\n" in path.read_bytes()
        assert plyio.read_ply(path)["xyz"].shape == (0, 3)


def test_large_cloud_is_written_and_read_whole(tmp_path: Path) -> None:
    n = 1_000_000
    xyz = np.arange(3 * n, dtype=np.float32).reshape(n, 3)
    intensity = (np.arange(n) % 251).astype(np.uint8)
    path = tmp_path / "big.ply"
    plyio.write_ply(path, xyz, intensity=intensity)
    header = plyio.read_ply_header(path)
    assert path.stat().st_size == header.size + 13 * n
    got = plyio.read_ply(path)
    np.testing.assert_array_equal(got["xyz"], xyz)
    np.testing.assert_array_equal(got["intensity"], intensity)
    ascii_path = tmp_path / "big.txt.ply"
    plyio.write_ply(ascii_path, xyz[:200_000], binary=False)
    np.testing.assert_array_equal(plyio.read_ply(ascii_path)["xyz"], xyz[:200_000])


def test_reads_other_writers_files(tmp_path: Path) -> None:
    """Big-endian data, extra properties and a face element after the vertices."""
    n = 4
    rec = np.zeros(n, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("quality", ">f4")])
    rec["x"] = np.arange(n)
    rec["z"] = -1.5
    rec["quality"] = 0.25
    header = (
        "ply\nformat binary_big_endian 1.0\nobj_info made elsewhere\n"
        f"element vertex {n}\nproperty double x\nproperty double y\nproperty double z\n"
        "property float32 quality\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    )
    faces = np.array([3], ">u1").tobytes() + np.array([0, 1, 2], ">i4").tobytes()
    path = tmp_path / "be.ply"
    path.write_bytes(header.encode() + rec.tobytes() + faces)
    got = plyio.read_ply(path)
    np.testing.assert_array_equal(got["xyz"][:, 0], np.arange(n))
    np.testing.assert_array_equal(got["xyz"][:, 2], -1.5)
    np.testing.assert_array_equal(got["quality"], 0.25)
    assert plyio.read_ply_header(path).comments == ("made elsewhere",)

    text = tmp_path / "mesh.ply"
    text.write_text(
        "ply\r\nformat ascii 1.0\r\nelement vertex 3\r\nproperty float x\r\nproperty float y\r\n"
        "property float z\r\nelement face 1\r\nproperty list uchar int vertex_indices\r\n"
        "end_header\r\n0 0 0\r\n1 0 0\r\n0 1 0\r\n3 0 1 2\r\n"
    )
    np.testing.assert_array_equal(
        plyio.read_ply(text)["xyz"], np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    )


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"solid stl\n", "not a PLY"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n", "end_header"),
        (b"ply\nformat binary_little_endian 1.0\nend_header\n", "no vertex"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\nend_header\n1\n", "x, y, z"),
        (b"ply\nformat ascii 2.0 x\nend_header\n", "format"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n", "property"),
    ],
)
def test_read_rejects_bad_files(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(plyio.PlyError, match=message):
        plyio.read_ply(path)


def test_read_rejects_truncated_body(tmp_path: Path) -> None:
    path = tmp_path / "c.ply"
    plyio.write_ply(path, np.ones((10, 3)))
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(plyio.PlyError, match="truncated"):
        plyio.read_ply(path)
    plyio.write_ply(path, np.ones((10, 3)), binary=False)
    path.write_bytes(path.read_bytes().rsplit(b"\n", 3)[0])
    with pytest.raises(plyio.PlyError, match="vertices"):
        plyio.read_ply(path)


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_cloudcompare_scalar_fields(tmp_path: Path, binary: bool) -> None:
    """``scalar_pass`` (ushort) and ``scalar_time`` (double: seconds keep their nanoseconds
    over a long recording) after the intensity, named as CloudCompare names scalar fields."""
    rng = np.random.default_rng(11)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    intensity = rng.integers(0, 256, 50).astype(np.uint8)
    t = 3600.0 + np.arange(50) * 1.000000001e-4
    path = tmp_path / "s.ply"
    with plyio.PlyStreamWriter(
        path, has_intensity=True, binary=binary, scalars=("scalar_pass", "scalar_time")
    ) as w:
        w.write(xyz[:20], intensity[:20], scalars={"scalar_pass": 1, "scalar_time": t[:20]})
        w.write(xyz[20:], intensity[20:], scalars={"scalar_pass": 2, "scalar_time": t[20:]})
    header = plyio.read_ply_header(path)
    vertex = header.element("vertex")
    assert vertex is not None
    assert [p for p, _ in vertex.properties][-3:] == ["intensity", "scalar_pass", "scalar_time"]
    text = path.read_bytes()[: header.size].decode("ascii")
    assert "property ushort scalar_pass\n" in text and "property double scalar_time\n" in text
    got = plyio.read_ply(path)
    np.testing.assert_array_equal(got["xyz"], xyz)
    np.testing.assert_array_equal(got["intensity"], intensity)
    np.testing.assert_array_equal(got["scalar_pass"], [1] * 20 + [2] * 30)
    np.testing.assert_array_equal(got["scalar_time"], t)
    one = tmp_path / "one.ply"
    plyio.write_ply(one, xyz, scalars={"scalar_pass": 7}, binary=binary)
    np.testing.assert_array_equal(plyio.read_ply(one)["scalar_pass"], 7)


def test_scalar_fields_must_match_the_declared_ones(tmp_path: Path) -> None:
    with plyio.PlyStreamWriter(tmp_path / "a.ply", scalars=("scalar_pass",)) as w:
        with pytest.raises(ValueError, match="scalar fields"):
            w.write(np.zeros((2, 3)))
        with pytest.raises(ValueError, match="scalar fields"):
            w.write(np.zeros((2, 3)), scalars={"scalar_time": 0.0})
    with pytest.raises(ValueError, match="bad scalar field name"):
        plyio.write_ply(tmp_path / "b.ply", np.zeros((2, 3)), scalars={"x": 1.0})
