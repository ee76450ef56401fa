"""An analytic radar-inertial run for the filter and odometry tests (no tests here; helpers only).

The base drives a circle at constant speed (x forward, tangent to the circle; yaw rate = speed / radius)
past static landmarks; the radar is mounted as in ColoRadar (boresight along base +y, i.e. towards the
circle centre). Radar points of static landmarks carry the exact Doppler ``-u . v_radar`` plus noise;
clutter points have random positions and Doppler (label 1), ghosts are static points beyond the walls
(label 2, Doppler consistent with a static point, like multipath mirror images). The IMU measures the
exact angular rate and specific force (gravity included) plus optional noise and bias.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.geometry import pose_matrix
from tests.test_ingest_logs import BASE_FROM_IMU, BASE_FROM_RADAR, T0, Scene

G = 9.81


@dataclass
class CircleRun:
    scene: Scene
    labels: list[np.ndarray] = field(default_factory=list)
    #: true radar velocity in the radar frame per scan
    v_radar: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    radius: float = 4.0
    speed: float = 1.0
    base_from_radar: np.ndarray = field(default_factory=lambda: pose_matrix(*BASE_FROM_RADAR))


def base_pose(t: np.ndarray, radius: float, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """Position (N, 3) and yaw (N,) of the base at times t (s): counter-clockwise circle from (radius, 0)."""
    w = speed / radius
    pos = np.stack([radius * np.cos(w * t), radius * np.sin(w * t), np.zeros_like(t)], axis=1)
    return pos, w * t + np.pi / 2


def _visible(world: np.ndarray, p_wr: np.ndarray, R_wr: np.ndarray, prob: float, rng: np.random.Generator
             ) -> np.ndarray:
    """Points in the radar's field of view (radar frame), each detected with probability ``prob``."""
    q = (world - p_wr) @ R_wr
    r = np.linalg.norm(q, axis=1)
    az = np.arctan2(q[:, 1], q[:, 0])
    ok = (r > 0.5) & (r < 9.0) & (np.abs(az) < np.radians(60)) & (rng.random(len(q)) < prob)
    return q[ok]


def circle_run(duration: float = 8.0, radius: float = 4.0, speed: float = 1.0, seed: int = 0, radar_rate: float = 10.0,
               imu_rate: float = 200.0, gt_rate: float = 50.0, doppler_noise: float = 0.03, pos_noise: float = 0.03,
               clutter: float = 3.0, ghosts: float = 1.0, detect_prob: float = 0.85, gyro_noise: float = 0.0,
               accel_noise: float = 0.0, gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
               accel_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> CircleRun:
    rng = np.random.default_rng(seed)
    w = speed / radius
    T_br = pose_matrix(*BASE_FROM_RADAR)
    R_br, t_br = T_br[:3, :3], T_br[:3, 3]
    # landmarks: an inner ring of posts and an outer wall, a few heights
    ang_in = np.arange(0, 2 * np.pi, 0.35 / (radius - 2.0))
    ang_out = np.arange(0, 2 * np.pi, 0.35 / (radius + 2.5))
    inner = np.stack([(radius - 2.0) * np.cos(ang_in), (radius - 2.0) * np.sin(ang_in),
                      rng.uniform(-0.3, 0.5, len(ang_in))], axis=1)
    outer = np.stack([(radius + 2.5) * np.cos(ang_out), (radius + 2.5) * np.sin(ang_out),
                      rng.uniform(-0.3, 0.5, len(ang_out))], axis=1)
    landmarks = np.vstack([inner, outer])
    ghost_src = np.stack([(radius - 5.0) * np.cos(ang_in), (radius - 5.0) * np.sin(ang_in),
                          rng.uniform(-0.3, 0.5, len(ang_in))], axis=1)  # mirror images behind the posts

    sc = Scene()
    out = CircleRun(sc, radius=radius, speed=speed, base_from_radar=T_br)
    n_scans = int(duration * radar_rate)
    v_list = []
    for i in range(n_scans):
        t = i / radar_rate
        pos, yaw = base_pose(np.array([t]), radius, speed)
        c, s = np.cos(yaw[0]), np.sin(yaw[0])
        R_wb = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        R_wr = R_wb @ R_br
        p_wr = pos[0] + R_wb @ t_br
        v_base = np.array([speed, 0.0, 0.0])
        v_r = R_br.T @ (v_base + np.cross([0, 0, w], t_br))
        v_list.append(v_r)

        pts = _visible(landmarks, p_wr, R_wr, detect_prob, rng)
        gh = _visible(ghost_src, p_wr, R_wr, 1.0, rng)
        gh = gh[rng.random(len(gh)) < ghosts / max(len(gh), 1)]
        n_cl = rng.poisson(clutter)
        cl_r = rng.uniform(1.0, 8.0, n_cl)
        cl_a = rng.uniform(-1.0, 1.0, n_cl)
        cl = np.stack([cl_r * np.cos(cl_a), cl_r * np.sin(cl_a), rng.uniform(-0.5, 0.5, n_cl)], axis=1)
        xyz = np.vstack([pts, gh, cl])
        u = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
        dop = -u @ v_r
        dop[len(pts) + len(gh):] = rng.uniform(-2.0, 2.0, n_cl)
        dop += rng.normal(0, doppler_noise, len(xyz))
        xyz = xyz + rng.normal(0, pos_noise, xyz.shape)
        labels = np.r_[np.zeros(len(pts)), np.full(len(gh), 2), np.ones(n_cl)].astype(np.int8)
        inten = np.r_[rng.uniform(12, 30, len(pts)), rng.uniform(8, 15, len(gh)), rng.uniform(4, 14, n_cl)]
        sc.radar.append((T0 + round(t * 1e9), {"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
                                               "z": xyz[:, 2].astype(np.float32),
                                               "intensity": inten.astype(np.float32),
                                               "doppler": dop.astype(np.float32)}))
        out.labels.append(labels)
    out.v_radar = np.array(v_list)
    # IMU = base orientation (identity extrinsic rotation in this scene): gyro (0, 0, w), specific force
    t_imu = np.arange(int(duration * imu_rate) + 1) / imu_rate - 0.05
    yaw = w * t_imu + np.pi / 2
    a_world = -w * w * np.stack([radius * np.cos(w * t_imu), radius * np.sin(w * t_imu), np.zeros_like(t_imu)], 1)
    f_world = a_world + np.array([0.0, 0.0, G])
    c, s = np.cos(yaw), np.sin(yaw)
    f_body = np.stack([c * f_world[:, 0] + s * f_world[:, 1], -s * f_world[:, 0] + c * f_world[:, 1], f_world[:, 2]], 1)
    f_body[:, :2] -= w * w * np.asarray(BASE_FROM_IMU[0][:2])  # centripetal term of the IMU's lever arm
    gyro = np.tile([0.0, 0.0, w], (len(t_imu), 1))
    f_body += np.asarray(accel_bias) + rng.normal(0, accel_noise * np.sqrt(imu_rate), f_body.shape)
    gyro += np.asarray(gyro_bias) + rng.normal(0, gyro_noise * np.sqrt(imu_rate), gyro.shape)
    sc.imu_t = T0 + np.round(t_imu * 1e9).astype(np.int64)
    sc.imu = np.hstack([f_body, gyro])
    for i in range(int(duration * 2)):  # a sparse lidar (ingest's ColoRadar profile requires the topic)
        cols = {k: rng.normal(size=20).astype(np.float32) for k in ("x", "y", "z", "intensity")}
        sc.lidar.append((T0 + i * 500_000_000 + 20_000_000, cols))
    t_gt = np.arange(int(duration * gt_rate) + 1) / gt_rate - 0.05
    pos, yaw = base_pose(t_gt, radius, speed)
    q = np.stack([np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2), np.cos(yaw / 2)], axis=1)
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    sc.gt_t = T0 + np.round(t_gt * 1e9).astype(np.int64)
    sc.gt = np.hstack([pos, q])
    return out


def write_circle_log(path: Path, run: CircleRun, form: str = "ros1", labels: bool = True) -> Path:
    """Write the run as a log (see tests.test_ingest_logs.write_log) plus the simulator's label sidecar."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from tests.test_ingest_logs import write_log

    out = write_log(path, run.scene, form)
    if labels:
        side = out / "sim" if out.is_dir() else out.parent / (out.stem + ".sim")
        side.mkdir(parents=True, exist_ok=True)
        rows = [(i, t, j, lab) for i, ((t, _), labs) in enumerate(zip(run.scene.radar, run.labels, strict=True))
                for j, lab in enumerate(labs)]
        a = np.array(rows, dtype=np.int64).reshape(-1, 4)
        pq.write_table(pa.table({"scan": a[:, 0].astype(np.int32), "t_ns": a[:, 1], "point": a[:, 2].astype(np.int32),
                                 "label": a[:, 3].astype(np.int8)}), side / "radar_labels.parquet")
    return out
