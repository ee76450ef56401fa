"""The `voxel` stage end to end on synthetic ingest artifacts (a box room; no simulator needed)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from core.errors import UserError
from core.recording import entity_paths_in
from schemas.io import read_artifact, write_artifact
from stages.odometry.stage import cov_columns
from stages.voxel.stage import STAGE, VoxelParams
from stages.voxel.voxel_map import coord_to_key
from tests.test_voxel_synthetic import BASE_FROM_LIDAR, distance_to_surfaces, make_context, write_ingest

RES = 0.15


@pytest.fixture(scope="module")
def ingest_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("ingest")
    write_ingest(d, duration=5.0)
    return d


@pytest.fixture(scope="module")
def gt_run(tmp_path_factory: pytest.TempPathFactory, ingest_dir: Path) -> tuple[Path, dict]:
    return _run(tmp_path_factory.mktemp("voxel_gt"), VoxelParams(), {"ingest": ingest_dir})


def _run(tmp: Path, params: VoxelParams, inputs: dict[str, Path]) -> tuple[Path, dict]:
    ctx = make_context("voxel", params, inputs, tmp / "voxel")
    STAGE.run(ctx)
    ctx.close()
    return tmp / "voxel", ctx.stats


def _map(path: Path, kind: str) -> tuple[np.ndarray, np.ndarray]:
    tab = read_artifact(path / f"{kind}_map.parquet", f"{kind}_map")
    return np.stack([tab.column(c).to_numpy() for c in "xyz"], 1), tab.column("log_odds").to_numpy()


def test_voxel_stage_groundtruth(gt_run: tuple[Path, dict]) -> None:
    out, stats = gt_run
    radar, radar_lo = _map(out, "radar")
    lidar, lidar_lo = _map(out, "lidar")
    assert len(radar) > 200 and len(lidar) > 1000
    assert (radar_lo > 0).all() and (lidar_lo > 0).all()
    # voxel centres on the 0.15 m grid, next to the room's surfaces (a frame or pose error would break this)
    assert np.allclose((radar / RES - 0.5) - np.round(radar / RES - 0.5), 0, atol=1e-4)
    assert np.percentile(distance_to_surfaces(lidar), 100) <= RES * np.sqrt(3) / 2 + 1e-3
    assert np.percentile(distance_to_surfaces(radar), 95) <= 0.2
    assert stats["lr_ratio"] == pytest.approx(len(lidar) / len(radar))
    assert stats["radar"]["scans"] == 49 and stats["lidar"]["scans"] == 49
    assert {"/world/voxel/radar", "/world/voxel/lidar"} <= entity_paths_in(out / "voxel.rrd")


def test_lidar_map_equals_octomap_on_the_stage_inputs(gt_run: tuple[Path, dict], ingest_dir: Path) -> None:
    """The stage's lidar map against OctoMap's insertPointCloud fed from the artifacts with poses and the
    180 degree field of view computed here independently."""
    octomap = pytest.importorskip("octomap")
    out, _ = gt_run
    lidar, _ = _map(out, "lidar")
    lid = read_artifact(ingest_dir / "lidar.parquet", "lidar")
    gt = read_artifact(ingest_dir / "groundtruth.parquet", "groundtruth")
    g_t = gt.column("t_ns").to_numpy().astype(np.float64)
    slerp = Slerp(g_t, Rotation.from_quat(np.stack([gt.column(c).to_numpy() for c in ("qx", "qy", "qz", "qw")], 1)))
    g_xyz = np.stack([gt.column(c).to_numpy() for c in "xyz"], 1)
    tree = octomap.OcTree(RES)
    scan = lid.column("scan").to_numpy()
    t_ns = lid.column("t_ns").to_numpy()
    pts = np.stack([lid.column(c).to_numpy() for c in "xyz"], 1).astype(np.float64)
    for s in np.unique(scan):
        m = scan == s
        t = float(t_ns[m][0])
        T = np.eye(4)
        T[:3, :3] = slerp([t]).as_matrix()[0]
        T[:3, 3] = [np.interp(t, g_t, g_xyz[:, i]) for i in range(3)]
        T = T @ BASE_FROM_LIDAR
        p = pts[m]
        # radar boresight = base +y = lidar -y (lidar yawed 180 deg): keep the half-space y_lidar <= 0
        p = p[(p[:, 1] <= 0) & (np.linalg.norm(p, axis=1) <= 20.0)]
        tree.insertPointCloud(p @ T[:3, :3].T + T[:3, 3], T[:3, 3].copy())
    ref = set()
    for leaf in tree.begin_leafs():
        if tree.isNodeOccupied(leaf):
            assert leaf.getSize() == pytest.approx(RES)  # no pruned occupied nodes in this small map
            ref.add(tuple(coord_to_key(np.asarray(leaf.getCoordinate())[None], RES)[0]))
    got = {tuple(k) for k in coord_to_key(lidar, RES).tolist()}
    assert len(ref) > 1000
    assert len(got ^ ref) <= 3, (len(got ^ ref), len(ref))  # equal on these scans; allow rare edge ties


def _write_odometry(odo: Path, gt: Any, level: bool = False, t_shift_ns: int = 0) -> None:
    """The ground truth written as an odometry artifact (x, y, yaw, and z, roll, pitch unless ``level``)."""
    q = np.stack([gt.column(c).to_numpy() for c in ("qx", "qy", "qz", "qw")], 1)
    yaw, pitch, roll = Rotation.from_quat(q).as_euler("ZYX").T
    n = gt.num_rows
    odo.mkdir(exist_ok=True)
    zero = np.zeros(n)
    write_artifact({"scan": np.arange(n, dtype=np.int32), "t_ns": gt.column("t_ns").to_numpy() + t_shift_ns,
                    "x": gt.column("x").to_numpy(), "y": gt.column("y").to_numpy(), "yaw": yaw,
                    "z": zero if level else gt.column("z").to_numpy(), "roll": zero if level else roll,
                    "pitch": zero if level else pitch, **cov_columns(n)}, odo / "odometry.parquet", "odometry")


def _keys(points: Any) -> set[tuple[int, ...]]:
    return {tuple(k) for k in coord_to_key(points, RES).tolist()}


def test_voxel_stage_odometry_trajectory(tmp_path: Path, ingest_dir: Path, gt_run: tuple[Path, dict]) -> None:
    """A radar-only map along the odometry's 3D pose (here the ground truth written as odometry) is the
    ground-truth map; the level lift (zero roll and pitch at one height) is not."""
    params = VoxelParams.model_validate({"trajectory": {"source": "odometry"}})
    assert STAGE.input_stages(params) == ("ingest", "odometry")
    filtered = VoxelParams.model_validate({"trajectory": {"source": "slam"}, "radar": {"points": "filtered"}})
    assert STAGE.input_stages(filtered) == (
        "ingest", "slam", "odometry", "filter")
    level = VoxelParams.model_validate({"trajectory": {"source": "slam", "attitude": "level"}})
    assert STAGE.input_stages(level) == ("ingest", "slam")
    gt = read_artifact(ingest_dir / "groundtruth.parquet", "groundtruth")
    _write_odometry(tmp_path / "odometry", gt)
    out, stats = _run(tmp_path, params, {"ingest": ingest_dir, "odometry": tmp_path / "odometry"})
    assert stats["attitude"] == "odometry" and stats["trajectory_coverage"] == 1.0
    radar_odo, _ = _map(out, "radar")
    radar_gt, _ = _map(gt_run[0], "radar")
    a, b = _keys(radar_odo), _keys(radar_gt)
    assert len(a ^ b) <= 0.02 * len(b)  # the same poses up to interpolation: the same map
    meta = read_artifact(out / "radar_map.parquet", "radar_map").schema.metadata
    assert meta[b"trajectory"] == b"odometry"
    # level: zero roll and pitch at the first height, as before the 3D poses
    level_dir = tmp_path / "level"
    level_dir.mkdir()
    level = VoxelParams.model_validate({"trajectory": {"source": "odometry", "attitude": "level"}})
    out2, stats2 = _run(level_dir, level,
                        {"ingest": ingest_dir, "odometry": tmp_path / "odometry"})
    assert stats2["se2_height"] == pytest.approx(gt.column("z").to_numpy()[0])
    a2 = _keys(_map(out2, "radar")[0])
    assert len(a2 & b) > 0.3 * len(b)  # the same room up to the ground truth's roll, pitch and height changes
    assert len(a2 ^ b) > len(a ^ b)


def test_voxel_stage_trajectory_that_misses_the_scans_or_a_method_not_run(tmp_path: Path, ingest_dir: Path) -> None:
    gt = read_artifact(ingest_dir / "groundtruth.parquet", "groundtruth")
    span = int(gt.column("t_ns").to_numpy()[-1] - gt.column("t_ns").to_numpy()[0])
    _write_odometry(tmp_path / "odometry", gt, t_shift_ns=span // 2)  # covers about half the radar scans
    with pytest.raises(UserError, match=r"covers \d+\.\d % of the \d+ radar scans "
                                         r"\(voxel.trajectory.min_coverage = 0.9\)"):
        _run(tmp_path, VoxelParams.model_validate({"trajectory": {"source": "odometry"}}),
             {"ingest": ingest_dir, "odometry": tmp_path / "odometry"})
    assert not (tmp_path / "out" / "radar_map.parquet").exists()
    slam = tmp_path / "slam"
    slam.mkdir()
    write_artifact({"scan": np.arange(3, dtype=np.int32), "t_ns": np.arange(3), "x": np.zeros(3), "y": np.zeros(3),
                    "yaw": np.zeros(3), "n_eff": np.ones(3)}, slam / "trajectory_rich_slam.parquet", "trajectory")
    with pytest.raises(UserError, match=r"slam method 'fastslam_grid' was not run \(ran: rich_slam\)"):
        _run(tmp_path, VoxelParams.model_validate({"trajectory": {"source": "slam", "slam_method": "fastslam_grid"}}),
             {"ingest": ingest_dir, "odometry": tmp_path / "odometry", "slam": slam})


def test_voxel_stage_bad_calibration(tmp_path: Path, ingest_dir: Path) -> None:
    bad = tmp_path / "ingest"
    bad.mkdir()
    for f in ingest_dir.iterdir():
        (bad / f.name).write_bytes(f.read_bytes())
    calib = json.loads((bad / "calibration.json").read_text())
    calib["base_from_lidar"] = [[1, 0, 0]]
    (bad / "calibration.json").write_text(json.dumps(calib))
    with pytest.raises(UserError, match=r"calibration.json: 'base_from_lidar' must be a 4x4"):
        _run(tmp_path, VoxelParams(), {"ingest": bad})


def test_voxel_stage_without_groundtruth(tmp_path: Path, ingest_dir: Path) -> None:
    bare = tmp_path / "ingest"
    bare.mkdir()
    for f in ingest_dir.iterdir():
        (bare / f.name).write_bytes(f.read_bytes())
    empty = {c: np.zeros(0) for c in ("x", "y", "z", "qx", "qy", "qz", "qw")}
    write_artifact({"t_ns": np.zeros(0, np.int64), **empty}, bare / "groundtruth.parquet", "groundtruth")
    with pytest.raises(UserError, match=r"groundtruth.parquet: no ground-truth poses; "
                                         r".*voxel.trajectory.source=odometry"):
        _run(tmp_path, VoxelParams(), {"ingest": bare})


def test_voxel_stage_writes_the_trajectory_the_radar_map_was_built_along(gt_run: tuple[Path, dict],
                                                                          ingest_dir: Path) -> None:
    """Log sequences write ``map_trajectory.parquet`` as map sets do: the radar's positions at the integrated
    scans (ground truth at the scan times, through the radar mount), which the band pre-filter reads."""
    from stages.complete.voxel_grid import Band, in_band
    from stages.voxel.poses import interpolate_se3
    from tests.test_voxel_synthetic import BASE_FROM_RADAR

    out, stats = gt_run
    tab = read_artifact(out / "map_trajectory.parquet", "map_trajectory")
    traj = np.stack([tab.column(c).to_numpy() for c in "xyz"], 1)
    assert len(traj) == stats["radar"]["scans"] == 49
    assert tab.schema.metadata[b"trajectory"] == b"groundtruth"
    radar = read_artifact(ingest_dir / "radar.parquet", "radar", columns=["scan", "t_ns"])
    _, first = np.unique(radar.column("scan").to_numpy(), return_index=True)
    gt = read_artifact(ingest_dir / "groundtruth.parquet", "groundtruth")
    T, ok = interpolate_se3(radar.column("t_ns").to_numpy()[first], gt.column("t_ns").to_numpy(),
                            np.stack([gt.column(c).to_numpy() for c in "xyz"], 1),
                            np.stack([gt.column(c).to_numpy() for c in ("qx", "qy", "qz", "qw")], 1))
    expect = (T[ok] @ BASE_FROM_RADAR)[:, :3, 3]
    assert np.allclose(traj, expect, atol=1e-9)
    assert not np.allclose(traj, T[ok][:, :3, 3], atol=0.05)  # the radar's position, not the base's
    radar_map, _ = _map(out, "radar")
    keep = in_band(radar_map, traj, Band(2.0, -1.0, 1.0))
    assert 0 < keep.sum() < len(radar_map)  # the band pre-filter now runs on a log sequence
