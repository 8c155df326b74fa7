"""The robot pose notations of imported stop-and-go data (calib/pose_conventions) against se3."""

from __future__ import annotations

import numpy as np
import pytest

from wristscan.calib import pose_conventions as pc
from wristscan.calib import se3


def _poses(n: int = 25, seed: int = 3) -> np.ndarray:
    """Random flange poses, including orientations near the Euler angles' gimbal lock."""
    rng = np.random.default_rng(seed)
    rv = rng.normal(size=(n, 3))
    rv *= (rng.uniform(0.0, np.pi - 1e-3, n) / np.linalg.norm(rv, axis=1))[:, None]
    T = se3.make(se3.rotvec_to_matrix(rv), rng.uniform(-1.0, 1.0, (n, 3)))
    T[0, :3, :3] = se3.rot_y(np.radians(89.9))  # pitch near 90 deg
    return T


def _reference(convention: str, row: np.ndarray) -> np.ndarray:
    """The rotation a row stands for, written out with se3's elementary rotations."""
    o = row[3:]
    d = np.radians
    if convention == "ur-rotvec":
        return se3.pose_to_matrix(row)[:3, :3]
    if convention == "fanuc-xyzwpr":  # w, p, r about fixed X, Y, Z
        return se3.rot_z(d(o[2])) @ se3.rot_y(d(o[1])) @ se3.rot_x(d(o[0]))
    if convention == "kuka-abc":  # a about Z, b about Y, c about X
        return se3.rot_z(d(o[0])) @ se3.rot_y(d(o[1])) @ se3.rot_x(d(o[2]))
    if convention == "abb-quaternion":  # q1 scalar
        w, x, y, z = o
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
    return o.reshape(3, 3)


@pytest.mark.parametrize("convention", list(pc.CONVENTIONS))
def test_each_convention_round_trips_against_se3(convention: str) -> None:
    T = _poses()
    rows = pc.from_matrix(convention, T)
    assert rows.shape == (len(T), 3 + len(pc.CONVENTIONS[convention]))
    assert pc.columns(convention)[:3] == ("x", "y", "z")
    for k, row in enumerate(rows):
        np.testing.assert_allclose(_reference(convention, row), T[k, :3, :3], atol=1e-9)
    back = pc.to_matrix(convention, rows)
    np.testing.assert_allclose(back, T, atol=1e-9)


def test_fanuc_and_kuka_name_the_same_angles_in_opposite_order() -> None:
    # A Fanuc W, P, R of (10, 20, 30) deg is the KUKA A, B, C of (30, 20, 10) deg.
    f = pc.to_matrix("fanuc-xyzwpr", [[0.1, 0.2, 0.3, 10.0, 20.0, 30.0]])
    k = pc.to_matrix("kuka-abc", [[0.1, 0.2, 0.3, 30.0, 20.0, 10.0]])
    np.testing.assert_allclose(f, k, atol=1e-12)
    R = se3.rot_z(np.radians(30)) @ se3.rot_y(np.radians(20)) @ se3.rot_x(np.radians(10))
    np.testing.assert_allclose(f[0, :3, :3], R, atol=1e-12)


def test_printed_quaternions_and_matrices_are_normalised() -> None:
    T = _poses(4)
    q = np.round(pc.from_matrix("abb-quaternion", T), 5)
    m = np.round(pc.from_matrix("matrix", T), 6)
    for conv, rows in (("abb-quaternion", q), ("matrix", m)):
        back = pc.to_matrix(conv, rows)
        err = np.abs(np.swapaxes(back[:, :3, :3], 1, 2) @ back[:, :3, :3] - np.eye(3)).max()
        assert err < 1e-12
        np.testing.assert_allclose(back[:, :3, :3], T[:, :3, :3], atol=5e-5)


@pytest.mark.parametrize(
    ("convention", "row", "message"),
    [
        ("abb-quaternion", [0, 0, 0, 0.5, 0.5, 0.5, 0.0], "quaternion norm"),
        ("matrix", [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, -1], "reflection"),
        ("matrix", [0, 0, 0, 1, 0.1, 0, 0, 1, 0, 0, 0, 1], "not orthonormal"),
        ("ur-rotvec", [0, 0, float("nan"), 0, 0, 0], "not a finite number"),
    ],
)
def test_bad_rows_are_refused_by_row(convention: str, row: list[float], message: str) -> None:
    good = pc.from_matrix(convention, np.eye(4)[None])[0]
    with pytest.raises(pc.PoseRowError, match=message) as err:
        pc.to_matrix(convention, np.array([good, good, row]))
    assert err.value.row == 2


def test_unknown_convention_names_the_known_ones() -> None:
    with pytest.raises(ValueError, match="fanuc-xyzwpr"):
        pc.columns("fanuc")
