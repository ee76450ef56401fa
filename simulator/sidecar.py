"""Ground truth that real data does not have, written beside the log (``X.bag`` -> ``X.sim/``, ``X/`` -> ``X/sim/``).

- ``radar_labels.parquet``: scan:int32 (message index on the radar topic = .bin file index), t_ns:int64
  (header stamp), point:int32 (index within the scan), label:int8 (0 surface return, 1 clutter false
  alarm, 2 multipath ghost), x_true, y_true, z_true: float32 (noise-free position in the radar frame;
  for ghosts the mirror image behind the wall, for clutter the reported position), cell_scatterers:int16
  (returns within 10 dB of the strongest in the point's range-Doppler cell: 1 for a lone scatterer);
- ``trajectory.parquet``: at every IMU sample, t_ns:int64, the base pose x y z qx qy qz qw (world <- base),
  world velocity vx vy vz and acceleration ax ay az, base-frame angular velocity wx wy wz, and the true
  IMU biases bgx bgy bgz bax bay baz, all float64;
- ``world.toml`` (the world file used) and ``meta.json`` (seed, duration, sensor parameters, rig, stats).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from simulator import rig
from simulator.params import radar_dump
from simulator.simulate import NS, Simulation, Window

LABEL_NAMES = {0: "surface", 1: "clutter", 2: "ghost"}


class SidecarWriter:
    def __init__(self, folder: Path, sim: Simulation) -> None:
        self.folder = folder
        self.sim = sim
        self.labels: list[dict[str, np.ndarray]] = []
        self.traj: list[dict[str, np.ndarray]] = []
        self.points_per_scan: list[int] = []
        self.label_counts = np.zeros(3, dtype=np.int64)

    def add(self, w: Window) -> None:
        epoch = rig.EPOCH_S * NS
        for scan in w.radar:
            n = len(scan.points)
            self.points_per_scan.append(n)
            self.label_counts += np.bincount(scan.labels, minlength=3)[:3]
            self.labels.append({
                "scan": np.full(n, scan.index, np.int32),
                "t_ns": np.full(n, epoch + self.sim.radar_stamp_ns(scan.index), np.int64),
                "point": np.arange(n, dtype=np.int32),
                "label": scan.labels.astype(np.int8),
                "x_true": scan.xyz_true[:, 0], "y_true": scan.xyz_true[:, 1], "z_true": scan.xyz_true[:, 2],
                "cell_scatterers": scan.cell_scatterers.astype(np.int16),
            })
        st = w.truth
        q = st.quaternion
        cols = {
            "t_ns": epoch + np.round(st.t * NS).astype(np.int64),
            "x": st.position[:, 0], "y": st.position[:, 1], "z": st.position[:, 2],
            "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3],
            "vx": st.velocity[:, 0], "vy": st.velocity[:, 1], "vz": st.velocity[:, 2],
            "ax": st.acceleration[:, 0], "ay": st.acceleration[:, 1], "az": st.acceleration[:, 2],
            "wx": np.zeros_like(st.yaw_rate), "wy": np.zeros_like(st.yaw_rate), "wz": st.yaw_rate,
        }
        for i, name in enumerate(("bgx", "bgy", "bgz", "bax", "bay", "baz")):
            cols[name] = w.imu.bias[:, i]
        self.traj.append(cols)

    @staticmethod
    def _table(parts: list[dict[str, np.ndarray]], empty: dict[str, Any]) -> pa.Table:
        if not parts:
            return pa.table({k: pa.array([], type=v) for k, v in empty.items()})
        return pa.table({k: np.concatenate([p[k] for p in parts]) for k in parts[0]})

    def stats(self) -> dict[str, Any]:
        pps = np.asarray(self.points_per_scan)
        return {
            "radar_scans": len(pps),
            "points_per_scan": {
                "mean": float(pps.mean()) if len(pps) else 0.0, "median": float(np.median(pps)) if len(pps) else 0.0,
                "min": int(pps.min()) if len(pps) else 0, "max": int(pps.max()) if len(pps) else 0,
                "p05": float(np.percentile(pps, 5)) if len(pps) else 0.0,
                "p95": float(np.percentile(pps, 95)) if len(pps) else 0.0,
            },
            "labels": {LABEL_NAMES[i]: int(c) for i, c in enumerate(self.label_counts)},
        }

    def close(self, extra: dict[str, Any]) -> dict[str, Any]:
        self.folder.mkdir(parents=True, exist_ok=True)
        label_types = {"scan": pa.int32(), "t_ns": pa.int64(), "point": pa.int32(), "label": pa.int8(),
                       "x_true": pa.float32(), "y_true": pa.float32(), "z_true": pa.float32(),
                       "cell_scatterers": pa.int16()}
        pq.write_table(self._table(self.labels, label_types), self.folder / "radar_labels.parquet")
        pq.write_table(self._table(self.traj, {"t_ns": pa.int64()}), self.folder / "trajectory.parquet")
        (self.folder / "world.toml").write_text(self.sim.world.text)
        sim = self.sim
        meta = {
            "generator": "radar-pipeline simulator",
            "sidecar_version": 2,
            "world": sim.world.spec.name,
            "duration_s": sim.duration,
            "seed": sim.seed,
            "epoch_ns": rig.EPOCH_S * NS,
            "gravity": [0.0, 0.0, -sim.imu_p.gravity],
            "radar": radar_dump(sim.radar_p),
            "lidar": sim.lidar_p.model_dump(),
            "imu": sim.imu_p.model_dump(),
            "rates_hz": {"radar": rig.RADAR_RATE_HZ, "lidar": rig.LIDAR_RATE_HZ, "imu": rig.IMU_RATE_HZ,
                         "groundtruth": rig.GT_RATE_HZ, "tf": rig.TF_RATE_HZ},
            "rig": {f"{e.parent}<-{e.child}": {"translation": list(e.translation), "quaternion": list(e.quaternion)}
                    for e in (*rig.TF_TRANSFORMS, *rig.TF_STATIC_TRANSFORMS, rig.BASE_TO_LIDAR)},
            "stats": {**self.stats(), **extra},
            "scatterers": len(sim.scatterers),
        }
        drift = sim.drift_errors()
        if drift is not None:  # the true sensor errors of a drifting world (simulator.sensor_errors)
            meta["errors"] = drift
        if sim.handheld is not None:
            mount = sim.radar_mount
            meta["rates_hz"] = {"radar": sim.radar_rate, "imu": sim.imu_rate}
            meta["rig"] = {"handheld": sim.handheld.model_dump(),
                           f"{mount.parent}<-{mount.child}": {"translation": list(mount.translation),
                                                              "quaternion": list(mount.quaternion)}}
        (self.folder / "meta.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
        return meta
