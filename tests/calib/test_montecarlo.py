"""The Monte Carlo study of Borangiu 2009 section 3 and the ``wristscan simulate tcp`` command."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from wristscan.calib import montecarlo, se3, tcp
from wristscan.daemon.cli.app import main
from wristscan.daemon.cli.simulate import parse_alphas

SIGMA = montecarlo.PAPER_SIGMA_M
TRIALS = montecarlo.PAPER_TRIALS


@pytest.fixture(scope="module")
def rows() -> list[montecarlo.StudyRow]:
    return montecarlo.study([20.0, 45.0, 60.0, 90.0], TRIALS, SIGMA, n_poses=[4, 8], seed=5)


def pick(rows: list[montecarlo.StudyRow], alpha: float, method: str) -> montecarlo.StudyRow:
    (row,) = [r for r in rows if r.alpha_deg == alpha and r.method == method]
    return row


# ---------------------------------------------------------------------------- pose sets


def z_axes(R: np.ndarray) -> np.ndarray:
    return R[:, :, 2]


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1, 1)))


def test_paper_poses_match_the_description() -> None:
    R = montecarlo.paper_poses(np.radians(30.0))
    z = z_axes(R)
    np.testing.assert_allclose(z[0], [0, 0, -1], atol=1e-15)  # vertical, looking down
    assert angle_deg(z[0], z[1]) == pytest.approx(30.0)
    assert angle_deg(z[0], z[2]) == pytest.approx(30.0)
    # Pose 2 is rotated about X (its Z axis stays in the YZ plane), pose 3 about Y.
    assert z[1][0] == pytest.approx(0.0, abs=1e-15) and z[2][1] == pytest.approx(0.0, abs=1e-15)
    np.testing.assert_allclose(R[1] @ R[0].T, se3.rot_x(np.radians(30.0)), atol=1e-15)
    np.testing.assert_allclose(R[2] @ R[0].T, se3.rot_y(np.radians(30.0)), atol=1e-15)


def test_cone_poses_spread_evenly_on_the_cone() -> None:
    R = montecarlo.cone_poses(np.radians(25.0), 6)
    z = z_axes(R)
    np.testing.assert_allclose(angle_deg(z, np.array([0, 0, -1.0])), 25.0)
    azimuth = np.degrees(np.arctan2(z[:, 1], z[:, 0])) % 360
    np.testing.assert_allclose(np.diff(np.sort(azimuth)), 60.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    with pytest.raises(ValueError, match="n >= 3"):
        montecarlo.cone_poses(0.5, 2)


# ---------------------------------------------------------------------------- the paper's findings


def test_accuracy_collapses_below_45_degrees(rows: list[montecarlo.StudyRow]) -> None:
    s20, s45, s60, s90 = (np.array(pick(rows, a, "three").std_mm) for a in (20, 45, 60, 90))
    assert np.all(s20[:2] > 4 * s60[:2])  # x, y: ~8x worse at 20 deg than at 60 deg
    assert np.all(s20 > 2 * s45)
    # The loss from 45 down to 20 degrees is far larger than the gain from 45 up to 90.
    assert np.all((s20 - s45)[:2] > 4 * (s45 - s90)[:2])
    # At the paper's 0.1 mm noise, Eq. 7 at 20 deg is worse than 1 mm in x and y.
    assert np.all(s20[:2] > 1.0)


def test_z_has_the_smallest_std(rows: list[montecarlo.StudyRow]) -> None:
    for r in rows:
        assert r.std_mm[2] < min(r.std_mm[:2]), r
        assert r.analytic_std_mm[2] < min(r.analytic_std_mm[:2]), r


def test_more_poses_beat_the_three_pose_formula(rows: list[montecarlo.StudyRow]) -> None:
    for alpha in (20.0, 45.0, 60.0, 90.0):
        three = np.array(pick(rows, alpha, "three").analytic_std_mm)
        n4 = np.array(pick(rows, alpha, "lstsq-n4").analytic_std_mm)
        n8 = np.array(pick(rows, alpha, "lstsq-n8").analytic_std_mm)
        assert np.all(n4 < three) and np.all(n8 < n4)
        # Twice the poses of the same cone: the covariance halves (std / sqrt 2).
        np.testing.assert_allclose(n8, n4 / np.sqrt(2), rtol=1e-9)


def test_monte_carlo_agrees_with_analytic_within_chi_square_bounds(
    rows: list[montecarlo.StudyRow],
) -> None:
    # (N-1) s^2 / sigma^2 ~ chi2(N-1) for each axis; Bonferroni over all comparisons, 1 % in all.
    n_cmp = 3 * len(rows)
    q = 0.01 / n_cmp / 2
    lo, hi = (np.sqrt(chi2.ppf(p, TRIALS - 1) / (TRIALS - 1)) for p in (q, 1 - q))
    assert 0.75 < lo < 1 < hi < 1.3  # the bounds are tight enough to mean something
    for r in rows:
        ratio = np.array(r.std_mm) / np.array(r.analytic_std_mm)
        assert np.all((lo < ratio) & (ratio < hi)), (r, lo, hi)
        assert r.trials == TRIALS


def test_analytic_figures_are_the_documented_formulas() -> None:
    (row,) = montecarlo.study([45.0], 10, SIGMA)
    R = montecarlo.paper_poses(np.radians(45.0))
    Mi = np.linalg.inv(R[0] - (R[1] + R[2]) / 2)
    expected = 1e3 * np.sqrt(np.diag(1.5 * SIGMA**2 * Mi @ Mi.T))
    np.testing.assert_allclose(row.analytic_std_mm, expected)
    A = tcp.design_matrix(montecarlo.cone_poses(np.radians(45.0), 5))
    np.testing.assert_allclose(
        montecarlo.analytic_cov(montecarlo.cone_poses(np.radians(45.0), 5), SIGMA, "lstsq"),
        SIGMA**2 * np.linalg.inv(A.T @ A)[:3, :3],
    )


def test_rows_are_reproducible_and_independent_of_other_rows() -> None:
    a = montecarlo.study([30.0, 45.0], 50, SIGMA, n_poses=5, seed=3)
    b = montecarlo.study([45.0], 50, SIGMA, n_poses=5, seed=3)
    assert a[2:] == b
    c = montecarlo.study([45.0], 50, SIGMA, n_poses=5, seed=4)
    assert c[0].std_mm != b[0].std_mm
    assert [r.method for r in a] == ["three", "lstsq-n5", "three", "lstsq-n5"]


def test_errors_are_unbiased_and_scale_with_sigma() -> None:
    R = montecarlo.paper_poses(np.radians(60.0))
    rng = np.random.default_rng(0)
    e1 = montecarlo.monte_carlo_errors(R, 1e-4, 20000, rng, "three")
    rng = np.random.default_rng(0)
    e2 = montecarlo.monte_carlo_errors(R, 2e-4, 20000, rng, "three")
    np.testing.assert_allclose(e2, 2 * e1, rtol=1e-6, atol=1e-15)  # linear in the noise
    se = np.sqrt(np.diag(tcp.covariance_three(R, 1e-4)) / 20000)
    assert np.all(np.abs(e1.mean(axis=0)) < 4 * se)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"alphas_deg": [0.0]}, r"\(0, 180\)"),
        ({"alphas_deg": []}, "non-empty"),
        ({"trials": 1}, "trials"),
        ({"sigma_m": 0.0}, "sigma_m"),
        ({"n_poses": 2}, "n_poses"),
        ({"seed": -1}, "seed"),
    ],
)
def test_study_rejects_bad_arguments(kwargs: dict[str, object], match: str) -> None:
    args: dict[str, object] = {"alphas_deg": [45.0], "trials": 10, "sigma_m": SIGMA}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        montecarlo.study(**args)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------- the command


def test_parse_alphas() -> None:
    assert parse_alphas("10:90:5") == [10.0 + 5 * k for k in range(17)]
    assert parse_alphas("0.1:0.3:0.1") == [0.1, 0.2, 0.3]
    assert parse_alphas("20, 45,60:80:10") == [20.0, 45.0, 60.0, 70.0, 80.0]
    for bad in ("10:x", "90:10:5", "10:90", "10:90:0", "0", "nan", "180", ""):
        with pytest.raises(ValueError):
            parse_alphas(bad)


def test_cli_json(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--alpha", "20:60:20", "--trials", "50", "--json", "--poses", "5"]
    rc = main(["simulate", "tcp", *args])
    out, err = capsys.readouterr()
    assert rc == 0
    doc = json.loads(out)
    assert [(r["alpha_deg"], r["method"]) for r in doc] == [
        (a, m) for a in (20.0, 40.0, 60.0) for m in ("three", "lstsq-n5")
    ]
    for r in doc:
        assert {"alpha_deg", "method", "std_mm", "trials", "analytic_std_mm"} <= set(r)
        assert len(r["std_mm"]) == 3 and r["trials"] == 50
    # sigma on the command line is in millimetres: 0.1 mm gives the paper's figures.
    assert doc[0]["analytic_std_mm"][0] == pytest.approx(2.894, abs=1e-3)
    assert err == ""


def test_cli_table(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["simulate", "tcp", "--alpha", "45", "--trials", "20", "--sigma", "0.2"])
    out, _ = capsys.readouterr()
    assert rc == 0
    assert "Monte Carlo std (mm)" in out and "analytic std (mm)" in out
    lines = [line.split() for line in out.splitlines() if line.strip().startswith("45")]
    assert [line[1] for line in lines] == ["three", "lstsq-n6"]
    # 0.2 mm doubles the paper's analytic figure at 45 deg (0.616 mm in x).
    assert float(lines[0][5]) == pytest.approx(2 * 0.6157, abs=2e-3)


def test_cli_plot_writes_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    png = tmp_path / "fig4.png"
    rc = main(["simulate", "tcp", "--alpha", "20:80:30", "--trials", "20", "--plot", str(png)])
    assert rc == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 10_000
    assert "plot written" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--alpha", "10:x"], "START:STOP:STEP"),
        (["--alpha", "90:10:5"], "START <= STOP"),
        (["--alpha", "0:90:10"], "(0, 180)"),
        (["--trials", "1"], "--trials"),
        (["--sigma", "-0.1"], "--sigma"),
        (["--poses", "2"], "--poses"),
        (["--plot", "/nonexistent-dir/x.png"], "does not exist"),
        (["--plot", "fig.pdf"], ".png file name"),
    ],
)
def test_cli_bad_arguments_exit_2(
    args: list[str], words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(["simulate", "tcp", "--trials", "10", *args])
    out, err = capsys.readouterr()
    assert rc == 2
    assert err.startswith("error: ") and words in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err + out and out == ""


def test_cli_plot_without_matplotlib_names_the_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` fail
    rc = main(["simulate", "tcp", "--alpha", "45", "--plot", str(tmp_path / "x.png")])
    err = capsys.readouterr().err
    assert rc == 1
    assert "wristscan[plot]" in err and "Traceback" not in err
    assert not (tmp_path / "x.png").exists()
