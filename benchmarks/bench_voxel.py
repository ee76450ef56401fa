"""Voxel insertion throughput: the radar sensor model and the lidar ray casting, against OctoMap (C++).

Scene: a 30 m x 12 m x 3 m hall with pillars (analytic ray casting), a sensor moving along it.
- lidar: Ouster-OS1-64-like scans (64 x 1024 rays), restricted to 180 degrees (about 32k points per
  scan), inserted with ``raycast.scan_update_keys`` + ``VoxelMap.integrate`` and with OctoMap's
  ``OcTree.insertPointCloud`` (OpenMP, all cores) on the same float32 world points, both with and
  without OctoMap's ``discretize``; points/s and the ratio ours / OctoMap;
- radar: the fork's sensor model (fan of 10,816 rays, +-45 / +-45 deg, 10 m) with 150 returns per scan;
  scans/s and points/s; as a reference OctoMap casting the same fan (``insertPointCloud`` of the fan's
  end points with ``maxrange`` = 10 m: the same ray casting in C++, plus OctoMap's tree updates).
"""

from __future__ import annotations

import time

import numpy as np
import numpy.typing as npt

from benchmarks.common import Result
from stages.voxel import octomap_io
from stages.voxel.radar_model import fan_directions, radar_scan_keys
from stages.voxel.raycast import scan_update_keys
from stages.voxel.voxel_map import SensorModel, VoxelMap

RES = 0.15
HALL_LO = np.array([-15.0, -6.0, -0.5])
HALL_HI = np.array([15.0, 6.0, 2.5])
PILLARS = [(np.array([x - 0.3, y - 0.3, -0.5]), np.array([x + 0.3, y + 0.3, 2.5]))
           for x in (-9.0, -3.0, 3.0, 9.0) for y in (-2.5, 2.5)]
F64 = npt.NDArray[np.float64]


def _cast(o: F64, d: F64) -> F64:
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (HALL_HI - o) / d, np.where(d < 0, (HALL_LO - o) / d, np.inf)).min(axis=1)
        for lo, hi in PILLARS:
            t1, t2 = (lo - o) / d, (hi - o) / d
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            t = np.where((tmax >= tmin) & (tmin > 0) & (tmin < t), tmin, t)
    return t


def _poses(n: int) -> list[F64]:
    out = []
    for i in range(n):
        T = np.eye(4)
        yaw = 0.3 * np.sin(0.2 * i)
        T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        T[:3, 3] = [-12.0 + 0.1 * i, 0.5 * np.sin(0.1 * i), 0.4]
        out.append(T)
    return out


def lidar_scans(n: int, rng: np.random.Generator) -> list[tuple[F64, F64]]:
    """World-frame end points (float32 values) and origins of OS1-64-like scans, front 180 degrees."""
    az = np.linspace(-np.pi / 2, np.pi / 2, 512, endpoint=False)
    el = np.radians(np.linspace(-16.6, 16.6, 64))
    A, E = np.meshgrid(az, el, indexing="ij")
    dirs = np.stack([np.cos(A) * np.cos(E), np.sin(A) * np.cos(E), np.sin(E)], -1).reshape(-1, 3)
    scans = []
    for T in _poses(n):
        d = dirs @ T[:3, :3].T
        o = T[:3, 3]
        r = _cast(np.broadcast_to(o, d.shape), d) + 0.01 * rng.standard_normal(len(d))
        pts = (o + d * r[:, None]).astype(np.float32).astype(np.float64)
        scans.append((pts, o.astype(np.float32).astype(np.float64)))
    return scans


def _rate(fn: object, n_items: int, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()  # type: ignore[operator]
        best = min(best, time.perf_counter() - t0)
    return n_items / best


def run(quick: bool = False) -> list[Result]:
    rng = np.random.default_rng(0)
    n_lidar = 4 if quick else 12
    scans = lidar_scans(n_lidar, rng)
    n_pts = sum(len(p) for p, _ in scans)
    model = SensorModel()
    results: list[Result] = []
    have_octomap = octomap_io.available()
    repeat = 1 if quick else 3
    for disc in (False, True):

        def ours(disc: bool = disc) -> None:
            m = VoxelMap(RES, model)
            for pts, o in scans:
                m.integrate(*scan_update_keys(pts, o, RES, discretize=disc))

        def octo(disc: bool = disc) -> None:
            tree = octomap_io.make_octree(RES, model)
            for pts, o in scans:
                tree.insertPointCloud(pts, o, discretize=disc)

        ours_rate = _rate(ours, n_pts, repeat)
        ref_rate = _rate(octo, n_pts, repeat) if have_octomap else None
        results.append(Result(
            "voxel", f"lidar ray casting{' (discretize)' if disc else ''}", ours_rate, "points/s",
            reference="octomap insertPointCloud" if ref_rate else "",
            ratio=ours_rate / ref_rate if ref_rate else None,
            note=f"{n_lidar} scans x {n_pts // n_lidar} pts (180 deg of a 64x1024 scan); "
                 + (f"octomap {ref_rate:.3g} points/s (OpenMP)" if ref_rate else "octomap not installed")))

    # radar sensor model
    dirs = fan_directions(np.radians(45), np.radians(45), RES, 10.0)
    n_radar = 6 if quick else 20
    poses = _poses(n_radar)
    radar_pts = []
    for T in poses:
        az, el = rng.uniform(-0.7, 0.7, 150), rng.uniform(-0.5, 0.5, 150)
        d = np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)], 1)
        r = _cast(np.broadcast_to(T[:3, 3], d.shape), d @ T[:3, :3].T)
        radar_pts.append(d * np.minimum(r, 12.0)[:, None])

    def radar() -> None:
        m = VoxelMap(RES, model)
        for T, pts in zip(poses, radar_pts, strict=True):
            m.integrate(*radar_scan_keys(pts, T, dirs, RES, 0.0, 10.0), hits_need_free=True)

    def radar_fan_octomap() -> None:
        tree = octomap_io.make_octree(RES, model)
        for T in poses:
            tree.insertPointCloud(T[:3, 3] + dirs @ T[:3, :3].T * 10.5, T[:3, 3].copy(), maxrange=10.0)

    scans_rate = _rate(radar, n_radar, repeat)
    ref = _rate(radar_fan_octomap, n_radar, repeat) if have_octomap else None
    results.append(Result(
        "voxel", "radar sensor model", scans_rate * 150, "points/s",
        reference="octomap casting the same fan" if ref else "", ratio=scans_rate / ref if ref else None,
        note=f"{scans_rate:.3g} scans/s, fan of {len(dirs)} rays to 10 m, 150 returns per scan"
             + (f"; octomap fan {ref:.3g} scans/s" if ref else "")))
    return results
