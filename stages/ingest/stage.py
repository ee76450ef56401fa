"""`ingest` stage: read a ColoRadar-format log (bag, MCAP, extracted folder) into Parquet artifacts.

Streams the log once: radar and lidar clouds and IMU samples go to Parquet in row-group batches (memory
stays bounded on long bags), ground truth and an optional odometry topic are buffered (small) and
written at the end together with ``calibration.json`` (base <- radar / lidar / imu, 4x4). Topic names,
field names and frames come from the dataset profile ``data/datasets/<dataset>.toml`` (or a profile file
given as ``dataset = "path.toml"``).

Before streaming, the clock of every stream is chosen from its first messages (``clock.time_source``,
:mod:`stages.ingest.clock`): zero, constant or foreign header stamps are lined up and warned about, and
radar and IMU spans that still do not overlap are a user error. Empty radar scans and stretches without
radar points longer than ``clock.radar_gap_warn_s`` are counted in the manifest and warned about. Extrinsics
come from ``--set ingest.frames.<sensor>_extrinsic``, the folder's calib files, tf, the profile's
``[extrinsics.<sensor>]`` (no warning) or identity (warned, naming the frame or its absence).
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
from pydantic import Field, field_validator

from core.errors import UserError
from core.geometry import (
    F64,
    interpolate_poses,
    lookup,
    matrices_to_poses,
    pose_matrix,
    poses_to_matrices,
)
from core.stage import ParamGroup, Stage, StageContext, StageParams
from schemas.io import ArtifactWriter, write_artifact
from sources.recorded import fingerprint
from stages.ingest.clock import NS, ClockPlan, TimeSource, plan_clocks, spans_overlap
from stages.ingest.profile import DatasetProfile, load_profile, profiles_dir
from stages.ingest.readers import Message, Source, open_source
from stages.ingest.sink import LabelSidecar, ReorderBuffer, StreamStats, finite_mask, sort_poses

if TYPE_CHECKING:
    from sources.sequence import SequenceInfo

SENSORS = ("radar", "lidar", "imu")


def _seven(v: list[float]) -> list[float]:
    if v and (len(v) != 7 or not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-9):
        raise ValueError("give 7 numbers: tx ty tz (m) and a non-zero quaternion qx qy qz qw")
    return v


class TopicParams(ParamGroup):
    """Topics that override the dataset profile's ('' = the profile's)."""

    radar: str = Field("", description="radar PointCloud2 topic")
    lidar: str = Field("", description="lidar PointCloud2 topic")
    imu: str = Field("", description="sensor_msgs/Imu topic")
    groundtruth: str = Field("", description="ground-truth pose topic")
    odometry: str = Field("", description="an odometry topic to keep as bag_odometry.parquet")


class FieldParams(ParamGroup):
    """PointCloud2 field names and the Doppler convention that override the profile's."""

    radar_doppler: str = Field("", description="field holding the radar Doppler velocity")
    radar_intensity: str = Field("", description="field holding the radar intensity")
    lidar_intensity: str = Field("", description="field holding the lidar intensity")
    doppler_sign: float | None = Field(None, description="the Doppler sign factor (None: the profile's)")


class FrameParams(ParamGroup):
    """Frame names and extrinsics that override the profile's, tf's and the folder's calib files."""

    base: str = Field("", description="base (body) frame name")
    radar: str = Field("", description="radar frame name (when the messages' frame_id is empty)")
    imu: str = Field("", description="IMU frame name")
    lidar: str = Field("", description="lidar frame name")
    radar_extrinsic: list[float] = Field([], description="base <- radar: a list tx ty tz (m) qx qy qz qw; wins over "
                                                         "tf and the profile")
    imu_extrinsic: list[float] = Field([], description="base <- imu: a list tx ty tz (m) qx qy qz qw")
    lidar_extrinsic: list[float] = Field([], description="base <- lidar: a list tx ty tz (m) qx qy qz qw")

    _check_extrinsics = field_validator("radar_extrinsic", "imu_extrinsic", "lidar_extrinsic")(_seven)


class ClockParams(ParamGroup):
    """Stamps: the clock of each stream, the radar's latency, ordering and gaps."""

    time_source: TimeSource = Field(
        "auto", description="'auto': line up streams whose header stamps are zero, constant or on another clock; "
                            "'header': header stamps as they are; 'record': the log's record time")
    tolerance_s: float = Field(1.0, gt=0, description="auto: header-record offsets further apart than this are "
                                                      "different clocks, s")
    sample: int = Field(50, ge=2, le=1_000_000, description="first messages per stream examined to choose the clock")
    radar_latency_s: float = Field(0.0, ge=-0.5, le=0.5, description="radar stamp minus the time the scan measured "
                                   "the scene (s), subtracted from every radar stamp: a radar stamped on arrival "
                                   "(the TI sensors of ColoRadar) is late by its frame and processing time")
    reorder_window: int = Field(16, ge=1, le=1_000_000,
                                description="messages re-sorted by stamp per stream (out-of-order)")
    radar_gap_warn_s: float = Field(1.0, gt=0, description="warn about a time without radar points longer than this, s")
    max_gap_s: float = Field(5.0, gt=0, le=3600, description="longest time without radar points or IMU samples the "
                             "odometry may dead-reckon through (s); a longer one stops ingest, naming its times")


class IngestRerunParams(ParamGroup):
    """What of the raw streams goes to the Rerun recording."""

    radar_every: int = Field(1, ge=1, le=1_000_000, description="log every n-th raw radar scan")
    lidar_every: int = Field(10, ge=1, le=1_000_000, description="log every n-th lidar scan")
    lidar_points: int = Field(2000, ge=1, le=10_000_000, description="random points kept per logged lidar scan")
    flush_scans: int = Field(500, ge=1, le=1_000_000, description="scans buffered before a Rerun send_columns")
    seed: int = Field(0, description="seed of the lidar downsampling")


class IngestParams(StageParams):
    """Parameters of the `ingest` stage: the dataset profile, overrides of its topics, fields and frames, the
    clocks, and what is recorded."""

    dataset: str = Field("", description="dataset profile in data/datasets/ ('' = the sequence's dataset)")
    batch_rows: int = Field(262_144, ge=1000, le=16_777_216, description="rows per Parquet row group (bounds memory)")
    topics: TopicParams = Field(default_factory=TopicParams, description="topic overrides")
    fields: FieldParams = Field(default_factory=FieldParams, description="field overrides")
    frames: FrameParams = Field(default_factory=FrameParams, description="frame and extrinsic overrides")
    clock: ClockParams = Field(default_factory=ClockParams, description="stamps and gaps")
    rerun: IngestRerunParams = Field(default_factory=IngestRerunParams, description="the Rerun recording")


def _file_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path.is_file() else "missing"


class IngestStage(Stage):
    name = "ingest"
    description = "read a ColoRadar-format log (bag, MCAP, extracted folder) into Parquet artifacts"
    inputs = ()
    #: a map sequence (published maps) has no log: ingest and everything built on it is skipped there
    needs = frozenset({"log"})
    Params = IngestParams
    version = "1"
    outputs = ("radar.parquet", "imu.parquet", "lidar.parquet", "groundtruth.parquet", "calibration.json")

    def key_material(self, seq: SequenceInfo, params: StageParams) -> dict[str, Any]:
        assert isinstance(params, IngestParams)
        dataset = params.dataset or seq.dataset
        where = Path(dataset) if dataset.endswith(".toml") else profiles_dir() / f"{dataset}.toml"
        out: dict[str, Any] = {"profile": dataset, "profile_digest": _file_digest(where)}
        if seq.kind == "simulated":
            # the spec, plus the cache folder name: it hashes the simulator's code and world file too
            out["simulated"] = {"world": seq.world, "duration": seq.duration, "seed": seq.seed, "format": seq.format,
                                "cache": seq.simulated_path().parent.name}
            return out
        path = seq.locate()
        if path is None:
            out["source"] = {"missing": [str(p) for p in seq.expected_locations()]}
            return out
        out["source"] = fingerprint(path)
        sidecar = LabelSidecar.find(path)
        if sidecar is not None:
            out["labels"] = fingerprint(sidecar.path)
        return out

    def run(self, ctx: StageContext) -> None:
        p: IngestParams = ctx.params
        profile = load_profile(p.dataset or ctx.seq.dataset)
        path = ctx.seq.resolve_source()
        topics = {s: getattr(p.topics, s) for s in ("radar", "lidar", "imu", "groundtruth", "odometry")}
        fields = {"radar_doppler": p.fields.radar_doppler, "radar_intensity": p.fields.radar_intensity,
                  "lidar_intensity": p.fields.lidar_intensity}
        src = open_source(path, profile, {k: v for k, v in topics.items() if v}, {k: v for k, v in fields.items() if v})
        ctx.stats["source"] = {"path": str(path), "form": src.form, "profile": profile.name, "streams": src.streams}
        for what in src.missing_optional:
            ctx.warn(f"{path}: no {what}; its artifact will be empty")
        _Ingest(ctx, p, profile, src, path).run()


class _Ingest:
    """One ingest run: the streaming loop and what it writes."""

    def __init__(self, ctx: StageContext, p: IngestParams, profile: DatasetProfile, src: Source, path: Path) -> None:
        self.ctx, self.p, self.profile, self.src, self.path = ctx, p, profile, src, path
        self.sign = profile.radar.doppler_sign if p.fields.doppler_sign is None else p.fields.doppler_sign
        self.labels = LabelSidecar.find(path)
        self.stats = {s: StreamStats() for s in ("radar", "lidar", "imu", "groundtruth", "odometry")}
        self.reorder = {s: ReorderBuffer(p.clock.reorder_window) for s in ("radar", "lidar", "imu")}
        self.scan = {"radar": 0, "lidar": 0}
        self.frames: dict[str, str] = {}
        self.poses: dict[str, tuple[list[int], list[F64], list[str]]] = {
            "groundtruth": ([], [], []), "odometry": ([], [], [])}
        self.scan_times: dict[str, list[int]] = {"radar": [], "lidar": []}
        self.rng = np.random.default_rng(p.rerun.seed)
        self.rr_buf: dict[str, list[Any]] = {"radar": [], "lidar": []}
        self.imu_buf: list[tuple[int, F64]] = []
        self.clock: ClockPlan = plan_clocks(src.clock_samples(p.clock.sample), p.clock.time_source,
                                                  p.clock.tolerance_s)
        #: radar: time of the last scan with points, empty scans since, and the gaps found (start, length, empties)
        self.last_points_t: int | None = None
        self.empty_since = 0
        self.gaps: list[tuple[int, int, int]] = []
        self.imu_max_gap_ns = 0
        self.imu_max_gap_at = 0
        label_field = [pa.field("label", pa.int8(), nullable=False)]
        self.writers = {
            "radar": ArtifactWriter(ctx.output("radar.parquet"), "radar", extra=label_field, batch_rows=p.batch_rows),
            "lidar": ArtifactWriter(ctx.output("lidar.parquet"), "lidar", batch_rows=p.batch_rows),
            "imu": ArtifactWriter(ctx.output("imu.parquet"), "imu", batch_rows=p.batch_rows),
        }

    # -- main loop ------------------------------------------------------------------------------------------------
    def run(self) -> None:
        ctx = self.ctx
        t0 = time.perf_counter()
        total = sum(self.src.counts.values()) or None
        try:
            with ctx.progress(total, f"reading {self.path.name}") as advance:
                for i, msg in enumerate(self.src.messages()):
                    self._arrive(msg)
                    if i % 256 == 255:
                        advance(256)
                for buf in self.reorder.values():
                    for m in buf.flush():
                        self._emit(m)
            self._flush_imu()
            for stream in ("radar", "lidar"):
                self._flush_rerun(stream)
            for w in self.writers.values():
                w.close()
        except BaseException:
            for w in self.writers.values():
                w.abort()
            raise
        seconds = time.perf_counter() - t0
        gt = self._write_poses("groundtruth", ctx.output("groundtruth.parquet"))
        if "odometry" in self.src.streams:
            self._write_poses("odometry", ctx.output("bag_odometry.parquet"))
        calib = self._calibration()
        ctx.output("calibration.json").write_text(json.dumps(calib, indent=2) + "\n")
        self._log_transforms(gt, calib)
        self._report(seconds)

    def _arrive(self, msg: Message) -> None:
        st = self.stats[msg.stream]
        st.messages += 1
        clock = self.clock.streams.get(msg.stream)
        if clock is not None:
            msg.t_ns = clock.time(msg.header_ns, msg.record_ns)
            msg.record_time = clock.use == "record" or (clock.use == "header" and msg.header_ns == 0)
        if msg.stream == "radar" and self.p.clock.radar_latency_s:
            msg.t_ns -= round(self.p.clock.radar_latency_s * NS)
        st.record_time_used += int(msg.record_time)
        if msg.frame and msg.stream not in self.frames:
            self.frames[msg.stream] = msg.frame.lstrip("/")
        if msg.stream in self.reorder:
            for m in self.reorder[msg.stream].push(msg):
                self._emit(m)
        else:
            t, v, child = self.poses[msg.stream]
            assert msg.values is not None
            t.append(msg.t_ns)
            v.append(msg.values)
            child.append(msg.child_frame.lstrip("/"))
            if msg.frame and msg.stream + "_parent" not in self.frames:
                self.frames[msg.stream + "_parent"] = msg.frame.lstrip("/")

    def _emit(self, msg: Message) -> None:
        st = self.stats[msg.stream]
        st.first_t_ns = msg.t_ns if st.first_t_ns is None else st.first_t_ns
        if msg.stream == "imu" and st.last_t_ns is not None and msg.t_ns - st.last_t_ns > self.imu_max_gap_ns:
            self.imu_max_gap_ns = msg.t_ns - st.last_t_ns
            self.imu_max_gap_at = st.last_t_ns
        st.last_t_ns = msg.t_ns
        if msg.stream == "imu":
            assert msg.values is not None
            self.imu_buf.append((msg.t_ns, msg.values))  # non-finite samples are dropped in _flush_imu
            if len(self.imu_buf) >= 65536:
                self._flush_imu()
            return
        assert msg.columns is not None
        cols = msg.columns
        n_all = len(cols["x"])
        ok = finite_mask(cols)
        st.nonfinite_dropped += int(n_all - ok.sum())
        # no-return points (x = y = z = 0, e.g. the Ouster driver's organised cloud) are not measurements
        zero = (cols["x"] == 0) & (cols["y"] == 0) & (cols["z"] == 0)
        st.zero_dropped += int(zero.sum())
        ok &= ~zero
        n_bad = int(n_all - ok.sum())
        if n_bad:
            cols = {k: v[ok] for k, v in cols.items()}
        n = n_all - n_bad
        st.empty_messages += int(n_all == 0)
        st.scans_without_points += int(n == 0)
        if msg.stream == "radar":
            self._track_gap(msg.t_ns, n)
        scan = self.scan[msg.stream]
        self.scan[msg.stream] += 1
        self.scan_times[msg.stream].append(msg.t_ns)
        out: dict[str, Any] = {"scan": np.full(n, scan, np.int32), "t_ns": np.full(n, msg.t_ns, np.int64), **cols}
        if msg.stream == "radar":
            out["doppler"] = cols["doppler"] * np.float32(self.sign)
            if self.labels is not None:
                lab = self.labels.labels_for(msg.index, msg.t_ns, n_all)
                out["label"] = lab[ok] if n_bad else lab
            else:
                out["label"] = np.full(n, -1, np.int8)
        st.points += n
        self.writers[msg.stream].write(out)
        self._buffer_rerun(msg.stream, scan, msg.t_ns, cols)

    def _track_gap(self, t_ns: int, n: int) -> None:
        """Radar gaps: stretches longer than ``clock.radar_gap_warn_s`` between scans with points."""
        if n == 0:
            self.empty_since += 1
            return
        last = self.last_points_t
        if last is not None and t_ns - last > self.p.clock.radar_gap_warn_s * NS:
            self.gaps.append((last, t_ns - last, self.empty_since))
        self.last_points_t = t_ns
        self.empty_since = 0

    def _flush_imu(self) -> None:
        if not self.imu_buf:
            return
        t = np.fromiter((x[0] for x in self.imu_buf), np.int64, len(self.imu_buf))
        v = np.stack([x[1] for x in self.imu_buf])
        self.imu_buf = []
        ok = np.isfinite(v).all(axis=1)
        st = self.stats["imu"]
        st.nonfinite_dropped += int((~ok).sum())
        st.points += int(ok.sum())
        if not ok.all():
            t, v = t[ok], v[ok]
        names = ("ax", "ay", "az", "gx", "gy", "gz")
        self.writers["imu"].write({"t_ns": t, **{c: v[:, i] for i, c in enumerate(names)}})

    # -- ground truth / odometry -----------------------------------------------------------------------------
    def _write_poses(self, stream: str, out: Path) -> tuple[npt.NDArray[np.int64], F64]:
        t_list, v_list, children = self.poses[stream]
        t = np.asarray(t_list, dtype=np.int64)
        v = np.stack(v_list) if v_list else np.zeros((0, 7))
        t, v, backwards, dropped = sort_poses(t, v)
        st = self.stats[stream]
        st.backwards, st.out_of_order_dropped, st.points = backwards, dropped, len(t)
        if len(t):
            st.first_t_ns, st.last_t_ns = int(t[0]), int(t[-1])
        child = next((c for c in children if c), "")
        base = self._base_frame()
        if len(t) and child and base and child != base:
            # poses are of `child` in world: world <- base = (world <- child) (child <- base)
            T = lookup(self.src.tf_edges, child, base)
            if T is None:
                self.ctx.warn(f"{stream}: poses are of frame '{child}', not the base '{base}', and no tf links "
                              f"them; kept as they are")
            else:
                v = matrices_to_poses(poses_to_matrices(v) @ T)
        if v.size:
            v[:, 3:] *= np.where(v[:, 6:7] < 0, -1.0, 1.0)  # one hemisphere
        cols = {"t_ns": t, **{c: v[:, i] for i, c in enumerate(("x", "y", "z", "qx", "qy", "qz", "qw"))}}
        write_artifact(cols, out, "groundtruth", metadata={"frame_parent": self.frames.get(stream + "_parent", ""),
                                                            "frame_child": base})
        return t, v

    # -- calibration -------------------------------------------------------------------------------------------
    def _frame(self, sensor: str) -> str:
        """A sensor's frame name: --set ingest.frames.<sensor>, else the profile's [frames] entry when the
        messages carry an empty frame_id, else the messages' frame_id ('' when there is none)."""
        override = getattr(self.p.frames, sensor)
        return override or self.frames.get(sensor) or getattr(self.profile.frames, sensor)

    def _base_frame(self) -> str:
        return self.p.frames.base or self.profile.frames.base or self._frame("imu") or self._frame("radar") or "base"

    def _calibration(self) -> dict[str, Any]:
        base = self._base_frame()
        out: dict[str, Any] = {"base_frame": base, "convention": "base_from_<sensor>: 4x4, p_base = T @ p_sensor"}
        sources: dict[str, str] = {}
        frames: dict[str, str] = {}
        ext = self.profile.extrinsics
        given = set() if ext.fallback else ext.model_fields_set
        for sensor in SENSORS:
            frame = self._frame(sensor)
            frames[sensor] = frame
            T: F64 | None = None
            override = getattr(self.p.frames, f"{sensor}_extrinsic")
            if override:
                T, sources[sensor] = pose_matrix(override[:3], override[3:]), f"--set ingest.frames.{sensor}_extrinsic"
            elif sensor in self.src.calibration:
                T, how = self.src.calibration[sensor]
                sources[sensor] = f"file {how}"
            elif self.src.tf_edges and frame:
                T = lookup(self.src.tf_edges, base, frame)
                sources[sensor] = "tf"
            if T is None and sensor in given:
                T = getattr(self.profile.extrinsics, sensor).matrix()
                sources[sensor] = f"profile {self.profile.path or self.profile.name} [extrinsics.{sensor}]"
            if T is None and frame == base:
                T, sources[sensor] = np.eye(4), "identity (sensor frame is the base)"
            if T is None:
                T = getattr(self.profile.extrinsics, sensor).matrix()
                sources[sensor] = f"profile '{self.profile.name}' default"
                if sensor in self.src.streams and self.src.form != "folder":
                    named = f"frame '{frame}'" if frame else f"the {sensor} messages' empty frame_id"
                    how = "has no tf" if not self.src.tf_edges else f"has no tf from '{base}' to it"
                    self.ctx.warn(f"{self.path.name} {how} for {named} (topic {self.src.streams[sensor]}) and "
                                  f"profile '{self.profile.name}' gives no [extrinsics.{sensor}]: assuming base<-"
                                  f"{sensor} = identity; give it in a profile (pipeline profile new my_rig.toml) or "
                                  f"with --set ingest.frames.{sensor}_extrinsic=[tx,ty,tz,qx,qy,qz,qw]")
            out[f"base_from_{sensor}"] = np.round(T, 12).tolist()
        out["frames"] = frames
        out["sources"] = sources
        self.ctx.stats["calibration"] = sources
        return out

    # -- Rerun -----------------------------------------------------------------------------------------------------
    def _buffer_rerun(self, stream: str, scan: int, t_ns: int, cols: dict[str, Any]) -> None:
        p = self.p
        every = p.rerun.radar_every if stream == "radar" else p.rerun.lidar_every
        if scan % every:
            return
        xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
        if stream == "lidar" and len(xyz) > p.rerun.lidar_points:
            xyz = xyz[np.sort(self.rng.choice(len(xyz), p.rerun.lidar_points, replace=False))]
        self.rr_buf[stream].append((scan, t_ns, xyz))
        if len(self.rr_buf[stream]) >= p.rerun.flush_scans:
            self._flush_rerun(stream)

    def _flush_rerun(self, stream: str) -> None:
        buf = self.rr_buf[stream]
        if not buf:
            return
        self.rr_buf[stream] = []
        import rerun as rr

        from core.recording import time_columns

        radar = stream == "radar"
        entity = "world/radar/raw" if radar else "world/lidar"
        colour = np.asarray((255, 140, 0) if radar else (140, 140, 160), np.uint8)
        xyz = np.concatenate([b[2] for b in buf]).astype(np.float32)
        # lidar sweeps have their own clock: on the sensor_time timeline only (the scan timeline is the radar's)
        index = time_columns([b[0] for b in buf] if radar else None, [b[1] for b in buf])
        cols = rr.Points3D.columns(positions=xyz, colors=np.tile(colour, (len(xyz), 1)),
                                   radii=np.full(len(xyz), 0.04 if radar else 0.02, np.float32))
        self.ctx.recording.rec.send_columns(entity, indexes=index,
                                            columns=cols.partition(lengths=[len(b[2]) for b in buf]))

    def _log_transforms(self, gt: tuple[npt.NDArray[np.int64], F64], calib: dict[str, Any]) -> None:
        """Ground truth as a path; sensor clouds placed in the world by ground truth (world <- sensor)."""
        import rerun as rr

        from core.recording import time_columns

        t, v = gt
        rec = self.ctx.recording
        if len(t) == 0:
            return
        # ground truth has its own clock: on the sensor_time timeline only (no scan index)
        green = np.asarray((60, 200, 60), np.uint8)
        path = rr.LineStrips3D([v[:, :3].astype(np.float32)], colors=[green])
        rec.rec.log("world/groundtruth/path", path, static=True)
        rec.rec.send_columns("world/groundtruth/pose", indexes=time_columns(None, t),
                             columns=rr.Points3D.columns(positions=v[:, :3], colors=np.tile(green, (len(t), 1)),
                                                         radii=np.full(len(t), 0.08, np.float32)).partition(
                                 lengths=np.ones(len(t), np.int64)))
        for stream, entity in (("radar", "world/radar/raw"), ("lidar", "world/lidar")):
            every = self.p.rerun.radar_every if stream == "radar" else self.p.rerun.lidar_every
            times = np.asarray(self.scan_times[stream], dtype=np.int64)
            scans = np.arange(len(times))[::every]
            times = times[::every]
            if times.size == 0:
                continue
            T, _ = interpolate_poses(t, v, times)
            T = T @ np.asarray(calib[f"base_from_{stream}"])
            quat = matrices_to_poses(T)[:, 3:]
            rec.rec.send_columns(entity, indexes=time_columns(scans if stream == "radar" else None, times),
                                 columns=rr.Transform3D.columns(translation=T[:, :3, 3], quaternion=quat))

    def _report(self, seconds: float) -> None:
        ctx = self.ctx
        for stream, buf in self.reorder.items():
            st = self.stats[stream]
            st.backwards, st.out_of_order_dropped = buf.backwards, buf.dropped
        for stream, st in self.stats.items():
            if st.backwards:
                ctx.warn(f"{stream}: time went backwards {st.backwards} time(s) in {self.path.name}"
                         + (f" (first at t={buf_first(self.reorder.get(stream))})" if stream in self.reorder else "")
                         + f"; re-sorted, {st.out_of_order_dropped} message(s) older than already written ones dropped")
            if st.nonfinite_dropped:
                what = "samples" if stream == "imu" else "points"
                ctx.warn(f"{stream}: dropped {st.nonfinite_dropped} {what} with NaN/inf values")
            if st.record_time_used and not (stream in self.clock.streams and self.clock.changed):
                ctx.warn(f"{stream}: {st.record_time_used} message(s) had a zero header stamp; used the record time")
        self._report_clocks_and_gaps()
        if self.labels is not None and self.labels.unmatched_scans:
            ctx.warn(f"{self.labels.path}: no labels for {self.labels.unmatched_scans} radar scan(s)")
        ctx.stats["streams"] = {s: st.as_dict() for s, st in self.stats.items() if st.messages or st.points}
        ctx.stats["nonfinite_dropped"] = {s: st.nonfinite_dropped for s, st in self.stats.items()}
        ctx.stats["zero_points_dropped"] = {s: self.stats[s].zero_dropped for s in ("radar", "lidar")}
        ctx.stats["labels"] = str(self.labels.path) if self.labels is not None else None
        n_msgs = sum(st.messages for st in self.stats.values())
        ctx.stats["read"] = {"seconds": round(seconds, 3), "messages": n_msgs, "bytes": self.src.bytes_read,
                             "messages_per_s": round(n_msgs / max(seconds, 1e-9), 1),
                             "mb_per_s": round(self.src.bytes_read / 1e6 / max(seconds, 1e-9), 2)}
        if "radar" in self.src.streams and self.stats["radar"].messages == 0:
            raise UserError(f"{self.path}: radar topic '{self.src.streams['radar']}' holds no messages")
        radar = self.stats["radar"]
        if "radar" in self.src.streams and radar.points == 0:
            raise UserError(f"{self.path}: radar topic '{self.src.streams['radar']}': all {radar.messages} scan(s) are "
                            f"empty or hold only NaN/inf points ({radar.nonfinite_dropped} non-finite dropped); there "
                            f"is nothing to run on: check the topic (--set ingest.topics.radar=TOPIC) and the "
                            "recording")
        self._check_gaps()

    def _check_gaps(self) -> None:
        """A stretch without radar points or IMU samples longer than ``clock.max_gap_s`` (a clock jump, a pause, a
        dropout) is an error naming its times: the odometry would dead-reckon through it."""
        limit = self.p.clock.max_gap_s * NS
        found = [("radar points", a, d) for a, d, _e in self.gaps if d > limit]
        if self.imu_max_gap_ns > limit:
            found.append(("IMU samples", self.imu_max_gap_at, self.imu_max_gap_ns))
        if not found:
            return
        what, start, length = max(found, key=lambda g: g[2])
        firsts = [st.first_t_ns for st in self.stats.values() if st.first_t_ns is not None]
        t0 = min(firsts) if firsts else start
        more = f" ({len(found) - 1} more)" if len(found) > 1 else ""
        raise UserError(
            f"{self.path}: no {what} for {length / NS:.1f} s, from {(start - t0) / NS:.1f} s to "
            f"{(start + length - t0) / NS:.1f} s into the log (stamps {start / NS:.3f} to {(start + length) / NS:.3f})"
            f"{more}: a clock jump or a pause longer than the odometry can bridge (ingest.clock.max_gap_s="
            f"{self.p.clock.max_gap_s:g} s); cut the log there (e.g. with `rosbag filter`) or raise "
            "ingest.clock.max_gap_s")


    def _report_clocks_and_gaps(self) -> None:
        ctx, plan, name = self.ctx, self.clock, self.path.name
        ctx.stats["clock"] = {"time_source": plan.source, "streams": plan.as_dict()}
        if plan.changed:
            if plan.source == "auto":
                ctx.warn(f"{name}: streams on different clocks, lined up (ingest.clock.time_source=auto): "
                         f"{plan.describe()}")
            elif plan.source == "header":
                bad = [c for c in plan.streams.values() if c.problem]
                if bad:
                    ctx.warn(f"{name}: {'; '.join(f'{c.stream}: {c.problem}' for c in bad)} (ingest.clock.time_source="
                             f"header); --set ingest.clock.time_source=auto lines the streams up")
            else:
                ctx.warn(f"{name}: every stream timed by the bag's record time (ingest.clock.time_source=record): "
                         f"{plan.describe()}")
        spans = {s: (st.first_t_ns, st.last_t_ns) for s, st in self.stats.items()
                 if st.first_t_ns is not None and st.last_t_ns is not None}
        if "radar" in spans and "imu" in spans and not spans_overlap(spans["radar"], spans["imu"]):
            t0 = min(spans["radar"][0], spans["imu"][0])

            def rel(s: str) -> str:
                a, b = spans[s]
                return f"{(a - t0) / NS:.1f}-{(b - t0) / NS:.1f} s"

            fix = ("set ingest.clock.time_source=record (the bag's record time for both)" if plan.source == "auto" else
                   "set ingest.clock.time_source=auto (lines up zero or foreign stamps) or record")
            raise UserError(f"{self.path}: radar and IMU clocks never overlap (radar {rel('radar')}, IMU {rel('imu')}, "
                            f"time_source={plan.source}); {fix}")
        radar = self.stats["radar"]
        ctx.stats["radar_empty_scans"] = radar.scans_without_points
        first = radar.first_t_ns or 0
        ctx.stats["radar_gaps"] = [{"start_s": round((a - first) / NS, 3), "length_s": round(d / NS, 3),
                                    "empty_scans": e} for a, d, e in self.gaps]
        ctx.stats["imu_max_gap_s"] = round(self.imu_max_gap_ns / NS, 4)
        if radar.scans_without_points:
            ctx.warn(f"radar: {radar.scans_without_points} of {radar.messages} scan(s) hold no points "
                     f"({radar.empty_messages} published empty)")
        for a, d, e in [g for g in self.gaps if g[1] <= self.p.clock.max_gap_s * NS][:5]:
            ctx.warn(f"radar: no points for {d / NS:.2f} s from {(a - (radar.first_t_ns or a)) / NS:.2f} s into the "
                     f"radar stream (stamp {a / NS:.3f}, {e} empty scan(s)); odometry dead-reckons through it")
        if len(self.gaps) > 5:
            ctx.warn(f"radar: {len(self.gaps) - 5} more gap(s) longer than {self.p.clock.radar_gap_warn_s:g} s "
                     f"(all in the manifest: radar_gaps)")


def buf_first(buf: ReorderBuffer | None) -> str:
    if buf is None or buf.first_backwards_ns is None:
        return "?"
    return f"{buf.first_backwards_ns * 1e-9:.6f} s"


STAGE = IngestStage()
