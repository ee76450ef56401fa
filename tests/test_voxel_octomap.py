"""The vectorised voxel maps against the real OctoMap library (Python binding octomap-python, dev extra)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.voxel import octomap_io
from stages.voxel.poses import horizontal_fov_mask, interpolate_se3
from stages.voxel.radar_model import fan_directions, radar_scan_keys
from stages.voxel.raycast import ray_keys, scan_update_keys
from stages.voxel.voxel_map import SensorModel, VoxelMap, coord_to_key
from tests.test_voxel_core import dda_ray_keys
from tests.test_voxel_synthetic import BASE_FROM_LIDAR, BASE_FROM_RADAR, write_ingest

octomap = pytest.importorskip("octomap")
RES = 0.15


def octree_voxels(tree: object, res: float = RES) -> dict[tuple[int, int, int], float]:
    """All leaf voxels of an OcTree at full depth (pruned nodes expanded) -> log-odds."""
    out: dict[tuple[int, int, int], float] = {}
    for leaf in tree.begin_leafs():  # type: ignore[attr-defined]
        size = leaf.getSize()
        c = np.asarray(leaf.getCoordinate(), dtype=np.float64)
        v = float(leaf.getValue())
        n = round(size / res)
        if n == 1:
            out[tuple(coord_to_key(c[None], res)[0])] = v
            continue
        lo = coord_to_key((c - size / 2 + res / 2)[None], res)[0]
        g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3) + lo
        out.update(dict.fromkeys(map(tuple, g.tolist()), v))
    return out


def test_ray_keys_equal_octomap_compute_ray_keys() -> None:
    """Per ray: our free voxels equal those OctoMap's insertPointCloud marks free for that single ray."""
    rng = np.random.default_rng(0)
    mismatched = 0
    for _ in range(150):
        o = rng.uniform(-2, 2, 3).astype(np.float32).astype(np.float64)
        e = (o + rng.normal(size=3) * rng.uniform(0.1, 5)).astype(np.float32).astype(np.float64)
        tree = octomap.OcTree(RES)
        tree.insertPointCloud(e[None], o)
        free = {k for k, v in octree_voxels(tree).items() if v < 0}
        mine = {tuple(k) for k in ray_keys(o, e[None], RES).tolist()}
        mismatched += mine != free
    assert mismatched == 0


def _lidar_scans(tmp_path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """World-frame lidar scans (float32 end points as OctoMap gets them) and origins of the synthetic room."""
    from schemas.io import read_artifact

    write_ingest(tmp_path, duration=3.0)
    lid = read_artifact(tmp_path / "lidar.parquet", "lidar")
    gt = read_artifact(tmp_path / "groundtruth.parquet", "groundtruth")
    gt_xyz = np.stack([gt.column(c).to_numpy() for c in "xyz"], 1)
    gt_q = np.stack([gt.column(c).to_numpy() for c in ("qx", "qy", "qz", "qw")], 1)
    scan = lid.column("scan").to_numpy()
    t_ns = lid.column("t_ns").to_numpy()
    pts = np.stack([lid.column(c).to_numpy() for c in "xyz"], 1).astype(np.float64)
    boresight = np.linalg.inv(BASE_FROM_LIDAR)[:3, :3] @ BASE_FROM_RADAR[:3, :3] @ [1.0, 0, 0]
    out = []
    for s in np.unique(scan):
        m = scan == s
        T, ok = interpolate_se3(t_ns[m][:1], gt.column("t_ns").to_numpy(), gt_xyz, gt_q)
        if not ok[0]:
            continue
        T_wl = T[0] @ BASE_FROM_LIDAR
        local = pts[m][horizontal_fov_mask(pts[m], boresight, np.pi)]
        world = (local @ T_wl[:3, :3].T + T_wl[:3, 3]).astype(np.float32).astype(np.float64)
        out.append((world, T_wl[:3, 3].astype(np.float32).astype(np.float64)))
    return out


@pytest.mark.parametrize(("max_range", "discretize"), [(-1.0, False), (3.0, False), (-1.0, True)])
def test_lidar_map_equals_octomap_insert_point_cloud(tmp_path: Path, max_range: float, discretize: bool) -> None:
    scans = _lidar_scans(tmp_path)
    model = SensorModel()
    tree = octomap_io.make_octree(RES, model)
    mine = VoxelMap(RES, model)
    for world, origin in scans:
        tree.insertPointCloud(world, origin, maxrange=max_range, discretize=discretize)
        mine.integrate(*scan_update_keys(world, origin, RES, max_range=max_range, discretize=discretize))
    ref = octree_voxels(tree)
    keys, vals = mine.voxels(occupied_only=False)
    got = dict(zip(map(tuple, keys.tolist()), vals.tolist(), strict=True))
    assert len(ref) > 5000
    # known voxels and their log-odds: equal (exactly on these scans; a ray grazing a voxel edge within
    # float rounding could flip a voxel, hence the allowance of a handful)
    only = set(got) ^ set(ref)
    differ = [k for k in set(got) & set(ref) if abs(got[k] - ref[k]) > 1e-5]
    assert len(only) + len(differ) <= 5, (len(only), len(differ), len(ref))
    occ_ref = {k for k, v in ref.items() if v > 0}
    occ_got = {k for k, v in got.items() if v > 0}
    assert len(occ_ref) > 300 and len(occ_ref ^ occ_got) <= 2


def test_radar_model_equals_fork_emulated_with_octomap() -> None:
    """The fork's insertRadarScanToMap with the real library's updateNode: fan keys from the literal DDA,
    returns inside the fan are hits, the rest of the fan misses; compared voxel by voxel."""
    rng = np.random.default_rng(5)
    model = SensorModel()
    max_range = 2.5
    dirs = fan_directions(np.radians(45), np.radians(20), RES, max_range)
    tree = octomap_io.make_octree(RES, model)
    mine = VoxelMap(RES, model)
    for i in range(6):
        T = np.eye(4)
        yaw = 0.2 * i
        T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        T[:3, 3] = [0.1 * i, 0.05 * i, 0.3]
        pts = np.c_[rng.uniform(0.5, 3.0, 60), rng.uniform(-1.5, 1.5, 60), rng.uniform(-0.5, 0.5, 60)]
        pts[:20] = [2.0, 0.3, 0.0]  # a persistent reflector
        fan, hits = radar_scan_keys(pts, T, dirs, RES, 0.0, max_range)
        mine.integrate(fan, hits, hits_need_free=True)
        ends = T[:3, 3] + dirs @ T[:3, :3].T * max_range
        free = set().union(*(dda_ray_keys(T[:3, 3], e, RES) for e in ends))
        world = pts @ T[:3, :3].T + T[:3, 3]
        occ = {tuple(k) for k in coord_to_key(world, RES).tolist()} & free
        free -= occ
        for keys, hit in ((free, False), (occ, True)):
            for k in keys:
                tree.updateNode((np.asarray(k, float) + 0.5) * RES, hit)
    ref = octree_voxels(tree)
    keys, vals = mine.voxels(occupied_only=False)
    got = dict(zip(map(tuple, keys.tolist()), vals.tolist(), strict=True))
    assert got.keys() == ref.keys()
    assert max(abs(got[k] - ref[k]) for k in ref) < 1e-6
    assert any(v > 0 for v in got.values())


def test_bt_export_reads_back(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    keys = np.unique(rng.integers(-30, 30, size=(3000, 3)), axis=0)
    vals = rng.choice(np.float32([0.85, -0.4, 1.7, -1.2, 3.4]), len(keys))
    path = octomap_io.write_bt(tmp_path / "m.bt", keys, vals, RES, SensorModel())
    tree = octomap.OcTree(str(path).encode())
    back = octree_voxels(tree)
    assert set(back) == set(map(tuple, keys.tolist()))
    occupied = {k for k, v in back.items() if v > 0}
    assert occupied == {tuple(k) for k, v in zip(keys.tolist(), vals, strict=True) if v > 0}
