"""Write a simulated run as a ColoRadar ROS1 bag (rosbags, ROS1 Noetic message types).

Topics, types, frames and PointCloud2 layouts are those of the real dataset (data/datasets/coloradar.md).
Header stamps are sensor time; the bag's record time is the stamp plus a small, realistic delivery
latency (the lidar cloud is published after its 100 ms sweep). Messages are written in record-time order.
"""

from __future__ import annotations

import heapq
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from simulator import rig
from simulator.lidar import LIDAR_DTYPE
from simulator.params import ImuParams
from simulator.radar import RADAR_DTYPE
from simulator.simulate import NS, STREAM_LATENCY, Window

FLOAT32, UINT8, UINT16, UINT32 = 7, 2, 4, 6
_DATATYPES = {np.dtype("<f4"): FLOAT32, np.dtype("u1"): UINT8, np.dtype("<u2"): UINT16, np.dtype("<u4"): UINT32}


def coloradar_typestore() -> Typestore:
    """ROS1 Noetic types plus tf2_msgs/TFMessage (same definition and md5 as ROS)."""
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


class BagWriter:
    """Streams simulation windows into a ROS1 bag."""

    # (topic, type, callerid, latching); written in this order when record times tie
    CONNECTIONS: tuple[tuple[str, str, str, int], ...] = (
        (rig.TF_STATIC_TOPIC, "tf2_msgs/msg/TFMessage", "/os1_node", 1),
        (rig.TF_TOPIC, "tf2_msgs/msg/TFMessage", "/static_tf_publishers", 0),
        (rig.IMU_TOPIC, "sensor_msgs/msg/Imu", "/gx5/microstrain_3dm_gx5_node", 0),
        (rig.RADAR_TOPIC, "sensor_msgs/msg/PointCloud2", "/mmWave_Manager", 0),
        (rig.LIDAR_TOPIC, "sensor_msgs/msg/PointCloud2", "/os1_cloud_node", 0),
        (rig.GT_TOPIC, "nav_msgs/msg/Odometry", "/lidar_ground_truth_publisher", 0),
    )

    def __init__(self, path: Path, seed: int, imu_params: ImuParams) -> None:
        self.ts = coloradar_typestore()
        self.T = self.ts.types
        self.seed = seed
        self.imu_p = imu_params
        self.writer = Writer(path)
        self.writer.open()
        self.conns = {}
        self.order = {}
        for i, (topic, msgtype, callerid, latching) in enumerate(self.CONNECTIONS):
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts, callerid=callerid,
                                                           latching=latching)
            self.order[topic] = i
        self.seq: dict[str, int] = defaultdict(int)
        self.heap: list[tuple[int, int, int, bytes]] = []
        self.counter = 0
        self.static_done = False
        self.messages: dict[str, int] = defaultdict(int)

    # -- message helpers ---------------------------------------------------------------------------------
    def _header(self, topic: str, stamp_ns: int, frame: str) -> Any:
        seq = self.seq[topic]
        self.seq[topic] += 1
        return self.T["std_msgs/msg/Header"](
            seq=seq, stamp=self.T["builtin_interfaces/msg/Time"](sec=stamp_ns // NS, nanosec=stamp_ns % NS),
            frame_id=frame,
        )

    def _push(self, topic: str, record_ns: int, msg: Any) -> None:
        data = self.ts.serialize_ros1(msg, msg.__msgtype__)
        heapq.heappush(self.heap, (record_ns, self.order[topic], self.counter, bytes(data)))
        self.counter += 1

    def _fields(self, dtype: np.dtype) -> list[Any]:
        pf = self.T["sensor_msgs/msg/PointField"]
        assert dtype.fields is not None
        return [pf(name=n, offset=f[1], datatype=_DATATYPES[f[0]], count=1) for n, f in dtype.fields.items()]

    def _cloud(self, topic: str, stamp_ns: int, frame: str, arr: np.ndarray, height: int, width: int) -> Any:
        return self.T["sensor_msgs/msg/PointCloud2"](
            header=self._header(topic, stamp_ns, frame), height=height, width=width,
            fields=self._fields(arr.dtype), is_bigendian=False, point_step=arr.dtype.itemsize,
            row_step=arr.dtype.itemsize * width, data=np.frombuffer(arr.tobytes(), dtype=np.uint8), is_dense=True,
        )

    def _tf(self, topic: str, stamp_ns: int, transforms: tuple[rig.Extrinsic, ...]) -> Any:
        T = self.T
        out = []
        for e in transforms:
            hdr = T["std_msgs/msg/Header"](
                seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // NS, nanosec=stamp_ns % NS),
                frame_id=e.parent,
            )
            tr = T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=e.translation[0], y=e.translation[1], z=e.translation[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=e.quaternion[0], y=e.quaternion[1], z=e.quaternion[2],
                                                           w=e.quaternion[3]),
            )
            out.append(T["geometry_msgs/msg/TransformStamped"](header=hdr, child_frame_id=e.child, transform=tr))
        return T["tf2_msgs/msg/TFMessage"](transforms=out)

    # -- windows ---------------------------------------------------------------------------------------------
    def add(self, w: Window) -> None:
        T = self.T
        rng = np.random.default_rng([self.seed, STREAM_LATENCY, w.index])
        epoch = rig.EPOCH_S * NS

        def stamp(t: float) -> int:
            return epoch + round(t * NS)

        if not self.static_done:
            self._push(rig.TF_STATIC_TOPIC, epoch, self._tf(rig.TF_STATIC_TOPIC, epoch, rig.TF_STATIC_TRANSFORMS))
            self.messages[rig.TF_STATIC_TOPIC] += 1
            self.static_done = True
        for t in w.tf_t:
            s = stamp(float(t))
            self._push(rig.TF_TOPIC, s, self._tf(rig.TF_TOPIC, s, rig.TF_TRANSFORMS))
        self.messages[rig.TF_TOPIC] += len(w.tf_t)

        for scan in w.radar:
            s = stamp(scan.t)
            msg = self._cloud(rig.RADAR_TOPIC, s, rig.RADAR_FRAME, scan.points, 1, len(scan.points))
            self._push(rig.RADAR_TOPIC, s + int(rng.uniform(4e6, 9e6)), msg)
        self.messages[rig.RADAR_TOPIC] += len(w.radar)

        for cloud in w.lidar:
            s = stamp(cloud.t)
            assert cloud.cloud.dtype == LIDAR_DTYPE and RADAR_DTYPE.itemsize == 32
            msg = self._cloud(rig.LIDAR_TOPIC, s, rig.LIDAR_FRAME, cloud.cloud, cloud.height, cloud.width)
            self._push(rig.LIDAR_TOPIC, s + round(NS / rig.LIDAR_RATE_HZ) + int(rng.uniform(5e6, 15e6)), msg)
        self.messages[rig.LIDAR_TOPIC] += len(w.lidar)

        p = self.imu_p
        g_var = (p.gyro_noise_density**2) * rig.IMU_RATE_HZ
        a_var = (p.accel_noise_density**2) * rig.IMU_RATE_HZ
        vec3 = T["geometry_msgs/msg/Vector3"]
        no_orientation = np.zeros(9)
        no_orientation[0] = -1.0
        g_cov = np.diag([g_var] * 3).ravel()
        a_cov = np.diag([a_var] * 3).ravel()
        quat0 = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        lat = rng.uniform(0.5e6, 1.5e6, len(w.imu.t)).astype(np.int64)
        for i, t in enumerate(w.imu.t.tolist()):
            s = stamp(t)
            a, g = w.imu.accel[i], w.imu.gyro[i]
            msg = T["sensor_msgs/msg/Imu"](
                header=self._header(rig.IMU_TOPIC, s, rig.IMU_FRAME), orientation=quat0,
                orientation_covariance=no_orientation,
                angular_velocity=vec3(x=float(g[0]), y=float(g[1]), z=float(g[2])),
                angular_velocity_covariance=g_cov,
                linear_acceleration=vec3(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                linear_acceleration_covariance=a_cov,
            )
            self._push(rig.IMU_TOPIC, s + int(lat[i]), msg)
        self.messages[rig.IMU_TOPIC] += len(w.imu.t)

        zeros36 = np.zeros(36)
        for i, t in enumerate(w.gt.t.tolist()):
            s = stamp(t)
            pos, q = w.gt.position[i], w.gt.quaternion[i]
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=float(pos[0]), y=float(pos[1]), z=float(pos[2])),
                orientation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                              w=float(q[3])),
            )
            twist = T["geometry_msgs/msg/Twist"](linear=vec3(x=0.0, y=0.0, z=0.0), angular=vec3(x=0.0, y=0.0, z=0.0))
            msg = T["nav_msgs/msg/Odometry"](
                header=self._header(rig.GT_TOPIC, s, rig.WORLD_FRAME), child_frame_id=rig.BASE_FRAME,
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=zeros36),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=zeros36),
            )
            self._push(rig.GT_TOPIC, s, msg)
        self.messages[rig.GT_TOPIC] += len(w.gt.t)
        self._flush(epoch + w.t1_ns - NS // 2)

    def _flush(self, upto_ns: int | None) -> None:
        while self.heap and (upto_ns is None or self.heap[0][0] < upto_ns):
            rec, order, _, data = heapq.heappop(self.heap)
            self.writer.write(self.conns[self.CONNECTIONS[order][0]], rec, data)

    def close(self) -> None:
        self._flush(None)
        self.writer.close()
