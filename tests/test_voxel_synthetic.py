"""Synthetic ingest artifacts for the voxel / patches tests: a box room with a pillar, a circular path.

Independent of the simulator: ranges come from analytic ray/box intersections. The lidar is a small
spinning scanner, the radar a few dozen noisy detections per scan inside +-45 degrees plus clutter.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import numpy.typing as npt
from rich.console import Console
from scipy.spatial.transform import Rotation

from core.stage import StageContext, StageParams
from pipeline.sequences import SequenceInfo
from schemas.io import write_artifact

ROOM_LO = np.array([-4.0, -3.0, -0.5])
ROOM_HI = np.array([4.0, 3.0, 2.5])
PILLAR_LO = np.array([1.0, 0.5, -0.5])
PILLAR_HI = np.array([1.6, 1.1, 2.5])
#: radar boresight along base +y (ColoRadar's base_to_single_chip rotation), lidar yawed by 180 degrees
BASE_FROM_RADAR = np.eye(4)
BASE_FROM_RADAR[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
BASE_FROM_RADAR[:3, 3] = [-0.145, 0.09, -0.025]
_AZ, _EL = np.meshgrid(np.radians(np.arange(-44, 45, 2)), np.radians(np.arange(-40, 41, 5)), indexing="ij")
RADAR_BINS = np.stack([_AZ.ravel(), _EL.ravel()], axis=1)
BASE_FROM_LIDAR = np.eye(4)
BASE_FROM_LIDAR[:3, :3] = Rotation.from_euler("z", 180, degrees=True).as_matrix()
BASE_FROM_LIDAR[:3, 3] = [0.0, 0.0, 0.1]


def ray_box_exit(o: npt.NDArray[np.float64], d: npt.NDArray[np.float64], lo: npt.NDArray[np.float64],
                 hi: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Distance along unit rays ``d`` from ``o`` (inside the box) to the box boundary."""
    with np.errstate(divide="ignore"):
        t_hi = (hi - o) / d
        t_lo = (lo - o) / d
    t = np.where(d > 0, t_hi, np.where(d < 0, t_lo, np.inf))
    return t.min(axis=1)


def ray_box_entry(o: npt.NDArray[np.float64], d: npt.NDArray[np.float64], lo: npt.NDArray[np.float64],
                  hi: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Distance to the entry of a box from outside (inf when missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((tmax >= tmin) & (tmin > 0), tmin, np.inf)


def cast(o: npt.NDArray[np.float64], d: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """First hit range in the room with the pillar."""
    return np.minimum(ray_box_exit(o, d, ROOM_LO, ROOM_HI), ray_box_entry(o, d, PILLAR_LO, PILLAR_HI))


def distance_to_surfaces(p: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Distance of points (inside the room) to the nearest room wall or pillar face."""
    pts = np.asarray(p, dtype=np.float64)
    walls = np.minimum(np.abs(pts - ROOM_LO), np.abs(pts - ROOM_HI)).min(axis=1)
    q = np.maximum(np.maximum(PILLAR_LO - pts, pts - PILLAR_HI), 0)
    outside = np.linalg.norm(q, axis=1)
    inside = np.maximum(PILLAR_LO - pts, pts - PILLAR_HI).max(axis=1)
    pillar = np.where(outside > 0, outside, np.abs(inside))
    return np.minimum(walls, pillar)


def base_pose(t: npt.ArrayLike) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Base position and quaternion (xyzw) at times (s): a circle of radius 1.8 m around (-1, -0.5)."""
    tt = np.asarray(t, dtype=np.float64)
    ang = 0.25 * tt
    xyz = np.stack([-1.0 + 1.8 * np.cos(ang), -0.5 + 1.2 * np.sin(ang), 0.3 + 0.05 * np.sin(0.7 * tt)], axis=1)
    yaw = ang + np.pi / 2
    rot = Rotation.from_euler("zyx", np.stack([yaw, 0.03 * np.sin(tt), 0.02 * np.cos(0.5 * tt)], axis=1))
    return xyz, rot.as_quat()


def pose_matrix(t: float) -> npt.NDArray[np.float64]:
    xyz, q = base_pose([t])
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q[0]).as_matrix()
    T[:3, 3] = xyz[0]
    return T


def write_ingest(folder: Path, duration: float = 6.0, seed: int = 0, lidar_cols: int = 180,
                 lidar_beams: int = 12) -> dict[str, np.ndarray]:
    """Write radar/lidar/groundtruth/calibration artifacts of the synthetic room into ``folder``."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    t_gt = np.arange(0.0, duration + 1e-9, 0.1) + 0.003 * rng.standard_normal(round(duration / 0.1) + 1)
    t_gt.sort()
    gxyz, gq = base_pose(t_gt)
    t0_ns = 1_600_000_000_000_000_000
    write_artifact({"t_ns": (t_gt * 1e9).astype(np.int64) + t0_ns, "x": gxyz[:, 0], "y": gxyz[:, 1],
                    "z": gxyz[:, 2], "qx": gq[:, 0], "qy": gq[:, 1], "qz": gq[:, 2], "qw": gq[:, 3]},
                   folder / "groundtruth.parquet", "groundtruth")
    scan_t = np.arange(0.05, duration - 0.05, 0.1)
    radar_rows: dict[str, list[np.ndarray]] = {k: [] for k in ("scan", "t_ns", "x", "y", "z")}
    lidar_rows: dict[str, list[np.ndarray]] = {k: [] for k in ("scan", "t_ns", "x", "y", "z")}
    az_l = np.linspace(-np.pi, np.pi, lidar_cols, endpoint=False)
    el_l = np.radians(np.linspace(-15, 15, lidar_beams))
    A, E = np.meshgrid(az_l, el_l, indexing="ij")
    lidar_dirs = np.stack([np.cos(A) * np.cos(E), np.sin(A) * np.cos(E), np.sin(E)], -1).reshape(-1, 3)
    for i, ts in enumerate(scan_t):
        T = pose_matrix(ts)
        t_ns = int(ts * 1e9) + t0_ns
        # lidar
        Tl = T @ BASE_FROM_LIDAR
        dw = lidar_dirs @ Tl[:3, :3].T
        r = cast(np.broadcast_to(Tl[:3, 3], dw.shape), dw) + 0.005 * rng.standard_normal(len(dw))
        pts_l = lidar_dirs * r[:, None]
        # radar: detections in fixed angular bins (every 2 deg in azimuth, 5 deg in elevation, like a
        # radar's angle bins) of which 90 % are reported, noisy ranges, two clutter points
        Tr = T @ BASE_FROM_RADAR
        reported = rng.random(len(RADAR_BINS)) < 0.9
        az, el = RADAR_BINS[reported, 0], RADAR_BINS[reported, 1]
        dr = np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)], 1)
        rr = cast(np.broadcast_to(Tr[:3, 3], dr.shape), dr @ Tr[:3, :3].T)
        keep = rr < 11
        pts_r = dr[keep] * (rr[keep] + 0.05 * rng.standard_normal(int(keep.sum())))[:, None]
        pts_r = np.concatenate([pts_r, rng.uniform([1, -3, -1], [8, 3, 1], size=(2, 3))])
        for rows, pts in ((lidar_rows, pts_l), (radar_rows, pts_r)):
            rows["scan"].append(np.full(len(pts), i, np.int32))
            rows["t_ns"].append(np.full(len(pts), t_ns, np.int64))
            for j, c in enumerate("xyz"):
                rows[c].append(pts[:, j].astype(np.float32))
    radar = {k: np.concatenate(v) for k, v in radar_rows.items()}
    radar["intensity"] = np.ones(len(radar["x"]), np.float32)
    radar["doppler"] = np.zeros(len(radar["x"]), np.float32)
    lidar = {k: np.concatenate(v) for k, v in lidar_rows.items()}
    lidar["intensity"] = np.ones(len(lidar["x"]), np.float32)
    write_artifact(radar, folder / "radar.parquet", "radar")
    write_artifact(lidar, folder / "lidar.parquet", "lidar")
    calib = {"base_frame": "imu_viz_link", "base_from_radar": BASE_FROM_RADAR.tolist(),
             "base_from_lidar": BASE_FROM_LIDAR.tolist(), "base_from_imu": np.eye(4).tolist()}
    (folder / "calibration.json").write_text(json.dumps(calib))
    return {"scan_t": scan_t, "t0_ns": np.array([t0_ns])}


def make_context(stage: str, params: StageParams, input_dirs: dict[str, Path], out: Path,
                 seq: str = "synthetic_room") -> StageContext:
    out.mkdir(parents=True, exist_ok=True)
    info = SequenceInfo(name=seq, kind="source", source=Path("/nonexistent"))
    return StageContext(stage=stage, seq=info, params=params, out_dir=out, input_dirs=input_dirs,
                        console=Console(stderr=True, quiet=True))
