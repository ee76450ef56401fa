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
from pydantic import Field

from core.geometry import interpolate_poses, matrices_to_poses
from core.stage import Stage, StageContext, StageParams
from schemas.io import read_artifact, write_artifact
from stages.filter import ego_velocity as ev
from stages.filter.evaluation import label_fractions, radar_velocity_from_groundtruth, velocity_errors
from stages.filter.tracking import frame_motions, interval_rotations, track_masks
from stages.filter.uncertainty import max_sigma, point_covariances

DEG = np.pi / 180.0


class FilterParams(StageParams):
    """Parameters of the `filter` stage (REVE defaults for the ego-velocity estimator)."""

    seed: int = Field(0, description="seed of the RANSAC sampling")
    min_range_m: float = Field(0.25, ge=0, description="points closer than this are dropped (REVE min_dist)")
    max_range_m: float = Field(100.0, gt=0, description="points farther than this are dropped (REVE max_dist)")
    min_intensity: float = Field(5.0, description="intensity gate, in the radar's intensity unit (REVE min_db, dB)")
    estimator_max_azimuth_deg: float = Field(56.5, gt=0, le=180,
                                             description="|azimuth| limit of points used for the ego-velocity (REVE)")
    estimator_max_elevation_deg: float = Field(
        45.0, gt=0, le=90, description="|elevation| limit of points used for the ego-velocity (ColoRadar tools' "
                                       "+-45 deg field of view; REVE's own sensor used 22.5)")
    inlier_threshold_mps: float = Field(0.15, gt=0, description="RANSAC Doppler inlier threshold (REVE)")
    outlier_probability: float = Field(0.4, gt=0, lt=1, description="assumed outlier fraction for the RANSAC count")
    success_probability: float = Field(0.9999, gt=0, lt=1, description="RANSAC success probability")
    max_iterations: int = Field(200, ge=1, le=100_000, description="cap on RANSAC hypotheses")
    min_points: int = Field(5, ge=3, le=100_000, description="fewest usable points for an ego-velocity estimate")
    zero_velocity_threshold_mps: float = Field(0.05, ge=0, description="zero-velocity test threshold (REVE)")
    allowed_outlier_fraction: float = Field(0.3, ge=0, lt=1,
                                            description="outlier share tolerated by the zero-velocity test (REVE)")
    sigma_offset_mps: float = Field(0.05, ge=0, description="added to the LSQ velocity std (REVE sigma_offset)")
    max_condition: float = Field(1000.0, gt=1, description="LSQ condition bound; above it v_z is fixed to 0")
    max_sigma_xy_mps: float = Field(0.2, gt=0, description="largest LSQ std of v_x, v_y for a valid estimate (REVE)")
    max_sigma_z_mps: float = Field(0.2, gt=0, description="largest LSQ std of v_z; above it v_z is fixed to 0")
    max_vz_mps: float = Field(1.0, gt=0, description="largest plausible |v_z| (radar z up); 3D solutions beyond it "
                                                     "fall back to the planar model")
    doppler_sigma_floor_mps: float = Field(0.05, ge=0,
                                           description="floor of the LSQ residual std (Doppler resolution ~0.04 m/s)")
    temporal_prior: bool = Field(True, description="offer the previous scan's velocity as a RANSAC hypothesis; "
                                                   "it wins ties in the inlier count")
    static_threshold_mps: float = Field(0.15, gt=0,
                                        description="keep points with |d + r.v| below this (static world)")
    range_sigma_m: float = Field(0.0625, ge=0, description="modelled range noise std (half a 0.125 m range bin)")
    azimuth_sigma_deg: float = Field(5.5, ge=0, description="modelled azimuth noise std (half the ~11 deg resolution)")
    elevation_sigma_deg: float = Field(22.5, ge=0,
                                       description="modelled elevation noise std (half the ~45 deg resolution)")
    max_point_sigma_m: float = Field(1.0, gt=0, description="point-uncertainty gate: largest position std, m")
    uncertainty_horizontal: bool = Field(True, description="gate on the horizontal (base xy) block of the covariance")
    track_frames: int = Field(2, ge=0, le=100,
                              description="previous scans a point must be matched in (0 = no tracking)")
    track_gate_m: float = Field(0.3, ge=0, description="match radius for tracking, m")
    track_gate_sigma_scale: float = Field(1.0, ge=0, description="adds this many modelled point stds to the gate")
    track_use_z: bool = Field(False, description="match in 3D (default: horizontal x, y of the radar frame)")
    max_scan_gap_s: float = Field(0.5, gt=0, description="a larger gap between scans breaks every track")
    gt_velocity_half_window_s: float = Field(0.05, gt=0,
                                             description="central difference half-window for ground-truth velocity")
    rerun_every: int = Field(1, ge=1, le=1_000_000, description="log every n-th scan's kept/rejected points to Rerun")


def _config(p: FilterParams) -> ev.EgoVelocityConfig:
    return ev.EgoVelocityConfig(
        inlier_threshold=p.inlier_threshold_mps, outlier_probability=p.outlier_probability,
        success_probability=p.success_probability, max_iterations=p.max_iterations, min_points=p.min_points,
        zero_velocity_threshold=p.zero_velocity_threshold_mps, allowed_outlier_fraction=p.allowed_outlier_fraction,
        sigma_offset=p.sigma_offset_mps, max_condition=p.max_condition, max_sigma_xy=p.max_sigma_xy_mps,
        max_sigma_z=p.max_sigma_z_mps, doppler_sigma_floor=p.doppler_sigma_floor_mps, max_vz=p.max_vz_mps)


def filter_scans(xyz: npt.NDArray[np.float64], intensity: npt.NDArray[np.float64], doppler: npt.NDArray[np.float64],
                 starts: npt.NDArray[np.int64], scan_t: npt.NDArray[np.int64], imu_t: npt.NDArray[np.int64],
                 gyro_radar: npt.NDArray[np.float64], base_from_radar: npt.NDArray[np.float64], p: FilterParams
                 ) -> dict[str, Any]:
    """All per-point masks and per-scan velocities for a radar sequence (points sorted by scan).

    ``starts`` has S+1 offsets into the point arrays; ``gyro_radar`` is the angular rate in the radar frame.
    """
    S = len(scan_t)
    n = len(doppler)
    cfg = _config(p)
    rng = np.random.default_rng(p.seed)
    dirs, rng_m = ev.unit_directions(xyz)
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    el = np.arcsin(np.clip(xyz[:, 2] / np.where(rng_m > 0, rng_m, 1.0), -1, 1))
    in_range = (rng_m >= p.min_range_m) & (rng_m <= p.max_range_m)
    bright = intensity >= p.min_intensity
    estimable = in_range & bright & (np.abs(az) <= p.estimator_max_azimuth_deg * DEG) & \
        (np.abs(el) <= p.estimator_max_elevation_deg * DEG)
    vel = np.full((S, 3), np.nan)
    cov = np.full((S, 3, 3), np.nan)
    n_inl = np.zeros(S, np.int32)
    dims = np.zeros(S, np.int8)
    valid = np.zeros(S, bool)
    R_rel = interval_rotations(imu_t, gyro_radar, scan_t)
    gap_ok = np.r_[True, np.diff(scan_t) * 1e-9 <= p.max_scan_gap_s]
    for s in range(S):
        a, b = starts[s], starts[s + 1]
        sel = np.flatnonzero(estimable[a:b]) + a
        prior = None
        if p.temporal_prior and s > 0 and valid[s - 1] and gap_ok[s]:
            prior = R_rel[s].T @ vel[s - 1]  # previous velocity in this scan's frame
        est = ev.estimate(dirs[sel], doppler[sel], cfg, rng, prior)
        vel[s], cov[s], valid[s], dims[s] = est.v, est.cov, est.valid, est.dims
        n_inl[s] = int(est.inliers.sum())
    scan_of = np.repeat(np.arange(S), np.diff(starts))
    v_pt = vel[scan_of] if n else np.zeros((0, 3))
    static = valid[scan_of] & (np.abs(doppler + (dirs * np.nan_to_num(v_pt)).sum(axis=1)) < p.static_threshold_mps)
    covs = point_covariances(xyz, p.range_sigma_m, p.azimuth_sigma_deg * DEG, p.elevation_sigma_deg * DEG)
    sig = max_sigma(covs, base_from_radar[:3, :3], horizontal=p.uncertainty_horizontal)
    certain = sig <= p.max_point_sigma_m
    candidate = in_range & static & bright & certain
    if p.track_frames > 0:
        motions = frame_motions(R_rel, np.nan_to_num(vel), scan_t)
        usable = valid & np.r_[True, valid[:-1]] & gap_ok
        pts = [xyz[starts[s]:starts[s + 1]][candidate[starts[s]:starts[s + 1]]] for s in range(S)]
        gates = [p.track_gate_m + p.track_gate_sigma_scale * sig[starts[s]:starts[s + 1]][
            candidate[starts[s]:starts[s + 1]]] for s in range(S)]
        masks = track_masks(pts, motions, p.track_frames, gates, use_z=p.track_use_z, usable=usable)
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
        if p.track_frames > 0 and len(imu_t) < 2:
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
