"""Readers for every source form a ColoRadar user has: ROS1 ``.bag``, ROS2 bag (``.db3`` / ``.mcap`` or the
bag folder), a bare ``.mcap`` file (all via rosbags' ``AnyReader``), and the extracted folder form.

A reader resolves the profile's topics against the log (a clear error lists what the log has), then
yields :class:`Message` records one at a time in log order, so memory stays bounded. Extrinsics found
in the log (tf / calibration files) are available from :meth:`Source.transforms` after iteration.
"""

from __future__ import annotations

import sqlite3
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from core.errors import UserError
from core.geometry import pose_matrix
from stages.ingest import pointcloud2 as pc2
from stages.ingest.profile import DatasetProfile

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_TYPES = (ODOMETRY, "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped")
TF = "tf2_msgs/msg/TFMessage"
EXPECTED_TYPES: dict[str, tuple[str, ...]] = {
    "radar": (POINTCLOUD2,), "lidar": (POINTCLOUD2,), "imu": (IMU,),
    "groundtruth": POSE_TYPES, "odometry": POSE_TYPES,
}
POINT_STREAMS = ("radar", "lidar")


@dataclass
class Message:
    """One message of one stream, in sensor time."""

    stream: str
    t_ns: int
    #: arrival index within its stream (message order in the log)
    index: int
    #: point clouds: output column -> float32 array
    columns: dict[str, npt.NDArray[np.float32]] | None = None
    #: imu: (ax, ay, az, gx, gy, gz); poses: (x, y, z, qx, qy, qz, qw)
    values: npt.NDArray[np.float64] | None = None
    frame: str = ""
    child_frame: str = ""
    #: True when the header stamp was zero and the log's record time was used instead
    record_time: bool = False
    #: the header stamp and the log's record time, ns (the folder form has header stamps only: both equal)
    header_ns: int = 0
    record_ns: int = 0


@dataclass
class Source:
    """Common state of a resolved source."""

    path: Path
    profile: DatasetProfile
    form: str = ""
    #: stream -> topic (or file) it is read from; absent streams are not in the dict
    streams: dict[str, str] = field(default_factory=dict)
    #: stream -> number of messages expected (progress bars)
    counts: dict[str, int] = field(default_factory=dict)
    #: (parent, child) -> 4x4 parent <- child, first seen
    tf_edges: dict[tuple[str, str], npt.NDArray[np.float64]] = field(default_factory=dict)
    #: sensor -> (4x4 base <- sensor, how it was found), filled by folder calibration files
    calibration: dict[str, tuple[npt.NDArray[np.float64], str]] = field(default_factory=dict)
    bytes_read: int = 0
    #: optional streams the profile names but the log lacks (reported as warnings)
    missing_optional: list[str] = field(default_factory=list)

    def messages(self) -> Iterator[Message]:
        raise NotImplementedError

    def clock_samples(self, n: int) -> dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]]:
        """(header stamps, record times) of the first ``n`` messages of each streamed sensor; the folder
        form has one clock only (empty: nothing to line up)."""
        return {}

    def describe(self) -> str:
        return f"{self.form} {self.path}"


def detect_form(path: Path) -> str:
    """``ros1`` (.bag), ``ros2`` (bag folder, .db3, or .mcap) or ``folder`` (extracted ColoRadar run)."""
    if path.is_file():
        if path.suffix == ".bag":
            return "ros1"
        if path.suffix in (".db3", ".mcap"):
            return "ros2"
        raise UserError(f"{path}: unknown file type '{path.suffix}' (expected .bag, .db3, .mcap or a folder)")
    if path.is_dir():
        if (path / "metadata.yaml").exists() or any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return "ros2"
        return "folder"
    raise UserError(f"{path}: no such file or folder")


def open_source(path: Path, profile: DatasetProfile, topics: dict[str, str] | None = None,
                fields: dict[str, str] | None = None) -> Source:
    """Open ``path`` in the right reader with the profile's topics (``topics`` overrides them)."""
    form = detect_form(path)
    if form == "folder":
        return FolderSource(path, profile)
    return BagSource(path, profile, topic_overrides=topics or {}, field_overrides=fields or {})


# -- rosbags (ROS1 bag, ROS2 db3/mcap, bare mcap) -------------------------------------------------------------
def _read_errors() -> tuple[type[BaseException], ...]:
    from rosbags.highlevel.anyreader import AnyReaderError
    from rosbags.rosbag1 import ReaderError as R1
    from rosbags.rosbag2 import ReaderError as R2
    from rosbags.serde import SerdeError

    return (AnyReaderError, R1, R2, SerdeError, struct.error, zlib.error, sqlite3.DatabaseError, EOFError,
            OSError, KeyError, IndexError, ValueError, AssertionError)


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _pose_values(msg: Any, msgtype: str) -> tuple[npt.NDArray[np.float64], str, str]:
    if msgtype == "geometry_msgs/msg/TransformStamped":
        tr, rot, child = msg.transform.translation, msg.transform.rotation, msg.child_frame_id
        pos = tr
    else:
        pose = msg.pose.pose if msgtype in (ODOMETRY, "geometry_msgs/msg/PoseWithCovarianceStamped") else msg.pose
        pos, rot = pose.position, pose.orientation
        child = getattr(msg, "child_frame_id", "")
    vals = np.array([pos.x, pos.y, pos.z, rot.x, rot.y, rot.z, rot.w], dtype=np.float64)
    return vals, msg.header.frame_id, child


class BagSource(Source):
    """Any log rosbags' ``AnyReader`` opens."""

    def __init__(self, path: Path, profile: DatasetProfile, topic_overrides: dict[str, str],
                 field_overrides: dict[str, str]) -> None:
        super().__init__(path=path, profile=profile, form=detect_form(path))
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        if path.suffix == ".mcap" and path.is_file():
            self.form = "mcap"
        self.field_overrides = field_overrides
        errors = _read_errors()
        try:
            self.reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS1_NOETIC))
            self.reader.open()
        except FileNotFoundError:
            raise UserError(f"{path}: no such file") from None
        except errors as exc:
            raise UserError(f"{path}: corrupt or truncated log, cannot open it ({_why(exc)})") from exc
        try:
            self.topics = self.reader.topics
            self._resolve(topic_overrides)
        except BaseException:
            self.reader.close()
            raise

    # -- topic resolution --------------------------------------------------------------------------------------
    def available(self) -> str:
        items = [f"{name} ({info.msgtype.replace('/msg/', '/') if info.msgtype else '?'}, {info.msgcount})"
                 for name, info in sorted(self.topics.items())]
        return ", ".join(items) or "no topics"

    def _first(self, topic: str) -> Any:
        conns = [c for c in self.reader.connections if c.topic == topic]
        for conn, _, raw in self.reader.messages(connections=conns):
            return self.reader.deserialize(raw, conn.msgtype)
        return None

    def _has_doppler(self, topic: str) -> bool:
        msg = self._first(topic)
        if msg is None:
            return False
        names = {f.name for f in msg.fields}
        return any(c in names for c in self.profile.radar_fields.get("doppler", []))

    def _detect(self, stream: str, taken: set[str]) -> str:
        types = EXPECTED_TYPES[stream]
        cands = [t for t, info in sorted(self.topics.items()) if info.msgtype in types and t not in taken]
        if stream == "radar":
            cands = [t for t in cands if self._has_doppler(t)]
        elif stream == "lidar":
            cands = [t for t in cands if not self._has_doppler(t)]
        elif stream == "odometry":
            return ""  # never guessed: a log's odometry topic is usually the ground truth
        if len(cands) > 1:
            raise UserError(
                f"{self.path}: several candidate {stream} topics ({', '.join(cands)}); pick one with "
                f"--set ingest.topics.{stream}=TOPIC"
            )
        return cands[0] if cands else ""

    def _resolve(self, overrides: dict[str, str]) -> None:
        prof = self.profile
        taken: set[str] = set()
        for stream in ("radar", "imu", "groundtruth", "odometry", "lidar"):
            topic = overrides.get(stream) or getattr(prof.topics, stream)
            if not topic:
                topic = self._detect(stream, taken)
            if not topic:
                if stream in prof.required:
                    raise UserError(
                        f"{self.path}: no {stream} topic found for profile '{prof.name}'; set it with "
                        f"--set ingest.topics.{stream}=TOPIC (the log has: {self.available()})"
                    )
                continue
            if topic not in self.topics:
                if stream in prof.required or overrides.get(stream):
                    raise UserError(
                        f"{self.path}: topic '{topic}' ({stream}, profile '{prof.name}') not found; the log has: "
                        f"{self.available()}; set --set ingest.topics.{stream}=TOPIC"
                    )
                self.missing_optional.append(f"{stream} topic '{topic}'")
                continue
            msgtype = self.topics[topic].msgtype or "?"
            if msgtype not in EXPECTED_TYPES[stream]:
                raise UserError(
                    f"{self.path}: topic '{topic}' ({stream}) has type {msgtype}, expected "
                    f"{' or '.join(EXPECTED_TYPES[stream])}"
                )
            self.streams[stream] = topic
            self.counts[stream] = self.topics[topic].msgcount
            taken.add(topic)
        self.tf_topics = [t for t in prof.topics.tf if t in self.topics and self.topics[t].msgtype == TF]

    # -- iteration ---------------------------------------------------------------------------------------------
    def clock_samples(self, n: int) -> dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]]:
        out: dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]] = {}
        errors = _read_errors()
        for stream, topic in self.streams.items():
            conns = [c for c in self.reader.connections if c.topic == topic]
            head: list[int] = []
            rec: list[int] = []
            try:
                for conn, rec_ns, raw in self.reader.messages(connections=conns):
                    msg: Any = self.reader.deserialize(raw, conn.msgtype)
                    head.append(_stamp_ns(msg.header))
                    rec.append(int(rec_ns))
                    if len(head) >= n:
                        break
            except errors as exc:
                raise UserError(f"{self.path}: corrupt or truncated log while reading '{topic}' ({_why(exc)}); "
                                f"re-download or re-index the file") from exc
            out[stream] = (np.asarray(head, np.int64), np.asarray(rec, np.int64))
        return out

    def messages(self) -> Iterator[Message]:
        by_topic: dict[str, list[str]] = {}
        for stream, topic in self.streams.items():
            by_topic.setdefault(topic, []).append(stream)
        wanted = set(by_topic) | set(self.tf_topics)
        conns = [c for c in self.reader.connections if c.topic in wanted]
        counters = dict.fromkeys(self.streams, 0)
        layouts: dict[Any, pc2.Layout] = {}
        errors = _read_errors()
        it = self.reader.messages(connections=conns)
        conn: Any = None
        msg: Any = None
        try:
            while True:
                try:
                    conn, rec_ns, raw = next(it)
                    msg = self.reader.deserialize(raw, conn.msgtype)
                except StopIteration:
                    break
                except errors as exc:
                    raise UserError(
                        f"{self.path}: corrupt or truncated log while reading '{getattr(conn, 'topic', '?')}' "
                        f"({_why(exc)}); re-download or re-index the file"
                    ) from exc
                self.bytes_read += len(raw)
                if conn.topic in self.tf_topics:
                    self._add_tf(msg)
                    continue
                for stream in by_topic[conn.topic]:
                    stamp = _stamp_ns(msg.header)
                    out = Message(stream, stamp if stamp else int(rec_ns), counters[stream],
                                  frame=msg.header.frame_id, record_time=stamp == 0, header_ns=stamp,
                                  record_ns=int(rec_ns))
                    counters[stream] += 1
                    if stream in POINT_STREAMS:
                        out.columns = self._decode_cloud(stream, msg, layouts)
                    elif stream == "imu":
                        a, w = msg.linear_acceleration, msg.angular_velocity
                        out.values = np.array([a.x, a.y, a.z, w.x, w.y, w.z], dtype=np.float64)
                    else:
                        out.values, out.frame, out.child_frame = _pose_values(msg, conn.msgtype)
                    yield out
        finally:
            self.reader.close()

    def _decode_cloud(self, stream: str, msg: Any, layouts: dict[Any, pc2.Layout]) -> dict[str, Any]:
        key = (stream, int(msg.point_step), bool(msg.is_bigendian),
               tuple((f.name, f.offset, f.datatype, f.count) for f in msg.fields))
        layout = layouts.get(key)
        try:
            if layout is None:
                fields = pc2.fields_of(msg)
                wanted = dict(self.profile.radar_fields if stream == "radar" else self.profile.lidar_fields)
                for col, name in self.field_overrides.items():
                    if col.startswith(stream + "_"):
                        wanted[col.removeprefix(stream + "_")] = [name]
                mapping, missing = pc2.resolve_fields(fields, wanted)
                if missing:
                    raise UserError(
                        f"{self.path}: topic '{self.streams[stream]}' lacks field(s) for {', '.join(missing)} "
                        f"(candidates {[wanted[m] for m in missing]}; message has: "
                        f"{', '.join(f.name for f in fields)}); "
                        f"map them with --set ingest.fields.{stream}_{missing[0]}=NAME"
                    )
                layout = layouts[key] = pc2.prepare(fields, int(msg.point_step), bool(msg.is_bigendian), mapping)
            return pc2.view(layout, msg.data, row_step=int(msg.row_step), width=int(msg.width), height=int(msg.height))
        except pc2.PointCloudError as exc:
            raise UserError(f"{self.path}: topic '{self.streams[stream]}': malformed PointCloud2 ({exc})") from exc

    def _add_tf(self, msg: Any) -> None:
        for tr in msg.transforms:
            key = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
            if key not in self.tf_edges:
                t, q = tr.transform.translation, tr.transform.rotation
                self.tf_edges[key] = pose_matrix([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])


def _why(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# -- extracted folder form ------------------------------------------------------------------------------------
def read_timestamps(path: Path) -> npt.NDArray[np.int64]:
    """Seconds with any number of decimals, one per line, to integer nanoseconds (exact)."""
    try:
        lines = path.read_text().split()
    except OSError as exc:
        raise UserError(f"{path}: cannot read timestamps ({exc})") from exc
    out = np.empty(len(lines), dtype=np.int64)
    try:
        for i, s in enumerate(lines):
            sec, _, frac = s.partition(".")
            sign = -1 if sec.startswith("-") else 1
            out[i] = int(sec) * 1_000_000_000 + sign * int((frac + "000000000")[:9])
    except ValueError:
        raise UserError(f"{path}: line {i + 1} is not a timestamp in seconds ('{lines[i]}')") from None
    return out


def read_table(path: Path, ncols: int) -> npt.NDArray[np.float64]:
    """A whitespace-separated text table with ``ncols`` columns."""
    try:
        arr = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot parse a {ncols}-column text table ({_why(exc)})") from exc
    if arr.size == 0:
        return np.zeros((0, ncols))
    if arr.shape[1] != ncols:
        raise UserError(f"{path}: expected {ncols} columns per line, found {arr.shape[1]}")
    return arr


def read_transform_file(path: Path) -> npt.NDArray[np.float64]:
    """ColoRadar calib transform: ``tx ty tz`` then ``qx qy qz qw`` (base <- sensor)."""
    try:
        nums = [float(v) for v in path.read_text().split()]
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot parse a transform ({_why(exc)})") from exc
    if len(nums) != 7:
        raise UserError(f"{path}: expected 'tx ty tz' and 'qx qy qz qw' (7 numbers), found {len(nums)}")
    return pose_matrix(nums[:3], nums[3:])


def _rows(stream: str, times: npt.NDArray[np.int64], table: npt.NDArray[np.float64]) -> Iterator[Message]:
    for i, t in enumerate(times):
        yield Message(stream, int(t), i, values=table[i], header_ns=int(t), record_ns=int(t))


class FolderSource(Source):
    """The extracted ColoRadar folder (``single_chip/``, ``lidar/``, ``imu/``, ``groundtruth/``, ``calib/``)."""

    def __init__(self, path: Path, profile: DatasetProfile) -> None:
        super().__init__(path=path, profile=profile, form="folder")
        lay = profile.folder
        self.layout = lay
        present = {
            "radar": (path / lay.radar_timestamps).exists(),
            "lidar": (path / lay.lidar_timestamps).exists(),
            "imu": (path / lay.imu_timestamps).exists() and (path / lay.imu_data).exists(),
            "groundtruth": (path / lay.groundtruth_timestamps).exists() and (path / lay.groundtruth_data).exists(),
        }
        where = {"radar": lay.radar_timestamps, "lidar": lay.lidar_timestamps, "imu": lay.imu_data,
                 "groundtruth": lay.groundtruth_data}
        missing = [s for s in profile.required if s in present and not present[s]]
        if missing:
            have = sorted(str(p.relative_to(path)) for p in path.rglob("*.txt"))[:12]
            raise UserError(
                f"{path}: not a complete extracted run: missing {', '.join(where[s] for s in missing)} "
                f"(found: {', '.join(have) or 'no .txt files'}); expected the ColoRadar folder layout"
            )
        self.missing_optional = [where[s] for s, ok in present.items() if not ok and s not in profile.required]
        self.times: dict[str, npt.NDArray[np.int64]] = {}
        for stream, ok in present.items():
            if ok:
                ts_file = getattr(lay, f"{stream}_timestamps")
                self.times[stream] = read_timestamps(path / ts_file)
                self.streams[stream] = ts_file
                self.counts[stream] = len(self.times[stream])
        # calib/ inside the run (a self-contained run), else the dataset's shared calib/ beside the runs
        for sensor in ("radar", "lidar", "imu"):
            rel = getattr(lay, f"calib_{sensor}")
            for base in (path, path.parent):
                f = base / rel
                if f.exists():
                    self.calibration[sensor] = (read_transform_file(f), str(f.relative_to(path.parent)))
                    break

    def _file_index_offset(self, template: str) -> int:
        """0 when files count from ``_0``, 1 when from ``_1``."""
        if (self.path / template.format(i=0)).exists():
            return 0
        return 1 if (self.path / template.format(i=1)).exists() else 0

    def _clouds(self, stream: str) -> Iterator[Message]:
        lay = self.layout
        template = getattr(lay, f"{stream}_files")
        cols = list(getattr(lay, f"{stream}_columns"))
        wanted = ["x", "y", "z", "intensity"] + (["doppler"] if stream == "radar" else [])
        absent = [c for c in wanted if c not in cols]
        if absent:
            raise UserError(f"profile '{self.profile.name}': folder.{stream}_columns lacks {', '.join(absent)}")
        offset = self._file_index_offset(template)
        for i, t in enumerate(self.times[stream]):
            f = self.path / template.format(i=i + offset)
            try:
                raw = f.read_bytes()
            except FileNotFoundError:
                raise UserError(f"{f}: missing ({stream} scan {i} of {self.times[stream].size} listed in "
                                f"{getattr(lay, f'{stream}_timestamps')})") from None
            if len(raw) % (4 * len(cols)):
                raise UserError(f"{f}: {len(raw)} bytes is not a whole number of {len(cols)}-float32 points "
                                f"(truncated file?)")
            self.bytes_read += len(raw)
            arr = np.frombuffer(raw, dtype="<f4").reshape(-1, len(cols))
            yield Message(stream, int(t), i, columns={c: np.ascontiguousarray(arr[:, cols.index(c)]) for c in wanted},
                          header_ns=int(t), record_ns=int(t))

    def messages(self) -> Iterator[Message]:
        import heapq

        lay = self.layout
        gens: list[Iterator[Message]] = []
        for stream in ("radar", "lidar"):
            if stream in self.streams:
                gens.append(self._clouds(stream))
        for stream, data_file, ncols in (("imu", lay.imu_data, 6), ("groundtruth", lay.groundtruth_data, 7)):
            if stream not in self.streams:
                continue
            table = read_table(self.path / data_file, ncols)
            times = self.times[stream]
            if len(table) != len(times):
                raise UserError(
                    f"{self.path / data_file}: {len(table)} lines but {len(times)} timestamps in "
                    f"{getattr(lay, f'{stream}_timestamps')}"
                )
            self.bytes_read += table.nbytes
            gens.append(_rows(stream, times, table))
        # in log order (by time), like a bag; each stream keeps its own order
        yield from heapq.merge(*gens, key=lambda m: m.t_ns)
