"""`filter` stage: Doppler ego-velocity and multi-frame radar point filtering (RICH-SLAM Sec. IV-B).

Per scan: REVE ego-velocity (zero-velocity test, 3-point RANSAC, least squares), then a point is kept
when it is (1) consistent with the ego-velocity for a static world, (2) above the intensity gate, (3)
within the modelled point-uncertainty gate, and (4) tracked: matched in each of the ``track_frames``
previous scans after predicting them into the current frame with the gyro rotation and ego-velocity
translation. When ingest found simulator labels, the fractions of clutter / ghost points rejected and
of true points kept go into the manifest; with ground truth, the ego-velocity RMSE does too.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa

from core.geometry import interpolate_poses, matrices_to_poses
from core.stage import Stage, StageContext
from schemas.io import read_artifact, write_artifact
from stages.filter import ego_velocity as ev
from stages.filter.evaluation import label_fractions, radar_velocity_from_groundtruth, velocity_errors
from stages.filter.params import FilterParams
from stages.filter.tracking import frame_motions, interval_rotations, track_masks
from stages.filter.uncertainty import max_sigma, point_covariances

DEG = np.pi / 180.0


def filter_scans(xyz: npt.NDArray[np.float64], intensity: npt.NDArray[np.float64], doppler: npt.NDArray[np.float64],
                 starts: npt.NDArray[np.int64], scan_t: npt.NDArray[np.int64], imu_t: npt.NDArray[np.int64],
                 gyro_radar: npt.NDArray[np.float64], base_from_radar: npt.NDArray[np.float64], p: FilterParams
                 ) -> dict[str, Any]:
    """All per-point masks and per-scan velocities for a radar sequence (points sorted by scan).

    ``starts`` has S+1 offsets into the point arrays; ``gyro_radar`` is the angular rate in the radar frame.
    """
    S = len(scan_t)
    n = len(doppler)
    cfg = p.ego_velocity
    rng = np.random.default_rng(p.seed)
    dirs, rng_m = ev.unit_directions(xyz)
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    el = np.arcsin(np.clip(xyz[:, 2] / np.where(rng_m > 0, rng_m, 1.0), -1, 1))
    in_range = (rng_m >= p.points.min_range_m) & (rng_m <= p.points.max_range_m)
    bright = intensity >= p.points.min_intensity
    estimable = in_range & bright & (np.abs(az) <= p.points.max_azimuth_deg * DEG) & \
        (np.abs(el) <= p.points.max_elevation_deg * DEG)
    vel = np.full((S, 3), np.nan)
    cov = np.full((S, 3, 3), np.nan)
    n_inl = np.zeros(S, np.int32)
    dims = np.zeros(S, np.int8)
    valid = np.zeros(S, bool)
    R_rel = interval_rotations(imu_t, gyro_radar, scan_t)
    gap_ok = np.r_[True, np.diff(scan_t) * 1e-9 <= p.tracking.max_scan_gap_s]
    for s in range(S):
        a, b = starts[s], starts[s + 1]
        sel = np.flatnonzero(estimable[a:b]) + a
        prior = None
        if p.ego_velocity.temporal_prior and s > 0 and valid[s - 1] and gap_ok[s]:
            prior = R_rel[s].T @ vel[s - 1]  # previous velocity in this scan's frame
        est = ev.estimate(dirs[sel], doppler[sel], cfg, rng, prior)
        vel[s], cov[s], valid[s], dims[s] = est.v, est.cov, est.valid, est.dims
        n_inl[s] = int(est.inliers.sum())
    scan_of = np.repeat(np.arange(S), np.diff(starts))
    v_pt = vel[scan_of] if n else np.zeros((0, 3))
    residual = np.abs(doppler + (dirs * np.nan_to_num(v_pt)).sum(axis=1))
    static = valid[scan_of] & (residual < p.points.static_threshold_mps)
    u = p.uncertainty
    covs = point_covariances(xyz, u.range_sigma_m, u.azimuth_sigma_deg * DEG, u.elevation_sigma_deg * DEG)
    sig = max_sigma(covs, base_from_radar[:3, :3], horizontal=p.uncertainty.horizontal)
    certain = sig <= p.uncertainty.max_sigma_m
    candidate = in_range & static & bright & certain
    if p.tracking.frames > 0:
        motions = frame_motions(R_rel, np.nan_to_num(vel), scan_t)
        usable = valid & np.r_[True, valid[:-1]] & gap_ok
        pts = [xyz[starts[s]:starts[s + 1]][candidate[starts[s]:starts[s + 1]]] for s in range(S)]
        gates = [p.tracking.gate_m + p.tracking.gate_sigma_scale * sig[starts[s]:starts[s + 1]][
            candidate[starts[s]:starts[s + 1]]] for s in range(S)]
        masks = track_masks(pts, motions, p.tracking.frames, gates, use_z=p.tracking.use_z, usable=usable)
        tracked = np.zeros(n, bool)
        cand_idx = np.flatnonzero(candidate)
        tracked[cand_idx] = np.concatenate(masks) if masks else np.zeros(0, bool)
    else:
        tracked = candidate.copy()
    return {"velocity": vel, "covariance": cov, "n_inliers": n_inl, "dims": dims, "valid": valid,
            "in_range": in_range, "static": static, "bright": bright, "certain": certain, "candidate": candidate,
            "kept": tracked, "sigma": sig}


class FilterStage(Stage):
    name = "filter"
    description = "Doppler ego-velocity and multi-frame radar point filtering (RICH-SLAM Sec. IV-B)"
    inputs = ("ingest",)
    Params = FilterParams
    version = "1"
    outputs = ("radar_filtered.parquet", "ego_velocity.parquet")

    def run(self, ctx: StageContext) -> None:
        p: FilterParams = ctx.params
        radar = read_artifact(ctx.input("ingest", "radar.parquet"), "radar")
        calib = json.loads(ctx.input("ingest", "calibration.json").read_text())
        base_from_radar = np.asarray(calib["base_from_radar"], dtype=np.float64)
        base_from_imu = np.asarray(calib["base_from_imu"], dtype=np.float64)
        imu = read_artifact(ctx.input("ingest", "imu.parquet"), "imu", columns=["t_ns", "gx", "gy", "gz"])
        imu_t = imu["t_ns"].to_numpy()
        gyro = np.stack([imu[c].to_numpy() for c in ("gx", "gy", "gz")], axis=1)
        radar_from_imu = np.linalg.inv(base_from_radar)[:3, :3] @ base_from_imu[:3, :3]
        gyro_radar = gyro @ radar_from_imu.T
        if p.tracking.frames > 0 and len(imu_t) < 2:
            ctx.warn("no IMU samples: scan-to-scan rotation taken as zero for tracking")

        scans = radar["scan"].to_numpy()
        order = np.argsort(scans, kind="stable")
        if np.any(order != np.arange(len(order))):
            radar = radar.take(pa.array(order))
            scans = scans[order]
        uniq, first = np.unique(scans, return_index=True)
        starts = np.r_[first, len(scans)].astype(np.int64)
        t_pt = radar["t_ns"].to_numpy()
        scan_t = t_pt[first] if len(first) else np.zeros(0, np.int64)
        xyz = np.stack([radar[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], axis=1)
        intensity = radar["intensity"].to_numpy().astype(np.float64)
        doppler = radar["doppler"].to_numpy().astype(np.float64)

        res = filter_scans(xyz, intensity, doppler, starts, scan_t, imu_t, gyro_radar, base_from_radar, p)
        kept = res["kept"]
        write_artifact(radar.filter(pa.array(kept)), ctx.output("radar_filtered.parquet"), "radar_filtered")
        vel, cov = res["velocity"], res["covariance"]
        iu = np.triu_indices(3)
        cov_cols = {f"cov_{'xyz'[i]}{'xyz'[j]}": cov[:, i, j] for i, j in zip(*iu, strict=True)}
        write_artifact({"scan": uniq.astype(np.int32), "t_ns": scan_t, "vx": vel[:, 0], "vy": vel[:, 1],
                        "vz": vel[:, 2], "n_inliers": res["n_inliers"], "valid": res["valid"],
                        "dims": res["dims"], "n_points": np.diff(starts).astype(np.int32), **cov_cols},
                       ctx.output("ego_velocity.parquet"), "ego_velocity")
        gt = read_artifact(ctx.input("ingest", "groundtruth.parquet"), "groundtruth")
        gt_t = gt["t_ns"].to_numpy()
        gt_poses = np.stack([gt[c].to_numpy() for c in ("x", "y", "z", "qx", "qy", "qz", "qw")], axis=1)
        v_gt = None
        if len(gt_t) >= 2 and len(scan_t):
            v_gt = radar_velocity_from_groundtruth(gt_t, gt_poses, base_from_radar, scan_t,
                                                   p.gt_velocity_half_window_s)
        self._stats(ctx, radar, res, uniq, v_gt)
        self._log(ctx, radar, res, uniq, scan_t, calib, (gt_t, gt_poses), v_gt)

    def _stats(self, ctx: StageContext, radar: pa.Table, res: dict[str, Any], scans: npt.NDArray[Any],
               v_gt: tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]] | None) -> None:
        n = radar.num_rows
        kept = res["kept"]
        stats: dict[str, Any] = {
            "scans": len(scans), "points": n, "kept": int(kept.sum()),
            "kept_fraction": round(float(kept.mean()), 4) if n else None,
            "ego_velocity_valid_scans": int(res["valid"].sum()),
            "ego_velocity_planar_scans": int((res["dims"] == 2).sum()),
            "ego_velocity_zero_scans": int((res["valid"] & (res["dims"] == 0)).sum()),
            "passed": {k: int(res[k].sum()) for k in ("in_range", "static", "bright", "certain", "candidate", "kept")},
        }
        if "label" in radar.column_names:
            labels = radar["label"].to_numpy()
            if (labels >= 0).any():
                stats["labels"] = label_fractions(labels, res)
                lab = stats["labels"]
                ctx.console.print(
                    f"[dim]filter: true points kept {lab['true_kept']:.3f}, clutter rejected "
                    f"{lab['clutter_rejected']}, ghosts rejected {lab['ghost_rejected']}[/]")
        if v_gt is not None:
            stats["ego_velocity_error"] = velocity_errors(res["velocity"], v_gt[0], res["valid"] & v_gt[1])
            ctx.console.print(f"[dim]filter: ego-velocity RMSE {stats['ego_velocity_error'].get('rmse_mps')} m/s[/]")
        if not res["valid"].any():
            ctx.warn("no scan gave an ego-velocity estimate (too few points?)")
        ctx.stats.update(stats)

    def _log(self, ctx: StageContext, radar: pa.Table, res: dict[str, Any], scans: npt.NDArray[Any],
             scan_t: npt.NDArray[np.int64], calib: dict[str, Any],
             gt: tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]],
             v_gt: tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]] | None) -> None:
        import rerun as rr

        from core.recording import time_columns

        p: FilterParams = ctx.params
        rec = ctx.recording
        scan_col = radar["scan"].to_numpy()
        every = np.isin(scan_col, scans[:: p.rerun_every])
        xyz = np.stack([radar[c].to_numpy() for c in ("x", "y", "z")], axis=1)
        kept = res["kept"]
        for entity, mask, colour in (("world/radar/filtered", kept & every, (40, 220, 90)),
                                     ("world/radar/filtered/rejected", ~kept & every, (230, 50, 50))):
            idx = np.flatnonzero(mask)
            rec.points_by_scan(entity, scan_col[idx], radar["t_ns"].to_numpy()[idx], xyz[idx],
                               colors=np.tile(np.asarray(colour, np.uint8), (len(idx), 1)), radii=0.05)
        valid = res["valid"]
        for k, axis in enumerate("xyz"):
            rec.scalars(f"metrics/ego_velocity/v{axis}", scans[valid], scan_t[valid], res["velocity"][valid, k])
        if v_gt is not None:
            v, inside = v_gt
            for k, axis in enumerate("xyz"):
                rec.scalars(f"metrics/ego_velocity/groundtruth_v{axis}", scans[inside], scan_t[inside], v[inside, k])
        gt_t, gt_poses = gt
        if len(gt_t) >= 2 and len(scan_t):
            sel = np.arange(len(scans))[:: p.rerun_every]
            T, _ = interpolate_poses(gt_t, gt_poses, scan_t[sel])
            T = T @ np.asarray(calib["base_from_radar"])
            rec.rec.send_columns("world/radar/filtered", indexes=time_columns(scans[sel], scan_t[sel]),
                                 columns=rr.Transform3D.columns(translation=T[:, :3, 3],
                                                                quaternion=matrices_to_poses(T)[:, 3:]))


STAGE = FilterStage()
