"""kinematics: FK against an independent product-of-exponentials model and a separately written
elementary chain, UR's documented home pose, IK round trips for every model (nominal and
calibrated), nearest-solution choice, unreachable poses, singular poses and the Jacobian."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm
from support import REAL_UR10E

from wristscan.calib import kinematics as kin
from wristscan.calib import se3

# Nominal table as published in PROTOCOLS.md (d1, a2, a3, d4, d5, d6), typed in again here so a
# typo in the module's table shows up.
TABLE = {
    "UR3": (0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819),
    "UR5": (0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823),
    "UR10": (0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922),
    "UR3e": (0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
    "UR5e": (0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    "UR10e": (0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
    "UR16e": (0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
    "UR20": (0.2363, -0.862, -0.7287, 0.201, 0.1593, 0.1543),
}


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(2009)


def _small_deltas_model(rng: np.random.Generator, name: str = "UR5e") -> kin.DHParams:
    """Calibration-sized deltas: ~1 mm and ~1 mrad on every parameter."""
    return kin.with_deltas(
        name,
        delta_theta=rng.normal(0.0, 1e-3, 6),
        delta_a=rng.normal(0.0, 1e-3, 6),
        delta_d=rng.normal(0.0, 1e-3, 6),
        delta_alpha=rng.normal(0.0, 1e-3, 6),
    )


# --- independent formulations ---------------------------------------------------------------


def _twist(omega: tuple[float, float, float], point: tuple[float, float, float]) -> np.ndarray:
    w = np.array(omega, dtype=float)
    v = -np.cross(w, np.array(point, dtype=float))
    S = np.zeros((4, 4))
    S[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    S[:3, 3] = v
    return S


def _poe_forward(name: str, q: np.ndarray) -> np.ndarray:
    """Space-frame product of exponentials, axes read off the zero pose by hand:
    joint 1 vertical through the base origin; joints 2, 3, 4 along -y through the shoulder,
    elbow and wrist 1; joint 5 along -z; joint 6 along -y; flange frame rotated +90 deg about x."""
    d1, a2, a3, d4, d5, d6 = TABLE[name]
    twists = [
        _twist((0, 0, 1), (0, 0, 0)),
        _twist((0, -1, 0), (0, 0, d1)),
        _twist((0, -1, 0), (a2, 0, d1)),
        _twist((0, -1, 0), (a2 + a3, 0, d1)),
        _twist((0, 0, -1), (a2 + a3, -d4, d1)),
        _twist((0, -1, 0), (a2 + a3, -d4, d1 - d5)),
    ]
    M = np.array(
        [[1, 0, 0, a2 + a3], [0, 0, -1, -(d4 + d6)], [0, 1, 0, d1 - d5], [0, 0, 0, 1]], dtype=float
    )
    T = np.eye(4)
    for S, qi in zip(twists, q, strict=True):
        T = T @ expm(S * qi)
    return T @ M


def _elementary_forward(model: kin.DHParams, q: np.ndarray) -> np.ndarray:
    """DH written as separate elementary 4x4 factors (rotations from se3/scipy), one sample."""

    def trans(x: float, y: float, z: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, 3] = (x, y, z)
        return T

    T = np.eye(4)
    for i in range(6):
        T = (
            T
            @ se3.make(R=se3.rot_z(q[i] + model.theta_offset[i]))
            @ trans(0.0, 0.0, model.d[i])
            @ trans(model.a[i], 0.0, 0.0)
            @ se3.make(R=se3.rot_x(model.alpha[i]))
        )
    return T


def _contains(solutions: np.ndarray, q: np.ndarray, tol: float) -> bool:
    if solutions.shape[0] == 0:
        return False
    diff = np.abs(kin.wrap_angle(solutions - q)).max(axis=1)
    return bool(diff.min() < tol)


def _assert_all_reach(model: kin.DHParams | str, solutions: np.ndarray, T: np.ndarray) -> None:
    assert np.all(np.isfinite(solutions))
    F = kin.forward(model, solutions)
    pos = np.linalg.norm(F[:, :3, 3] - T[:3, 3], axis=-1)
    rot = se3.rotation_angle(F[:, :3, :3] @ T[:3, :3].T)
    assert pos.max(initial=0.0) <= 1e-9
    assert rot.max(initial=0.0) <= 1e-9


# --- models -----------------------------------------------------------------------------------


def test_model_table_matches_protocols() -> None:
    assert set(kin.UR_MODELS) == set(TABLE)
    for name, (d1, a2, a3, d4, d5, d6) in TABLE.items():
        m = kin.UR_MODELS[name]
        assert m.name == name
        assert m.d == (d1, 0.0, 0.0, d4, d5, d6)
        assert m.a == (0.0, a2, a3, 0.0, 0.0, 0.0)
        assert m.alpha == (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
        assert m.theta_offset == (0.0,) * 6


def test_get_model() -> None:
    assert kin.get_model("UR5e") is kin.UR_MODELS["UR5e"]
    assert kin.get_model("ur10e") is kin.UR_MODELS["UR10e"]
    custom = kin.DHParams("x", d=(0.1,) * 6, a=(0.0,) * 6, alpha=(0.0,) * 6)
    assert kin.get_model(custom) is custom
    with pytest.raises(ValueError, match="unknown robot model 'UR7'") as info:
        kin.get_model("UR7")
    for name in TABLE:
        assert name in str(info.value)


def test_dhparams_validation_and_hashing() -> None:
    m = kin.DHParams("x", d=(0, 1, 2, 3, 4, 5), a=(0,) * 6, alpha=(0.0,) * 6)
    assert m.d == (0.0, 1.0, 2.0, 3.0, 4.0, 5.0)
    assert all(type(v) is float for v in m.d + m.a + m.theta_offset)
    assert hash(m) == hash(kin.DHParams("x", d=(0.0, 1, 2, 3, 4, 5), a=(0.0,) * 6, alpha=(0,) * 6))
    with pytest.raises(ValueError, match=r"DHParams\.a: expected 6 values"):
        kin.DHParams("x", d=(0.0,) * 6, a=(0.0,) * 5, alpha=(0.0,) * 6)
    with pytest.raises(ValueError, match="NaN"):
        kin.DHParams("x", d=(0.0,) * 5 + (math.nan,), a=(0.0,) * 6, alpha=(0.0,) * 6)


# --- forward kinematics --------------------------------------------------------------------------


def test_ur5e_home_pose_from_ur_docs() -> None:
    # At q = 0 the flange sits at (a2 + a3, -(d4 + d6), d1 - d5), z pointing along -y.
    T = kin.forward("UR5e", np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [-0.8172, -0.2329, 0.0628], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    # Turning the base +90 degrees moves the flange counter-clockwise seen from above.
    T90 = kin.forward("UR5e", [math.pi / 2, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(T90[:3, 3], [0.2329, -0.8172, 0.0628], atol=1e-12)


@pytest.mark.parametrize("name", list(TABLE))
def test_forward_matches_product_of_exponentials(name: str, rng: np.random.Generator) -> None:
    d1, a2, a3, d4, d5, d6 = TABLE[name]
    np.testing.assert_allclose(
        kin.forward(name, np.zeros(6))[:3, 3], [a2 + a3, -(d4 + d6), d1 - d5], atol=1e-12
    )
    q = rng.uniform(-2 * np.pi, 2 * np.pi, size=(12, 6))
    F = kin.forward(name, q)
    for qi, Fi in zip(q, F, strict=True):
        np.testing.assert_allclose(Fi, _poe_forward(name, qi), atol=1e-12)


def test_forward_with_deltas_matches_elementary_chain(rng: np.random.Generator) -> None:
    for model in (_small_deltas_model(rng), REAL_UR10E):
        q = rng.uniform(-np.pi, np.pi, size=(10, 6))
        F = kin.forward(model, q)
        for qi, Fi in zip(q, F, strict=True):
            # Raw calibrated d of ~450 m costs ~1e-13 m of rounding in any formulation.
            np.testing.assert_allclose(Fi, _elementary_forward(model, qi), atol=1e-12)


def test_deltas_change_the_pose_by_calibration_amounts(rng: np.random.Generator) -> None:
    nominal = kin.UR_MODELS["UR5e"]
    zero = kin.with_deltas(nominal, np.zeros(6), np.zeros(6), np.zeros(6), np.zeros(6))
    q = rng.uniform(-np.pi, np.pi, size=(200, 6))
    np.testing.assert_array_equal(kin.forward(zero, q), kin.forward(nominal, q))
    calibrated = _small_deltas_model(rng)
    shift = np.linalg.norm(
        kin.forward(calibrated, q)[:, :3, 3] - kin.forward(nominal, q)[:, :3, 3], axis=-1
    )
    assert shift.min() > 1e-5 and shift.max() < 0.02
    # delta_theta acts as a joint offset: a delta on joint 1 alone equals turning joint 1.
    z = np.zeros(6)
    turn1 = np.array([0.1, 0, 0, 0, 0, 0])
    only_theta1 = kin.with_deltas(nominal, turn1, z, z, z)
    np.testing.assert_allclose(
        kin.forward(only_theta1, q), kin.forward(nominal, q + turn1), atol=1e-14
    )


def test_real_kinematics_info_is_close_to_nominal(rng: np.random.Generator) -> None:
    # Read as complete parameters, a real UR10e's calibration moves the flange by millimetres;
    # read wrongly (for example added to the nominal table) it would be off by metres.
    real = REAL_UR10E
    q = rng.uniform(-np.pi, np.pi, size=(500, 6))
    shift = np.linalg.norm(
        kin.forward(real, q)[:, :3, 3] - kin.forward("UR10e", q)[:, :3, 3], axis=-1
    )
    assert 1e-4 < np.median(shift) < 0.01
    assert shift.max() < 0.01


def test_forward_batch_shapes_and_dtypes() -> None:
    rng = np.random.default_rng(3)
    q = rng.uniform(-np.pi, np.pi, size=(2, 3, 6))
    F = kin.forward("UR10", q)
    assert F.shape == (2, 3, 4, 4) and F.dtype == np.float64
    np.testing.assert_array_equal(F[1, 2], kin.forward("UR10", q[1, 2]))
    assert kin.forward("UR10", q[0, 0]).shape == (4, 4)
    np.testing.assert_array_equal(F[..., 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (2, 3, 4)))
    # Integer input is cast to float, not truncated anywhere.
    np.testing.assert_allclose(kin.forward("UR10", [1, 0, 0, 0, 0, 0]),
                               kin.forward("UR10", [1.0, 0, 0, 0, 0, 0]))  # fmt: skip
    assert kin.forward("UR10", np.zeros((0, 6))).shape == (0, 4, 4)
    # A NaN row stays a NaN row and leaves its neighbours alone.
    qn = q[0].copy()
    qn[1, 3] = np.nan
    Fn = kin.forward("UR10", qn)
    assert np.isnan(Fn[1]).any() and np.all(np.isfinite(Fn[[0, 2]]))
    for bad in (np.zeros(5), np.zeros((4, 7)), np.float64(0.0)):
        with pytest.raises(ValueError, match=r"shape \(\.\.\., 6\)"):
            kin.forward("UR10", bad)
        with pytest.raises(ValueError, match=r"shape \(\.\.\., 6\)"):
            kin.jacobian("UR10", bad)


def test_with_deltas_rejects_wrong_shapes() -> None:
    z = np.zeros(6)
    with pytest.raises(ValueError, match="delta_a: expected 6 values"):
        kin.with_deltas("UR5e", z, np.zeros(5), z, z)
    with pytest.raises(ValueError, match="delta_alpha: expected 6 values"):
        kin.with_deltas("UR5e", z, z, z, np.zeros((6, 1)))
    with pytest.raises(ValueError, match="theta: expected 6 values"):
        kin.from_kinematics_info(np.zeros(7), z, z, z)


# --- Jacobian -------------------------------------------------------------------------------------


def _numeric_jacobian(model: kin.DHParams | str, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    J = np.zeros((6, 6))
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        Fp, Fm = kin.forward(model, q + dq), kin.forward(model, q - dq)
        J[:3, i] = (Fp[:3, 3] - Fm[:3, 3]) / (2 * h)
        J[3:, i] = se3.matrix_to_rotvec(Fp[:3, :3] @ Fm[:3, :3].T) / (2 * h)
    return J


@pytest.mark.parametrize("which", ["UR5e", "UR20", "deltas"])
def test_jacobian_matches_finite_differences(which: str, rng: np.random.Generator) -> None:
    model = _small_deltas_model(rng) if which == "deltas" else kin.get_model(which)
    q = rng.uniform(-np.pi, np.pi, size=(5, 6))
    J = kin.jacobian(model, q)
    assert J.shape == (5, 6, 6)
    for qi, Ji in zip(q, J, strict=True):
        np.testing.assert_allclose(Ji, _numeric_jacobian(model, qi), atol=1e-8)
    assert kin.jacobian(model, q.reshape(5, 1, 6)).shape == (5, 1, 6, 6)


def test_jacobian_base_joint_column_at_home() -> None:
    # Joint 1 turns about base z: v = z x p, omega = z.
    p = kin.forward("UR5e", np.zeros(6))[:3, 3]
    J = kin.jacobian("UR5e", np.zeros(6))
    np.testing.assert_allclose(J[:, 0], [-p[1], p[0], 0, 0, 0, 1], atol=1e-14)


# --- inverse kinematics ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(TABLE))
def test_inverse_round_trip_nominal(name: str, rng: np.random.Generator) -> None:
    for q in rng.uniform(-np.pi, np.pi, size=(25, 6)):
        T = kin.forward(name, q)
        sols = kin.inverse(name, T)
        assert 1 <= sols.shape[0] <= 8 and sols.shape[1] == 6
        assert np.all(sols > -np.pi) and np.all(sols <= np.pi)
        _assert_all_reach(name, sols, T)
        assert _contains(sols, q, 1e-9)


def test_inverse_finds_eight_distinct_solutions_for_a_generic_pose() -> None:
    q = np.array([0.3, -1.2, 1.4, -1.5, 1.2, 0.4])
    T = kin.forward("UR5e", q)
    sols = kin.inverse("UR5e", T)
    assert sols.shape == (8, 6)
    _assert_all_reach("UR5e", sols, T)
    gaps = np.abs(kin.wrap_angle(sols[:, None, :] - sols[None, :, :])).max(axis=-1)
    assert np.all(gaps[~np.eye(8, dtype=bool)] > 1e-3)


def test_inverse_round_trip_with_deltas(rng: np.random.Generator) -> None:
    models = [_small_deltas_model(rng, "UR5e"), _small_deltas_model(rng, "UR3"),
              REAL_UR10E]  # fmt: skip
    for model in models:
        n = 0
        while n < 12:
            q = rng.uniform(-np.pi, np.pi, 6)
            if abs(math.sin(q[4])) < 0.05:  # see inverse(): near-wrist-singular pairs
                continue
            n += 1
            T = kin.forward(model, q)
            sols = kin.inverse(model, T)
            assert 1 <= sols.shape[0] <= 8
            _assert_all_reach(model, sols, T)
            assert _contains(sols, q, 1e-7)


def test_inverse_with_theta_offsets_only_stays_closed_form(rng: np.random.Generator) -> None:
    # Offsets keep the ideal geometry: solved in closed form, same accuracy as nominal.
    z = np.zeros(6)
    model = kin.with_deltas("UR10e", rng.normal(0.0, 0.05, 6), z, z, z)
    for q in rng.uniform(-np.pi, np.pi, size=(10, 6)):
        T = kin.forward(model, q)
        sols = kin.inverse(model, T)
        _assert_all_reach(model, sols, T)
        assert _contains(sols, q, 1e-9)
        err = np.abs(kin.forward(model, sols) - T).max()
        assert err < 1e-13


def test_calibrated_inverse_near_elbow_and_shoulder_limits(rng: np.random.Generator) -> None:
    # The ideal seed model puts these poses on the wrong side of its own reach limits; the
    # calibrated arm still has both elbow (and both shoulder) solutions and they must be found.
    for model in (_small_deltas_model(rng), REAL_UR10E):
        cases = [[0.4, -1.1, q3, -0.7, 1.0, 0.9] for q3 in (1e-4, -3e-3, 0.01, np.pi - 5e-3)]
        cases.append([0.3, -np.pi / 2, 0.01, np.pi / 2, 0.7, 0.2])
        for q in np.array(cases):
            T = kin.forward(model, q)
            sols = kin.inverse(model, T)
            _assert_all_reach(model, sols, T)
            assert _contains(sols, q, 1e-7)


def test_inverse_nearest_picks_seed_branch(rng: np.random.Generator) -> None:
    for model in (kin.UR_MODELS["UR10e"], _small_deltas_model(rng)):
        for q in rng.uniform(-np.pi, np.pi, size=(10, 6)):
            seed = q + rng.normal(0.0, 0.05, 6)
            got = kin.inverse_nearest(model, kin.forward(model, q), seed)
            assert got.shape == (6,)
            np.testing.assert_allclose(got, q, atol=1e-7)


def test_inverse_nearest_uses_two_pi_equivalents() -> None:
    q = np.array([0.2, -1.0, 1.3, -0.8, 1.1, 3.0])
    T = kin.forward("UR5e", q)
    # Seed on the far side of the wrap for joint 6: answer 3.0 - 2 pi, next to the seed.
    seed = q.copy()
    seed[5] = 3.0 - 2 * np.pi + 0.01
    got = kin.inverse_nearest("UR5e", T, seed)
    np.testing.assert_allclose(got, [0.2, -1.0, 1.3, -0.8, 1.1, 3.0 - 2 * np.pi], atol=1e-9)
    # Seed near -2 pi + 0.2 for joint 1 (inside the range): the equivalent there is returned.
    seed = q.copy()
    seed[0] = 0.2 - 2 * np.pi + 0.05
    got = kin.inverse_nearest("UR5e", T, seed)
    np.testing.assert_allclose(got, q - [2 * np.pi, 0, 0, 0, 0, 0], atol=1e-9)


def test_inverse_nearest_matches_brute_force_within_joint_limits(rng: np.random.Generator) -> None:
    shifts = np.array(np.meshgrid(*[[-2 * np.pi, 0.0, 2 * np.pi]] * 6)).reshape(6, -1).T
    for _ in range(5):
        q = rng.uniform(-np.pi, np.pi, 6)
        T = kin.forward("UR3e", q)
        seed = rng.uniform(-2 * np.pi, 2 * np.pi, 6)  # anywhere in the joint range
        got = kin.inverse_nearest("UR3e", T, seed)
        cands = (kin.inverse("UR3e", T)[:, None, :] + shifts[None]).reshape(-1, 6)
        cands = cands[np.all(np.abs(cands) <= 2 * np.pi, axis=1)]
        best = cands[np.argmin(np.linalg.norm(cands - seed, axis=1))]
        assert np.all(np.abs(got) <= 2 * np.pi)
        np.testing.assert_allclose(got, best, atol=1e-9)
        np.testing.assert_allclose(kin.forward("UR3e", got), T, atol=1e-9)


def test_unreachable_poses(rng: np.random.Generator) -> None:
    far = se3.make(t=[3.0, 0.0, 0.5])
    # Wrist centre on the base axis: closer to it than d4 is out of reach for every arm.
    on_axis = se3.make(R=se3.rot_x(np.pi), t=[0.0, 0.0, 0.4])
    for model in (kin.UR_MODELS["UR5e"], _small_deltas_model(rng)):
        for T in (far, on_axis):
            assert kin.inverse(model, T).shape == (0, 6)
            with pytest.raises(kin.Unreachable, match="out of reach"):
                kin.inverse_nearest(model, T, np.zeros(6))
    assert issubclass(kin.Unreachable, ValueError)


def test_inverse_validates_inputs() -> None:
    T = kin.forward("UR5e", np.full(6, 0.3))
    with pytest.raises(ValueError, match="expected one"):
        kin.inverse("UR5e", np.stack([T, T]))
    with pytest.raises(ValueError, match="orthonormal"):
        kin.inverse("UR5e", T * np.array([[1.1], [1.0], [1.0], [1.0]]))
    with pytest.raises(ValueError, match="seed"):
        kin.inverse_nearest("UR5e", T, np.zeros(5))
    with pytest.raises(ValueError, match="seed"):
        kin.inverse_nearest("UR5e", T, [0, 0, 0, 0, 0, np.nan])
    # A rotation orthonormal only to ~1e-8 is projected onto SO(3) and still solved exactly.
    Tn = T.copy()
    Tn[:3, :3] += 1e-8 * np.random.default_rng(0).normal(size=(3, 3))
    sols = kin.inverse("UR5e", Tn)
    assert _contains(sols, np.full(6, 0.3), 1e-6)


SINGULAR_Q = {
    "wrist": [0.4, -1.1, 1.2, -0.7, 0.0, 0.9],
    "wrist_pi": [0.4, -1.1, 1.2, -0.7, np.pi, 0.9],
    "elbow_straight": [0.4, -1.1, 0.0, -0.7, 1.0, 0.9],
    # Wrist centre exactly |d4| from axis 1 (the two shoulder solutions merge), elbow straight.
    "shoulder": [0.3, -np.pi / 2, 0.0, np.pi / 2, 0.7, 0.2],
    "shoulder_and_wrist": [0.3, -np.pi / 2, 0.0, np.pi / 2, 0.0, 0.2],
}


@pytest.mark.parametrize("case", list(SINGULAR_Q))
def test_inverse_at_singular_poses(case: str) -> None:
    q = np.array(SINGULAR_Q[case])
    for name in ("UR5e", "UR16e"):
        T = kin.forward(name, q)
        sols = kin.inverse(name, T, wrist_q6=q[5])
        assert sols.shape[0] >= 1
        _assert_all_reach(name, sols, T)
        assert _contains(sols, q, 1e-6)
        got = kin.inverse_nearest(name, T, q)
        np.testing.assert_allclose(got, q, atol=1e-6)


def test_wrist_singularity_uses_requested_q6() -> None:
    q = np.array(SINGULAR_Q["wrist"])
    T = kin.forward("UR10e", q)
    for q6 in (-2.0, 0.0, 1.5):
        sols = kin.inverse("UR10e", T, wrist_q6=q6)
        _assert_all_reach("UR10e", sols, T)
        singular = np.abs(np.sin(sols[:, 4])) < 1e-9
        assert singular.any()
        np.testing.assert_allclose(sols[singular, 5], q6, atol=1e-9)


def test_calibrated_model_near_wrist_singularity(rng: np.random.Generator) -> None:
    # Every solution returned is exact, and a nearby seed recovers the arm's own q.
    model = _small_deltas_model(rng)
    for q5 in (0.0, 1e-3, -0.02, np.pi - 1e-3):
        q = rng.uniform(-np.pi, np.pi, 6)
        q[4] = q5
        T = kin.forward(model, q)
        _assert_all_reach(model, kin.inverse(model, T), T)
        got = kin.inverse_nearest(model, T, q + rng.normal(0.0, 1e-3, 6))
        np.testing.assert_allclose(kin.forward(model, got), T, atol=1e-9)
        np.testing.assert_allclose(got, q, atol=1e-5)


def test_wrap_angle() -> None:
    x = np.array([-np.pi, np.pi, 0.0, 3 * np.pi, -3 * np.pi + 1e-3, 7.0])
    w = kin.wrap_angle(x)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(x), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(x), atol=1e-12)
    assert w[0] == np.pi and w[1] == np.pi
