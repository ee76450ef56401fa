"""The odometry's increment covariance (issue 27, item 1): stochastic cloning in EKF-RIO, the SE(2) increment
covariance, its NEES on a synthetic run with a matched gyro model, and the bag source's fallback."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.io import read_artifact
from stages.ingest.geometry import pose_matrix, yaw_of
from stages.odometry.ekf_rio import EkfConfig, increment_covariance, run_ekf
from stages.odometry.metrics import increment_nees, se2_increments
from stages.odometry.stage import COV_COLS, bag_increment_covariance
from tests.test_filter import run_stages
from tests.test_filter_scene import base_pose, circle_run, write_circle_log
from tests.test_ingest_logs import BASE_FROM_IMU, GT_TOPIC, T0


def _circle(seed: int):
    run = circle_run(duration=15.0, seed=seed, gyro_noise=1e-3, accel_noise=0.01, gyro_bias=(0.001, -0.001, 0.002),
                     clutter=0, ghosts=0)
    rng = np.random.default_rng(seed)
    sc = run.scene
    scan_t = np.array([t for t, _ in sc.radar], dtype=np.int64)
    vel = run.v_radar + rng.normal(0, 0.05, run.v_radar.shape)
    cov = np.tile(np.eye(3) * 0.05 ** 2, (len(scan_t), 1, 1))
    B = pose_matrix(*BASE_FROM_IMU)
    res = run_ekf(sc.imu_t, sc.imu[:, :3], sc.imu[:, 3:], scan_t, vel, cov, np.full(len(scan_t), 3),
                  np.ones(len(scan_t), bool), np.linalg.inv(B) @ run.base_from_radar,
                  EkfConfig(accel_noise_density=0.01, gyro_noise_density=1e-3, sigma_gyro_bias0=0.002))
    T_wb = res.T_world_imu @ np.linalg.inv(B)
    est = np.stack([T_wb[:, 0, 3], T_wb[:, 1, 3], yaw_of(T_wb[:, :3, :3])], axis=1)
    pos, yaw = base_pose((scan_t - T0) * 1e-9, run.radius, run.speed)
    return res, B, est, np.column_stack([pos[:, :2], yaw])


@pytest.mark.parametrize("seed", [0, 1])
def test_cloned_increment_covariance_is_small_positive_and_honest_in_yaw(seed: int) -> None:
    res, B, est, ref = _circle(seed)
    c = increment_covariance(res.T_world_imu, res.pose_pair_cov, B)
    assert np.all(c[0] == 0.0)
    assert np.all(np.linalg.eigvalsh(c[1:])[:, 0] > 0)  # positive definite
    # the clone's cross covariance matters: position is unobserved, its marginal std grows to decimetres while
    # the increment's stays millimetres (treating the two poses as independent would overstate it ~100x)
    i = len(c) - 1
    marg = res.pose_pair_cov[i][:2, :2] + res.pose_pair_cov[i][6:8, 6:8]
    assert np.trace(c[i][:2, :2]) < 0.01 * np.trace(marg)
    # with the gyro model matched to the synthetic IMU the yaw increments are honest (normalised variance ~1)
    nees = increment_nees(est, ref, c, res.initialized)
    assert 0.5 < nees["axis_mean"][2] < 2.0


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
    over = {"ingest": {"odometry_topic": GT_TOPIC}, "odometry": {"source": "bag", "bag_std_xy": 0.01}}
    out = run_stages(bag, tmp_path / "runs", ["odometry"], over)
    odo = read_artifact(out / "odometry" / "odometry.parquet", "odometry")
    u = se2_increments(np.stack([odo[c].to_numpy() for c in ("x", "y", "yaw")], axis=1))
    want = bag_increment_covariance(u, 0.01, 0.05, 0.001, 0.03)
    got = {c: odo[c].to_numpy() for c in COV_COLS}
    np.testing.assert_allclose(got["cov_xx"], want[:, 0, 0])
    np.testing.assert_allclose(got["cov_yawyaw"], want[:, 2, 2])
    assert np.all(got["cov_xy"] == 0) and got["cov_xx"][0] == 0
    assert got["cov_xx"][1] == pytest.approx((0.01 + 0.05 * 0.1) ** 2, rel=0.05)  # 1 m/s at 10 Hz
