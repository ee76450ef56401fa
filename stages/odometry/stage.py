"""`odometry` stage: radar-inertial odometry (EKF-RIO) at radar scan times.

``source = "ekf"`` fuses the IMU with the filter's Doppler ego-velocity (stages/odometry/ekf_rio.py);
``source = "bag"`` takes the odometry topic the dataset profile (or ``ingest.topics.odometry``) names,
interpolated at the radar scan times. Either way the output is world <- base as SE(2) (x, y, yaw).

Anchoring: the filter runs in its own gravity-aligned frame with zero initial yaw. With ``anchor =
"groundtruth"`` (default) the planar trajectory is moved rigidly so that its first pose equals the
ground-truth pose at that time (the first scan that ground truth covers, if it starts later), so
odometry, SLAM and ground truth share one world frame; without ground truth, or with ``anchor =
"origin"``, the first pose is (0, 0, 0). Nothing else uses ground truth.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import numpy.typing as npt

from core.errors import UserError
from core.geometry import interpolate_poses, roll_pitch_of, yaw_of
from core.stage import Stage, StageContext, StageParams
from core.trajectory_metrics import drift, increment_nees, se2_compose_anchor, se2_increments
from schemas.artifacts import ODOMETRY_COV_COLS, ODOMETRY_COV_IDX
from schemas.io import read_artifact, write_artifact
from stages.odometry.ekf_rio import increment_covariance, run_ekf
from stages.odometry.params import OdometryParams

POSE_COLS = ("x", "y", "z", "qx", "qy", "qz", "qw")
#: the increment covariance's columns (body frame of the previous scan: dx, dy, dyaw)
COV_COLS, _COV_IDX = ODOMETRY_COV_COLS, ODOMETRY_COV_IDX


def bag_increment_covariance(u: npt.NDArray[np.float64], std_xy: float, rel_trans: float, std_yaw: float,
                             rot_per_trans: float) -> npt.NDArray[np.float64]:
    """The ``bag`` source's increment covariance (its odometry topic carries none we can trust): diagonal,
    ``(std_xy + rel_trans |t|)^2`` on x and y, ``(std_yaw + rot_per_trans |t|)^2`` on yaw; row 0 zero."""
    trans = np.hypot(u[:, 0], u[:, 1])
    out = np.zeros((len(u), 3, 3))
    out[:, 0, 0] = out[:, 1, 1] = (std_xy + rel_trans * trans) ** 2
    out[:, 2, 2] = (std_yaw + rot_per_trans * trans) ** 2
    out[:1] = 0.0
    return out


class OdometryStage(Stage):
    name = "odometry"
    description = "radar-inertial odometry (EKF-RIO) at radar scan times"
    inputs = ("ingest", "filter")
    Params = OdometryParams
    version = "4"
    outputs = ("odometry.parquet",)

    def input_stages(self, params: StageParams) -> tuple[str, ...]:
        assert isinstance(params, OdometryParams)
        return ("ingest",) if params.source == "bag" else self.inputs

    def run(self, ctx: StageContext) -> None:
        p: OdometryParams = ctx.params
        calib = json.loads(ctx.input("ingest", "calibration.json").read_text())
        base_from_imu = np.asarray(calib["base_from_imu"], dtype=np.float64)
        base_from_radar = np.asarray(calib["base_from_radar"], dtype=np.float64)
        if p.source == "bag":
            ekf_only = [f"height.{k}={getattr(p.height, k):g}" for k in ("mount_sigma0_deg", "level_velocity_sigma")
                        if getattr(p.height, k)]
            if ekf_only:
                ctx.warn(f"odometry.{', odometry.'.join(ekf_only)}: EKF settings, unused with odometry.source=bag "
                         f"(the log's odometry topic is taken as it is)")
            scans, scan_t, T_wb, valid = self._from_bag(ctx)
            u = se2_increments(np.stack([T_wb[:, 0, 3], T_wb[:, 1, 3], yaw_of(T_wb[:, :3, :3])], axis=1))
            inc_cov = bag_increment_covariance(u, p.bag.std_xy, p.bag.rel_trans, p.bag.std_yaw, p.bag.rot_per_trans)
        else:
            scans, scan_t, T_wb, valid, inc_cov = self._from_ekf(ctx, base_from_imu, base_from_radar)
            inc_cov = inc_cov * p.covariance.scale
        x, y, yaw = T_wb[:, 0, 3], T_wb[:, 1, 3], yaw_of(T_wb[:, :3, :3])
        z, roll, pitch = T_wb[:, 2, 3].copy(), *roll_pitch_of(T_wb[:, :3, :3])

        gt = read_artifact(ctx.input("ingest", "groundtruth.parquet"), "groundtruth")
        gt_t = gt["t_ns"].to_numpy()
        gt_poses = np.stack([gt[c].to_numpy() for c in POSE_COLS], axis=1)
        T_gt, inside = interpolate_poses(gt_t, gt_poses, scan_t)
        first = int(np.argmax(valid)) if valid.any() else 0
        anchored = "origin"
        if len(scan_t):
            with_gt = valid & inside
            if p.anchor == "groundtruth" and with_gt.any():
                at = int(np.argmax(with_gt))  # first estimated pose that ground truth covers
                ref = T_gt[at]
                x, y, yaw = se2_compose_anchor(x, y, yaw, at, ref[0, 3], ref[1, 3], float(yaw_of(ref[:3, :3])))
                z = z - z[at] + ref[2, 3]
                anchored = "groundtruth"
                ctx.stats["anchor_scan"] = int(scans[at])
            else:
                if p.anchor == "groundtruth" and len(gt_t):
                    ctx.warn("no ground truth during the odometry: anchored at the origin instead")
                elif p.anchor == "groundtruth":  # a radar + IMU log: nothing to anchor to, nothing wrong
                    ctx.console.print("[dim]odometry: the log has no ground truth; anchored at the origin[/]")
                x, y, yaw = se2_compose_anchor(x, y, yaw, first, 0.0, 0.0, 0.0)
                z = z - z[first]
        cols = {c: inc_cov[:, i, j] for c, (i, j) in zip(COV_COLS, _COV_IDX, strict=True)}
        write_artifact({"scan": scans.astype(np.int32), "t_ns": scan_t, "x": x, "y": y, "z": z,
                        "roll": roll, "pitch": pitch, "yaw": yaw, **cols, "valid": valid},
                       ctx.output("odometry.parquet"), "odometry", metadata={"anchor": anchored, "source": p.source})
        ctx.stats["anchor"] = anchored
        ctx.stats["source"] = p.source
        ctx.stats["scans"] = len(scans)
        ok = valid & inside
        if len(gt_t) >= 2 and ok.sum() >= 2:
            ref = np.stack([T_gt[:, 0, 3], T_gt[:, 1, 3], yaw_of(T_gt[:, :3, :3])], axis=1)
            est = np.stack([x, y, yaw], axis=1)
            ctx.stats["drift"] = drift(scan_t[ok], est[ok], ref[ok])
            ctx.stats["increment_nees"] = increment_nees(est, ref, inc_cov, ok)
            d = ctx.stats["drift"]
            ctx.console.print(f"[dim]odometry: drift {d.get('drift_pct_of_distance')} % of "
                              f"{d.get('path_length_m')} m, yaw {d.get('yaw_drift_deg_per_min')} deg/min[/]")
        ctx.recording.trajectory("world/odometry", scans, scan_t, np.stack([x, y, z], axis=1), color=(70, 130, 255))

    def _from_ekf(self, ctx: StageContext, base_from_imu: npt.NDArray[np.float64],
                  base_from_radar: npt.NDArray[np.float64]
                  ) -> tuple[npt.NDArray[Any], npt.NDArray[np.int64], npt.NDArray[np.float64], npt.NDArray[np.bool_],
                             npt.NDArray[np.float64]]:
        """Poses world <- base and the increment covariance per scan (:func:`increment_covariance`)."""
        p: OdometryParams = ctx.params
        ego = read_artifact(ctx.input("filter", "ego_velocity.parquet"), "ego_velocity")
        imu = read_artifact(ctx.input("ingest", "imu.parquet"), "imu")
        if imu.num_rows < 2:
            raise UserError(f"{ctx.input('ingest', 'imu.parquet')}: no IMU samples; EKF-RIO needs an IMU "
                            f"(or use --set odometry.source=bag with an odometry topic)")
        scans = ego["scan"].to_numpy()
        scan_t = ego["t_ns"].to_numpy()
        vel = np.stack([ego[c].to_numpy() for c in ("vx", "vy", "vz")], axis=1)
        names = ego.column_names
        valid = ego["valid"].to_numpy() if "valid" in names else np.isfinite(vel).all(axis=1)
        dims = ego["dims"].to_numpy() if "dims" in names else np.full(len(scans), 3)
        cov = np.tile(np.eye(3) * p.velocity.sigma_mps ** 2, (len(scans), 1, 1))
        if all(f"cov_{a}{b}" in names for a, b in ("xx", "xy", "xz", "yy", "yz", "zz")):
            for a, b in ("xx", "xy", "xz", "yy", "yz", "zz"):
                i, j = "xyz".index(a), "xyz".index(b)
                cov[:, i, j] = cov[:, j, i] = ego[f"cov_{a}{b}"].to_numpy()
        imu_t = imu["t_ns"].to_numpy()
        acc = np.stack([imu[c].to_numpy() for c in ("ax", "ay", "az")], axis=1)
        gyro = np.stack([imu[c].to_numpy() for c in ("gx", "gy", "gz")], axis=1)
        imu_from_radar = np.linalg.inv(base_from_imu) @ base_from_radar
        res = run_ekf(imu_t, acc, gyro, scan_t, vel, cov, dims, valid, imu_from_radar, p)
        if not res.initialized.any():
            t0 = min(int(imu_t[0]), int(scan_t[0])) if len(scan_t) else int(imu_t[0])
            span = (f"radar scans {(scan_t[0] - t0) * 1e-9:.1f}-{(scan_t[-1] - t0) * 1e-9:.1f} s, "
                    f"{int(valid.sum())} with a valid ego-velocity" if len(scan_t) else "no radar scans")
            raise UserError(f"{ctx.input('filter', 'ego_velocity.parquet')}: no scan with a valid ego-velocity "
                            f"inside the IMU time span ({span}; IMU {(imu_t[0] - t0) * 1e-9:.1f}-"
                            f"{(imu_t[-1] - t0) * 1e-9:.1f} s); rerun ingest with --set ingest.clock.time_source=auto "
                            f"(or record) to line the clocks up")
        self._report_ekf(ctx, res.stats, scan_t)
        ctx.stats["ekf"] = res.stats
        ctx.stats["gyro_bias_final"] = [round(float(b), 6) for b in res.gyro_bias[-1]]
        ctx.stats["accel_bias_final"] = [round(float(b), 5) for b in res.accel_bias[-1]]
        if p.height.mount_sigma0_deg > 0:
            ctx.stats["mount_error_deg"] = [round(float(np.degrees(v)), 3) for v in res.mount_error[-1]]
            ctx.stats["mount_error_sigma_deg"] = [round(float(np.degrees(v)), 3) for v in res.mount_sigma[-1]]
            ctx.console.print(f"[dim]odometry: radar mount rotation error (radar frame) "
                              f"{ctx.stats['mount_error_deg']} deg, std {ctx.stats['mount_error_sigma_deg']} deg[/]")
        T_wb = res.T_world_imu @ np.linalg.inv(base_from_imu)
        return scans, scan_t, T_wb, res.initialized, increment_covariance(res.T_world_imu, res.pose_pair_cov,
                                                                          base_from_imu)

    @staticmethod
    def _report_ekf(ctx: StageContext, st: dict[str, Any], scan_t: npt.NDArray[np.int64]) -> None:
        """Warnings: a large share of rejected velocity updates, recoveries, the standstill used."""
        p: OdometryParams = ctx.params
        n_upd, n_rej = st["velocity_updates"], st["velocity_rejected"]
        total = n_upd + n_rej
        t0 = int(scan_t[0]) if len(scan_t) else 0
        if total and n_rej / total > p.reject_warn_share:
            ctx.warn(f"EKF: the chi-square gate rejected {n_rej} of {total} velocity updates "
                     f"({100 * n_rej / total:.0f} % > {100 * p.reject_warn_share:g} %): the IMU is noisier than "
                     f"odometry.imu.accel_noise_density={p.imu.accel_noise_density:g} / gyro_noise_density="
                     f"{p.imu.gyro_noise_density:g}, or the radar-IMU extrinsic or clocks are off")
        if st["recoveries"] or st["reinitialisations"]:
            when = ", ".join(f"{(t - t0) * 1e-9:.1f}" for t in st["recovery_t_ns"][:8])
            more = " ..." if len(st["recovery_t_ns"]) > 8 else ""
            ctx.warn(f"EKF: recovered {st['recoveries']} time(s) after {p.recovery.after} rejected velocity updates "
                     f"in a row (covariance inflated; at {when}{more} s)"
                     + (f", re-initialised {st['reinitialisations']} time(s) from a non-finite state"
                        if st["reinitialisations"] else ""))
        if st.get("recoveries_declined"):
            ctx.console.print(f"[dim]odometry: {st['recoveries_declined']} rejection streak(s) of scattered "
                              f"ego-velocities (radar outliers) kept rejected, not recovered from[/]")
        n_level = st.get("level_rejected", 0)
        if p.height.level_velocity_sigma > 0 and total and n_level / total > p.reject_warn_share:
            ctx.warn(f"EKF: the level prior (odometry.height.level_velocity_sigma={p.height.level_velocity_sigma:g}) "
                     f"was rejected by the gate at {n_level} of {total} scans: the platform climbs; set "
                     f"odometry.height.level_velocity_sigma=0 for a log that is not level on average")
        still = st.get("standstill")
        if still:
            ctx.console.print(f"[dim]odometry: started from a {still['seconds']} s standstill (gyro noise "
                              f"{still['gyro_noise_density']:.2g} rad/s/sqrt(Hz), accel "
                              f"{still['accel_noise_density']:.2g} m/s^2/sqrt(Hz))[/]")

    def _from_bag(self, ctx: StageContext
                  ) -> tuple[npt.NDArray[Any], npt.NDArray[np.int64], npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
        path = ctx.input_dirs["ingest"] / "bag_odometry.parquet"
        if not path.exists():
            raise UserError(f"{path}: the log has no odometry topic; name one in the dataset profile or with "
                            f"--set ingest.topics.odometry=TOPIC, or use --set odometry.source=ekf")
        odo = read_artifact(path, "groundtruth")
        radar = read_artifact(ctx.input("ingest", "radar.parquet"), "radar", columns=["scan", "t_ns"])
        scans, first = np.unique(radar["scan"].to_numpy(), return_index=True)
        scan_t = radar["t_ns"].to_numpy()[first]
        if odo.num_rows == 0:
            raise UserError(f"{path}: the odometry topic holds no messages")
        T, inside = interpolate_poses(odo["t_ns"].to_numpy(), np.stack([odo[c].to_numpy() for c in POSE_COLS], 1),
                                      scan_t)
        if (~inside).any():
            ctx.warn(f"{int((~inside).sum())} radar scan(s) outside the odometry topic's time span (held)")
        ctx.stats["bag_odometry_messages"] = odo.num_rows
        return scans, scan_t, T, inside


STAGE = OdometryStage()


def cov_columns(n: int, std_xy: float = 0.01, std_yaw: float = 0.002) -> dict[str, npt.NDArray[np.float64]]:
    """The ``cov_*`` columns of an odometry artifact with a diagonal increment covariance (fixtures, tools)."""
    cov = np.zeros((n, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = std_xy ** 2
    cov[:, 2, 2] = std_yaw ** 2
    cov[:1] = 0.0
    return {c: cov[:, i, j] for c, (i, j) in zip(COV_COLS, _COV_IDX, strict=True)}
