"""The simulator writes real ColoRadar formats: checked with independent readers (rosbags AnyReader, numpy)."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from tests.test_simulator_reference import cloud_array, read_bag, simulated, stamp_ns, transforms

FLOAT32, UINT8, UINT16, UINT32 = 7, 2, 4, 6
RADAR_FIELDS = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 16, FLOAT32),
                ("range", 20, FLOAT32), ("doppler", 24, FLOAT32)]
LIDAR_FIELDS = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 16, FLOAT32),
                ("t", 20, UINT32), ("reflectivity", 24, UINT16), ("ring", 26, UINT8), ("noise", 28, UINT16),
                ("range", 32, UINT32)]
TOPICS = {
    "/mmWaveDataHdl/RScan": ("sensor_msgs/msg/PointCloud2", "base_radar_link", 10.0),
    "/os1_cloud_node/points": ("sensor_msgs/msg/PointCloud2", "os1_lidar", 10.0),
    "/gx5/imu/data": ("sensor_msgs/msg/Imu", "gx5_link", 300.0),
    "/lidar_ground_truth": ("nav_msgs/msg/Odometry", "world", 10.0),
    "/tf": ("tf2_msgs/msg/TFMessage", None, 10.0),
}


@pytest.fixture(scope="module")
def bag_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated(tmp_path_factory, fmt="bag")


@pytest.fixture(scope="module")
def folder_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated(tmp_path_factory, fmt="folder")


@pytest.fixture(scope="module")
def bag(bag_path: Path) -> dict[str, list[tuple[int, Any, str]]]:
    return read_bag(bag_path)


def test_bag_topics_types_frames_and_rates(bag: dict[str, list[tuple[int, Any, str]]]) -> None:
    assert set(TOPICS) | {"/tf_static"} == set(bag)
    for topic, (msgtype, frame, rate) in TOPICS.items():
        msgs = bag[topic]
        assert {m[2] for m in msgs} == {msgtype}, topic
        stamps = np.array([stamp_ns(m[1].transforms[0]) if topic == "/tf" else stamp_ns(m[1]) for m in msgs])
        assert np.all(np.diff(stamps) > 0), f"{topic}: header stamps not strictly increasing"
        assert abs(1e9 / np.median(np.diff(stamps)) - rate) < 0.02 * rate, topic
        records = np.array([m[0] for m in msgs])
        assert np.all(records >= stamps) and np.all(records - stamps < 200_000_000), topic
        if frame is not None:
            assert {m[1].header.frame_id for m in msgs} == {frame}, topic
        if topic != "/tf":
            assert [m[1].header.seq for m in msgs] == list(range(len(msgs))), topic
    assert {m[1].child_frame_id for m in bag["/lidar_ground_truth"]} == {"imu_viz_link"}
    # unix-epoch stamps like the real bags
    assert stamp_ns(bag["/gx5/imu/data"][0][1]) > 1_500_000_000 * 10**9


def test_pointcloud2_layouts(bag: dict[str, list[tuple[int, Any, str]]]) -> None:
    layouts = (("/mmWaveDataHdl/RScan", RADAR_FIELDS, 32), ("/os1_cloud_node/points", LIDAR_FIELDS, 48))
    for topic, fields, step in layouts:
        for _, msg, _ in bag[topic]:
            assert [(f.name, f.offset, f.datatype) for f in msg.fields] == fields
            assert all(f.count == 1 for f in msg.fields)
            assert msg.point_step == step and msg.row_step == step * msg.width
            assert not msg.is_bigendian and msg.is_dense
            assert len(msg.data) == step * msg.width * msg.height
    radar = [m for _, m, _ in bag["/mmWaveDataHdl/RScan"]]
    assert all(m.height == 1 for m in radar)
    counts = np.array([m.width for m in radar])
    # sparse like the TI chain's output (CFAR + peak grouping: about one point per strong feature), never empty
    # for long, and never above the driver's cap
    assert 20 <= np.median(counts) and counts.max() <= 200 and np.mean(counts > 0) > 0.9  # tens to ~200
    lidar = [m for _, m, _ in bag["/os1_cloud_node/points"]]
    assert {(m.height, m.width) for m in lidar} == {(16, 256)}
    a = cloud_array(lidar[3])
    assert np.array_equal(a["ring"].reshape(16, 256), np.repeat(np.arange(16)[:, None], 256, 1))
    t = a["t"].reshape(16, 256)
    assert np.all(np.diff(t[0].astype(np.int64)) > 0) and t[0, -1] < 100_000_000
    valid = a["range"] > 0
    assert valid.mean() > 0.9  # indoors nearly every beam returns
    r = np.linalg.norm(np.column_stack([a["x"], a["y"], a["z"]]), axis=1)
    assert np.allclose(r[valid], a["range"][valid] / 1000.0, atol=2e-3)
    assert np.all(r[~valid] == 0)  # missing returns are zero points, as the Ouster driver publishes them


def test_radar_range_field_and_fov(bag: dict[str, list[tuple[int, Any, str]]]) -> None:
    a = np.concatenate([cloud_array(m) for _, m, _ in bag["/mmWaveDataHdl/RScan"]])
    r = np.linalg.norm(np.column_stack([a["x"], a["y"], a["z"]]), axis=1)
    assert np.allclose(a["range"], r, atol=1e-4)
    assert np.allclose(a["range"] / 0.125, np.round(a["range"] / 0.125), atol=1e-3)  # range-bin centres
    assert np.all(a["x"] > 0)  # boresight is +x
    assert np.all(np.abs(np.degrees(np.arctan2(a["y"], a["x"]))) < 60.0 + 1e-3)
    assert np.all(a["range"] <= 12.0) and np.all(np.abs(a["doppler"]) <= 2.56 + 1e-6)


def test_tf_extrinsics(bag: dict[str, list[tuple[int, Any, str]]]) -> None:
    tf = transforms(bag)
    radar = tf[("imu_viz_link", "base_radar_link")]
    assert np.allclose(radar[:3, 3], [-0.145, 0.09, -0.025])
    assert np.allclose(radar[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=2e-3)  # radar boresight along base +y
    assert np.allclose(tf[("os1_sensor", "os1_lidar")][:3, 3], [0, 0, 0.03618])
    assert {("imu_viz_link", c) for c in ("gx5_link", "os1_sensor", "cascade_link")} <= set(tf)
    static = [m for _, m, _ in bag["/tf_static"]]
    assert len(static) == 1 and [t.child_frame_id for t in static[0].transforms] == ["os1_lidar"]


def test_folder_layout_and_text_formats(folder_path: Path) -> None:
    f = folder_path
    ts_re = re.compile(r"^\d{10}\.\d{6}$")
    for ts in ("single_chip/pointclouds/timestamps.txt", "lidar/timestamps.txt", "imu/timestamps.txt",
               "groundtruth/timestamps.txt"):
        lines = (f / ts).read_text().splitlines()
        assert lines and all(ts_re.match(x) for x in lines), ts
        assert np.all(np.diff(np.array(lines, dtype=float)) > 0), ts
    n_radar = len((f / "single_chip/pointclouds/timestamps.txt").read_text().splitlines())
    n_lidar = len((f / "lidar/timestamps.txt").read_text().splitlines())
    assert sorted(p.name for p in (f / "single_chip/pointclouds/data").iterdir()) == sorted(
        f"radar_pointcloud_{i}.bin" for i in range(n_radar))
    assert sorted(p.name for p in (f / "lidar/pointclouds").iterdir()) == sorted(
        f"lidar_pointcloud_{i}.bin" for i in range(n_lidar))
    assert (f / "single_chip/pointclouds/data/radar_pointcloud_0.bin").stat().st_size % 20 == 0
    lid = np.fromfile(f / "lidar/pointclouds/lidar_pointcloud_0.bin", dtype="<f4")
    assert lid.size == 16 * 256 * 4
    imu = np.loadtxt(f / "imu/imu_data.txt")
    assert imu.shape == (len((f / "imu/timestamps.txt").read_text().splitlines()), 6)
    assert abs(np.median(imu[:30, 2]) - 9.80665) < 0.2  # gravity on +z of a level IMU at rest
    gt = np.loadtxt(f / "groundtruth/groundtruth_poses.txt")
    assert gt.shape[1] == 7 and np.allclose(np.linalg.norm(gt[:, 3:], axis=1), 1.0)
    for name in ("base_to_single_chip", "base_to_lidar", "base_to_imu"):
        lines = (f / "calib/transforms" / f"{name}.txt").read_text().splitlines()
        assert [len(x.split()) for x in lines] == [3, 4], name
    cfg = dict(x.split(" ", 1) for x in (f / "calib/single_chip/waveform_cfg.txt").read_text().splitlines())
    assert int(cfg["num_tx"]) == 3 and int(cfg["num_rx"]) == 4
    assert (f / "calib/single_chip/heatmap_cfg.txt").read_text().startswith("num_range_bins ")


def test_folder_matches_bag_for_the_same_seed(bag: dict[str, list[tuple[int, Any, str]]], folder_path: Path) -> None:
    f = folder_path
    radar = [m for _, m, _ in bag["/mmWaveDataHdl/RScan"]]
    ts = (f / "single_chip/pointclouds/timestamps.txt").read_text().splitlines()
    assert len(ts) == len(radar)
    for i in (0, len(radar) // 2, len(radar) - 1):
        a = cloud_array(radar[i])
        b = np.fromfile(f / f"single_chip/pointclouds/data/radar_pointcloud_{i}.bin", dtype="<f4").reshape(-1, 5)
        assert np.array_equal(b, np.column_stack([a[k] for k in ("x", "y", "z", "intensity", "doppler")]))
        assert ts[i] == "%6f" % (radar[i].header.stamp.sec + radar[i].header.stamp.nanosec / 1e9)
    lidar = cloud_array(bag["/os1_cloud_node/points"][5][1])
    b = np.fromfile(f / "lidar/pointclouds/lidar_pointcloud_5.bin", dtype="<f4").reshape(-1, 4)
    assert np.array_equal(b, np.column_stack([lidar[k] for k in ("x", "y", "z", "intensity")]))
    imu = np.loadtxt(f / "imu/imu_data.txt")
    m = bag["/gx5/imu/data"][100][1]
    assert np.array_equal(imu[100], [m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z,
                                     m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z])
    gt = np.loadtxt(f / "groundtruth/groundtruth_poses.txt")
    p = bag["/lidar_ground_truth"][3][1].pose.pose
    assert np.array_equal(gt[3], [p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y,
                                  p.orientation.z, p.orientation.w])
    # calibration files are what the dataset's bag_to_config script derives from the bag's tf
    tf = transforms(bag)

    def read(name: str) -> np.ndarray:
        t, q = [np.array(x.split(), dtype=float) for x in (f / "calib/transforms" / name).read_text().splitlines()]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.from_quat(q).as_matrix(), t
        return T

    assert np.allclose(read("base_to_single_chip.txt"), tf[("imu_viz_link", "base_radar_link")])
    assert np.allclose(read("base_to_imu.txt"), tf[("imu_viz_link", "gx5_link")])
    assert np.allclose(read("base_to_lidar.txt"), tf[("imu_viz_link", "os1_sensor")] @ tf[("os1_sensor", "os1_lidar")])


def test_sidecar_labels_match_the_log(bag_path: Path, bag: dict[str, list[tuple[int, Any, str]]],
                                      folder_path: Path) -> None:
    side = bag_path.with_suffix(".sim")
    t = pq.read_table(side / "radar_labels.parquet")
    assert [(f.name, str(f.type)) for f in t.schema][:4] == [("scan", "int32"), ("t_ns", "int64"),
                                                             ("point", "int32"), ("label", "int8")]
    d = t.to_pydict()
    radar = [m for _, m, _ in bag["/mmWaveDataHdl/RScan"]]
    assert len(d["scan"]) == sum(m.width for m in radar)
    scan, point, tns = np.array(d["scan"]), np.array(d["point"]), np.array(d["t_ns"])
    for i, m in enumerate(radar):
        sel = scan == i
        assert np.array_equal(point[sel], np.arange(m.width)) and np.all(tns[sel] == stamp_ns(m))
    counts = np.bincount(np.array(d["label"]), minlength=3)
    assert counts[0] > 0.5 * counts.sum() and counts[1] > 0 and counts[2] > 0 and counts.size == 3
    meta = json.loads((side / "meta.json").read_text())
    assert meta["seed"] == 7 and meta["world"] == "hallway_loop" and (side / "world.toml").exists()
    assert (folder_path / "sim" / "radar_labels.parquet").exists()
    assert pq.read_table(folder_path / "sim" / "radar_labels.parquet").equals(t)


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for p in files:
        h.update(str(p.relative_to(path)).encode() if path.is_dir() else b"")
        h.update(p.read_bytes())
    return h.hexdigest()


@pytest.mark.parametrize("fmt", ["bag", "folder"])
def test_same_seed_same_bytes(tmp_path: Path, fmt: str) -> None:
    from simulator import simulate_to

    a = simulate_to("cluttered_lab", tmp_path / "a", duration=1.2, seed=3, fmt=fmt)
    b = simulate_to("cluttered_lab", tmp_path / "b", duration=1.2, seed=3, fmt=fmt)
    c = simulate_to("cluttered_lab", tmp_path / "c", duration=1.2, seed=4, fmt=fmt)
    assert _digest(a) == _digest(b)
    assert _digest(a) != _digest(c)
    if fmt == "bag":
        assert _digest(a.with_suffix(".sim")) == _digest(b.with_suffix(".sim"))
