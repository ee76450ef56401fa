"""Write a simulated run in the extracted ColoRadar folder form (what the dataset's bag_to_dataset script makes).

Binary clouds are raw little-endian float32 rows (radar ``x y z intensity doppler``, lidar ``x y z
intensity``), one file per message numbered from 0; timestamps are ``'%6f' % header.stamp.to_sec()``;
IMU and pose lines are Python ``str(float)`` values separated by single spaces. See coloradar.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import TextIO

import numpy as np

from simulator import rig
from simulator.simulate import NS, Window

_PATHS = {
    "radar": "single_chip/pointclouds/data",
    "lidar": "lidar/pointclouds",
    "imu": "imu",
    "gt": "groundtruth",
}


def to_sec_str(stamp_ns: int) -> str:
    """``'%6f' % stamp.to_sec()`` as rospy computes it (float(secs) + float(nsecs) / 1e9)."""
    return "%6f" % (float(stamp_ns // NS) + float(stamp_ns % NS) / 1e9)


def _line(values: np.ndarray) -> str:
    return " ".join(str(v) for v in values.tolist()) + "\n"


class FolderWriter:
    """Streams simulation windows into ``root/`` (calibration goes to ``root/calib`` on close)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        for sub in _PATHS.values():
            (root / sub).mkdir(parents=True, exist_ok=True)
        self.files: dict[str, TextIO] = {
            "radar_t": (root / "single_chip/pointclouds/timestamps.txt").open("w"),
            "lidar_t": (root / "lidar/timestamps.txt").open("w"),
            "imu_t": (root / "imu/timestamps.txt").open("w"),
            "imu": (root / "imu/imu_data.txt").open("w"),
            "gt_t": (root / "groundtruth/timestamps.txt").open("w"),
            "gt": (root / "groundtruth/groundtruth_poses.txt").open("w"),
        }
        self.n_radar = 0
        self.n_lidar = 0

    def add(self, w: Window) -> None:
        epoch = rig.EPOCH_S * NS
        f = self.files
        for scan in w.radar:
            rows = np.column_stack([scan.points[k] for k in ("x", "y", "z", "intensity", "doppler")]).astype("<f4")
            rows.tofile(self.root / _PATHS["radar"] / f"radar_pointcloud_{self.n_radar}.bin")
            f["radar_t"].write(to_sec_str(epoch + round(scan.t * NS)) + "\n")
            self.n_radar += 1
        for cloud in w.lidar:
            c = cloud.cloud
            rows = np.column_stack([c[k] for k in ("x", "y", "z", "intensity")]).astype("<f4")
            rows.tofile(self.root / _PATHS["lidar"] / f"lidar_pointcloud_{self.n_lidar}.bin")
            f["lidar_t"].write(to_sec_str(epoch + round(cloud.t * NS)) + "\n")
            self.n_lidar += 1
        imu = np.column_stack([w.imu.accel, w.imu.gyro])
        for i, t in enumerate(w.imu.t.tolist()):
            f["imu_t"].write(to_sec_str(epoch + round(t * NS)) + "\n")
            f["imu"].write(_line(imu[i]))
        poses = np.column_stack([w.gt.position, w.gt.quaternion])
        for i, t in enumerate(w.gt.t.tolist()):
            f["gt_t"].write(to_sec_str(epoch + round(t * NS)) + "\n")
            f["gt"].write(_line(poses[i]))

    def close(self) -> None:
        from simulator.calib import write_calib

        for fh in self.files.values():
            fh.close()
        write_calib(self.root / "calib")
