"""The simulated sensors agree with the world and the trajectory, within the noise levels they declare.

References are independent of the simulator: surfaces come from the world file (tests/test_simulator_reference.py),
extrinsics from the bag's /tf, ground truth from the sidecar's trajectory table, noise levels from its meta.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from tests.test_simulator_reference import WorldGeometry, cloud_array, read_bag, simulated, stamp_ns, transforms


class Run:
    """A simulated bag with its sidecar, decoded once."""

    def __init__(self, path: Path) -> None:
        self.bag = read_bag(path)
        side = path.with_suffix(".sim")
        self.meta = json.loads((side / "meta.json").read_text())
        self.world = WorldGeometry((side / "world.toml").read_text())
        self.traj = pq.read_table(side / "trajectory.parquet").to_pandas()
        self.labels = pq.read_table(side / "radar_labels.parquet").to_pandas()
        self.tf = transforms(self.bag)
        self.radar_msgs = [m for _, m, _ in self.bag["/mmWaveDataHdl/RScan"]]
        self.radar = np.concatenate([cloud_array(m) for m in self.radar_msgs])
        assert len(self.radar) == len(self.labels)

    def base_pose(self, t_ns: np.ndarray) -> tuple[np.ndarray, Rotation]:
        """World <- base at times ``t_ns`` (linear position, interpolated yaw; the base stays level)."""
        T = self.traj.t_ns.to_numpy()
        pos = np.column_stack([np.interp(t_ns, T, self.traj[c]) for c in ("x", "y", "z")])
        q = self.traj[["qx", "qy", "qz", "qw"]].to_numpy()
        yaw = np.unwrap(Rotation.from_quat(q).as_euler("xyz")[:, 2])
        return pos, Rotation.from_euler("z", np.interp(t_ns, T, yaw)[:, None])

    def twist(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = self.traj.t_ns.to_numpy()
        v = np.column_stack([np.interp(t_ns, T, self.traj[c]) for c in ("vx", "vy", "vz")])
        w = np.column_stack([np.interp(t_ns, T, self.traj[c]) for c in ("wx", "wy", "wz")])
        return v, w

    def radar_to_world(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (radar frame, one row per radar point) to world; also the radar origin per point."""
        T_br = self.tf[("imu_viz_link", "base_radar_link")]
        pos, rot = self.base_pose(self.labels.t_ns.to_numpy())
        origin = pos + rot.apply(T_br[:3, 3])
        return origin + rot.apply(xyz @ T_br[:3, :3].T), origin


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    """The hallway with the TI out-of-box peak grouping on, so that each return is reported in its peak cell
    (the default, grouping off, also reports the main-lobe neighbours; see test_simulator_formats)."""
    src = Path(__file__).resolve().parents[1] / "data" / "worlds" / "hallway_loop.toml"
    world = tmp_path_factory.mktemp("world-grouping") / "hallway_grouping.toml"
    world.write_text(src.read_text() + "\n[radar]\npeak_grouping = true\n")
    return Run(simulated(tmp_path_factory, world=str(world), fmt="bag"))


def _spherical(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r = np.linalg.norm(xyz, axis=1)
    return r, np.arctan2(xyz[:, 1], xyz[:, 0]), np.arcsin(np.clip(xyz[:, 2] / r, -1, 1))


def test_radar_points_lie_on_world_surfaces_except_flagged(run: Run) -> None:
    lab = run.labels.label.to_numpy()
    xyz = np.column_stack([run.radar[k] for k in ("x", "y", "z")]).astype(float)
    true = run.labels[["x_true", "y_true", "z_true"]].to_numpy(float)
    w_true, _ = run.radar_to_world(true)
    w_meas, _ = run.radar_to_world(xyz)
    surf = lab == 0
    assert surf.sum() > 100
    # the noise-free scatterers (surface patches, edges, corners, pillar surfaces) are on a surface of the world file
    assert run.world.distance(w_true[surf]).max() < 2e-3
    # reported points stay near a surface: within the range bin and the azimuth grid step at 12 m (elevation
    # errors of cells shared by several returns can move some further)
    d = run.world.distance(w_meas)
    p = run.meta["radar"]
    cell = np.hypot(p["range_resolution"], 2 * p["max_range"] / p["n_azimuth_bins"])
    assert np.median(d[surf]) < cell / 2 and np.mean(d[surf] < cell) > 0.8
    # clutter false alarms are mostly nowhere near a surface
    assert np.mean(d[lab == 1] > 0.3) > 0.5


def test_radar_points_come_from_the_processing_chain_grids(run: Run) -> None:
    """Range bins (no interpolation), the 64-bin azimuth FFT grid in sin(azimuth), Doppler bins."""
    p = run.meta["radar"]
    xyz = np.column_stack([run.radar[k] for k in ("x", "y", "z")]).astype(float)
    rng = run.radar["range"].astype(float)
    assert np.abs(rng / p["range_resolution"] - np.round(rng / p["range_resolution"])).max() < 1e-4
    assert np.abs(np.linalg.norm(xyz, axis=1) - rng).max() < 1e-4 * rng.max()
    wx = xyz[:, 1] / rng * p["n_azimuth_bins"] / 2  # azimuth sine in FFT bins
    assert np.abs(wx - np.round(wx)).max() < 1e-3
    dop = run.radar["doppler"].astype(float) / p["doppler_resolution"]
    assert np.abs(dop - np.round(dop)).max() < 1e-3
    # elevation is a phase comparison, not a grid: it takes many values (at most one per 0.001 of its span)
    wz = np.round(xyz[:, 2] / rng, 3)
    possible = min(len(rng), round(float(wz.max() - wz.min()) / 1e-3) + 1)
    assert len(np.unique(wz)) > 0.5 * possible


def test_radar_points_are_within_their_scatterers_quantisation_cell(run: Run) -> None:
    """Against the noise-free scatterer (sidecar): a return spreads over +-2 bins (Hann main lobe), so every
    point is within 2.5 range bins of its source; a point whose cell holds no other return within 10 dB
    (``cell_scatterers == 1``) is on its source's nearest range bin and azimuth grid step, with an accurate
    elevation; cells shared by several returns have biased angles (most of the elevation error)."""
    p = run.meta["radar"]
    lab = run.labels.label.to_numpy()
    lone = run.labels.cell_scatterers.to_numpy() == 1
    xyz = np.column_stack([run.radar[k] for k in ("x", "y", "z")]).astype(float)
    true = run.labels[["x_true", "y_true", "z_true"]].to_numpy(float)
    rng = run.radar["range"].astype(float)
    r_t = np.linalg.norm(true, axis=1)
    dr = np.abs(rng - r_t) / p["range_resolution"]
    step = 2.0 / p["n_azimuth_bins"]
    d_az = np.abs(xyz[:, 1] / rng - true[:, 1] / r_t) / step
    d_el = np.abs(xyz[:, 2] / rng - true[:, 2] / r_t)
    static = lab != 1
    assert np.all(dr[static] <= 2.5 + 1e-3)
    one = static & lone
    assert one.sum() > 50 and (static & ~lone).sum() > 20
    assert np.mean(dr[one] <= 0.5 + 1e-3) > 0.99 and np.all(dr[one] <= 1.0 + 1e-3)
    assert np.mean(d_az[one] <= 1.0) > 0.95 and np.median(d_az[one]) <= 0.5
    assert np.median(d_el[one]) < 0.03 and np.median(d_el[one]) < np.median(d_el[static & ~lone])


def test_true_detections_repeat_from_persistent_scatterers(run: Run) -> None:
    """Scan after scan, most true detections come from the same scatterers (world positions to 1 cm)."""
    lab = run.labels.label.to_numpy()
    true = run.labels[["x_true", "y_true", "z_true"]].to_numpy(float)
    w_true, _ = run.radar_to_world(true)
    surf = lab == 0
    scans = run.labels.scan.to_numpy()[surf]
    key = np.round(w_true[surf] / 0.01).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    pairs = np.unique(np.column_stack([inv, scans]), axis=0)
    n_scans = np.bincount(pairs[:, 0])
    assert np.mean(n_scans[inv] >= 5) > 0.4  # of 40 scans


def test_ghosts_are_behind_walls(run: Run) -> None:
    ghost = run.labels.label.to_numpy() == 2
    assert ghost.sum() > 0
    true = run.labels[["x_true", "y_true", "z_true"]].to_numpy(float)
    w_true, origin = run.radar_to_world(true)
    frac = run.world.first_vertical_crossing(origin[ghost], w_true[ghost])
    assert np.all(frac < 1.0 - 1e-3)  # the line of sight to a ghost crosses a wall or box face first


def test_doppler_is_the_radial_projection_of_the_radar_velocity(run: Run) -> None:
    p = run.meta["radar"]
    lab = run.labels.label.to_numpy()
    t_ns = run.labels.t_ns.to_numpy()
    T_br = run.tf[("imu_viz_link", "base_radar_link")]
    _, rot = run.base_pose(t_ns)
    v, w = run.twist(t_ns)
    lever = rot.apply(T_br[:3, 3])
    v_radar_world = v + np.cross(rot.apply(w), lever)
    v_radar = (rot.apply(v_radar_world, inverse=True)) @ T_br[:3, :3]  # into the radar frame
    true = run.labels[["x_true", "y_true", "z_true"]].to_numpy(float)
    u = true / np.linalg.norm(true, axis=1, keepdims=True)
    analytic = -(u * v_radar).sum(1)
    dop = run.radar["doppler"].astype(float)
    static = lab != 1
    lone = static & (run.labels.cell_scatterers.to_numpy() == 1)
    err = np.abs(dop - analytic) / p["doppler_resolution"]
    # a return spreads over +-2 Doppler bins; a lone one is reported in its nearest bin
    assert np.all(err[static] <= 2.5 + 0.05) and np.mean(err[lone] <= 0.5 + 0.05) > 0.99
    # with the reported (quantised) directions the relation still holds on average and the sign is right
    xyz = np.column_stack([run.radar[k] for k in ("x", "y", "z")]).astype(float)
    um = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    measured_dir = -(um * v_radar).sum(1)
    moving = np.linalg.norm(v_radar, axis=1) > 0.5
    assert np.corrcoef(dop[static & moving], measured_dir[static & moving])[0, 1] > 0.9
    ahead = static & moving & (um[:, 0] > 0.97)
    assert ahead.sum() > 10 and np.all(dop[ahead] < 0)  # approaching what is straight ahead: negative
    # clutter Doppler is unrelated to the motion
    assert np.mean(np.abs(dop[lab == 1] - analytic[lab == 1]) > 0.2) > 0.5


def _integrate(acc: np.ndarray, gyro: np.ndarray, t: np.ndarray, R0: Rotation, v0: np.ndarray, p0: np.ndarray,
               g: np.ndarray) -> tuple[Rotation, np.ndarray, np.ndarray]:
    """Strapdown integration (trapezoidal) of specific force and angular rate in the IMU frame."""
    R, v, p = R0, v0.copy(), p0.copy()
    a_prev = R.apply(acc[0]) + g
    for k in range(len(t) - 1):
        dt = t[k + 1] - t[k]
        R_next = R * Rotation.from_rotvec(0.5 * (gyro[k] + gyro[k + 1]) * dt)
        a_next = R_next.apply(acc[k + 1]) + g
        p = p + v * dt + (a_prev / 3 + a_next / 6) * dt * dt
        v = v + 0.5 * (a_prev + a_next) * dt
        R, a_prev = R_next, a_next
    return R, v, p


def test_imu_integrates_back_to_the_trajectory_within_noise(run: Run) -> None:
    imu = run.bag["/gx5/imu/data"]
    t_ns = np.array([stamp_ns(m) for _, m, _ in imu])
    acc = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for _, m, _ in imu])
    gyro = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for _, m, _ in imu])
    tr = run.traj
    assert np.array_equal(tr.t_ns.to_numpy(), t_ns)  # the sidecar holds the truth at every IMU sample
    p = run.meta["imu"]
    g = np.array(run.meta["gravity"])
    # at rest (start of the run) the accelerometer reads gravity, up
    assert np.allclose(acc[:20].mean(0), -g + tr[["bax", "bay", "baz"]].to_numpy()[:20].mean(0), atol=0.02)
    T_bi = run.tf[("imu_viz_link", "gx5_link")]
    R_bi = Rotation.from_matrix(T_bi[:3, :3])
    k0 = int(np.searchsorted(t_ns, t_ns[0] + 1_000_000_000))
    k1 = k0 + 600  # 2 s at 300 Hz
    sl = slice(k0, k1 + 1)
    t = (t_ns[sl] - t_ns[k0]) / 1e9
    T = t[-1]
    pos, rot = run.base_pose(t_ns[sl])
    v, w = run.twist(t_ns[sl])
    lever = rot.apply(T_bi[:3, 3])
    p_imu = pos + lever
    v_imu = v + np.cross(rot.apply(w), lever)
    R_wi = rot * R_bi
    bg = tr[["bgx", "bgy", "bgz"]].to_numpy()[sl]
    ba = tr[["bax", "bay", "baz"]].to_numpy()[sl]
    R_end, v_end, p_end = _integrate(acc[sl] - ba, gyro[sl] - bg, t, R_wi[0], v_imu[0], p_imu[0], g)
    # tolerances from the declared white-noise densities (random walks over T), 5 sigma, plus 1 mm / 1 mm/s
    ng, na, gm = p["gyro_noise_density"], p["accel_noise_density"], np.linalg.norm(g)
    s_ang = ng * np.sqrt(T)
    s_vel = na * np.sqrt(T) + gm * ng * np.sqrt(T**3 / 3)
    s_pos = na * np.sqrt(T**3 / 3) + gm * ng * np.sqrt(T**5 / 20)
    ang_err = (R_end.inv() * R_wi[-1]).magnitude()
    assert ang_err < 5 * s_ang + 1e-4
    assert np.linalg.norm(v_end - v_imu[-1]) < 5 * s_vel + 1e-3
    assert np.linalg.norm(p_end - p_imu[-1]) < 5 * s_pos + 1e-3
    travelled = np.linalg.norm(p_imu[-1] - p_imu[0])
    assert travelled > 1.0  # the window has real motion
    # the biases are there (ignoring them breaks dead reckoning) and drift slowly
    _, _, p_raw = _integrate(acc[sl], gyro[sl], t, R_wi[0], v_imu[0], p_imu[0], g)
    assert np.linalg.norm(p_raw - p_imu[-1]) > 5 * s_pos + 1e-3
    drift = np.abs(tr[["bax", "bay", "baz"]].to_numpy()[-1] - tr[["bax", "bay", "baz"]].to_numpy()[0])
    assert np.all(drift < 5 * p["accel_bias_walk"] * np.sqrt(run.meta["duration_s"]))


def test_lidar_points_lie_on_world_surfaces(run: Run) -> None:
    T_bs = run.tf[("imu_viz_link", "os1_sensor")] @ run.tf[("os1_sensor", "os1_lidar")]
    pts, times = [], []
    for _, m, _ in run.bag["/os1_cloud_node/points"][::7]:
        a = cloud_array(m)
        ok = a["range"] > 0
        pts.append(np.column_stack([a["x"], a["y"], a["z"]])[ok][::5].astype(float))
        times.append(stamp_ns(m) + a["t"][ok][::5].astype(np.int64))
    xyz, t_ns = np.concatenate(pts), np.concatenate(times)
    pos, rot = run.base_pose(t_ns)
    world = pos + rot.apply(xyz @ T_bs[:3, :3].T + T_bs[:3, 3])
    d = run.world.distance(world)
    assert len(d) > 1000 and np.all(d < 5 * run.meta["lidar"]["range_noise"] + 0.01)


def test_groundtruth_topic_follows_the_trajectory(run: Run) -> None:
    gt = run.bag["/lidar_ground_truth"]
    t_ns = np.array([stamp_ns(m) for _, m, _ in gt])
    pos = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for _, m, _ in gt])
    ref, rot = run.base_pose(t_ns)
    assert np.abs(pos - ref).max() < 1e-4
    q = np.array([[m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z,
                   m.pose.pose.orientation.w] for _, m, _ in gt])
    assert (Rotation.from_quat(q).inv() * rot).magnitude().max() < 1e-4
    # the rig moves along base +y (the radar, looking along base +y, sees where it goes)
    v, _ = run.twist(t_ns)
    vb = Rotation.from_quat(q).apply(v, inverse=True)
    moving = np.linalg.norm(v[:, :2], axis=1) > 0.3
    assert np.all(vb[moving, 1] > 0.95 * np.linalg.norm(v[moving, :2], axis=1))
    dt = np.diff(t_ns) / 1e9
    assert 0.09 < np.median(dt) < 0.11 and dt.max() < 0.35


def _first_hit_by_sphere_tracing(world: WorldGeometry, o: np.ndarray, d: np.ndarray, max_range: float) -> np.ndarray:
    t = np.zeros(len(o))
    for _ in range(2000):
        step = world.distance(o + t[:, None] * d)
        t = np.where(step > 1e-6, t + step, t)
        if np.all((step <= 1e-6) | (t > max_range)):
            break
    return np.where(t <= max_range, t, np.inf)


@pytest.mark.parametrize("name", ["demo", "cluttered_lab", "outdoor_open"])
def test_ray_caster_agrees_with_sphere_tracing(name: str) -> None:
    from simulator.raycast import cast, directions
    from simulator.world import load_world

    w = load_world(name)
    ref = WorldGeometry(w.text)
    rng = np.random.default_rng(0)
    n = 300
    # origins along the trajectory, random headings and slopes
    wp = np.array(w.spec.trajectory.waypoints)
    o = np.column_stack([wp[rng.integers(0, len(wp), n)] + rng.normal(0, 0.1, (n, 2)),
                         rng.uniform(0.4, 1.6, n)])
    yaw = rng.uniform(-np.pi, np.pi, n)
    h = np.column_stack([np.cos(yaw), np.sin(yaw)])
    m = np.tan(rng.uniform(-0.6, 0.6, n))[:, None]
    hits = cast(w.scene, o, h, m, 30.0)
    d = directions(h, m)[:, 0]
    ref_t = _first_hit_by_sphere_tracing(ref, o, d, 30.0)
    got = hits.range[:, 0]
    assert np.array_equal(np.isfinite(got), np.isfinite(ref_t))
    fin = np.isfinite(got)
    # sphere tracing halts 1e-6 short of the surface, i.e. 1e-6 / cos(incidence) along the ray
    cos_inc = hits.cos_incidence[fin, 0]
    assert np.all(np.abs(got[fin] - ref_t[fin]) < 1e-4 + 2e-6 / np.maximum(cos_inc, 1e-6))
    assert np.all((hits.cos_incidence[fin, 0] > 0) & (hits.cos_incidence[fin, 0] <= 1 + 1e-9))
