"""The ColoRadar sensor rig: frame names, topics, extrinsics and rates (see data/datasets/coloradar.md).

Extrinsics are ``base <- sensor`` (a point in the sensor frame maps to the base frame as ``R p + t``),
exactly what the ``/tf`` transforms ``imu_viz_link -> child`` and the ``calib/transforms/base_to_*.txt``
files hold. Values for the radar, cascade and lidar mounts are copied from ``/tf`` dumps of the real
bags; the IMU mount is not published anywhere we could find and is assumed to coincide with the base.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

BASE_FRAME = "imu_viz_link"
WORLD_FRAME = "world"
RADAR_FRAME = "base_radar_link"
CASCADE_FRAME = "cascade_link"
IMU_FRAME = "gx5_link"
LIDAR_SENSOR_FRAME = "os1_sensor"
LIDAR_FRAME = "os1_lidar"

RADAR_TOPIC = "/mmWaveDataHdl/RScan"
LIDAR_TOPIC = "/os1_cloud_node/points"
IMU_TOPIC = "/gx5/imu/data"
GT_TOPIC = "/lidar_ground_truth"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

RADAR_RATE_HZ = 10.0
LIDAR_RATE_HZ = 10.0
IMU_RATE_HZ = 300.0
GT_RATE_HZ = 10.0
TF_RATE_HZ = 10.0  # ROS1 tf static_transform_publisher default period: 100 ms

#: first header stamp of a simulated run (2021-01-01T00:00:00Z), like the real bags' Unix stamps
EPOCH_S = 1_609_459_200


@dataclass(frozen=True)
class Extrinsic:
    parent: str
    child: str
    translation: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]  # x, y, z, w

    @property
    def rotation(self) -> Rotation:
        return Rotation.from_quat(self.quaternion)

    @property
    def t(self) -> np.ndarray:
        return np.asarray(self.translation, dtype=np.float64)

    def matrix(self) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = self.rotation.as_matrix()
        out[:3, 3] = self.t
        return out

    def compose(self, other: Extrinsic) -> Extrinsic:
        """``self`` (a <- b) then ``other`` (b <- c) gives a <- c."""
        t = self.t + self.rotation.apply(other.t)
        q = (self.rotation * other.rotation).as_quat()
        q = q * (1.0 if q[3] >= 0 else -1.0)
        return Extrinsic(self.parent, other.child, tuple(float(v) for v in t), tuple(float(v) for v in q))  # type: ignore[arg-type]


_Q_RADAR = (0.0, 0.0, 0.706825181105366, 0.7073882691671998)
BASE_TO_RADAR = Extrinsic(BASE_FRAME, RADAR_FRAME, (-0.145, 0.09, -0.025), _Q_RADAR)
BASE_TO_CASCADE = Extrinsic(BASE_FRAME, CASCADE_FRAME, (0.03, 0.12, -0.09), _Q_RADAR)
BASE_TO_LIDAR_SENSOR = Extrinsic(
    BASE_FRAME, LIDAR_SENSOR_FRAME, (-0.075, -0.02, 0.0), (0.0, 0.0, 0.6925369985634015, 0.7213823574366062)
)
#: Ouster OS1 sensor -> lidar frame (fixed by the driver; /tf_static in the bags)
LIDAR_SENSOR_TO_LIDAR = Extrinsic(LIDAR_SENSOR_FRAME, LIDAR_FRAME, (0.0, 0.0, 0.03618), (0.0, 0.0, 1.0, 0.0))
BASE_TO_LIDAR = BASE_TO_LIDAR_SENSOR.compose(LIDAR_SENSOR_TO_LIDAR)
#: assumption (no public value found): the GX5 frame coincides with the base frame
BASE_TO_IMU = Extrinsic(BASE_FRAME, IMU_FRAME, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

#: transforms published on /tf (periodically, like the recording rig's static_transform_publisher nodes)
TF_TRANSFORMS = (BASE_TO_RADAR, BASE_TO_IMU, BASE_TO_CASCADE, BASE_TO_LIDAR_SENSOR)
#: transforms published once, latched, on /tf_static (the Ouster driver's sensor -> lidar transform)
TF_STATIC_TRANSFORMS = (LIDAR_SENSOR_TO_LIDAR,)


def yaw_of(ext: Extrinsic) -> float:
    """Yaw (about z) of a mount that is a pure rotation about z (all rig mounts are)."""
    x, y, z, w = ext.quaternion
    if abs(x) > 1e-9 or abs(y) > 1e-9:
        raise ValueError(f"{ext.child}: mount is not a pure yaw rotation")
    return float(2.0 * np.arctan2(z, w))
