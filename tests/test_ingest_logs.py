"""Tiny ColoRadar-format logs for the ingest tests, written with rosbags' own writers and plain files.

``make_scene`` draws known values; ``write_log`` stores them as a ROS1 bag, a ROS2 bag (sqlite3 or
MCAP), a bare MCAP file or the extracted folder form, so every reader can be checked against the same
numbers. (No tests here: the helpers are imported by the test modules.)
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stages.ingest.pointcloud2 import Field, encode

RADAR_TOPIC = "/mmWaveDataHdl/RScan"
LIDAR_TOPIC = "/os1_cloud_node/points"
IMU_TOPIC = "/gx5/imu/data"
GT_TOPIC = "/lidar_ground_truth"
T0 = 1_600_000_000_000_000_000

# ColoRadar's TI driver point type: PCL 4D point (x y z + pad), intensity, range, doppler; 32 bytes
RADAR_LAYOUT = [Field("x", 0, 7), Field("y", 4, 7), Field("z", 8, 7), Field("intensity", 16, 7),
                Field("range", 20, 7), Field("doppler", 24, 7)]
# Ouster OS1 point type
LIDAR_LAYOUT = [Field("x", 0, 7), Field("y", 4, 7), Field("z", 8, 7), Field("intensity", 16, 7), Field("t", 20, 6),
                Field("reflectivity", 24, 4), Field("ring", 26, 2), Field("noise", 28, 4), Field("range", 32, 6)]

BASE_FROM_RADAR = ((-0.145, 0.09, -0.025), (0.0, 0.0, 0.7068, 0.7074))
BASE_FROM_IMU = ((0.01, -0.02, 0.03), (0.0, 0.0, 0.0, 1.0))
BASE_FROM_OS1 = ((0.0, 0.1, 0.2), (0.0, 0.0, 0.0, 1.0))
OS1_FROM_LIDAR = ((0.0, 0.0, 0.03618), (0.0, 0.0, 1.0, 0.0))


@dataclass
class Scene:
    radar: list[tuple[int, dict[str, np.ndarray]]] = field(default_factory=list)
    lidar: list[tuple[int, dict[str, np.ndarray]]] = field(default_factory=list)
    imu_t: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    imu: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    gt_t: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    gt: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))


def make_scene(n_radar: int = 6, n_lidar: int = 4, n_imu: int = 40, n_gt: int = 6, seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    sc = Scene()
    for i in range(n_radar):
        n = 3 + i
        cols = {k: rng.normal(size=n).astype(np.float32) for k in ("x", "y", "z", "intensity", "doppler")}
        sc.radar.append((T0 + i * 100_000_000 + 7, cols))
    for i in range(n_lidar):
        n = 50 + 10 * i
        cols = {k: rng.normal(size=n).astype(np.float32) for k in ("x", "y", "z", "intensity")}
        sc.lidar.append((T0 + i * 100_000_000 + 50_000_000, cols))
    sc.imu_t = T0 + np.arange(n_imu, dtype=np.int64) * 3_333_333
    sc.imu = rng.normal(size=(n_imu, 6))
    sc.gt_t = T0 + np.arange(n_gt, dtype=np.int64) * 100_000_000 + 1_000
    q = rng.normal(size=(n_gt, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, 3:] < 0, -1, 1)
    sc.gt = np.hstack([rng.normal(size=(n_gt, 3)), q])
    return sc


# -- rosbags messages ------------------------------------------------------------------------------------------------
def _header(ts: Any, t_ns: int, frame: str, ros1: bool) -> Any:
    H = ts.types["std_msgs/msg/Header"]
    T = ts.types["builtin_interfaces/msg/Time"]
    stamp = T(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
    return H(seq=0, stamp=stamp, frame_id=frame) if ros1 else H(stamp=stamp, frame_id=frame)


def cloud_msg(ts: Any, t_ns: int, frame: str, cols: dict[str, np.ndarray], layout: list[Field], point_step: int,
              ros1: bool, big_endian: bool = False, height: int = 1, row_pad: int = 0) -> Any:
    PF = ts.types["sensor_msgs/msg/PointField"]
    n = len(cols["x"])
    data = encode(cols, layout, point_step, big_endian)
    width = n // height
    if row_pad:
        rows = [data[r * width * point_step:(r + 1) * width * point_step] + b"\xee" * row_pad for r in range(height)]
        data = b"".join(rows)
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, t_ns, frame, ros1), height=height, width=width,
        fields=[PF(name=f.name, offset=f.offset, datatype=f.datatype, count=1) for f in layout],
        is_bigendian=big_endian, point_step=point_step, row_step=width * point_step + row_pad,
        data=np.frombuffer(data, np.uint8), is_dense=True)


def imu_msg(ts: Any, t_ns: int, v: np.ndarray, ros1: bool) -> Any:
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    return ts.types["sensor_msgs/msg/Imu"](
        header=_header(ts, t_ns, "gx5_link", ros1), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=V3(x=v[3], y=v[4], z=v[5]),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=V3(x=v[0], y=v[1], z=v[2]),
        linear_acceleration_covariance=np.zeros(9))


def odom_msg(ts: Any, t_ns: int, v: np.ndarray, ros1: bool, child: str = "imu_viz_link") -> Any:
    P = ts.types["geometry_msgs/msg/Point"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    pose = ts.types["geometry_msgs/msg/Pose"](position=P(x=v[0], y=v[1], z=v[2]),
                                               orientation=Q(x=v[3], y=v[4], z=v[5], w=v[6]))
    twist = ts.types["geometry_msgs/msg/Twist"](linear=V3(x=0.0, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0))
    return ts.types["nav_msgs/msg/Odometry"](
        header=_header(ts, t_ns, "world", ros1), child_frame_id=child,
        pose=ts.types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))


def tf_msg(ts: Any, t_ns: int, ros1: bool) -> Any:
    TS = ts.types["geometry_msgs/msg/TransformStamped"]
    Tr = ts.types["geometry_msgs/msg/Transform"]
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    out = []
    for parent, child, (t, q) in (("imu_viz_link", "base_radar_link", BASE_FROM_RADAR),
                                  ("imu_viz_link", "gx5_link", BASE_FROM_IMU),
                                  ("imu_viz_link", "os1_sensor", BASE_FROM_OS1),
                                  ("os1_sensor", "os1_lidar", OS1_FROM_LIDAR)):
        out.append(TS(header=_header(ts, t_ns, parent, ros1), child_frame_id=child,
                      transform=Tr(translation=V3(x=t[0], y=t[1], z=t[2]), rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3]))))
    return ts.types["tf2_msgs/msg/TFMessage"](transforms=out)


def messages(sc: Scene, ts: Any, ros1: bool, radar_topic: str = RADAR_TOPIC, big_endian: bool = False,
             skip: tuple[str, ...] = ()) -> list[tuple[str, str, int, Any]]:
    """(topic, msgtype, record time, message) sorted by record time."""
    out: list[tuple[str, str, int, Any]] = [("/tf_static", "tf2_msgs/msg/TFMessage", T0 - 1, tf_msg(ts, T0 - 1, ros1))]
    for t, cols in sc.radar:
        out.append((radar_topic, "sensor_msgs/msg/PointCloud2", t,
                    cloud_msg(ts, t, "base_radar_link", cols, RADAR_LAYOUT, 32, ros1, big_endian)))
    for t, cols in sc.lidar:
        out.append((LIDAR_TOPIC, "sensor_msgs/msg/PointCloud2", t,
                    cloud_msg(ts, t, "os1_lidar", cols, LIDAR_LAYOUT, 48, ros1)))
    for t, v in zip(sc.imu_t, sc.imu, strict=True):
        out.append((IMU_TOPIC, "sensor_msgs/msg/Imu", int(t), imu_msg(ts, int(t), v, ros1)))
    for t, v in zip(sc.gt_t, sc.gt, strict=True):
        out.append((GT_TOPIC, "nav_msgs/msg/Odometry", int(t), odom_msg(ts, int(t), v, ros1)))
    out = [m for m in out if m[0] not in skip]
    out.sort(key=lambda m: m[2])
    return out


def typestore(ros1: bool) -> Any:
    """The ROS1 Noetic or ROS2 Humble typestore plus tf2_msgs/TFMessage."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


def write_log(path: Path, sc: Scene, form: str, **kw: Any) -> Path:
    """Write ``sc`` as ``form`` in {ros1, ros2, mcap, bare_mcap, folder}; return the path to ingest."""
    if form == "folder":
        return write_folder(path, sc)
    ros1 = form == "ros1"
    ts = typestore(ros1)
    msgs = messages(sc, ts, ros1, **kw)
    if ros1:
        from rosbags.rosbag1 import Writer as W1

        bag = path.with_suffix(".bag")
        with W1(bag) as w:
            conns: dict[str, Any] = {}
            for topic, typ, t, msg in msgs:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, typ, typestore=ts)
                w.write(conns[topic], t, ts.serialize_ros1(msg, typ))
        return bag
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as W2

    plugin = StoragePlugin.SQLITE3 if form == "ros2" else StoragePlugin.MCAP
    with W2(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, typ, t, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], t, ts.serialize_cdr(msg, typ))
    if form == "bare_mcap":
        inner = next(path.glob("*.mcap"))
        bare = path.parent / f"{path.name}_bare.mcap"
        shutil.move(inner, bare)
        shutil.rmtree(path)
        return bare
    return path


def _stamps(t: np.ndarray) -> str:
    return "".join(f"{int(x) // 1_000_000_000}.{int(x) % 1_000_000_000:09d}\n" for x in t)


def write_folder(path: Path, sc: Scene) -> Path:
    for sub in ("single_chip/pointclouds/data", "lidar/pointclouds", "imu", "groundtruth", "calib/transforms"):
        (path / sub).mkdir(parents=True, exist_ok=True)
    (path / "single_chip/pointclouds/timestamps.txt").write_text(_stamps(np.array([t for t, _ in sc.radar])))
    for i, (_, c) in enumerate(sc.radar):
        arr = np.stack([c[k] for k in ("x", "y", "z", "intensity", "doppler")], axis=1).astype("<f4")
        (path / f"single_chip/pointclouds/data/radar_pointcloud_{i}.bin").write_bytes(arr.tobytes())
    (path / "lidar/timestamps.txt").write_text(_stamps(np.array([t for t, _ in sc.lidar])))
    for i, (_, c) in enumerate(sc.lidar):
        arr = np.stack([c[k] for k in ("x", "y", "z", "intensity")], axis=1).astype("<f4")
        (path / f"lidar/pointclouds/lidar_pointcloud_{i}.bin").write_bytes(arr.tobytes())
    (path / "imu/timestamps.txt").write_text(_stamps(sc.imu_t))
    np.savetxt(path / "imu/imu_data.txt", sc.imu, fmt="%.17g")
    (path / "groundtruth/timestamps.txt").write_text(_stamps(sc.gt_t))
    np.savetxt(path / "groundtruth/groundtruth_poses.txt", sc.gt, fmt="%.17g")
    from core.geometry import matrices_to_poses, pose_matrix

    lidar = pose_matrix(*BASE_FROM_OS1) @ pose_matrix(*OS1_FROM_LIDAR)
    lt = matrices_to_poses(lidar[None])[0]
    for name, (t, q) in (("base_to_single_chip", BASE_FROM_RADAR), ("base_to_imu", BASE_FROM_IMU),
                         ("base_to_lidar", (tuple(lt[:3]), tuple(lt[3:])))):
        (path / f"calib/transforms/{name}.txt").write_text(" ".join(repr(float(x)) for x in t) + "\n"
                                                             + " ".join(repr(float(x)) for x in q) + "\n")
    return path
