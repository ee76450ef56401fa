"""EKF-RIO on real IMUs: the initial standstill (attitude, biases, noise) and recovery from repeated rejections."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.geometry import pose_matrix
from stages.odometry.ekf_rio import (
    EkfResult,
    EkfRio,
    find_standstill,
    innovations_agree,
    radar_moving,
    run_ekf,
)
from stages.odometry.params import OdometryParams
from tests.test_filter_scene import CircleRun, circle_run
from tests.test_ingest_logs import BASE_FROM_IMU

#: the increment covariance of the filter's own noise model (no separate covariance analysis)
OWN_COVARIANCE = {"accel_noise_density": None, "gyro_noise_density": None, "velocity_scale": 1.0}


def ekf_params(**groups: Any) -> OdometryParams:
    """The odometry parameters with ``groups`` (``imu={"accel_noise_density": 0.02}``), the filter's own
    increment covariance unless ``covariance`` is given."""
    groups.setdefault("covariance", OWN_COVARIANCE)
    return OdometryParams(**groups)

NS = 1_000_000_000


def _still_then_move(still_s: float = 2.0, rate: float = 400.0, seed: int = 0) -> tuple[np.ndarray, ...]:
    """IMU at rest (white noise, biases, tilted) for ``still_s``, then shaken; radar speeds zero then 1 m/s."""
    rng = np.random.default_rng(seed)
    n = int(4.0 * rate)
    t = (np.arange(n) / rate * NS).astype(np.int64)
    g_up = np.array([0.3, -0.2, 9.8])  # tilted: gravity partly on x and y
    bias_g = np.array([0.004, -0.003, 0.006])
    acc = np.tile(g_up, (n, 1)) + rng.normal(0, 0.002 * np.sqrt(rate), (n, 3))
    gyro = np.tile(bias_g, (n, 1)) + rng.normal(0, 2.5e-4 * np.sqrt(rate), (n, 3))
    moving = t >= still_s * NS
    acc[moving] += rng.normal(0, 1.5, (int(moving.sum()), 3))
    gyro[moving] += rng.normal(0, 0.2, (int(moving.sum()), 3))
    scan_t = (np.arange(40) * 0.1 * NS).astype(np.int64)
    vel = np.zeros((40, 3))
    vel[scan_t >= still_s * NS, 0] = 1.0
    return t, acc, gyro, scan_t, vel, bias_g


def test_standstill_found_with_its_bias_and_noise() -> None:
    t, acc, gyro, scan_t, vel, bias_g = _still_then_move()
    cov = np.tile(np.eye(3) * 0.01, (len(scan_t), 1, 1))
    moving = radar_moving(vel, cov, np.ones(len(scan_t), bool), 0.15)
    st = find_standstill(t, acc, gyro, 0, scan_t, moving, ekf_params())
    assert st is not None
    assert 1.6 <= (st.t1_ns - st.t0_ns) / NS <= 2.0  # ends before the motion (one window of margin)
    np.testing.assert_allclose(st.gyro_mean, bias_g, atol=3e-4)
    assert st.gyro_noise_density == pytest.approx(2.5e-4, rel=0.1)
    assert st.accel_noise_density == pytest.approx(0.002, rel=0.1)
    # a log that starts moving has none
    assert find_standstill(t, acc, gyro, int(2.0 * NS), scan_t, moving, ekf_params()) is None


def test_radar_moving_needs_speed_and_significance() -> None:
    vel = np.array([[0.0, 0.0, 0.2], [0.5, 0.0, 0.0], [0.05, 0.0, 0.0]])
    cov = np.stack([np.diag([1e-3, 1e-3, 0.05]), np.eye(3) * 1e-3, np.eye(3) * 1e-6])
    # 0.2 m/s in z with a 0.22 m/s std is noise; 0.5 m/s in x is motion; 0.05 m/s is below the speed floor
    np.testing.assert_array_equal(radar_moving(vel, cov, np.ones(3, bool), 0.15), [False, True, False])


def test_ekf_starts_from_the_standstill() -> None:
    t, acc, gyro, scan_t, vel, bias_g = _still_then_move()
    vel[:] = 0.0  # stays still for the radar: only the start matters here
    acc[:], gyro[:] = acc[:800].mean(axis=0), gyro[:800].mean(axis=0)
    cov = np.tile(np.eye(3) * 0.01, (len(scan_t), 1, 1))
    res = run_ekf(t, acc, gyro, scan_t, vel, cov, np.full(len(scan_t), 3), np.ones(len(scan_t), bool), np.eye(4),
                  ekf_params())
    assert res.stats["standstill"] is not None
    np.testing.assert_allclose(res.gyro_bias[0], bias_g, atol=3e-4)
    up = res.T_world_imu[0, :3, :3] @ (acc[0] / np.linalg.norm(acc[0]))
    np.testing.assert_allclose(up, [0, 0, 1], atol=1e-6)  # attitude from the standstill's specific force
    assert np.abs(res.T_world_imu[-1, :3, 3]).max() < 0.05  # and it stays put


def _circle_ekf(offset_from: int | None, recover_after: int, outliers_from: int | None = None,
                recover_consistent: bool = True) -> tuple[EkfResult, CircleRun, np.ndarray, np.ndarray]:
    """EKF-RIO on a 20 s circle; the result, the run, the scan stamps and imu <- radar."""
    run = circle_run(duration=20.0, seed=0, gyro_noise=1.5e-4, accel_noise=6e-4, clutter=0, ghosts=0)
    sc = run.scene
    scan_t = np.array([t for t, _ in sc.radar], dtype=np.int64)
    rng = np.random.default_rng(1)
    vel = run.v_radar + rng.normal(0, 0.02, run.v_radar.shape)
    if offset_from is not None:
        vel[offset_from:, 0] += 0.6  # the radar disagrees with the IMU from here on (e.g. a bad IMU stretch)
    if outliers_from is not None:
        # 40 scans of which four in every five are a wild, claimed-precise estimate (clutter's own Doppler
        # consensus): streaks of rejections whose innovations scatter, as at a standstill among clutter
        bad = np.arange(outliers_from, outliers_from + 40)
        bad = bad[(bad - outliers_from) % 5 != 4]
        vel[bad] += rng.uniform(-2.5, 2.5, (len(bad), 3))
    cov = np.tile(np.eye(3) * 0.02 ** 2, (len(scan_t), 1, 1))
    imu_from_radar = np.linalg.inv(pose_matrix(*BASE_FROM_IMU)) @ run.base_from_radar
    res = run_ekf(sc.imu_t, sc.imu[:, :3], sc.imu[:, 3:], scan_t, vel, cov, np.full(len(scan_t), 3),
                  np.ones(len(scan_t), bool), imu_from_radar,
                  ekf_params(imu={"accel_noise_density": 0.02},
                             recovery={"after": recover_after, "consistent": recover_consistent}))
    return res, run, scan_t, imu_from_radar


def _circle(offset_from: int | None, recover_after: int) -> tuple[dict[str, object], np.ndarray, np.ndarray]:
    """Stats, the estimated radar velocity and what the radar says (without its noise)."""
    res, run, _, imu_from_radar = _circle_ekf(offset_from, recover_after)
    v_radar_est = np.einsum("ji,sj->si", imu_from_radar[:3, :3],
                            np.einsum("sji,sj->si", res.T_world_imu[:, :3, :3], res.velocity))
    target = run.v_radar.copy()  # what the radar says, without its noise
    if offset_from is not None:
        target[offset_from:, 0] += 0.6
    return res.stats, v_radar_est, target


def _circle_heading(outliers_from: int | None = None, recover_consistent: bool = True
                    ) -> tuple[dict[str, object], np.ndarray]:
    """Stats and the heading error (deg, from the first scan) with ``recover_after`` 3 and no offset."""
    res, run, scan_t, _ = _circle_ekf(None, 3, outliers_from, recover_consistent)
    yaw = np.unwrap(np.arctan2(res.T_world_imu[:, 1, 0], res.T_world_imu[:, 0, 0]))
    err = np.degrees(yaw - run.speed / run.radius * scan_t * 1e-9)  # the true heading turns at v / r
    return res.stats, err - err[0]


def test_recovery_follows_the_radar_instead_of_rejecting_it_forever() -> None:
    # a clean run never needs a recovery; its velocity error is the baseline of this comparison (which leaves
    # out the lever-arm term w x t of the radar velocity)
    clean, v_c, target_c = _circle(offset_from=None, recover_after=3)
    assert clean["recoveries"] == 0 and clean["velocity_rejected"] <= 3
    base = np.abs(v_c[110:, 0] - target_c[110:, 0]).mean()
    stats, v_est, target = _circle(offset_from=100, recover_after=3)
    assert stats["recoveries"] >= 1 and stats["velocity_rejected"] <= 10
    assert np.abs(v_est[110:, 0] - target[110:, 0]).mean() < base + 0.02  # on the radar again within a second
    # without recovery the gate keeps rejecting: a silent divergence
    stats_off, v_off, _ = _circle(offset_from=100, recover_after=10 ** 5)
    assert stats_off["recoveries"] == 0 and stats_off["velocity_rejected"] > 50
    assert np.abs(v_off[110:, 0] - target[110:, 0]).mean() > base + 0.2


def test_scattered_outliers_are_rejected_without_a_recovery() -> None:
    # streaks of wild ego-velocities (each far from the last) are the radar's outliers, not a filter that is off:
    # no recovery, so no attitude inflation that lets them into the heading
    _, err_clean = _circle_heading()
    stats, err = _circle_heading(outliers_from=60)
    assert stats["recoveries"] == 0 and stats["recoveries_declined"] >= 3 and stats["velocity_rejected"] >= 25
    assert np.abs(err).max() < np.abs(err_clean).max() + 0.5  # deg (1.6 against 1.4 when written)
    # the rule off: the same streaks inflate the attitude and the outliers turn the heading
    stats_off, err_off = _circle_heading(outliers_from=60, recover_consistent=False)
    assert stats_off["recoveries"] >= 3 and "recoveries_declined" in stats_off
    assert np.abs(err_off).max() > np.abs(err).max() + 3.0  # (9.1 when written)


def test_innovations_agree_on_the_rows_both_have() -> None:
    S = np.eye(3) * 0.01
    r3, r2 = np.arange(3), np.arange(2)
    # consecutive pairs on their common rows: the planar middle one has no z to disagree with
    same = [(r3, np.array([0.6, 0.0, 0.0]), S), (r2, np.array([0.62, 0.01]), S[:2, :2]),
            (r3, np.array([0.58, -0.02, 0.8]), S)]
    assert innovations_agree(same, 0.999)
    assert not innovations_agree([same[0], same[2]], 0.999)  # side by side, z differs by 0.8 (5.7 sigma)
    assert not innovations_agree([*same[:2], (r3, np.array([-0.1, 0.0, 0.0]), S)], 0.999)  # x jumps on the last
    assert innovations_agree([(r3, np.array([0.6, 0.0, 0.0]), S)], 0.999)  # one alone agrees with itself
    scattered = [(r3, np.array([1.5, -1.0, 0.2]), S), (r3, np.array([-0.9, 1.1, 0.0]), S)]
    assert not innovations_agree(scattered, 0.999)


def _pitched_mount(mount_sigma0: float, level_sigma: float) -> tuple[EkfResult, np.ndarray]:
    """A level 30 s circle at 1 m/s whose radar is truly pitched by 1.5 deg against its stated mount: the filter
    is given the stated extrinsic; returns the result and the true mount error (its height stays 0)."""
    run = circle_run(duration=30.0, seed=0, gyro_noise=1.5e-4, accel_noise=6e-4, clutter=0, ghosts=0)
    sc = run.scene
    scan_t = np.array([t for t, _ in sc.radar], dtype=np.int64)
    err = np.radians([1.5, 0.0, 0.0])  # about the radar's x axis (it looks sideways): forward speed read as climb
    R_err = Rotation.from_rotvec(err).as_matrix()
    rng = np.random.default_rng(2)
    vel = run.v_radar @ R_err + rng.normal(0, 0.02, run.v_radar.shape)  # R_err^T v: the truly mounted radar
    cov = np.tile(np.eye(3) * 0.02 ** 2, (len(scan_t), 1, 1))
    imu_from_radar = np.linalg.inv(pose_matrix(*BASE_FROM_IMU)) @ run.base_from_radar
    res = run_ekf(sc.imu_t, sc.imu[:, :3], sc.imu[:, 3:], scan_t, vel, cov, np.full(len(scan_t), 3),
                  np.ones(len(scan_t), bool), imu_from_radar,
                  ekf_params(height={"mount_sigma0_deg": float(np.degrees(mount_sigma0)),
                                     "level_velocity_sigma": level_sigma}))
    return res, err


def test_mount_pitch_estimated_with_the_level_prior_and_the_height_stops_drifting() -> None:
    """A pitched radar makes EKF-RIO climb (the stated mount reads forward speed as vertical); with the mount
    state and the level prior the pitch is estimated within 3 sigma, its sigma shrinks, and z stays put."""
    plain, err = _pitched_mount(0.0, 0.0)
    z_plain = plain.T_world_imu[-1, 2, 3]
    assert abs(z_plain) > 0.5  # ~30 m * sin(1.5 deg) = 0.79 m of made-up height
    res, err = _pitched_mount(np.radians(3.0), 0.2)
    assert abs(res.mount_error[-1, 0] - err[0]) < 3 * res.mount_sigma[-1, 0]
    assert res.mount_sigma[-1, 0] < 0.3 * np.radians(3.0)
    assert res.stats["level_rejected"] == 0  # a level platform: the gate never refuses the prior
    assert abs(res.T_world_imu[-1, 2, 3]) < 0.2 * abs(z_plain)
    # the mount state alone cannot tell a pitched radar from a real climb at constant speed: unobservable
    alone, _ = _pitched_mount(np.radians(3.0), 0.0)
    assert alone.mount_sigma[-1, 0] > 0.8 * np.radians(3.0)
    # without the state, the level prior alone only pulls the height part of the way (the radar keeps pushing)
    level, _ = _pitched_mount(0.0, 0.2)
    assert abs(level.T_world_imu[-1, 2, 3]) > abs(res.T_world_imu[-1, 2, 3])


def test_level_update_is_a_schmidt_update_on_height_vertical_velocity_and_mount() -> None:
    """The level pseudo-measurement moves only p_z, v_z and the mount (attitude, biases and the planar state
    keep their means even where the covariance correlates them); the full update moves them too."""
    rng = np.random.default_rng(3)
    for schmidt in (True, False):
        ekf = EkfRio(ekf_params(height={"mount_sigma0_deg": 2.0, "level_schmidt": schmidt}), np.eye(3),
                     np.array([1.0, 0.0, 0.1]))
        A = rng.normal(0, 0.05, (18, 18))
        ekf.P = ekf.P + A @ A.T  # correlated, positive definite
        before = (ekf.p.copy(), ekf.v.copy(), ekf.R.copy(), ekf.bg.copy(), ekf.ba.copy())
        assert ekf.update_level(0.2)
        moved = [not np.allclose(a, b) for a, b in zip((ekf.p, ekf.v, ekf.R, ekf.bg, ekf.ba), before, strict=True)]
        assert ekf.v[2] != before[1][2] and np.any(ekf.mount != 0)
        if schmidt:
            assert moved == [True, True, False, False, False]
            np.testing.assert_array_equal(ekf.p[:2], before[0][:2])
            np.testing.assert_array_equal(ekf.v[:2], before[1][:2])
        else:
            assert all(moved)
        assert np.all(np.linalg.eigvalsh(ekf.P) > 0)
