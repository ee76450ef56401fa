"""`voxel` stage: radar and lidar OctoMap-style voxel maps (RMap Sec. III-A).

Both maps are sparse log-odds voxel maps at 0.15 m (``voxel_map.py``) built along a trajectory:

- radar map: the radar-specific sensor model of the ColoRadar OctoMap fork (``radar_model.py``): the
  voxels on a fan of rays covering the radar field of view are misses, returns inside the fan are hits;
  built along ``trajectory`` (``groundtruth`` as in the paper, or ``odometry`` / ``slam`` for a radar-only
  map);
- lidar map: OctoMap ray casting (``raycast.py``, equal to ``OcTree.insertPointCloud`` up to edge ties)
  of the lidar restricted to a horizontal field of view of 180 degrees centred on the radar boresight;
  always built along the ground truth (it is the reference map of the evaluation).

Radar-only maps (``trajectory.source = "odometry" | "slam"``): the planar estimate (x, y, yaw: the odometry's or a
SLAM method's) is combined with the odometry's height, roll and pitch at the same radar scan times
(``attitude = "odometry"``, default; ``interpolate_planar_attitude``). RICH-SLAM and the grid filter estimate
only the planar pose and start from the odometry's, so the 3D pose is the odometry's with its x, y and yaw
replaced by the SLAM method's. How good that is depends on the EKF's vertical channel: on coloradar_5_twin its
height drifts to -2.9 m and its pitch error reaches 11 degrees (docs/radar_only.md), where the level lift
wins. The level lift (zero roll and pitch at the constant base height ``trajectory.level_height``: default the first
ground-truth height, 0 without ground truth) stays as ``attitude = "level"``;
on the handheld ColoRadar rig, whose roll and pitch reach several degrees, it tilts far walls by decimetres.
A trajectory that covers less than ``trajectory.min_coverage`` of the radar scans is an error; a named SLAM method that
was not run is an error that lists the ones that were. Poses at sensor times: linear position and slerp
rotation between ground-truth samples; scans outside the trajectory's time span are skipped (counted).

Cost: the radar fan (10,816 rays to 10 m, about 1.1 M voxel crossings per scan) takes about 40 ms of
CPU per radar scan whatever the number of returns (about 25 s for a 60 s sequence at 10 Hz); the lidar
ray casting runs at about 1e5 points/s (``lidar_stride`` inserts every k-th scan when lidar scans are
dense, e.g. a full OS1-64).

Writes the occupied voxel centres with their log-odds (``radar_map.parquet``, ``lidar_map.parquet``),
optionally OctoMap ``.bt`` files (when the ``octomap`` binding is importable), and logs both maps to
Rerun (``world/voxel/radar``, ``world/voxel/lidar``, static, coloured by height).

Map sequences (``rmap_<scene>``, ``maps = "import"``): the published maps *are* this stage's outputs. The
scene's radar map and ``lidar_filtered`` map (the RMap ground truth) are read from the map set
(``sources.mapset``, either layout) and written unchanged in float64 as ``radar_map.parquet`` and
``lidar_map.parquet`` (``log_odds`` NaN: not published), with ``map_poses.parquet`` and
``map_trajectory.parquet``; the manifest's ``stats.map_set`` records the scene, split, environment and
where ``lidar_filtered`` came from (``map`` or ``rebuilt``). Nothing is written when any file is bad.
Log sequences write ``map_trajectory.parquet`` too: the radar's positions at the scans the radar map was built
from (along ``trajectory.source``), so the band pre-filter and the voxel completion model run on every sequence.

A log without ground truth (radar + IMU only) cannot give the paper's maps: with ``trajectory.source =
"groundtruth"`` the stage is skipped with that reason (``--set voxel.trajectory.source=odometry`` builds the radar
map along the odometry instead).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt
from pydantic import Field, model_validator

from core.errors import UserError
from core.recording import scan_lengths
from core.stage import ParamGroup, Stage, StageContext, StageParams, parquet_rows
from schemas.io import read_artifact, write_artifact
from sources import mapset
from stages.voxel import octomap_io
from stages.voxel.poses import horizontal_fov_mask, interpolate_planar_attitude, interpolate_se2, interpolate_se3
from stages.voxel.radar_model import fan_directions, radar_scan_keys
from stages.voxel.raycast import scan_update_keys
from stages.voxel.voxel_map import SensorModel, VoxelMap

if TYPE_CHECKING:
    from sources.sequence import SequenceInfo

F64 = npt.NDArray[np.float64]


class TrajectoryParams(ParamGroup):
    """The path the radar map is built along (the lidar map always uses ground truth)."""

    source: Literal["groundtruth", "odometry", "slam"] = Field(
        "groundtruth", description="groundtruth (as the paper), the odometry, or a slam trajectory")
    slam_method: str = Field(
        "", description="with source=slam: read trajectory_<method>.parquet ('' = trajectory.parquet)")
    attitude: Literal["odometry", "level"] = Field(
        "odometry", description="with source=odometry|slam: z, roll and pitch from the odometry (its EKF's 3D pose) "
        "or 'level' (zero roll and pitch at the constant height level_height)")
    level_height: float | None = Field(
        None, description="with attitude=level: base height (m); None = first ground-truth z (0 without ground truth)")
    min_coverage: float = Field(
        0.9, ge=0, le=1, description="with source=odometry|slam: the least share of radar scans the trajectory must "
        "cover (an error below it; the uncovered scans are skipped with a warning above it)")


class OccupancyParams(ParamGroup):
    """OctoMap's log-odds sensor model (RMap Sec. III-A)."""

    prob_hit: float = Field(0.7, gt=0, lt=1, description="occupancy probability of a hit")
    prob_miss: float = Field(0.4, gt=0, lt=1, description="occupancy probability of a miss")
    radar_prob_miss: float | None = Field(
        None, gt=0, lt=1, description="miss probability of the radar model only (default: prob_miss); 0.5 makes the "
        "radar map the plain accumulation of hits")
    clamp_min: float = Field(0.12, gt=0, lt=1, description="lower clamping threshold (probability)")
    clamp_max: float = Field(0.97, gt=0, lt=1, description="upper clamping threshold (probability)")
    threshold: float = Field(0.5, gt=0, lt=1, description="a voxel is occupied above this probability")

    @model_validator(mode="after")
    def _clamps(self) -> OccupancyParams:
        if self.clamp_min >= self.clamp_max:
            raise ValueError(f"clamp_min ({self.clamp_min}) must be below clamp_max ({self.clamp_max})")
        return self


class RadarFanParams(ParamGroup):
    """The radar's points and its ray fan."""

    points: Literal["raw", "filtered"] = Field(
        "raw", description="ingest's raw radar.parquet (as the paper) or the filter stage's output")
    azimuth_fov_deg: float = Field(45.0, gt=0, le=90, description="fan half-angle in azimuth (deg)")
    elevation_fov_deg: float = Field(45.0, gt=0, le=90, description="fan half-angle in elevation (deg)")
    min_range: float = Field(0.0, ge=0, description="fan rays start at this range (m)")
    max_range: float = Field(10.0, gt=0, description="fan range (m); returns beyond it are ignored")


class LidarScanParams(ParamGroup):
    """The lidar scans inserted into the reference map."""

    fov_deg: float = Field(180.0, gt=0, le=360, description="horizontal field of view kept, centred on the radar "
                                                             "boresight (deg)")
    min_range: float = Field(0.0, ge=0, description="drop points closer than this (m)")
    max_range: float = Field(20.0, ge=0, description="drop points farther than this (m); 0 = no limit")
    stride: int = Field(1, ge=1, le=1_000_000, description="insert every k-th scan (speed)")
    discretize: bool = Field(False, description="cast one ray per distinct end voxel (OctoMap's discretize option: "
                                                "same hits, slightly different misses, faster on dense scans)")


class VoxelParams(StageParams):
    """Parameters of the `voxel` stage (defaults: RMap Sec. III-A and the ColoRadar OctoMap fork)."""

    maps: Literal["build", "import"] = Field(
        "build", description="build the maps from the ingested log, or import a published map set (the default "
        "of map sequences, rmap_<scene>)")
    resolution: float = Field(0.15, ge=0.01, description="voxel edge length (m)")
    export_bt: bool = Field(False, description="also write radar_map.bt / lidar_map.bt (needs the octomap binding)")
    trajectory: TrajectoryParams = Field(default_factory=TrajectoryParams, description="the radar map's path")
    occupancy: OccupancyParams = Field(default_factory=OccupancyParams, description="the sensor model")
    radar: RadarFanParams = Field(default_factory=RadarFanParams, description="the radar")
    lidar: LidarScanParams = Field(default_factory=LidarScanParams, description="the lidar")


class VoxelStage(Stage):
    name = "voxel"
    description = "radar and lidar OctoMap-style voxel maps (RMap Sec. III-A)"
    inputs = ("ingest",)
    Params = VoxelParams
    version = "3"
    outputs = ("radar_map.parquet", "lidar_map.parquet")

    def input_stages(self, params: StageParams) -> tuple[str, ...]:
        assert isinstance(params, VoxelParams)
        if params.maps == "import":
            return ()
        extra: list[str] = []
        if params.trajectory.source in ("odometry", "slam"):
            extra.append(params.trajectory.source)
        if params.trajectory.source == "slam" and params.trajectory.attitude == "odometry":
            extra.append("odometry")
        if params.radar.points == "filtered":
            extra.append("filter")
        return (*self.inputs, *extra)

    def skip_reason(self, seq: SequenceInfo, params: StageParams) -> str | None:
        assert isinstance(params, VoxelParams)
        if params.maps == "import" and "maps" not in seq.provides:
            return f"voxel.maps=import needs a published map set; '{seq.name}' is a {seq.kind_label}"
        return super().skip_reason(seq, params)

    def skip_reason_for_inputs(self, seq: SequenceInfo, params: StageParams,
                               input_dirs: Mapping[str, Path]) -> str | None:
        assert isinstance(params, VoxelParams)
        if params.maps == "build" and params.trajectory.source == "groundtruth" and "ingest" in input_dirs:
            if parquet_rows(input_dirs["ingest"] / "groundtruth.parquet") == 0:
                return ("the log has no ground truth, so no paper maps (--set voxel.trajectory.source=odometry "
                        "builds the "
                        "radar map along the odometry)")
        return None

    def key_material(self, seq: SequenceInfo, params: StageParams) -> dict[str, Any]:
        assert isinstance(params, VoxelParams)
        if params.maps != "import" or seq.kind != "rmap":
            return {}
        root = seq.map_root_or_none()
        scene = seq.scene or seq.name
        return {"map_set": mapset.fingerprint(root, scene) if root is not None else {"missing": scene}}

    def run(self, ctx: StageContext) -> None:
        p: VoxelParams = ctx.params
        if p.maps == "import":
            self._import(ctx, p)
            return
        calib = _read_calibration(ctx)
        gt = read_artifact(ctx.input("ingest", "groundtruth.parquet"), "groundtruth")
        gt_t = gt.column("t_ns").to_numpy()
        gt_xyz = np.stack([gt.column(c).to_numpy() for c in ("x", "y", "z")], axis=1)
        gt_q = np.stack([gt.column(c).to_numpy() for c in ("qx", "qy", "qz", "qw")], axis=1)
        occ = p.occupancy
        model = SensorModel(occ.prob_hit, occ.prob_miss, occ.clamp_min, occ.clamp_max, occ.threshold)
        radar_miss = occ.radar_prob_miss if occ.radar_prob_miss is not None else occ.prob_miss
        radar_model = SensorModel(occ.prob_hit, radar_miss, occ.clamp_min, occ.clamp_max, occ.threshold)
        if len(gt_t) == 0:
            if p.trajectory.source == "groundtruth":
                raise UserError(f"{ctx.input('ingest', 'groundtruth.parquet')}: no ground-truth poses; build the radar "
                                "map along another trajectory with --set voxel.trajectory.source=odometry")
            ctx.warn("no ground-truth poses: the lidar map is empty")

        def gt_poses(t: npt.NDArray[np.int64]) -> tuple[F64, npt.NDArray[np.bool_]]:
            if len(gt_t) == 0:
                return np.tile(np.eye(4), (len(t), 1, 1)), np.zeros(len(t), bool)
            return interpolate_se3(t, gt_t, gt_xyz, gt_q)

        radar_poses, traj_path = ((gt_poses, None) if p.trajectory.source == "groundtruth"
                                    else self._se2_poses(ctx, p, gt_xyz))
        radar_map, sensor_xyz = self._radar_map(ctx, p, radar_model, calib["base_from_radar"], radar_poses, traj_path)
        lidar_map = self._lidar_map(ctx, p, model, calib, gt_poses)
        # the positions the radar map was built along (the radar's, one per integrated scan): what the band
        # pre-filter and the voxel completion model read, as for a map set's recorded trajectory
        write_artifact({"x": sensor_xyz[:, 0], "y": sensor_xyz[:, 1], "z": sensor_xyz[:, 2]},
                       ctx.output("map_trajectory.parquet"), "map_trajectory",
                       metadata={"trajectory": p.trajectory.source,
                                 "frame": "radar sensor positions at the radar scans"})

        for kind, vmap in (("radar", radar_map), ("lidar", lidar_map)):
            xyz, lo = vmap.centres()
            write_artifact({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "log_odds": lo},
                           ctx.output(f"{kind}_map.parquet"), f"{kind}_map",
                           metadata={"resolution": str(p.resolution), "trajectory":
                                     p.trajectory.source if kind == "radar" else "groundtruth"})
            ctx.stats[f"{kind}_voxels"] = vmap.counts()
            ctx.recording.static_points(f"world/voxel/{kind}", xyz, colors=height_colors(xyz[:, 2]),
                                        radii=p.resolution / 2)
            if p.export_bt:
                if octomap_io.available():
                    keys, values = vmap.voxels(occupied_only=False)
                    octomap_io.write_bt(ctx.output(f"{kind}_map.bt"), keys, values, p.resolution,
                                        radar_model if kind == "radar" else model)
                else:
                    ctx.warn("export_bt: the octomap binding is not installed (pip install octomap-python); "
                             "no .bt written")
        n_r, n_l = ctx.stats["radar_voxels"]["occupied"], ctx.stats["lidar_voxels"]["occupied"]
        ctx.stats["lr_ratio"] = n_l / n_r if n_r else float("nan")

    # -- published map sets ----------------------------------------------------------------------------
    def _import(self, ctx: StageContext, p: VoxelParams) -> None:
        """Write a map set's radar and lidar_filtered maps (float64 as stored) and trajectories."""
        seq = ctx.seq
        scene = seq.scene or seq.name
        ms = mapset.read_map_set(seq.map_root(), scene)
        meta = {"resolution": str(p.resolution), "source": f"map set {ms.layout} {ms.root}", "scene": scene,
                "log_odds": "not published (imported map)"}
        for kind, pts in (("radar", ms.radar), ("lidar", ms.lidar_filtered)):
            extra = {"lidar_filtered_source": ms.lidar_filtered_source} if kind == "lidar" else {}
            write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2],
                            "log_odds": np.full(len(pts), np.nan, np.float32)},
                           ctx.output(f"{kind}_map.parquet"), f"{kind}_map", metadata={**meta, **extra})
            ctx.recording.static_points(f"world/voxel/{kind}", pts, colors=height_colors(pts[:, 2]),
                                        radii=p.resolution / 2)
        for name, pts in (("map_poses", ms.poses), ("map_trajectory", ms.trajectory)):
            write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, ctx.output(f"{name}.parquet"), name,
                           metadata={"scene": scene})
        ctx.recording.static_points("world/groundtruth", ms.trajectory, colors=[255, 255, 255], radii=0.03)
        n_r, n_l = len(ms.radar), len(ms.lidar_filtered)
        ctx.stats["map_set"] = {
            "scene": scene, "layout": ms.layout, "root": str(ms.root),
            "split": seq.split or ms.split, "environment": seq.environment or ms.environment,
            "lidar_filtered_source": ms.lidar_filtered_source, "lidar_filtered_detail": ms.source_detail,
            "has_lidar": ms.lidar is not None, "files": {k: str(v) for k, v in ms.files.items()},
        }
        ctx.stats["radar_voxels"] = {"occupied": n_r}
        ctx.stats["lidar_voxels"] = {"occupied": n_l}
        ctx.stats["lr_ratio"] = n_l / n_r
        if ms.lidar_filtered_source != "map":
            ctx.warn(f"scene '{scene}': lidar_filtered is rebuilt ({ms.source_detail}), not the authors' map file")

    # -- trajectories --------------------------------------------------------------------------------
    def _se2_poses(self, ctx: StageContext, p: VoxelParams, gt_xyz: F64) -> tuple[Any, Path]:
        """Poses along the odometry or a SLAM method: their x, y, yaw with the odometry's z, roll and pitch
        (``attitude = "odometry"``) or level at ``trajectory.level_height``."""
        tr = p.trajectory
        if tr.source == "odometry":
            path = ctx.input("odometry", "odometry.parquet")
            tab = read_artifact(path, "odometry")
        else:
            fname = f"trajectory_{tr.slam_method}.parquet" if tr.slam_method else "trajectory.parquet"
            path = ctx.input_dirs["slam"] / fname
            if not path.exists():
                ran = sorted(f.stem.removeprefix("trajectory_") for f in path.parent.glob("trajectory_*.parquet"))
                raise UserError(f"{path}: slam method '{tr.slam_method}' was not run (ran: {', '.join(ran) or 'none'});"
                                f" add it with --set 'slam.methods=[\"{tr.slam_method}\"]' or pick one of those "
                                f"with --set voxel.trajectory.slam_method=NAME")
            tab = read_artifact(path, "trajectory")
        if "valid" in tab.column_names:
            tab = tab.filter(tab.column("valid"))
        if tab.num_rows == 0:
            raise UserError(f"{path}: the {tr.source} trajectory is empty; rerun `pipeline run {tr.source} "
                            f"--seq {ctx.seq.name} --force`")
        cols = {c: tab.column(c).to_numpy() for c in ("t_ns", "x", "y", "yaw")}
        if tr.attitude == "level":
            z = tr.level_height if tr.level_height is not None else (float(gt_xyz[0, 2]) if len(gt_xyz) else 0.0)
            ctx.stats["se2_height"] = z

            def poses(t: npt.NDArray[np.int64]) -> tuple[F64, npt.NDArray[np.bool_]]:
                return interpolate_se2(t, cols["t_ns"], cols["x"], cols["y"], cols["yaw"], z)

            return poses, path
        odo = tab if p.trajectory.source == "odometry" else read_artifact(ctx.input("odometry", "odometry.parquet"),
                                                                   "odometry")
        if "valid" in odo.column_names:
            odo = odo.filter(odo.column("valid"))
        att = {c: odo.column(c).to_numpy() for c in ("t_ns", "z", "roll", "pitch")}
        ctx.stats["attitude"] = "odometry"

        def poses3(t: npt.NDArray[np.int64]) -> tuple[F64, npt.NDArray[np.bool_]]:
            return interpolate_planar_attitude(t, cols["t_ns"], cols["x"], cols["y"], cols["yaw"], att["t_ns"],
                                               att["z"], att["roll"], att["pitch"])

        return poses3, path

    # -- radar ---------------------------------------------------------------------------------------
    def _radar_map(self, ctx: StageContext, p: VoxelParams, model: SensorModel, base_from_radar: F64,
                   poses: Any, traj_path: Path | None = None) -> tuple[VoxelMap, F64]:
        if p.radar.points == "filtered":
            tab = read_artifact(ctx.input("filter", "radar_filtered.parquet"), "radar_filtered",
                                columns=["scan", "t_ns", "x", "y", "z"])
        else:
            tab = read_artifact(ctx.input("ingest", "radar.parquet"), "radar", columns=["scan", "t_ns", "x", "y", "z"])
        scan = tab.column("scan").to_numpy()
        t_ns = tab.column("t_ns").to_numpy()
        pts = np.stack([tab.column(c).to_numpy() for c in ("x", "y", "z")], axis=1)
        scans, lengths = scan_lengths(scan)
        starts = np.r_[0, np.cumsum(lengths)[:-1]].astype(np.int64)
        T_wb, valid = poses(t_ns[starts]) if len(starts) else (np.zeros((0, 4, 4)), np.zeros(0, bool))
        if traj_path is not None and len(valid):  # a radar-only trajectory must cover the scans
            share = float(valid.mean())
            ctx.stats["trajectory_coverage"] = round(share, 4)
            if share < p.trajectory.min_coverage:
                raise UserError(f"{traj_path}: the {p.trajectory.source} trajectory covers {100 * share:.1f} % of the "
                                f"{len(valid)} radar scans (voxel.trajectory.min_coverage = "
                                f"{p.trajectory.min_coverage:g}); rerun "
                                f"`pipeline run {p.trajectory.source} --seq {ctx.seq.name} --force` or lower "
                                f"voxel.trajectory.min_coverage")
        T_ws = T_wb @ base_from_radar
        dirs = fan_directions(np.radians(p.radar.azimuth_fov_deg), np.radians(p.radar.elevation_fov_deg),
                              p.resolution, p.radar.max_range)
        vmap = VoxelMap(p.resolution, model)
        t0 = time.perf_counter()
        n_pts = 0
        with ctx.progress(len(scans), "radar map") as advance:
            for i in np.flatnonzero(valid):
                sl = slice(starts[i], starts[i] + lengths[i])
                fan, hits = radar_scan_keys(pts[sl], T_ws[i], dirs, p.resolution, p.radar.min_range, p.radar.max_range)
                vmap.integrate(fan, hits, hits_need_free=True)
                n_pts += int(lengths[i])
                advance(1)
        dt = time.perf_counter() - t0
        if p.trajectory.source != "groundtruth" and valid.any():  # the 3D poses the radar-only map was built along
            ctx.recording.trajectory("world/voxel/trajectory", scans[valid], t_ns[starts][valid],
                                     T_wb[valid, :3, 3], color=(255, 160, 40))
        n_skip = int((~valid).sum())
        if n_skip:
            ctx.warn(f"{n_skip} of {len(scans)} radar scans lie outside the {p.trajectory.source} trajectory's "
                     f"time span "
                     "and were skipped")
        ctx.stats["radar"] = {"scans": int(valid.sum()), "scans_skipped": n_skip, "points": n_pts,
                              "fan_rays": len(dirs), "seconds": round(dt, 3),
                              "points_per_s": round(n_pts / dt, 1) if dt > 0 else None,
                              "scans_per_s": round(float(valid.sum()) / dt, 2) if dt > 0 else None,
                              "voxel_updates": vmap.n_updates}
        return vmap, np.ascontiguousarray(T_ws[valid, :3, 3], dtype=np.float64)

    # -- lidar ---------------------------------------------------------------------------------------
    def _lidar_map(self, ctx: StageContext, p: VoxelParams, model: SensorModel, calib: dict[str, F64],
                   poses: Any) -> VoxelMap:
        vmap = VoxelMap(p.resolution, model)
        tab = read_artifact(ctx.input("ingest", "lidar.parquet"), "lidar", columns=["scan", "t_ns", "x", "y", "z"])
        if tab.num_rows == 0:
            ctx.warn("lidar.parquet holds no points: the lidar map is empty")
            ctx.stats["lidar"] = {"scans": 0}
            return vmap
        scan = tab.column("scan").to_numpy()
        t_ns = tab.column("t_ns").to_numpy()
        pts = np.stack([tab.column(c).to_numpy() for c in ("x", "y", "z")], axis=1)
        del tab
        # restrict the lidar to the radar's horizontal field of view and to the range limits
        base_from_lidar, base_from_radar = calib["base_from_lidar"], calib["base_from_radar"]
        boresight_lidar = np.linalg.inv(base_from_lidar)[:3, :3] @ (base_from_radar[:3, :3] @ np.array([1.0, 0, 0]))
        keep = horizontal_fov_mask(pts, boresight_lidar, np.radians(p.lidar.fov_deg))
        rng = np.linalg.norm(pts, axis=1)
        keep &= rng >= p.lidar.min_range
        if p.lidar.max_range > 0:
            keep &= rng <= p.lidar.max_range
        scans, lengths = scan_lengths(scan)
        starts = np.r_[0, np.cumsum(lengths)[:-1]].astype(np.int64)
        use = np.zeros(len(scans), bool)
        use[:: p.lidar.stride] = True
        T_wb, valid = poses(t_ns[starts])
        T_wl = T_wb @ base_from_lidar
        t0 = time.perf_counter()
        n_pts = 0
        sel = np.flatnonzero(valid & use)
        with ctx.progress(len(sel), "lidar map") as advance:
            for i in sel:
                sl = slice(starts[i], starts[i] + lengths[i])
                local = pts[sl][keep[sl]].astype(np.float64)
                T = T_wl[i]
                world = local @ T[:3, :3].T + T[:3, 3]
                free, hits = scan_update_keys(world, T[:3, 3], p.resolution, -1.0, discretize=p.lidar.discretize)
                vmap.integrate(free, hits)
                n_pts += len(local)
                advance(1)
        dt = time.perf_counter() - t0
        n_skip = int((~valid[use]).sum())
        if n_skip:
            ctx.warn(f"{n_skip} lidar scans lie outside the ground truth's time span and were skipped")
        ctx.stats["lidar"] = {"scans": len(sel), "scans_total": len(scans), "stride": p.lidar.stride,
                              "scans_skipped": n_skip, "points_in_fov": n_pts,
                              "points_dropped_by_fov_range": int((~keep).sum()),
                              "seconds": round(dt, 3), "points_per_s": round(n_pts / dt, 1) if dt > 0 else None,
                              "voxel_updates": vmap.n_updates}
        return vmap


def _read_calibration(ctx: StageContext) -> dict[str, F64]:
    path = ctx.input("ingest", "calibration.json")
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: unreadable calibration ({exc}); rerun `pipeline run ingest --force`") from exc
    out: dict[str, F64] = {}
    for sensor in ("radar", "lidar"):
        key = f"base_from_{sensor}"
        T = np.asarray(raw.get(key, []), dtype=np.float64)
        if T.shape != (4, 4):
            raise UserError(f"{path}: '{key}' must be a 4x4 matrix; rerun `pipeline run ingest --force`")
        out[key] = T
    return out


def height_colors(z: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """RGB colours (turbo colormap) by height, 2nd to 98th percentile."""
    from matplotlib import colormaps

    zz = np.asarray(z, dtype=np.float64)
    if len(zz) == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(zz, [2, 98])
    u = np.clip((zz - lo) / max(hi - lo, 1e-6), 0, 1)
    return (colormaps["turbo"](u)[:, :3] * 255).astype(np.uint8)


STAGE = VoxelStage()
