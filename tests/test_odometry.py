"""EKF-RIO on a synthetic trajectory with a known IMU, the drift metrics, and the odometry stage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.errors import UserError
from core.geometry import pose_matrix, yaw_of
from core.trajectory_metrics import drift, se2_compose_anchor
from schemas.io import read_artifact
from stages.odometry.ekf_rio import gravity_aligned, run_ekf
from tests.test_filter import run_stages
from tests.test_filter_scene import base_pose, circle_run, write_circle_log
from tests.test_ingest_logs import BASE_FROM_IMU, GT_TOPIC, T0
from tests.test_odometry_robust import ekf_params


def _ekf_on(run, velocity_noise: float, seed: int, updates: bool = True):
    # the synthetic IMU is tactical grade without vibration (white noise 6e-4 m/s^2/sqrt(Hz)): the filter is told
    # so; the default process noise (0.2) is sized for MEMS IMUs in handheld or vehicle motion
    rng = np.random.default_rng(seed)
    sc = run.scene
    scan_t = np.array([t for t, _ in sc.radar], dtype=np.int64)
    vel = run.v_radar + rng.normal(0, velocity_noise, run.v_radar.shape)
    cov = np.tile(np.eye(3) * velocity_noise ** 2, (len(scan_t), 1, 1))
    valid = np.full(len(scan_t), updates)
    valid[0] = True
    imu_from_radar = np.linalg.inv(pose_matrix(*BASE_FROM_IMU)) @ run.base_from_radar
    res = run_ekf(sc.imu_t, sc.imu[:, :3], sc.imu[:, 3:], scan_t, vel, cov, np.full(len(scan_t), 3), valid,
                  imu_from_radar, ekf_params(imu={"accel_noise_density": 0.02}))
    T_wb = res.T_world_imu @ np.linalg.inv(pose_matrix(*BASE_FROM_IMU))
    est = np.stack([T_wb[:, 0, 3], T_wb[:, 1, 3], yaw_of(T_wb[:, :3, :3])], axis=1)
    pos, yaw = base_pose((scan_t - T0) * 1e-9, run.radius, run.speed)
    ref = np.column_stack([pos[:, :2], yaw])
    x, y, h = se2_compose_anchor(est[:, 0], est[:, 1], est[:, 2], 0, ref[0, 0], ref[0, 1], ref[0, 2])
    return drift(scan_t, np.column_stack([x, y, h]), ref), res


@pytest.mark.parametrize("seed", [0, 1])
def test_ekf_tracks_a_circle_with_noisy_biased_imu(seed: int) -> None:
    bias_g = np.array([0.002, -0.001, 0.0005])
    run = circle_run(duration=30.0, seed=seed, gyro_noise=1.5e-4, accel_noise=6e-4, gyro_bias=tuple(bias_g),
                     accel_bias=(0.03, -0.02, 0.04), clutter=0, ghosts=0)
    d, res = _ekf_on(run, velocity_noise=0.05, seed=seed)
    assert res.stats["velocity_updates"] >= 295 and res.stats["velocity_rejected"] <= 3
    assert d["path_length_m"] == pytest.approx(30.0 - 0.1, rel=0.02)
    assert d["drift_pct_of_distance"] < 1.5
    assert abs(d["final_yaw_error_deg"]) < 3.0
    # roll/pitch gyro biases are observable: estimates within 3 sigma of the truth, and sigma shrank
    err = np.abs(res.gyro_bias[-1] - bias_g)
    assert np.all(err[:2] < 3 * res.sigma[-1, 9:11]) and np.all(res.sigma[-1, 9:11] < 0.5 * 0.005)
    # the vertical accelerometer bias too
    assert abs(res.accel_bias[-1, 2] - 0.04) < 3 * res.sigma[-1, 14]
    # IMU-only dead reckoning from the same start drifts far more: the radar updates matter
    d_imu, _ = _ekf_on(run, velocity_noise=0.05, seed=seed, updates=False)
    assert d_imu["final_position_error_m"] > 10 * d["final_position_error_m"]


def test_gravity_alignment_recovers_roll_and_pitch() -> None:
    R_true = Rotation.from_euler("xyz", [0.1, -0.2, 1.0]).as_matrix()  # world <- imu
    f = R_true.T @ np.array([0.0, 0.0, 9.81])  # specific force at rest, imu frame
    R = gravity_aligned(f)
    np.testing.assert_allclose(R @ f, [0, 0, 9.81], atol=1e-9)
    assert abs(yaw_of(R)) < 1e-9
    # same roll/pitch as the truth: the up axes agree
    np.testing.assert_allclose(R.T[:, 2], R_true.T[:, 2], atol=1e-9)


def test_anchor_and_drift_metrics() -> None:
    t = (np.arange(61) * 1e9).astype(np.int64)  # one minute
    ref = np.column_stack([np.arange(61.0), np.zeros(61), np.zeros(61)])
    yaw_err = np.radians(np.linspace(0, 3.0, 61))  # 3 deg over 1 min
    est = ref.copy()
    est[:, 1] = np.linspace(0, 1.2, 61)  # 1.2 m off after 60 m
    est[:, 2] = yaw_err
    d = drift(t, est, ref)
    assert d["path_length_m"] == pytest.approx(60.0)
    assert d["drift_pct_of_distance"] == pytest.approx(2.0)
    assert d["yaw_drift_deg_per_min"] == pytest.approx(3.0)
    assert d["yaw_drift_slope_deg_per_min"] == pytest.approx(3.0)
    zero = np.zeros(2)
    x, y, h = se2_compose_anchor(np.array([0.0, 1.0]), zero, zero, 0, 5.0, 2.0, np.pi / 2)
    np.testing.assert_allclose([x[1], y[1], h[1]], [5.0, 3.0, np.pi / 2], atol=1e-12)


@pytest.fixture(scope="module")
def circle_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    root = tmp_path_factory.mktemp("odo")
    run = circle_run(duration=12.0, seed=3, gyro_noise=1.5e-4, accel_noise=6e-4, gyro_bias=(0.0, 0.0, 0.001))
    return write_circle_log(root / "circle", run), run


def test_odometry_stage_ekf_anchored_at_groundtruth(circle_log, tmp_path: Path) -> None:
    bag, run = circle_log
    out = run_stages(bag, tmp_path / "runs", ["odometry"])
    odo = read_artifact(out / "odometry" / "odometry.parquet", "odometry")
    assert odo.num_rows == len(run.scene.radar)
    scan_t = odo["t_ns"].to_numpy()
    pos, _ = base_pose((scan_t - T0) * 1e-9, run.radius, run.speed)
    x, y = odo["x"].to_numpy(), odo["y"].to_numpy()
    assert np.hypot(x[0] - pos[0, 0], y[0] - pos[0, 1]) < 1e-4  # anchored at (interpolated) ground truth
    assert np.abs(np.hypot(x - pos[:, 0], y - pos[:, 1])).max() < 0.3
    # the 3D part: the circle is flown level at the ground truth's height
    z, roll, pitch = (odo[c].to_numpy() for c in ("z", "roll", "pitch"))
    gt = read_artifact(out / "ingest" / "groundtruth.parquet", "groundtruth")
    assert abs(z[0] - np.interp(scan_t[0], gt["t_ns"].to_numpy(), gt["z"].to_numpy())) < 1e-6  # z anchored too
    assert np.abs(z - z[0]).max() < 0.2
    assert np.abs(np.degrees(roll)).max() < 2.0 and np.abs(np.degrees(pitch)).max() < 2.0
    stats = json.loads((out / "odometry" / "manifest.json").read_text())["stats"]
    assert stats["anchor"] == "groundtruth" and stats["drift"]["drift_pct_of_distance"] < 2.0
    out2 = run_stages(bag, tmp_path / "runs2", ["odometry"], {"odometry": {"anchor": "origin"}})
    odo2 = read_artifact(out2 / "odometry" / "odometry.parquet", "odometry")
    assert (odo2["x"][0].as_py(), odo2["y"][0].as_py(), odo2["yaw"][0].as_py()) == (0.0, 0.0, 0.0)


def test_odometry_from_a_bag_topic(circle_log, tmp_path: Path) -> None:
    bag, run = circle_log
    over = {"ingest": {"topics": {"odometry": GT_TOPIC}}, "odometry": {"source": "bag"}}
    out = run_stages(bag, tmp_path / "runs", ["odometry"], over)
    assert not (out / "filter").exists()  # the bag source needs no filter
    odo = read_artifact(out / "odometry" / "odometry.parquet", "odometry")
    pos, yaw = base_pose((odo["t_ns"].to_numpy() - T0) * 1e-9, run.radius, run.speed)
    np.testing.assert_allclose(odo["x"].to_numpy(), pos[:, 0], atol=2e-3)
    np.testing.assert_allclose(np.cos(odo["yaw"].to_numpy() - yaw), 1.0, atol=1e-5)
    with pytest.raises(UserError, match="no odometry topic"):
        run_stages(bag, tmp_path / "runs3", ["odometry"], {"odometry": {"source": "bag"}})
    # the EKF's height settings mean nothing for a topic: said, not silently dropped
    over["odometry"]["height"] = {"level_velocity_sigma": 0.2}
    out = run_stages(bag, tmp_path / "runs4", ["odometry"], over)
    warnings = json.loads((out / "odometry" / "manifest.json").read_text())["stats"]["warnings"]
    assert any("odometry.height.level_velocity_sigma=0.2" in w and "source=bag" in w for w in warnings)
