"""Ingest throughput against plain rosbags iteration of the same bag, measured in the same run.

Bag: the simulator's ``demo`` world as a ROS1 bag (20 s with ``--quick``, 60 s otherwise; ColoRadar
topics: radar 10 Hz, Ouster-like lidar 10 Hz, IMU 300 Hz, ground truth, tf). Without the simulator a
synthetic bag with the same topics and point layouts is written instead.
- reference: ``AnyReader.messages()`` over the topics ingest reads, each message deserialized;
- ingest (full stage): topic resolution, PointCloud2 decoding, NaN and time-order checks, Parquet
  written in row groups (zstd), Rerun recording, calibration;
- ingest read + decode: the readers alone (no Parquet, no Rerun).
Messages/s and MB/s (bag bytes of the read topics); ratio = ours / reference (1 = as fast as iterating).
Interleaved best-of-``repeat`` timings, after one warm-up run of each.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import Result

AREA = "ingest"


def _synthetic_bag(path: Path, seconds: float) -> Path:
    """A ColoRadar-like ROS1 bag (fallback when the simulator is not installed)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    rng = np.random.default_rng(0)

    def header(t: int, frame: str) -> Any:
        return T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9,
                                                                                       nanosec=t % 10**9),
                                        frame_id=frame)

    def cloud(t: int, frame: str, names: list[tuple[str, int, int]], step: int, n: int) -> Any:
        PF = T["sensor_msgs/msg/PointField"]
        data = rng.normal(size=n * step // 4).astype(np.float32).view(np.uint8)
        return T["sensor_msgs/msg/PointCloud2"](
            header=header(t, frame), height=1, width=n,
            fields=[PF(name=a, offset=o, datatype=d, count=1) for a, o, d in names],
            is_bigendian=False, point_step=step, row_step=n * step, data=data, is_dense=True)

    radar_f = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("range", 20, 7), ("doppler", 24, 7)]
    lidar_f = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("t", 20, 6), ("reflectivity", 24, 4),
               ("ring", 26, 2), ("noise", 28, 4), ("range", 32, 6)]
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    t0 = 1_600_000_000 * 10**9
    msgs: list[tuple[str, str, int, Any]] = []
    for i in range(int(seconds * 10)):
        t = t0 + i * 10**8
        msgs.append(("/mmWaveDataHdl/RScan", "sensor_msgs/msg/PointCloud2", t, cloud(t, "base_radar_link", radar_f, 32,
                                                                                       120)))
        msgs.append(("/os1_cloud_node/points", "sensor_msgs/msg/PointCloud2", t + 5 * 10**7,
                     cloud(t + 5 * 10**7, "os1_lidar", lidar_f, 48, 4096)))
    for i in range(int(seconds * 300)):
        t = t0 + i * 10**9 // 300
        a = rng.normal(size=6)
        msgs.append(("/gx5/imu/data", "sensor_msgs/msg/Imu", t, T["sensor_msgs/msg/Imu"](
            header=header(t, "gx5_link"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9), angular_velocity=V3(x=a[0], y=a[1], z=a[2]),
            angular_velocity_covariance=np.zeros(9), linear_acceleration=V3(x=a[3], y=a[4], z=a[5]),
            linear_acceleration_covariance=np.zeros(9))))
    msgs.sort(key=lambda m: m[2])
    with Writer(path) as w:
        conns: dict[str, Any] = {}
        for topic, typ, t, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], t, ts.serialize_ros1(msg, typ))
    return path


def _make_bag(folder: Path, seconds: float) -> tuple[Path, str]:
    try:
        from simulator import simulate_to

        return simulate_to(world="demo", out=folder / "demo.bag", duration=seconds, seed=0, fmt="bag"), "simulated demo"
    except Exception:  # the simulator is optional here: fall back to a synthetic bag
        return _synthetic_bag(folder / "synthetic.bag", seconds), "synthetic"


def _reference(bag: Path, topics: set[str]) -> tuple[int, int]:
    """Plain rosbags: iterate the topics and deserialize every message. Returns (messages, bytes)."""
    from rosbags.highlevel import AnyReader

    n = nbytes = 0
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, _, raw in reader.messages(connections=conns):
            reader.deserialize(raw, conn.msgtype)
            n += 1
            nbytes += len(raw)
    return n, nbytes


def _ingest(bag: Path, out: Path) -> dict[str, Any]:
    from rich.console import Console

    from core.stage import StageContext
    from pipeline.sequences import SequenceInfo
    from stages.ingest.stage import STAGE, IngestParams

    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    ctx = StageContext("ingest", SequenceInfo(name="bench", kind="source", source=bag), IngestParams(), out, {},
                       Console(quiet=True))
    STAGE.run(ctx)
    ctx.close()
    return ctx.stats


def _read_decode(bag: Path) -> int:
    from stages.ingest.profile import load_profile
    from stages.ingest.readers import open_source

    return sum(1 for _ in open_source(bag, load_profile("coloradar")).messages())


def _best(fns: dict[str, Callable[[], Any]], repeat: int) -> dict[str, float]:
    best = dict.fromkeys(fns, float("inf"))
    for fn in fns.values():  # warm-up (imports, page cache)
        fn()
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - t0)
    return best


def run(quick: bool = False) -> list[Result]:
    seconds = 20.0 if quick else 60.0
    repeat = 2 if quick else 3
    with tempfile.TemporaryDirectory(prefix="bench_ingest_") as tmp:
        folder = Path(tmp)
        bag, kind = _make_bag(folder, seconds)
        stats = _ingest(bag, folder / "out")
        topics = set(stats["source"]["streams"].values()) | {"/tf_static", "/tf"}
        n_ref, bytes_ref = _reference(bag, topics)
        t = _best({"reference": lambda: _reference(bag, topics), "ingest": lambda: _ingest(bag, folder / "out"),
                   "read_decode": lambda: _read_decode(bag)}, repeat)
    mb = bytes_ref / 1e6
    note = f"{kind} bag, {seconds:.0f} s, {n_ref} messages, {mb:.1f} MB"
    ref_mps, ref_mbps = n_ref / t["reference"], mb / t["reference"]
    return [
        Result(AREA, "reference rosbags read+deserialize", ref_mps, "msg/s", note=f"{ref_mbps:.1f} MB/s; {note}"),
        Result(AREA, "ingest stage (Parquet + Rerun)", n_ref / t["ingest"], "msg/s",
               reference="rosbags AnyReader iteration", ratio=t["reference"] / t["ingest"],
               note=f"{mb / t['ingest']:.1f} MB/s"),
        Result(AREA, "ingest stage throughput", mb / t["ingest"], "MB/s", reference="rosbags AnyReader iteration",
               ratio=t["reference"] / t["ingest"]),
        Result(AREA, "ingest readers (read + decode only)", n_ref / t["read_decode"], "msg/s",
               reference="rosbags AnyReader iteration", ratio=t["reference"] / t["read_decode"]),
    ]
