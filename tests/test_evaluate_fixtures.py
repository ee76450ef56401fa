"""Synthetic artifacts for the evaluate / plan / report tests: a walled room, a loop, a 2D radar.

Everything here is written through ``schemas.write_artifact`` into a run-store layout
(``runs/<seq>/<stage>/``) so tests can build ``StageContext`` objects directly, without the upstream
stages. The world is independent of the code under test: walls are segments, the radar ray-casts
against them, ground truth is an analytic loop.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from rich.console import Console

from core.stage import StageContext, StageParams
from pipeline.sequences import SequenceInfo
from pipeline.store import MANIFEST, write_json_atomic
from schemas import write_artifact
from stages.odometry.stage import cov_columns

F64 = npt.NDArray[np.float64]

#: base <- radar: ColoRadar-like, boresight along base +y, 0.1 m forward
BASE_FROM_RADAR = np.array([[0.0, -1.0, 0.0, 0.1], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.2], [0, 0, 0, 1.0]])


def room_segments() -> F64:
    """Walls (x0, y0, x1, y1): a 16 m x 10 m room, a central block and a pillar."""
    w, h = 8.0, 5.0
    segs = [(-w, -h, w, -h), (w, -h, w, h), (w, h, -w, h), (-w, h, -w, -h)]
    bx, by = 3.5, 1.5  # central block the loop goes around
    segs += [(-bx, -by, bx, -by), (bx, -by, bx, by), (bx, by, -bx, by), (-bx, by, -bx, -by)]
    px, py, r = 6.0, 3.5, 0.4  # a pillar in a corner
    segs += [(px - r, py - r, px + r, py - r), (px + r, py - r, px + r, py + r),
             (px + r, py + r, px - r, py + r), (px - r, py + r, px - r, py - r)]
    return np.asarray(segs, np.float64)


def raycast(origins: F64, dirs: F64, segs: F64, max_range: float) -> F64:
    """Distance along each ray to the nearest segment (inf when none within ``max_range``)."""
    p = origins[:, None, :]
    r = dirs[:, None, :]
    a = segs[None, :, :2]
    s = segs[None, :, 2:] - segs[None, :, :2]
    cross = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    qp = a - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]) / cross
        u = (qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]) / cross
    ok = (np.abs(cross) > 1e-12) & (t > 1e-6) & (u >= 0) & (u <= 1) & (t <= max_range)
    t = np.where(ok, t, np.inf)
    return t.min(axis=1)


def loop_pose(t: F64, period: float) -> tuple[F64, F64, F64]:
    """A rounded-rectangle loop around the central block (x, y, yaw), constant speed."""
    ang = 2 * np.pi * t / period
    # superellipse-like loop: x = 5.5 cos, y = 3.2 sin with a flattening
    x = 5.6 * np.sign(np.cos(ang)) * np.abs(np.cos(ang)) ** 0.6
    y = 3.25 * np.sign(np.sin(ang)) * np.abs(np.sin(ang)) ** 0.6
    dt = 1e-3
    a2 = 2 * np.pi * (t + dt) / period
    x2 = 5.6 * np.sign(np.cos(a2)) * np.abs(np.cos(a2)) ** 0.6
    y2 = 3.25 * np.sign(np.sin(a2)) * np.abs(np.sin(a2)) ** 0.6
    return x, y, np.arctan2(y2 - y, x2 - x)


@dataclass
class SyntheticSequence:
    gt_t: npt.NDArray[np.int64]
    gt_xyyaw: F64
    scan_t: npt.NDArray[np.int64]
    radar: dict[str, npt.NDArray]  # radar.parquet columns (radar frame)
    base_from_radar: F64


def make_sequence(duration: float = 30.0, period: float = 30.0, rate: float = 10.0, beams: int = 24,
                  fov_deg: float = 120.0, max_range: float = 8.0, noise: float = 0.03,
                  seed: int = 0) -> SyntheticSequence:
    """Ground truth at 50 Hz and a 2D radar (ray-cast walls, range noise) at ``rate`` Hz."""
    rng = np.random.default_rng(seed)
    gt_t = np.arange(0, int(duration * 1e9) + 1, 20_000_000, dtype=np.int64) + 1_000_000_000
    x, y, yaw = loop_pose((gt_t - gt_t[0]) / 1e9, period)
    scan_t = np.arange(int(duration * rate)) * int(1e9 / rate) + gt_t[0]
    scan_t = scan_t[scan_t <= gt_t[-1]]
    sx, sy, syaw = loop_pose((scan_t - gt_t[0]) / 1e9, period)
    segs = room_segments()
    cols: dict[str, list[npt.NDArray]] = {k: [] for k in ("scan", "t_ns", "x", "y", "z", "intensity", "doppler")}
    R = BASE_FROM_RADAR
    for i, (bx, by, byaw) in enumerate(zip(sx, sy, syaw, strict=True)):
        c, s = np.cos(byaw), np.sin(byaw)
        ox, oy = bx + c * R[0, 3] - s * R[1, 3], by + s * R[0, 3] + c * R[1, 3]
        radar_yaw = byaw + np.arctan2(R[1, 0], R[0, 0])
        az = np.radians(np.linspace(-fov_deg / 2, fov_deg / 2, beams)) + rng.normal(0, 0.01, beams)
        dirs = np.stack([np.cos(radar_yaw + az), np.sin(radar_yaw + az)], 1)
        rng_m = raycast(np.tile([ox, oy], (beams, 1)), dirs, segs, max_range)
        ok = np.isfinite(rng_m) & (rng.uniform(size=beams) < 0.8)
        rr = rng_m[ok] + rng.normal(0, noise, ok.sum())
        a = az[ok]
        n = len(rr)
        cols["scan"].append(np.full(n, i, np.int32))
        cols["t_ns"].append(np.full(n, scan_t[i], np.int64))
        cols["x"].append((rr * np.cos(a)).astype(np.float32))
        cols["y"].append((rr * np.sin(a)).astype(np.float32))
        cols["z"].append(rng.normal(0, 0.05, n).astype(np.float32))
        cols["intensity"].append(np.full(n, 10.0, np.float32))
        cols["doppler"].append(np.zeros(n, np.float32))
    radar = {k: np.concatenate(v) for k, v in cols.items()}
    return SyntheticSequence(gt_t, np.stack([x, y, yaw], 1), scan_t, radar, BASE_FROM_RADAR)


def yaw_quat(yaw: F64) -> F64:
    return np.stack([np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2), np.cos(yaw / 2)], 1)


def drifted(xyyaw: F64, t_s: F64, yaw_rate: float, scale: float, offset: tuple[float, float, float]) -> F64:
    """An estimate with a slow yaw drift, a scale error, expressed in another frame (offset x, y, yaw)."""
    x, y, yaw = xyyaw.T
    d = yaw_rate * t_s
    cx, cy = x - x[0], y - y[0]
    xd = x[0] + scale * (np.cos(d) * cx - np.sin(d) * cy)
    yd = y[0] + scale * (np.sin(d) * cx + np.cos(d) * cy)
    ox, oy, oyaw = offset
    c, s = np.cos(oyaw), np.sin(oyaw)
    return np.stack([c * xd - s * yd + ox, s * xd + c * yd + oy, yaw + d + oyaw], 1)


def write_stage(runs: Path, seq: str, stage: str, files: dict[str, tuple[dict, str] | str]) -> Path:
    """Write artifacts (``name -> (columns, schema)`` or text) plus a complete manifest."""
    d = runs / seq / stage
    d.mkdir(parents=True, exist_ok=True)
    for name, spec in files.items():
        if isinstance(spec, str):
            (d / name).write_text(spec)
        else:
            write_artifact(spec[0], d / name, spec[1])
    write_json_atomic(d / MANIFEST, {"stage": stage, "complete": True, "key": "synthetic",
                                     "artifacts": {p.name: 1 for p in d.iterdir() if p.name != MANIFEST}})
    return d


def write_synthetic_run(runs: Path, seq: str = "synth", duration: float = 30.0, seed: int = 0,
                        with_maps: bool = True) -> SyntheticSequence:
    """ingest, filter, odometry and slam artifacts of a synthetic sequence (plus voxel maps if asked)."""
    s = make_sequence(duration=duration, seed=seed)
    q = yaw_quat(s.gt_xyyaw[:, 2])
    gt = {"t_ns": s.gt_t, "x": s.gt_xyyaw[:, 0], "y": s.gt_xyyaw[:, 1], "z": np.zeros(len(s.gt_t)),
          "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]}
    calib = {"base_from_radar": s.base_from_radar.tolist(), "base_from_lidar": np.eye(4).tolist(),
             "base_from_imu": np.eye(4).tolist()}
    write_stage(runs, seq, "ingest", {"groundtruth.parquet": (gt, "groundtruth"), "radar.parquet": (s.radar, "radar"),
                                      "calibration.json": json.dumps(calib)})
    write_stage(runs, seq, "filter", {"radar_filtered.parquet": (s.radar, "radar_filtered")})
    sx, sy, syaw = loop_pose((s.scan_t - s.gt_t[0]) / 1e9, 30.0)
    truth = np.stack([sx, sy, syaw], 1)
    ts = (s.scan_t - s.scan_t[0]) / 1e9
    scans = np.arange(len(s.scan_t), dtype=np.int32)
    odo = drifted(truth, ts, 0.01, 1.03, (1.0, -2.0, 0.3))
    slam = drifted(truth, ts, 0.002, 1.005, (1.0, -2.0, 0.3))

    def traj(a: F64) -> dict:
        return {"scan": scans, "t_ns": s.scan_t, "x": a[:, 0], "y": a[:, 1], "yaw": a[:, 2]}

    zeros = np.zeros(len(scans))
    write_stage(runs, seq, "odometry", {"odometry.parquet": ({**traj(odo), "z": zeros, "roll": zeros, "pitch": zeros,
                                                              **cov_columns(len(scans))},
                                                             "odometry")})
    slam_files: dict = {f"trajectory_{m}.parquet": ({**traj(a), "n_eff": np.ones(len(scans))}, "trajectory")
                        for m, a in (("rich_slam", slam), ("fastslam_grid", drifted(truth, ts, 0.005, 1.0, (0, 0, 0))))}
    slam_files["trajectory.parquet"] = slam_files["trajectory_rich_slam.parquet"]
    slam_files.update(_slam_map(truth))
    write_stage(runs, seq, "slam", slam_files)
    if with_maps:
        rng = np.random.default_rng(seed)
        lidar = _wall_points(room_segments(), 0.05, rng)
        n = len(lidar) // 4
        radar_map = lidar[rng.choice(len(lidar), n, replace=False)] + rng.normal(0, 0.1, (n, 3))
        write_stage(runs, seq, "voxel", {
            "radar_map.parquet": (_map_cols(radar_map), "radar_map"),
            "lidar_map.parquet": (_map_cols(lidar), "lidar_map"),
        })
    return s


def _wall_points(segs: F64, step: float, rng: np.random.Generator) -> F64:
    pts = []
    for x0, y0, x1, y1 in segs:
        n = max(2, int(np.hypot(x1 - x0, y1 - y0) / step))
        t = np.linspace(0, 1, n)
        for z in np.arange(0.0, 1.0, 0.15):
            pts.append(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0), np.full(n, z)], 1))
    return np.concatenate(pts)


def _map_cols(p: F64) -> dict:
    return {"x": p[:, 0].astype(np.float32), "y": p[:, 1].astype(np.float32), "z": p[:, 2].astype(np.float32),
            "log_odds": np.ones(len(p), np.float32)}


def _slam_map(truth: F64) -> dict:
    """A Hilbert-GP posterior with the slam stage's metadata (trained from the room's walls, GT poses)."""
    from core import hilbert_map as hm

    L, c, M, ell, sf, sn = (10.0, 7.0), (0.0, 0.0), 256, 1.5, 4.0, 0.36
    basis = hm.make_basis(L, c, M)
    segs = room_segments()
    rng = np.random.default_rng(1)
    occ = _wall_points(segs, 0.2, rng)[:, :2]
    free = rng.uniform([-7.5, -4.5], [7.5, 4.5], (600, 2))
    from scipy.spatial import cKDTree

    free = free[cKDTree(occ).query(free)[0] > 0.5]
    pts = np.concatenate([occ, free])
    lab = np.r_[np.ones(len(occ)), -np.ones(len(free))]
    prior_diag = hm.prior_variances(basis, ell, sf)
    theta, cov = hm.batch_posterior(prior_diag, hm.features(basis, pts), lab, sn)
    gx, gy = np.meshgrid(np.arange(-10, 10, 0.5), np.arange(-7, 7, 0.5), indexing="ij")
    g = np.stack([gx.ravel(), gy.ravel()], 1)
    _, var, occp = hm.query(basis, theta, cov, g)
    post = {"theta": [theta.tolist()], "cov": [cov.ravel().tolist()], "L1": [L[0]], "L2": [L[1]], "cx": [c[0]],
            "cy": [c[1]], "M": [M], "lengthscale": [ell], "signal_variance": [sf], "noise_variance": [sn]}
    grid = {"x": g[:, 0], "y": g[:, 1], "occupancy": occp, "variance": var}
    return {"map_posterior.parquet": (post, "map_posterior"), "map_grid.parquet": (grid, "map_grid")}


def make_context(runs: Path, seq: str, stage: str, params: StageParams, inputs: list[str], out: Path) -> StageContext:
    """A ``StageContext`` reading ``runs/<seq>/<input>/`` and writing into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    info = SequenceInfo(name=seq, kind="source", source=Path("/nonexistent"))
    return StageContext(stage=stage, seq=info, params=params, out_dir=out,
                        input_dirs={i: runs / seq / i for i in inputs if (runs / seq / i).exists()},
                        console=Console(stderr=True, quiet=True))
