"""``pipeline export``: trajectories as TUM (evo), maps as PLY, results as MCAP with Foxglove schemas."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import numpy.typing as npt

from pipeline.errors import UserError
from pipeline.store import RunStore
from schemas import artifact_for_file, read_artifact

#: (stage, file) of each map that PLY and MCAP export
MAP_FILES = (
    ("voxel", "radar_map.parquet"),
    ("voxel", "lidar_map.parquet"),
    ("complete", "completed_map.parquet"),
    ("slam", "map_grid.parquet"),
)


def yaw_to_quat(yaw: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(qx, qy, qz, qw) of a rotation about z."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    return np.stack([np.zeros_like(half), np.zeros_like(half), np.sin(half), np.cos(half)], axis=1)


def trajectories(store: RunStore) -> Iterator[tuple[str, npt.NDArray[np.int64], npt.NDArray[np.float64]]]:
    """(name, t_ns, [x y z qx qy qz qw]) for ground truth, odometry and every slam method present."""
    gt = store.stage_dir("ingest") / "groundtruth.parquet"
    if gt.exists():
        t = read_artifact(gt, "groundtruth")
        cols = np.column_stack([t[c].to_numpy() for c in ("x", "y", "z", "qx", "qy", "qz", "qw")])
        yield "groundtruth", t["t_ns"].to_numpy(), cols
    sources = [("odometry", store.stage_dir("odometry") / "odometry.parquet", "odometry")]
    slam_dir = store.stage_dir("slam")
    if slam_dir.exists():
        for f in sorted(slam_dir.glob("trajectory*.parquet")):
            method = f.stem.removeprefix("trajectory").lstrip("_") or "slam"
            sources.append((method, f, "trajectory"))
    for name, path, schema in sources:
        if not path.exists():
            continue
        t = read_artifact(path, schema)
        x, y, yaw = (t[c].to_numpy() for c in ("x", "y", "yaw"))
        pose = np.column_stack([x, y, np.zeros_like(x), yaw_to_quat(yaw)])
        yield name, t["t_ns"].to_numpy(), pose


def export_tum(store: RunStore, out: Path) -> list[Path]:
    """One ``<name>.tum`` per trajectory: ``timestamp tx ty tz qx qy qz qw`` (seconds)."""
    written = []
    for name, t_ns, pose in trajectories(store):
        path = out / f"{name}.tum"
        data = np.column_stack([t_ns / 1e9, pose])
        np.savetxt(path, data, fmt=["%.9f"] + ["%.6f"] * 3 + ["%.9f"] * 4)
        written.append(path)
    return written


def write_ply(path: Path, xyz: npt.NDArray[np.float32], scalars: dict[str, npt.NDArray[np.float32]]) -> None:
    """Binary little-endian PLY with float x, y, z and extra float properties."""
    names = ["x", "y", "z", *scalars]
    dtype = np.dtype([(n, "<f4") for n in names])
    rec = np.empty(len(xyz), dtype)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for n, v in scalars.items():
        rec[n] = v
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(xyz)}"]
    header += [f"property float {n}" for n in names] + ["end_header"]
    with path.open("wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        f.write(rec.tobytes())


def maps(store: RunStore) -> Iterator[tuple[str, npt.NDArray[np.float32], dict[str, npt.NDArray[np.float32]]]]:
    for stage, fname in MAP_FILES:
        path = store.stage_dir(stage) / fname
        if not path.exists():
            continue
        art = artifact_for_file(fname)
        assert art is not None
        t = read_artifact(path, art)
        x, y = t["x"].to_numpy(), t["y"].to_numpy()
        z = t["z"].to_numpy() if "z" in t.column_names else np.zeros_like(x)
        xyz = np.column_stack([x, y, z]).astype(np.float32)
        extra = {c: t[c].to_numpy().astype(np.float32) for c in ("log_odds", "occupancy", "variance")
                 if c in t.column_names}
        yield fname.removesuffix(".parquet"), xyz, extra


def export_ply(store: RunStore, out: Path) -> list[Path]:
    written = []
    for name, xyz, extra in maps(store):
        path = out / f"{name}.ply"
        write_ply(path, xyz, extra)
        written.append(path)
    return written


def export_mcap(store: RunStore, out: Path) -> list[Path]:
    """Trajectories as ``foxglove.PoseInFrame`` and maps as ``foxglove.PointCloud`` in one MCAP file."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
    from google.protobuf.timestamp_pb2 import Timestamp
    from mcap_protobuf.writer import Writer

    path = out / f"{store.seq}.mcap"
    tmp = path.with_suffix(".mcap.tmp")
    t_last = 0
    with tmp.open("wb") as f, Writer(f) as writer:
        for name, t_ns, pose in trajectories(store):
            for t, p in zip(t_ns.tolist(), pose, strict=True):
                msg = PoseInFrame(
                    timestamp=Timestamp(seconds=t // 1_000_000_000, nanos=t % 1_000_000_000),
                    frame_id="world",
                    pose=Pose(position=Vector3(x=p[0], y=p[1], z=p[2]),
                              orientation=Quaternion(x=p[3], y=p[4], z=p[5], w=p[6])),
                )
                writer.write_message(f"/trajectory/{name}", msg, log_time=t, publish_time=t)
                t_last = max(t_last, t)
        for name, xyz, _extra in maps(store):
            fields = [PackedElementField(name=n, offset=4 * i, type=PackedElementField.FLOAT32)
                      for i, n in enumerate("xyz")]
            msg = PointCloud(
                timestamp=Timestamp(seconds=t_last // 1_000_000_000, nanos=t_last % 1_000_000_000),
                frame_id="world", point_stride=12, fields=fields,
                data=np.ascontiguousarray(xyz, dtype="<f4").tobytes(),
            )
            writer.write_message(f"/map/{name}", msg, log_time=t_last, publish_time=t_last)
    tmp.replace(path)
    return [path]


def export(store: RunStore, fmt: str, out: Path) -> list[Path]:
    if not store.seq_dir.exists():
        raise UserError(
            f"no runs for sequence '{store.seq}' under {store.runs_dir}; run `pipeline run all --seq {store.seq}` first"
        )
    out.mkdir(parents=True, exist_ok=True)
    fn = {"tum": export_tum, "ply": export_ply, "mcap": export_mcap}.get(fmt)
    if fn is None:
        raise UserError(f"--format {fmt}: expected one of tum, ply, mcap")
    written = fn(store, out)
    if not written:
        need = "trajectories (ingest/odometry/slam)" if fmt == "tum" else "maps (voxel/complete/slam)"
        raise UserError(f"nothing to export for '{store.seq}': no {need} in {store.seq_dir}")
    return written
