"""Gyro integration, scan-to-scan motion, multi-frame tracking and the point-uncertainty model."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from stages.filter.tracking import frame_motions, interval_rotations, track_masks
from stages.filter.uncertainty import max_sigma, point_covariances

NS = 1_000_000_000


def test_interval_rotations_integrate_a_constant_rate() -> None:
    imu_t = np.arange(0, 2 * NS, NS // 200, dtype=np.int64)
    w = np.array([0.1, -0.2, 0.5])
    scan_t = np.array([0.13, 0.23, 0.33, 0.9]) * NS
    R = interval_rotations(imu_t, np.tile(w, (len(imu_t), 1)), scan_t.astype(np.int64))
    np.testing.assert_allclose(R[0], np.eye(3))
    for i, dt in ((1, 0.1), (2, 0.1), (3, 0.57)):
        np.testing.assert_allclose(Rotation.from_matrix(R[i]).as_rotvec(), w * dt, atol=1e-9)


def _world_to_sensor(points: np.ndarray, pos: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return (points - pos) @ R


def _moving_sensor(n_scans: int = 8, speed: float = 2.0, rate: float = 0.6, clutter: int = 6, seed: int = 0):
    rng = np.random.default_rng(seed)
    landmarks = np.column_stack([rng.uniform(2, 9, 25), rng.uniform(-5, 5, 25), rng.uniform(-0.3, 0.3, 25)])
    dt = 0.1
    scan_t = (np.arange(n_scans) * dt * NS).astype(np.int64)
    pts, is_landmark, vel = [], [], []
    for i in range(n_scans):
        t = i * dt
        yaw = rate * t
        # unicycle: velocity along the sensor's x axis, turning at `rate`
        pos = np.array([speed * np.sin(rate * t) / rate, speed * (1 - np.cos(rate * t)) / rate, 0.0])
        lm = _world_to_sensor(landmarks, pos, yaw) + rng.normal(0, 0.03, landmarks.shape)
        cl = np.column_stack([rng.uniform(1, 9, clutter), rng.uniform(-5, 5, clutter), rng.uniform(-0.3, 0.3, clutter)])
        pts.append(np.vstack([lm, cl]))
        is_landmark.append(np.r_[np.ones(len(lm), bool), np.zeros(clutter, bool)])
        vel.append([speed, 0.0, 0.0])
    imu_t = np.arange(-NS // 10, n_scans * NS // 10 + NS // 10, NS // 200, dtype=np.int64)
    gyro = np.tile([0.0, 0.0, rate], (len(imu_t), 1))
    return pts, is_landmark, np.array(vel), scan_t, imu_t, gyro


def test_tracking_keeps_static_landmarks_and_rejects_clutter() -> None:
    pts, is_lm, vel, scan_t, imu_t, gyro = _moving_sensor()
    motions = frame_motions(interval_rotations(imu_t, gyro, scan_t), vel, scan_t)
    gates = [np.full(len(p), 0.3) for p in pts]
    masks = track_masks(pts, motions, k=2, gates=gates)
    assert not masks[0].any() and not masks[1].any()  # no history yet
    kept_lm = np.concatenate([m[l] for m, l in zip(masks[2:], is_lm[2:], strict=True)])
    assert kept_lm.mean() > 0.97
    # clutter that happens to lie on a landmark is indistinguishable from it; clutter in free space is dropped
    far = []
    for m, l, p in zip(masks[2:], is_lm[2:], pts[2:], strict=True):
        d = np.linalg.norm(p[~l][:, None, :2] - p[l][None, :, :2], axis=2).min(axis=1)
        far.append(m[~l][d > 0.6])
    kept_far = np.concatenate(far)
    assert len(kept_far) > 20 and kept_far.mean() < 0.05
    # without motion compensation the same landmarks (moving 0.2 m per scan and turning) are lost
    still = frame_motions(np.tile(np.eye(3), (len(scan_t), 1, 1)), np.zeros_like(vel), scan_t)
    masks0 = track_masks(pts, still, k=2, gates=gates)
    kept0 = np.concatenate([m[l] for m, l in zip(masks0[2:], is_lm[2:], strict=True)])
    assert kept0.mean() < 0.5


def test_unusable_motion_breaks_tracks_and_k0_keeps_everything() -> None:
    pts, _, vel, scan_t, imu_t, gyro = _moving_sensor(n_scans=6)
    motions = frame_motions(interval_rotations(imu_t, gyro, scan_t), vel, scan_t)
    gates = [np.full(len(p), 0.3) for p in pts]
    usable = np.ones(6, bool)
    usable[3] = False
    masks = track_masks(pts, motions, k=2, gates=gates, usable=usable)
    assert not masks[3].any() and not masks[4].any() and masks[5].any()
    assert all(m.all() for m in track_masks(pts, motions, k=0, gates=gates))


def test_point_covariance_matches_the_spherical_model() -> None:
    r, az, el = 5.0, np.radians(30), np.radians(10)
    p = r * np.array([[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]])
    sr, sa, se = 0.05, np.radians(2), np.radians(8)
    cov = point_covariances(p, sr, sa, se)[0]
    # eigenvalues are the variances along range, azimuth arc and elevation arc
    np.testing.assert_allclose(np.sort(np.linalg.eigvalsh(cov)),
                               np.sort([sr ** 2, (r * np.cos(el) * sa) ** 2, (r * se) ** 2]), rtol=1e-9)
    # the range direction carries exactly the range variance
    u = p[0] / r
    np.testing.assert_allclose(u @ cov @ u, sr ** 2, rtol=1e-9)
    # Monte Carlo check of the horizontal spread on the level plane
    rng = np.random.default_rng(0)
    m = 200_000
    rr, aa, ee = r + rng.normal(0, sr, m), az + rng.normal(0, sa, m), el + rng.normal(0, se, m)
    xy = np.stack([rr * np.cos(ee) * np.cos(aa), rr * np.cos(ee) * np.sin(aa)], axis=1)
    mc = np.sqrt(np.linalg.eigvalsh(np.cov(xy.T))[-1])
    assert abs(max_sigma(cov[None])[0] - mc) / mc < 0.03
    assert max_sigma(cov[None], horizontal=False)[0] > max_sigma(cov[None])[0]
