"""Run a simulation: sensor timelines, then windows of radar, lidar, IMU and ground-truth data in time order.

Every random draw comes from ``np.random.default_rng([seed, stream, index])`` with a fixed stream per
sensor and the scan (or window) index, so results do not depend on how the run is chunked or threaded:
the same seed gives the same bytes.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from core.errors import UserError
from simulator import imu as imu_model
from simulator import lidar as lidar_model
from simulator import radar as radar_model
from simulator import rig
from simulator.handheld import HandheldRig, WalkingTrajectory, heel_strike
from simulator.params import ImuParams, LidarParams, RadarParams, make_params
from simulator.path_trajectory import PathTrajectory
from simulator.scatterers import Scatterers, build_scatterers
from simulator.sensor_errors import (
    MountError,
    SensorErrors,
    bias_instability,
    error_matrices,
    mount_error,
    rotate_points,
)
from simulator.trajectory import Trajectory, TrajectoryState
from simulator.twin import TwinWorld
from simulator.world import World

STREAM_TIMING, STREAM_RADAR, STREAM_LIDAR, STREAM_IMU, STREAM_IMU_BIAS, STREAM_LATENCY = 1, 2, 3, 4, 5, 6
STREAM_SCATTERERS = 7
STREAM_ERRORS, STREAM_VIBRATION, STREAM_RECORD_LATENCY = 8, 9, 10
STREAM_BIAS_INSTABILITY, STREAM_MOUNT = 11, 12

NS = 1_000_000_000


@dataclass(frozen=True)
class GtBlock:
    t: np.ndarray  # (n,) seconds
    position: np.ndarray  # (n, 3)
    quaternion: np.ndarray  # (n, 4) x y z w, world <- base


@dataclass(frozen=True)
class Window:
    index: int
    t0_ns: int  # window start, ns from the start of the run
    t1_ns: int
    radar: list[radar_model.RadarScan]
    lidar: list[lidar_model.LidarScan]
    imu: imu_model.ImuBlock
    truth: TrajectoryState  # ground truth at the IMU sample times
    gt: GtBlock
    tf_t: np.ndarray  # seconds of the /tf messages in this window


def _grid(start: float, period: float, end: float, jitter: np.ndarray | None = None) -> np.ndarray:
    n = max(0, int(np.floor((end - start) / period)) + 1)
    t = start + period * np.arange(n)
    if jitter is not None:
        t = t + jitter[:n]
    return t[(t >= 0) & (t < end)]


def _ns(t: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(t) * NS).astype(np.int64)


class Simulation:
    """All sensors of one run, driven by one trajectory in one world."""

    def __init__(self, world: World, duration: float, seed: int, window: float = 1.0, workers: int = 2) -> None:
        self.world = world
        self.duration = float(duration)
        self.seed = int(seed)
        self.window = float(window)
        self.workers = int(workers)
        where = str(world.path)
        self.radar_p: RadarParams = make_params(RadarParams, world.spec.radar, f"{where} [radar]")
        self.lidar_p: LidarParams = make_params(LidarParams, world.spec.lidar, f"{where} [lidar]")
        self.imu_p: ImuParams = make_params(ImuParams, world.spec.imu, f"{where} [imu]")
        self.errors: SensorErrors = make_params(SensorErrors, world.spec.errors, f"{where} [errors]")
        #: a handheld rig (simulator.handheld) instead of the ColoRadar one
        self.handheld: HandheldRig | None = (make_params(HandheldRig, world.spec.rig, f"{where} [rig]")
                                             if world.spec.rig else None)
        self.traj: Trajectory | PathTrajectory
        if isinstance(world, TwinWorld) and self.duration > world.duration + 1e-9:
            raise UserError(f"{where}: --duration {self.duration:g} s is longer than the recorded path "
                            f"({world.duration:g} s); simulate at most {world.duration:g} s")
        if self.handheld is not None:
            try:
                self.traj = WalkingTrajectory(world.spec.trajectory, self.duration, world.spec.floor, self.handheld)
            except ValueError as exc:
                raise UserError(f"{where}: {exc}") from None
            self.radar_mount = self.handheld.radar_mount()
            self.imu_mount = self.handheld.imu_mount()
            self.radar_rate, self.imu_rate = self.handheld.radar_rate_hz, self.handheld.imu_rate_hz
            self.radar_yaw = float(np.radians(self.handheld.radar_yaw_deg))
        else:
            self.traj = (world.trajectory if isinstance(world, TwinWorld)  # a recorded path in a voxel map
                         else Trajectory(world.spec.trajectory, self.duration, floor=world.spec.floor))
            self.radar_mount, self.imu_mount = rig.BASE_TO_RADAR, rig.BASE_TO_IMU
            self.radar_rate, self.imu_rate = rig.RADAR_RATE_HZ, rig.IMU_RATE_HZ
            self.radar_yaw = rig.yaw_of(rig.BASE_TO_RADAR)
        scat_rng = np.random.default_rng([self.seed, STREAM_SCATTERERS])
        self.scatterers: Scatterers = (world.scatterers(self.radar_p, scat_rng) if isinstance(world, TwinWorld)
                                       else build_scatterers(world.spec, self.radar_p, scat_rng))
        self.lidar_yaw = rig.yaw_of(rig.BASE_TO_LIDAR)
        self.error_mats = (error_matrices(self.errors, np.random.default_rng([self.seed, STREAM_ERRORS]))
                           if self.errors.active else None)
        #: the true radar mount against the stated one (``[errors]`` radar_mount_*), None: exact
        self.mount_error: MountError | None = (
            mount_error(self.errors, np.random.default_rng([self.seed, STREAM_MOUNT]))
            if self.errors.mount_active else None)

        rng = np.random.default_rng([self.seed, STREAM_TIMING])
        d = self.duration
        n_max = int(d * 300) + 10
        rj = np.clip(rng.normal(0, self.radar_p.time_jitter, n_max), -0.01, 0.01)
        gj = np.clip(rng.normal(0, 0.005, n_max), -0.02, 0.02)
        self.radar_ns = _ns(_grid(0.05, 1 / self.radar_rate, d, rj))
        sweep = 1 / rig.LIDAR_RATE_HZ
        self.lidar_ns = _ns(_grid(0.0, sweep, d - sweep + 1e-9))
        self.imu_ns = _ns(_grid(0.002, 1 / self.imu_rate, d))
        #: Gauss-Markov bias instability at the IMU samples (``[errors]``), None: off
        self._bias_gm = (bias_instability(self.errors, len(self.imu_ns), self.imu_rate,
                                          np.random.default_rng([self.seed, STREAM_BIAS_INSTABILITY]))
                         if self.errors.bias_instability_active else None)
        gt = _grid(0.08, 1 / rig.GT_RATE_HZ, d, gj)
        drop = rng.random(len(gt)) < 0.03
        drop[:1] = False
        self.gt_ns = _ns(gt[~drop])
        self.tf_ns = _ns(_grid(0.01, 1 / rig.TF_RATE_HZ, d))
        self.sweep = sweep
        self.n_windows = max(1, int(np.ceil(d / self.window - 1e-9)))
        self._bias0 = imu_model.initial_bias(self.imu_p, np.random.default_rng([self.seed, STREAM_IMU_BIAS]))
        if any(self.errors.gyro_bias):  # the unit's fixed zero-rate offset ([errors] gyro_bias)
            self._bias0[:3] += np.asarray(self.errors.gyro_bias, np.float64)
        self.radar_record_ns = self.radar_ns.copy()
        self.imu_record_ns = self.imu_ns.copy()
        if self.handheld is not None:
            h = self.handheld
            lat = np.random.default_rng([self.seed, STREAM_RECORD_LATENCY])
            r_lat = lat.uniform(h.radar_latency_s[0], h.radar_latency_s[1], size=len(self.radar_ns))
            i_lat = lat.uniform(h.imu_latency_s[0], h.imu_latency_s[1], size=len(self.imu_ns))
            self.radar_record_ns = self.radar_ns + _ns(r_lat)
            self.imu_record_ns = self.imu_ns + _ns(i_lat)
            assert isinstance(self.traj, WalkingTrajectory)
            self.steps = self.traj.step_times()

    def drift_errors(self) -> dict[str, object] | None:
        """The drawn radar time offset and mounting error and the bias instability settings (for the sidecar),
        None when none of them is set (the sidecar of such a world stays as it was)."""
        e, me = self.errors, self.mount_error
        if me is None and not e.bias_instability_active and not e.radar_time_offset_s:
            return None
        settings = e.model_dump()
        if not any(e.gyro_bias):  # added later: sidecars of worlds without it stay byte-identical
            settings.pop("gyro_bias")
        out: dict[str, object] = {"settings": settings, "radar_time_offset_s": e.radar_time_offset_s}
        if me is not None:
            out["radar_mount_rpy_deg"] = [float(v) for v in me.rotation.as_euler("xyz", degrees=True)]
            out["radar_mount_offset_m"] = [float(v) for v in me.offset]
        if self.error_mats is not None:
            out["gyro_matrix"], out["accel_matrix"] = (m.tolist() for m in self.error_mats)
        return out

    def radar_stamp_ns(self, index: int) -> int:
        """Time of radar scan ``index`` (ns from the start) as ingest will see it: the record time when the
        header stamps are zero (handheld rig), the header stamp otherwise."""
        if self.handheld is not None and self.handheld.radar_zero_stamps:
            return int(self.radar_record_ns[index])
        return int(self.radar_ns[index])

    # -------------------------------------------------------------------------------------------------------
    def _range(self, stamps: np.ndarray, k: int) -> np.ndarray:
        lo, hi = round(k * self.window * NS), round((k + 1) * self.window * NS)
        return np.nonzero((stamps >= lo) & (stamps < hi))[0]

    def radar_scans(self, k: int) -> list[radar_model.RadarScan]:
        idx = self._range(self.radar_ns, k)
        if not len(idx):
            return []
        t = self.radar_ns[idx] / NS
        off = self.errors.radar_time_offset_s  # the scan stamped t measured the scene at t - off
        st = self.traj.state(np.maximum(t - off, 0.0) if off else t)
        me = self.mount_error
        pos, vel, _ = st.sensor(self.radar_mount.t + me.offset if me is not None else self.radar_mount.t)
        scans = [
            radar_model.simulate_scan(self.world.scene, self.scatterers, self.radar_p, int(i), float(t[j]), pos[j],
                                      float(st.yaw[j] + self.radar_yaw), vel[j],
                                      np.random.default_rng([self.seed, STREAM_RADAR, int(i)]))
            for j, i in enumerate(idx)
        ]
        if me is not None:  # points as the truly mounted radar reports them
            for j, scan in enumerate(scans):
                pts, xyz = rotate_points(scan.points, scan.xyz_true, me)
                scans[j] = replace(scan, points=pts, xyz_true=xyz)
        if self.handheld is not None:
            scans = [self._handheld_scan(s) for s in scans]
        return scans

    def _handheld_scan(self, scan: radar_model.RadarScan) -> radar_model.RadarScan:
        """The handheld radar: points in its rotated (rolled) mount frame; empty during the dropout."""
        h = self.handheld
        assert h is not None
        if h.dropout_s > 0 and h.dropout_start_s <= scan.t < h.dropout_start_s + h.dropout_s:
            return replace(scan, points=scan.points[:0], labels=scan.labels[:0], xyz_true=scan.xyz_true[:0],
                           cell_scatterers=scan.cell_scatterers[:0])
        if h.radar_roll_deg == 180.0:  # published frame = level model frame rolled about x by 180 deg
            pts = scan.points.copy()
            pts["y"], pts["z"] = -pts["y"], -pts["z"]
            xyz = scan.xyz_true * np.array([1, -1, -1], np.float32)
            scan = replace(scan, points=pts, xyz_true=xyz)
        return scan

    def lidar_scans(self, k: int) -> list[lidar_model.LidarScan]:
        out: list[lidar_model.LidarScan] = []
        if self.handheld is not None:  # the handheld rig has no lidar
            return out
        w = self.lidar_p.columns
        for i in self._range(self.lidar_ns, k):
            t0 = self.lidar_ns[i] / NS
            tc = t0 + np.arange(w) * self.sweep / w
            st = self.traj.state(tc)
            pos, _, _ = st.sensor(rig.BASE_TO_LIDAR.t)
            out.append(lidar_model.simulate_scan(self.world.scene, self.lidar_p, int(i), float(t0), pos,
                                                 st.yaw + self.lidar_yaw, self.sweep,
                                                 np.random.default_rng([self.seed, STREAM_LIDAR, int(i)])))
        return out

    def _exteroceptive(self, k: int) -> tuple[list[radar_model.RadarScan], list[lidar_model.LidarScan]]:
        return self.radar_scans(k), self.lidar_scans(k)

    def windows(self) -> Iterator[Window]:
        """Windows in time order; radar and lidar ray casting runs ahead on a small thread pool."""
        bias = self._bias0
        with ThreadPoolExecutor(max_workers=max(1, self.workers)) as pool:
            ahead = max(1, self.workers)
            futures = {k: pool.submit(self._exteroceptive, k) for k in range(min(ahead, self.n_windows))}
            for k in range(self.n_windows):
                if k + ahead < self.n_windows:
                    futures[k + ahead] = pool.submit(self._exteroceptive, k + ahead)
                radar, lidar = futures.pop(k).result()
                ii = self._range(self.imu_ns, k)
                truth = self.traj.state(self.imu_ns[ii] / NS)
                extra = None
                if self.handheld is not None:
                    extra = heel_strike(truth.t, self.steps, self.handheld,
                                        np.random.default_rng([self.seed, STREAM_VIBRATION, k]))
                block, bias = imu_model.simulate_block(truth, self.imu_mount, self.imu_p, self.imu_rate, bias,
                                                       np.random.default_rng([self.seed, STREAM_IMU, k]),
                                                       extra=extra, errors=self.error_mats,
                                                       bias_extra=None if self._bias_gm is None
                                                       else self._bias_gm[ii])
                gi = self._range(self.gt_ns, k)
                gst = self.traj.state(self.gt_ns[gi] / NS)
                gt = GtBlock(t=gst.t, position=gst.position, quaternion=gst.quaternion)
                ti = self._range(self.tf_ns, k)
                yield Window(index=k, t0_ns=round(k * self.window * NS), t1_ns=round((k + 1) * self.window * NS),
                             radar=radar, lidar=lidar, imu=block, truth=truth, gt=gt, tf_t=self.tf_ns[ti] / NS)
