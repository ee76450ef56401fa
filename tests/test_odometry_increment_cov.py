"""The odometry's increment covariance: stochastic cloning in EKF-RIO, the SE(2) increment
covariance, its NEES on a synthetic run with a matched noise model (and on a mistuned filter told the actual noise),
the v3 clone update's overconfidence, and the bag source's fallback."""

from __future__ import annotations

import numpy as np
import pytest

from core.geometry import pose_matrix, yaw_of
from core.trajectory_metrics import increment_nees, se2_increments
from schemas.io import read_artifact
from stages.odometry.ekf_rio import increment_covariance, run_ekf
from stages.odometry.params import CovarianceParams, OdometryParams
from stages.odometry.stage import COV_COLS, bag_increment_covariance
from tests.test_filter import run_stages
from tests.test_filter_scene import base_pose, circle_run, write_circle_log
from tests.test_ingest_logs import BASE_FROM_IMU, GT_TOPIC, T0
from tests.test_odometry_robust import ekf_params

#: the synthetic circle's noise: IMU white noise (gyro rad/s/sqrt(Hz), accel m/s^2/sqrt(Hz)) and radar velocity std
GYRO_NOISE, ACCEL_NOISE, VEL_SIGMA = 1e-3, 0.01, 0.05
MATCHED = ekf_params(imu={"accel_noise_density": ACCEL_NOISE, "gyro_noise_density": GYRO_NOISE},
                     init={"sigma_gyro_bias0": 0.002})


def _band(n: int) -> tuple[float, float]:
    """Three standard deviations of the mean of ``n`` independent chi-square(3) values around 3."""
    h = 3.0 * np.sqrt(6.0 / n)
    return 3.0 - h, 3.0 + h


def _circle(seed: int, cfg: OdometryParams = MATCHED):
    run = circle_run(duration=15.0, seed=seed, gyro_noise=GYRO_NOISE, accel_noise=ACCEL_NOISE,
                     gyro_bias=(0.001, -0.001, 0.002), clutter=0, ghosts=0)
    rng = np.random.default_rng(seed)
    sc = run.scene
    scan_t = np.array([t for t, _ in sc.radar], dtype=np.int64)
    vel = run.v_radar + rng.normal(0, VEL_SIGMA, run.v_radar.shape)
    cov = np.tile(np.eye(3) * VEL_SIGMA ** 2, (len(scan_t), 1, 1))
    B = pose_matrix(*BASE_FROM_IMU)
    res = run_ekf(sc.imu_t, sc.imu[:, :3], sc.imu[:, 3:], scan_t, vel, cov, np.full(len(scan_t), 3),
                  np.ones(len(scan_t), bool), np.linalg.inv(B) @ run.base_from_radar, cfg)
    T_wb = res.T_world_imu @ np.linalg.inv(B)
    est = np.stack([T_wb[:, 0, 3], T_wb[:, 1, 3], yaw_of(T_wb[:, :3, :3])], axis=1)
    pos, yaw = base_pose((scan_t - T0) * 1e-9, run.radius, run.speed)
    return res, B, est, np.column_stack([pos[:, :2], yaw])


@pytest.mark.parametrize("seed", [0, 1])
def test_cloned_increment_covariance_is_small_positive_and_honest(seed: int) -> None:
    res, B, est, ref = _circle(seed)
    c = increment_covariance(res.T_world_imu, res.pose_pair_cov, B)
    assert np.all(c[0] == 0.0)
    assert np.all(np.linalg.eigvalsh(c[1:])[:, 0] > 0)  # positive definite
    # the clone's cross covariance matters: position is unobserved, its marginal std grows to decimetres while
    # the increment's stays millimetres (treating the two poses as independent would overstate it ~100x)
    i = len(c) - 1
    marg = res.pose_pair_cov[i][:2, :2] + res.pose_pair_cov[i][6:8, 6:8]
    assert np.trace(c[i][:2, :2]) < 0.01 * np.trace(marg)
    # with the noise model matched to the synthetic IMU and radar the increments are honest: mean NEES within 3
    # standard deviations of chi-square(3)'s mean, every axis' normalised variance near 1
    nees = increment_nees(est, ref, c, res.initialized)
    lo, hi = _band(nees["increments"])
    assert lo < nees["mean"] < hi, nees
    assert all(0.6 < v < 1.6 for v in nees["axis_mean"]), nees


def test_actual_noise_equal_to_the_filter_s_gives_the_filter_s_covariance() -> None:
    cov = CovarianceParams(accel_noise_density=ACCEL_NOISE, gyro_noise_density=GYRO_NOISE, velocity_scale=1.0)
    same = MATCHED.model_copy(update={"covariance": cov})
    a, _, _, _ = _circle(0)
    b, _, _, _ = _circle(0, same)
    np.testing.assert_allclose(b.pose_pair_cov, a.pose_pair_cov, rtol=1e-9, atol=1e-15)


def test_a_mistuned_filter_gets_an_honest_covariance_from_the_actual_noise() -> None:
    """A filter whose process noise is 10x the IMU's (and whose radar covariance is 4x the radar's) over-covers
    its increments; the same filter (same estimate) with the actual noise given writes an honest covariance."""
    loose = ekf_params(imu={"accel_noise_density": 10 * ACCEL_NOISE, "gyro_noise_density": 10 * GYRO_NOISE},
                       init={"sigma_gyro_bias0": 0.002}, velocity={"cov_scale": 4.0})
    res, B, est, ref = _circle(0, loose)
    own = increment_nees(est, ref, increment_covariance(res.T_world_imu, res.pose_pair_cov, B), res.initialized)
    assert own["mean"] < 1.0, own
    told = loose.model_copy(update={"covariance": CovarianceParams(
        accel_noise_density=ACCEL_NOISE, gyro_noise_density=GYRO_NOISE, velocity_scale=0.25)})
    res2, _, est2, _ = _circle(0, told)
    np.testing.assert_array_equal(est2, est)  # the estimate does not change
    nees = increment_nees(est, ref, increment_covariance(res2.T_world_imu, res2.pose_pair_cov, B), res.initialized)
    lo, hi = _band(nees["increments"])
    assert lo < nees["mean"] < hi, nees


def test_increments_and_their_covariance_ignore_a_rigid_motion_of_the_trajectory() -> None:
    res, B, _, _ = _circle(0)
    c = increment_covariance(res.T_world_imu, res.pose_pair_cov, B)
    # yaw the whole trajectory by 0.7 rad: the errors (right perturbations in attitude, world position) rotate
    a = 0.7
    Rz = np.array([[np.cos(a), -np.sin(a), 0, 0], [np.sin(a), np.cos(a), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    G = np.eye(12)
    G[:3, :3] = G[6:9, 6:9] = Rz[:3, :3]
    c2 = increment_covariance(Rz @ res.T_world_imu, G @ res.pose_pair_cov @ G.T, B)
    np.testing.assert_allclose(c2, c, rtol=1e-5, atol=1e-12)


def test_bag_source_writes_the_parameter_covariance(tmp_path) -> None:
    run = circle_run(duration=6.0, seed=3, gyro_noise=1.5e-4, accel_noise=6e-4)
    bag = write_circle_log(tmp_path / "circle", run)
    over = {"ingest": {"topics": {"odometry": GT_TOPIC}}, "odometry": {"source": "bag", "bag": {"std_xy": 0.01}}}
    out = run_stages(bag, tmp_path / "runs", ["odometry"], over)
    odo = read_artifact(out / "odometry" / "odometry.parquet", "odometry")
    u = se2_increments(np.stack([odo[c].to_numpy() for c in ("x", "y", "yaw")], axis=1))
    want = bag_increment_covariance(u, 0.01, 0.05, 0.001, 0.03)
    got = {c: odo[c].to_numpy() for c in COV_COLS}
    np.testing.assert_allclose(got["cov_xx"], want[:, 0, 0])
    np.testing.assert_allclose(got["cov_yawyaw"], want[:, 2, 2])
    assert np.all(got["cov_xy"] == 0) and got["cov_xx"][0] == 0
    assert got["cov_xx"][1] == pytest.approx((0.01 + 0.05 * 0.1) ** 2, rel=0.05)  # 1 m/s at 10 Hz


def test_heading_window_nees_is_one_for_independent_errors_and_grows_with_a_bias() -> None:
    from core.trajectory_metrics import heading_window_nees

    rng = np.random.default_rng(3)
    n, sd = 30001, 0.002
    ref = np.cumsum(rng.normal(0.0, 0.01, n))
    est = ref + np.r_[0.0, np.cumsum(rng.normal(0.0, sd, n - 1))]
    var, ok = np.full(n, sd**2), np.ones(n, bool)
    honest = heading_window_nees(est, ref, var, ok)
    for w, v in honest.items():  # mean of n / w chi-square(1) values: within 4 sd of 1
        assert abs(v - 1.0) < 4 * np.sqrt(2.0 / (n // w)), (w, v)
    # a constant gyro bias of a quarter of the per-increment sd: invisible per increment, dominant over 30 s
    biased = heading_window_nees(est + 0.25 * sd * np.arange(n), ref, var, ok)
    assert biased[1] < 1.3 and biased[300] > 10 * honest[300]
    # a missing pose removes the windows that span it, and only those
    gap = ok.copy()
    gap[5000] = False
    assert heading_window_nees(est, ref, var, gap)[10] == pytest.approx(honest[10], rel=0.01)
    assert np.isnan(heading_window_nees(est[:50], ref[:50], var[:50], ok[:50], windows=(100,))[100])


def test_distance_ratio_finds_a_speed_scale_and_ignores_a_standstill() -> None:
    from core.trajectory_metrics import distance_ratio

    rng = np.random.default_rng(4)
    t = np.arange(0.0, 120.0, 0.1)
    moving = t < 80  # 80 s on a circle at 1 m/s, then 40 s standing still
    s = np.where(moving, t, 80.0)
    ref = np.c_[20 * np.cos(s / 20), 20 * np.sin(s / 20)]
    est = ref[0] + 1.02 * (ref - ref[0]) + rng.normal(0, 0.02, ref.shape)  # 2 % too fast, 2 cm noise
    ok = np.ones(len(t), bool)
    r = distance_ratio(t, est, ref, ok)
    assert r["median"] == pytest.approx(1.02, abs=0.002) and r["p10"] > 1.01 and r["p90"] < 1.03
    # windows that end in the standstill count while the truth still moves 3 m (starts up to ~77 s); later ones not
    assert int(np.sum(t < 76)) <= r["windows"] <= int(np.sum(t < 78))
    bad = ok.copy()
    bad[:300] = False  # the first 30 s unusable: their windows are left out
    assert distance_ratio(t, est, ref, bad)["windows"] < r["windows"] - 250
    assert np.isnan(distance_ratio(t[:50], est[:50], ref[:50], ok[:50])["median"])  # no 10 s window
