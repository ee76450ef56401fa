"""REVE ego-velocity estimation against analytic Doppler scans with outliers."""

from __future__ import annotations

import numpy as np
import pytest

from stages.filter import ego_velocity as ev
from stages.filter.params import EgoVelocityParams


def _scan(rng: np.random.Generator, v: np.ndarray, n: int = 60, outliers: float = 0.35, noise: float = 0.02,
          elevation: float = 0.35) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    az = rng.uniform(-1.0, 1.0, n)
    el = rng.uniform(-elevation, elevation, n)
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    dop = -dirs @ v + rng.normal(0, noise, n)
    bad = rng.random(n) < outliers
    dop[bad] = rng.uniform(-2.5, 2.5, bad.sum())
    return dirs, dop, ~bad


def test_ransac_iteration_count_matches_reve() -> None:
    # ln(1 - 0.9999) / ln(1 - 0.6^3) = 37.9
    assert ev.ransac_iterations(EgoVelocityParams()) == 38
    assert ev.ransac_iterations(EgoVelocityParams(outlier_probability=0.1)) == 8  # 9.21 / 1.306 = 7.05


def test_sign_convention_approaching_is_negative() -> None:
    dirs = np.array([[1.0, 0, 0], [0.8, 0.6, 0], [0.8, -0.6, 0], [0.6, 0, 0.8], [0.6, 0.0, -0.8], [0.0, 1.0, 0.0]])
    # moving forward at 1 m/s: targets ahead approach, d = -r.v
    dop = -dirs @ np.array([1.0, 0.0, 0.0])
    assert dop[0] == -1.0
    est = ev.estimate(dirs, dop, EgoVelocityParams(), np.random.default_rng(0))
    assert est.valid and est.dims == 3
    np.testing.assert_allclose(est.v, [1.0, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_ransac_lsq_matches_the_oracle_least_squares(seed: int) -> None:
    rng = np.random.default_rng(seed)
    v = rng.uniform(-1.5, 1.5, 3) * np.array([1, 1, 0.3])
    dirs, dop, true_inliers = _scan(rng, v)
    est = ev.estimate(dirs, dop, EgoVelocityParams(), np.random.default_rng(seed))
    assert est.valid and est.dims == 3
    # independent reference: least squares on the points known to be static
    A = -dirs[true_inliers]
    oracle = np.linalg.lstsq(A, dop[true_inliers], rcond=None)[0]
    assert np.linalg.norm(est.v[:2] - oracle[:2]) < 0.03
    assert np.linalg.norm(est.v[:2] - v[:2]) < 0.05
    assert est.inliers[true_inliers].mean() > 0.9
    # an outlier lands within the 0.15 m/s band with probability ~ 0.3 / 5
    assert est.inliers[~true_inliers].mean() < 0.25
    sd = np.sqrt(np.diag(est.cov))
    assert np.all(sd > 0) and np.all(sd < 0.5)


def test_zero_velocity_detection() -> None:
    rng = np.random.default_rng(3)
    dirs, dop, _ = _scan(rng, np.zeros(3), outliers=0.2, noise=0.01)
    est = ev.estimate(dirs, dop, EgoVelocityParams(), rng)
    assert est.valid and est.dims == 0
    np.testing.assert_array_equal(est.v, 0.0)


def test_planar_scan_solves_2d_with_vz_zero() -> None:
    rng = np.random.default_rng(4)
    v = np.array([0.8, -0.4, 0.0])
    dirs, dop, _ = _scan(rng, v, elevation=0.0, outliers=0.2)
    est = ev.estimate(dirs, dop, EgoVelocityParams(), rng)
    assert est.valid and est.dims == 2 and est.v[2] == 0.0
    assert np.linalg.norm(est.v - v) < 0.03
    assert np.isinf(est.cov[2, 2])


def test_too_few_points_is_invalid() -> None:
    rng = np.random.default_rng(5)
    dirs, dop, _ = _scan(rng, np.array([1.0, 0, 0]), n=4, outliers=0.0)
    est = ev.estimate(dirs, dop, EgoVelocityParams(), rng)
    assert not est.valid and np.isnan(est.v).all() and not est.inliers.any()


def test_deterministic_for_a_seed() -> None:
    rng = np.random.default_rng(6)
    dirs, dop, _ = _scan(rng, np.array([1.0, 0.3, 0.0]), outliers=0.45)
    a = ev.estimate(dirs, dop, EgoVelocityParams(), np.random.default_rng(1))
    b = ev.estimate(dirs, dop, EgoVelocityParams(), np.random.default_rng(1))
    np.testing.assert_array_equal(a.v, b.v)


def test_sparse_ground_scan_prefers_the_planar_model() -> None:
    # a real failure case (simulated open field): ground returns in a narrow elevation band plus three
    # clutter points; the platform moves at (1.21, 0.01, 0.00) m/s in the radar frame. A 3D hypothesis
    # through clutter fits as many points as the true motion, so REVE's plain 3D RANSAC often picks it.
    pts = np.array([[1.418, 1.214, -0.719, -0.8], [2.126, -1.032, -0.816, -0.96], [2.491, 0.428, -0.709, -1.08],
                    [2.636, -1.257, -0.685, -0.96], [2.815, 0.496, -0.911, -1.16], [4.224, -2.895, -0.217, -2.4],
                    [4.087, 3.821, 1.327, 2.4], [7.772, 7.183, -4.17, 0.2]])
    dirs, _ = ev.unit_directions(pts[:, :3])
    truth = np.array([1.2146, 0.006, 0.0019])
    errors = [np.linalg.norm(ev.estimate(dirs, pts[:, 3], EgoVelocityParams(), np.random.default_rng(s)).v - truth)
              for s in range(100)]
    assert np.mean(np.array(errors) < 0.2) > 0.95
