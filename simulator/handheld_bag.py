"""Write a handheld-rig run (simulator.handheld) as a ROS1 bag: radar and IMU only, clocks as the real log's.

Radar: ``sensor_msgs/PointCloud2`` on the rig's radar topic, TI PointXYZIV layout (x y z intensity
velocity), an empty frame_id and a zero header stamp (the record time is the scan time plus the driver
latency). IMU: ``sensor_msgs/Imu`` stamped on another clock (record time + ``imu_clock_offset_s``). No
tf, lidar or ground truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from simulator import rig
from simulator.bagwriter import BagWriter
from simulator.handheld import TI_RADAR_DTYPE, HandheldRig
from simulator.simulate import NS, Simulation, Window


class HandheldBagWriter(BagWriter):
    """Streams the windows of a handheld simulation into a ROS1 bag."""

    def __init__(self, path: Path, sim: Simulation) -> None:
        h = sim.handheld
        assert h is not None
        self.h: HandheldRig = h
        self.sim = sim
        self.CONNECTIONS = (
            (h.imu_topic, "sensor_msgs/msg/Imu", "/imu_node", 0),
            (h.radar_topic, "sensor_msgs/msg/PointCloud2", "/ti_mmwave/ti_mmwave", 0),
        )
        super().__init__(path, sim.seed, sim.imu_p)

    def add(self, w: Window) -> None:
        T, h, sim = self.T, self.h, self.sim
        epoch = rig.EPOCH_S * NS
        for scan in w.radar:
            rec = epoch + int(sim.radar_record_ns[scan.index])
            stamp = 0 if h.radar_zero_stamps else epoch + int(sim.radar_ns[scan.index])
            arr = np.zeros(len(scan.points), dtype=TI_RADAR_DTYPE)
            for c in ("x", "y", "z", "intensity"):
                arr[c] = scan.points[c]
            arr["velocity"] = scan.points["doppler"]
            self._push(h.radar_topic, rec, self._cloud(h.radar_topic, stamp, h.radar_frame_id, arr, 1, len(arr)))
        self.messages[h.radar_topic] += len(w.radar)

        p = self.imu_p
        vec3 = T["geometry_msgs/msg/Vector3"]
        no_orientation = np.zeros(9)
        no_orientation[0] = -1.0
        g_cov = np.diag([p.gyro_noise_density**2 * h.imu_rate_hz] * 3).ravel()
        a_cov = np.diag([p.accel_noise_density**2 * h.imu_rate_hz] * 3).ravel()
        quat0 = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        idx = np.searchsorted(sim.imu_ns, np.round(w.imu.t * NS).astype(np.int64))
        offset = round(h.imu_clock_offset_s * NS)
        for i, j in enumerate(idx.tolist()):
            rec = epoch + int(sim.imu_record_ns[j])
            a, g = w.imu.accel[i], w.imu.gyro[i]
            msg = T["sensor_msgs/msg/Imu"](
                header=self._header(h.imu_topic, epoch + int(sim.imu_ns[j]) + offset, h.imu_frame_id),
                orientation=quat0, orientation_covariance=no_orientation,
                angular_velocity=vec3(x=float(g[0]), y=float(g[1]), z=float(g[2])),
                angular_velocity_covariance=g_cov,
                linear_acceleration=vec3(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                linear_acceleration_covariance=a_cov,
            )
            self._push(h.imu_topic, rec, msg)
        self.messages[h.imu_topic] += len(w.imu.t)
        self._flush(epoch + w.t1_ns - NS // 2)
