"""``pipeline export``: trajectories as TUM (evo), maps as PLY, results as MCAP with Foxglove schemas.

Each trajectory is written once: the odometry stage's (the slam stage's ``trajectory_odometry`` replays
it, and ``trajectory.parquet`` copies the main method's ``trajectory_<method>``). For TUM the ground
truth is interpolated at the estimates' stamps (linear in position, slerp in rotation), so that
``evo_ape tum groundtruth.tum rich_slam.tum`` pairs every estimated pose with its exact reference
instead of a ground-truth sample up to half a sample period away. Estimates are planar (x, y, yaw):
z comes from a ``z`` column where the estimate (or, for slam, the odometry it started from) has one,
and is 0 otherwise, which is said. Files are written to a temporary name and renamed.
"""

from __future__ import annotations

import os
import uuid
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from core.errors import UserError
from pipeline.store import RunStore
from schemas import artifact_for_file, read_artifact

#: (stage, file) of each map that PLY and MCAP export
MAP_FILES = (
    ("voxel", "radar_map.parquet"),
    ("voxel", "lidar_map.parquet"),
    ("complete", "completed_map.parquet"),
    ("slam", "map_grid.parquet"),
)
#: an estimate gets a ground-truth pose only when the samples around it are at most this far apart
#: (the evaluate stage's ``max_gt_gap_s`` default)
MAX_GT_GAP_S = 0.5
FORMATS = ("tum", "ply", "mcap")

Note = Callable[[str], None]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


@dataclass
class Trajectory:
    """``pose`` rows are x y z qx qy qz qw (world <- base) at ``t_ns``; ``has_z`` when z was estimated;
    ``roll_pitch`` (N, 2) the Z-Y-X roll and pitch of an estimate (zeros for a planar one)."""

    name: str
    t_ns: I64
    pose: F64
    source: Path
    has_z: bool = True
    roll_pitch: F64 | None = None


def _warn(message: str) -> None:
    warnings.warn(message, UserWarning, stacklevel=3)


def ypr_to_quat(yaw: npt.ArrayLike, pitch: npt.ArrayLike, roll: npt.ArrayLike) -> F64:
    """(qx, qy, qz, qw) of R = Rz(yaw) Ry(pitch) Rx(roll) (the odometry artifact's Z-Y-X angles)."""
    from scipy.spatial.transform import Rotation

    angles = np.stack([np.asarray(a, np.float64) for a in (yaw, pitch, roll)], axis=-1).reshape(-1, 3)
    return np.asarray(Rotation.from_euler("ZYX", angles).as_quat(), np.float64)


# -- reading -----------------------------------------------------------------------------------------------------
def groundtruth(store: RunStore) -> Trajectory | None:
    """The ingest stage's ground truth, sorted by time with repeated stamps dropped; None when absent or empty."""
    path = store.stage_dir("ingest") / "groundtruth.parquet"
    if not path.exists():
        return None
    t = read_artifact(path, "groundtruth")
    if t.num_rows == 0:
        return None
    t_ns = t["t_ns"].to_numpy().astype(np.int64)
    pose = np.column_stack([t[c].to_numpy() for c in ("x", "y", "z", "qx", "qy", "qz", "qw")]).astype(np.float64)
    t_ns, first = np.unique(t_ns, return_index=True)
    return Trajectory("groundtruth", t_ns, pose[first], path)


def _planar(name: str, path: Path, schema: str, z_from: Trajectory | None, note: Note) -> Trajectory | None:
    t = read_artifact(path, schema)
    cols = t.column_names
    t_ns = t["t_ns"].to_numpy().astype(np.int64)
    x, y, yaw = (t[c].to_numpy().astype(np.float64) for c in ("x", "y", "yaw"))
    keep = np.isfinite(x) & np.isfinite(y) & np.isfinite(yaw)
    if "valid" in cols:
        keep &= t["valid"].to_numpy(zero_copy_only=False).astype(bool)
    if (~keep).any():
        note(f"{name}: {int((~keep).sum())} of {len(keep)} poses are not valid estimates ({path}); left out")
    has_z = "z" in cols
    zeros = np.zeros_like(x)
    z, roll, pitch = (t[c].to_numpy().astype(np.float64) if c in cols else zeros for c in ("z", "roll", "pitch"))
    if not has_z and z_from is not None and z_from.has_z and len(z_from.t_ns):
        # a slam method corrects x, y, yaw of the odometry it started from; its z, roll, pitch are the odometry's
        at = np.searchsorted(z_from.t_ns, t_ns).clip(0, len(z_from.t_ns) - 1)
        has_z = bool(np.all(z_from.t_ns[at][keep] == t_ns[keep]))
        if has_z and z_from.roll_pitch is not None:
            z, roll, pitch = z_from.pose[at, 2], z_from.roll_pitch[at, 0], z_from.roll_pitch[at, 1]
    order = np.argsort(t_ns[keep], kind="stable")
    pose = np.column_stack([x, y, z, ypr_to_quat(yaw, pitch, roll)])[keep][order]
    rp = np.column_stack([roll, pitch])[keep][order]
    return Trajectory(name, t_ns[keep][order], pose, path, has_z, rp)


def estimates(store: RunStore, note: Note = _warn) -> list[Trajectory]:
    """The odometry and every slam method's trajectory, each once, in that order."""
    out: list[Trajectory] = []
    odo_path = store.stage_dir("odometry") / "odometry.parquet"
    odo = _planar("odometry", odo_path, "odometry", None, note) if odo_path.exists() else None
    if odo is not None:
        out.append(odo)
    slam_dir = store.stage_dir("slam")
    files = {f.stem.removeprefix("trajectory").lstrip("_"): f for f in sorted(slam_dir.glob("trajectory*.parquet"))}
    if not files:
        note(f"no SLAM trajectory in {slam_dir}, so none is exported; `pipeline run slam --seq {store.seq}` "
             f"writes the filters' trajectories")
        return out
    main = files.pop("", None)
    if main is not None and not files:  # only the main method's copy: name it after the method
        manifest = store.read_manifest("slam") or {}
        files[str(manifest.get("params", {}).get("method", "slam"))] = main
    if odo is not None:
        files.pop("odometry", None)  # the slam stage's replay of the odometry above
    for method, path in files.items():
        traj = _planar(method, path, "trajectory", odo, note)
        if traj is not None:
            out.append(traj)
    return out


def trajectories(store: RunStore, note: Note = _warn) -> Iterator[Trajectory]:
    """Ground truth (at its own stamps) and every estimate, each once."""
    gt = groundtruth(store)
    if gt is not None:
        yield gt
    yield from estimates(store, note)


# -- ground truth at the estimates' stamps ---------------------------------------------------------------------
def interpolate_poses(ref: Trajectory, t_ns: I64, max_gap_ns: int) -> tuple[F64, npt.NDArray[np.bool_]]:
    """``ref`` at ``t_ns``: linear in position, slerp in rotation; ``ok`` where the bracketing samples are at
    most ``max_gap_ns`` apart (an estimate at a reference stamp always matches it)."""
    from scipy.spatial.transform import Rotation, Slerp

    t_ref = ref.t_ns
    out = np.full((len(t_ns), 7), np.nan)
    ok = np.zeros(len(t_ns), dtype=bool)
    if len(t_ref) == 0 or len(t_ns) == 0:
        return out, ok
    hi = np.searchsorted(t_ref, t_ns, side="left").clip(0, len(t_ref) - 1)
    exact = t_ref[hi] == t_ns
    lo = np.maximum(hi - 1, 0)
    inside = (t_ns >= t_ref[0]) & (t_ns <= t_ref[-1])
    ok = exact | (inside & (t_ref[hi] - t_ref[lo] <= max_gap_ns))
    if len(t_ref) == 1:
        out[ok] = ref.pose[0]
        return out, ok
    rel = (t_ref - t_ref[0]).astype(np.float64) * 1e-9
    tq = (t_ns[ok] - t_ref[0]).astype(np.float64) * 1e-9
    rot = Slerp(rel, Rotation.from_quat(ref.pose[:, 3:7]))(tq)
    out[ok, :3] = np.column_stack([np.interp(tq, rel, ref.pose[:, k]) for k in range(3)])
    out[ok, 3:] = rot.as_quat()
    return out, ok


def groundtruth_at_estimates(gt: Trajectory, est: list[Trajectory], max_gap_s: float,
                             note: Note) -> Trajectory:
    """Ground truth at the union of the estimates' stamps that it covers."""
    stamps = np.unique(np.concatenate([e.t_ns for e in est]))
    pose, ok = interpolate_poses(gt, stamps, int(max_gap_s * 1e9))
    for e in est:
        missing = int((~np.isin(e.t_ns, stamps[ok])).sum())
        if missing:
            note(f"{e.name}: {missing} of {len(e.t_ns)} poses have no ground truth around them (outside "
                 f"{gt.source.name}'s time span or in a gap over {max_gap_s:g} s); evo leaves them out")
    return Trajectory("groundtruth", stamps[ok], pose[ok], gt.source)


# -- writers -------------------------------------------------------------------------------------------------------
def _atomic(path: Path) -> Path:
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")


def _commit(tmp: Path, path: Path) -> Path:
    os.replace(tmp, path)
    return path


def write_tum(path: Path, t_ns: I64, pose: F64) -> Path:
    """``timestamp tx ty tz qx qy qz qw``, the stamp in seconds written exactly from the nanoseconds."""
    tmp = _atomic(path)
    try:
        with tmp.open("w") as f:
            for t, p in zip(t_ns.tolist(), pose.tolist(), strict=True):
                sec, ns = divmod(int(t), 1_000_000_000)
                f.write(f"{sec}.{ns:09d} " + " ".join(f"{v:.9f}" for v in p) + "\n")
        return _commit(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def export_tum(store: RunStore, out: Path, note: Note = _warn, groundtruth_stamps: str = "estimates",
               max_gap_s: float = MAX_GT_GAP_S) -> list[Path]:
    """``groundtruth.tum`` and one ``<name>.tum`` per estimate (evo's TUM format, seconds)."""
    est = estimates(store, note)
    gt = groundtruth(store)
    written = []
    if gt is None:
        note(f"no ground truth in {store.stage_dir('ingest') / 'groundtruth.parquet'}: groundtruth.tum not written")
    elif groundtruth_stamps == "estimates" and est:
        at = groundtruth_at_estimates(gt, est, max_gap_s, note)
        if len(at.t_ns):
            written.append(write_tum(out / "groundtruth.tum", at.t_ns, at.pose))
            note(f"groundtruth.tum: ground truth interpolated at the {len(at.t_ns)} estimate stamps it covers "
                 f"(evo pairs each pose with its reference exactly; --groundtruth-stamps own for its "
                 f"{len(gt.t_ns)} samples)")
        else:
            note(f"no estimate stamp lies within the ground truth's time span ({gt.source}): groundtruth.tum "
                 f"not written")
    else:
        written.append(write_tum(out / "groundtruth.tum", gt.t_ns, gt.pose))
    for e in est:
        if len(e.t_ns) == 0:
            note(f"{e.name}: no valid poses in {e.source}; {e.name}.tum not written")
            continue
        written.append(write_tum(out / f"{e.name}.tum", e.t_ns, e.pose))
    planar = [e.name for e in est if not e.has_z and len(e.t_ns)]
    if planar:
        hint = "" if gt is None else (
            f" while the ground truth averages z = {np.mean(gt.pose[:, 2]):.2f} m; compare in the plane with "
            f"`evo_ape tum groundtruth.tum {planar[-1]}.tum --project_to_plane xy`")
        note(f"{', '.join(planar)}: planar estimates without z, written with z = 0{hint}")
    return written


def write_ply(path: Path, xyz: npt.NDArray[np.float32], scalars: dict[str, npt.NDArray[np.float32]]) -> Path:
    """Binary PLY (meshio, machine byte order) with float x, y, z and extra float properties, atomically."""
    from sources.ply import ply_bytes

    body = ply_bytes(xyz.astype(np.float32, copy=False), {n: v.astype(np.float32, copy=False)
                                                           for n, v in scalars.items()}, binary=True)
    tmp = _atomic(path)
    try:
        tmp.write_bytes(body)
        return _commit(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


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


def export_ply(store: RunStore, out: Path, note: Note = _warn) -> list[Path]:
    written = []
    for name, xyz, extra in maps(store):
        if len(xyz) == 0:
            note(f"{name}: the map is empty; {name}.ply not written")
            continue
        written.append(write_ply(out / f"{name}.ply", xyz, extra))
    return written


def export_mcap(store: RunStore, out: Path, note: Note = _warn) -> list[Path]:
    """Trajectories as ``foxglove.PoseInFrame`` (one channel each, messages in time order) and maps as
    ``foxglove.PointCloud`` at the last stamp, in one MCAP file."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
    from google.protobuf.timestamp_pb2 import Timestamp
    from mcap_protobuf.writer import Writer

    def stamp(t: int) -> Any:
        return Timestamp(seconds=t // 1_000_000_000, nanos=t % 1_000_000_000)

    trajs = [t for t in trajectories(store, note) if len(t.t_ns)]
    map_list = [m for m in maps(store) if len(m[1])]
    if not trajs and not map_list:
        return []
    # every pose of every trajectory, merged in log-time order (stable: a tie keeps the trajectory order)
    t_all = np.concatenate([t.t_ns for t in trajs]) if trajs else np.zeros(0, np.int64)
    which = np.concatenate([np.full(len(t.t_ns), k) for k, t in enumerate(trajs)]) if trajs else np.zeros(0, int)
    row = np.concatenate([np.arange(len(t.t_ns)) for t in trajs]) if trajs else np.zeros(0, int)
    order = np.argsort(t_all, kind="stable")
    t_last = int(t_all.max()) if len(t_all) else 0
    path = out / f"{store.seq}.mcap"
    tmp = _atomic(path)
    try:
        with tmp.open("wb") as f, Writer(f) as writer:
            for i in order.tolist():
                traj, t = trajs[which[i]], int(t_all[i])
                p = traj.pose[row[i]]
                msg = PoseInFrame(timestamp=stamp(t), frame_id="world",
                                  pose=Pose(position=Vector3(x=p[0], y=p[1], z=p[2]),
                                            orientation=Quaternion(x=p[3], y=p[4], z=p[5], w=p[6])))
                writer.write_message(f"/trajectory/{traj.name}", msg, log_time=t, publish_time=t)
            for name, xyz, _extra in map_list:
                fields = [PackedElementField(name=n, offset=4 * i, type=PackedElementField.FLOAT32)
                          for i, n in enumerate("xyz")]
                cloud = PointCloud(timestamp=stamp(t_last), frame_id="world", point_stride=12, fields=fields,
                                   data=np.ascontiguousarray(xyz, dtype="<f4").tobytes())
                writer.write_message(f"/map/{name}", cloud, log_time=t_last, publish_time=t_last)
        return [_commit(tmp, path)]
    finally:
        tmp.unlink(missing_ok=True)


def export(store: RunStore, fmt: str, out: Path, note: Note | None = None, groundtruth_stamps: str = "estimates",
           max_gap_s: float = MAX_GT_GAP_S) -> list[Path]:
    """Write ``fmt`` files of the run into ``out``; ``note`` receives what was left out or changed, and why
    (default: :func:`warnings.warn`)."""
    say = note or _warn
    if fmt not in FORMATS:
        raise UserError(f"--format {fmt}: expected one of {', '.join(FORMATS)}")
    if groundtruth_stamps not in ("estimates", "own"):
        raise UserError(f"--groundtruth-stamps {groundtruth_stamps}: expected estimates or own")
    if not store.seq_dir.is_dir():
        raise UserError(
            f"no runs for sequence '{store.seq}' under {store.runs_dir}; run `pipeline run all --seq {store.seq}` first"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {out}: cannot create the folder ({exc.strerror or exc}); name another") from None
    if fmt == "tum":
        written = export_tum(store, out, say, groundtruth_stamps, max_gap_s)
    elif fmt == "ply":
        written = export_ply(store, out, say)
    else:
        written = export_mcap(store, out, say)
    if not written:
        need = "trajectories (ingest/odometry/slam)" if fmt == "tum" else "maps (voxel/complete/slam)"
        if fmt == "mcap":
            need = "trajectories or maps"
        raise UserError(f"nothing to export for '{store.seq}': no {need} in {store.seq_dir}")
    stale = sorted(p.name for p in out.glob(f"*.{fmt}") if p not in written)
    if stale:
        say(f"{out} also holds {', '.join(stale)} from an earlier export (not written now); left as they are")
    return written
