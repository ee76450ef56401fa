"""`slam` stage: radar_graph (a keyframe pose graph), RICH-SLAM (RBPF with Hilbert-GP occupancy maps) as the paper
configures it, its ablations and the FastSLAM grid baseline.

Inputs: ``ingest/calibration.json`` (``base_from_radar``), ``filter/radar_filtered.parquet`` (radar
frame), ``odometry/odometry.parquet`` (world <- base at the radar scan times). Radar points go to the
base frame, are projected to the plane (optional height gate) and sampled along beams from the radar
origin (Fig. 3a). Every method in ``methods`` runs over the same samples and writes
``trajectory_<method>.parquet``; ``trajectory.parquet`` is ``method``'s. The map outputs (posterior,
grid, per-scan uncertainty statistics) come from ``method``: its best particle's final map for the
Hilbert methods, else a Hilbert map built along its trajectory. Units: see README.md.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import Field, model_validator

from core.errors import UserError
from core.stage import Stage, StageContext, StageParams

if TYPE_CHECKING:
    from pipeline.sequences import SequenceInfo

from core import hilbert_map as hm
from schemas.artifacts import ODOMETRY_COV_COLS, ODOMETRY_COV_IDX
from schemas.io import SchemaError, read_artifact, write_artifact
from stages.slam.backend import resolve_device
from stages.slam.beam_sampling import BeamSamples, radar_to_body_2d, sample_beams, to_world
from stages.slam.divergence import heading_deviation
from stages.slam.grid_map import GridModel
from stages.slam.methods import (
    GRAPH_METHODS,
    HILBERT_METHODS,
    METHODS,
    PAPER_ENDPOINT_TOLERANCE,
    Method,
    MethodResult,
    SlamConfig,
    domain_from_trajectory,
    run_method,
)
from stages.slam.pose_graph import GraphModel, GraphResult, optimise_graph
from stages.slam.rbpf import MotionNoise
from stages.slam.registration import MatcherModel

F64 = npt.NDArray[np.floating[Any]]


class SlamParams(StageParams):
    """Parameters of the `slam` stage (defaults: RICH-SLAM Table II and Sec. IV, ColoRadar profile; radar_graph's
    chosen on the calibration runs)."""

    method: Method = Field("radar_graph", description="method whose trajectory is trajectory.parquet; the map "
                           "outputs are built along it (a Hilbert method's best particle's own map)")
    methods: list[Method] = Field(list(METHODS), description="methods run and written as "
                                  "trajectory_<method>.parquet (the main method always runs)")
    n_particles: int = Field(200, ge=1, le=100_000, description="particles N_p of the filters (Sec. V-A2)")
    seed: int = Field(0, description="seed of the particle filters' random generator")
    # -- Hilbert-GP map (Table II)
    lengthscale: float = Field(20.0, gt=0, description="SE length scale l in map units (Table II: 20)")
    length_unit_m: float = Field(0.1, gt=0, le=100, description="metres per map unit: l in metres = lengthscale * "
                                 "this (decimetres reproduce the paper's maps; 1.0 = literal metres)")
    signal_variance: float = Field(16.0, gt=0, description="sigma_f^2 (Table II: 16 ColoRadar, 0.7 ARS548)")
    noise_variance: float = Field(0.36, gt=0, description="sigma_n^2 (Table II: 0.36 ColoRadar, 0.1 ARS548)")
    n_basis: int = Field(256, ge=4, le=4096, description="basis functions M (a perfect square: the tensor basis of "
                         "eq. 7)")
    domain_padding: float = Field(10.0, ge=0, description="Hilbert domain = odometry envelope padded by this (m)")
    map_update: Literal["kalman", "laplace"] = Field("kalman", description="map update: Kalman (eq. 15-19) or "
                                                     "recursive Laplace (Appendix)")
    # -- computation
    dtype: Literal["float64", "float32"] = Field("float64", description="precision of the particle maps")
    workers: int = Field(2, ge=0, le=256, description="worker processes sharing the particle maps, one BLAS "
                         "thread each; 0 = in process (numpy backend)")
    backend: Literal["numpy", "torch"] = Field(
        "numpy", description="array backend of the RICH-SLAM particle maps and filter loop: numpy (CPU, worker "
        "processes) or torch (batched tensors on slam.device; needs the learn extra)")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="device of the torch backend: cuda, cpu, or auto (cuda when torch sees one, else cpu)")
    torch_threads: int = Field(1, ge=0, le=256, description="CPU threads of the torch backend on the cpu (0 = torch's "
                               "default, one per core; one thread is far faster on a shared machine)")
    # -- measurements (Sec. IV-B, Fig. 3a)
    max_range: float = Field(5.0, gt=0, description="beams longer than this are dropped (m, Table II)")
    min_range: float = Field(0.0, ge=0, description="beams shorter than this are dropped (m)")
    ray_step: float = Field(1.0, ge=0.01, description="free-sample spacing along a beam (m, Table II)")
    free_clearance: float = Field(0.0, ge=0, description="no free sample closer than this to the endpoint (m)")
    z_min: float | None = Field(None, description="keep points with base-frame z >= z_min (m); None: no gate")
    z_max: float | None = Field(None, description="keep points with base-frame z <= z_max (m); None: no gate")
    # -- weights (Sec. IV-D2)
    endpoint_tolerance: float = Field(PAPER_ENDPOINT_TOLERANCE, ge=0, description="endpoint tolerance radius r_e "
                                      "(m, eq. 29; the paper: 0.25); rich_slam_no_et always 0")
    et_ring_points: int = Field(8, ge=1, le=64, description="points on the ring of the discretised r_e disc")
    # -- proposal (eq. 21, GMapping's motion model) and resampling (Sec. IV-D1, D3)
    motion_std_xy: float = Field(0.002, ge=0, description="process noise std on x and y per scan (m, eq. 21)")
    motion_std_yaw: float = Field(0.0005, ge=0, description="process noise std on yaw per scan (rad, eq. 21)")
    motion_rel_trans: float = Field(0.05, ge=0, description="extra xy std per metre of odometry translation")
    motion_rel_rot: float = Field(0.005, ge=0, description="extra yaw std per radian of odometry rotation")
    motion_rot_per_trans: float = Field(0.03, ge=0, description="extra yaw std per metre of odometry translation "
                                        "(rad/m; GMapping's str)")
    motion_trans_per_rot: float = Field(0.06, ge=0, description="extra xy std per radian of odometry rotation "
                                        "(m/rad; GMapping's srt)")
    resampling: Literal["systematic", "stratified", "multinomial"] = Field(
        "systematic", description="resampler (systematic = low variance)")
    resample_threshold: float = Field(0.5, gt=0, le=1, description="resample when N_eff < this * N_p (eq. 31)")
    # -- radar_graph: keyframe pose graph (stages/slam/pose_graph.py; settings chosen on the calibration runs)
    graph_max_range: float = Field(10.0, gt=0, description="radar_graph: endpoints up to this range (m) enter the "
                                   "keyframe clouds (longer than max_range, the Hilbert map's: more structure)")
    graph_keyframe_distance: float = Field(1.0, gt=0, description="radar_graph: a keyframe every this many metres "
                                           "of odometry travel")
    graph_keyframe_angle: float = Field(15.0, gt=0, description="radar_graph: or every this many degrees turned")
    graph_local_keyframes: int = Field(10, ge=1, le=1000, description="radar_graph: keyframes in the local cloud "
                                       "of each end of a loop closure")
    graph_bias_sigma0: float = Field(0.01, gt=0, le=1, description="radar_graph: prior std of the yaw-rate bias "
                                     "the odometry leaves, rad/s (each keyframe carries one)")
    graph_bias_walk: float = Field(1e-4, gt=0, le=1, description="radar_graph: random walk of that bias, "
                                   "rad/s/sqrt(s)")
    graph_loop_radius: float = Field(3.0, gt=0, description="radar_graph: keyframes this close on the odometry "
                                     "are loop candidates, and the verification's translation search (m)")
    graph_loop_min_travel: float = Field(15.0, gt=0, description="radar_graph: path length between the two "
                                         "keyframes of a loop candidate (m)")
    graph_loop_search_yaw: float = Field(20.0, gt=0, le=180, description="radar_graph: the loop verification's "
                                         "yaw search (+- deg)")
    graph_loop_min_inliers: float = Field(0.6, gt=0, le=1, description="radar_graph: share of a cloud's points "
                                          "within 0.3 m of the other for a closure to be proposed")
    graph_robust: Literal["gnc", "none"] = Field("gnc", description="radar_graph: graduated non-convexity (GTSAM, "
                                                 "truncated quadratic) on the loop closures, or plain least squares")
    graph_match_sigma: float = Field(0.15, gt=0, description="radar_graph: the likelihood field's std (m)")
    graph_match_temperature: float = Field(30.0, gt=0, description="radar_graph: divides the summed point "
                                           "log-likelihood in the registration covariance (points are not "
                                           "independent; chosen for a NEES near 3 on the calibration runs)")
    # -- FastSLAM grid baseline
    grid_resolution: float = Field(0.1, ge=0.01, description="fastslam_grid cell size (m)")
    grid_l_occ: float = Field(0.85, gt=0, description="fastslam_grid log-odds added at an endpoint cell")
    grid_l_free: float = Field(-0.4, lt=0, description="fastslam_grid log-odds added along a beam")
    grid_l_clamp: float = Field(4.0, gt=0, description="fastslam_grid log-odds clamp (+-)")
    grid_sigma_hit: float = Field(0.2, gt=0, description="likelihood-field std of the endpoint distance (m)")
    grid_max_dist: float = Field(0.5, gt=0, description="likelihood-field search radius / distance cap (m)")
    grid_z_hit: float = Field(0.9, gt=0, description="likelihood-field hit weight")
    grid_z_rand: float = Field(0.1, gt=0, description="likelihood-field random weight (keeps logs finite)")
    # -- outputs
    deviation_warn_sigmas: float = Field(
        3.0, gt=0, description="warn when a filter's heading leaves the odometry's by more than this many sigma of "
        "the odometry's accumulated heading uncertainty (stages/slam/divergence.py); the value is in the manifest "
        "either way")
    grid_spacing: float = Field(0.25, ge=0.01, description="spacing of the query grid of map_grid.parquet (m)")
    stats_every: int = Field(5, ge=1, le=1_000_000,
                             description="map_stats.parquet: uncertainty quartiles every N scans")
    stats_spacing: float = Field(1.0, ge=0.01, description="map_stats.parquet: spacing of the cells summarised (m)")
    n_map_snapshots: int = Field(8, ge=0, le=1000, description="occupancy / uncertainty images logged to Rerun")
    image_spacing: float = Field(0.25, ge=0.01, description="pixel size of the Rerun map images (m)")

    @model_validator(mode="after")
    def _check(self) -> SlamParams:
        if round(self.n_basis**0.5) ** 2 != self.n_basis:
            raise ValueError(f"n_basis = {self.n_basis} is not a perfect square (the tensor basis of eq. 7 needs one)")
        if self.z_min is not None and self.z_max is not None and self.z_min > self.z_max:
            raise ValueError(f"z_min {self.z_min} > z_max {self.z_max}")
        if self.backend == "torch" and self.map_update != "kalman":
            raise ValueError("backend = torch implements the Kalman map update only; use backend = numpy for "
                             "map_update = laplace")
        if self.backend == "numpy" and self.device == "cuda":
            raise ValueError("device = cuda needs backend = torch (the numpy backend runs on the cpu)")
        return self

    def graph_model(self) -> GraphModel:
        """radar_graph's parameter object (:class:`pose_graph.GraphModel`)."""
        return GraphModel(
            keyframe_distance=self.graph_keyframe_distance, keyframe_angle_deg=self.graph_keyframe_angle,
            local_keyframes=self.graph_local_keyframes,
            bias_sigma0=self.graph_bias_sigma0, bias_walk=self.graph_bias_walk, loop_radius=self.graph_loop_radius,
            loop_min_travel=self.graph_loop_min_travel, loop_search_yaw_deg=self.graph_loop_search_yaw,
            loop_min_inliers=self.graph_loop_min_inliers, robust=self.graph_robust,
            matcher=MatcherModel(sigma=self.graph_match_sigma, temperature=self.graph_match_temperature))

    def config(self) -> SlamConfig:
        """The filter methods' parameter object (:class:`methods.SlamConfig`)."""
        return SlamConfig(
            n_particles=self.n_particles, lengthscale_m=self.lengthscale * self.length_unit_m,
            signal_variance=self.signal_variance, noise_variance=self.noise_variance, n_basis=self.n_basis,
            endpoint_tolerance=self.endpoint_tolerance, et_ring_points=self.et_ring_points,
            noise=MotionNoise(self.motion_std_xy, self.motion_std_yaw, self.motion_rel_trans, self.motion_rel_rot,
                              self.motion_rot_per_trans, self.motion_trans_per_rot),
            resampling=self.resampling, resample_threshold=self.resample_threshold, map_update=self.map_update,
            dtype=self.dtype, workers=self.workers, backend=self.backend, device=self.device,
            torch_threads=self.torch_threads,
            grid=GridModel(self.grid_l_occ, self.grid_l_free, -self.grid_l_clamp, self.grid_l_clamp, 0.0,
                           self.grid_sigma_hit, self.grid_max_dist, self.grid_z_hit, self.grid_z_rand),
            grid_resolution=self.grid_resolution,
        )


class SlamStage(Stage):
    name = "slam"
    description = "RICH-SLAM: RBPF with Hilbert-GP occupancy maps, and baselines"
    inputs = ("ingest", "filter", "odometry")
    Params = SlamParams
    version = "3"
    outputs = ("trajectory.parquet", "map_posterior.parquet", "map_grid.parquet", "map_stats.parquet")

    def memory_estimate(self, seq: SequenceInfo, params: StageParams,
                        input_dirs: Mapping[str, Path]) -> tuple[int, str] | None:
        """The particle maps of the largest method, twice over (resampling copies them): N_p x M^2 for a Hilbert
        filter, N_p x cells for the grid filter over the odometry's envelope."""
        p = cast(SlamParams, params)
        methods = set(p.methods) | {p.method}
        item = 4 if p.dtype == "float32" else 8
        out: list[tuple[int, str]] = []
        if methods & set(HILBERT_METHODS):
            M = p.n_basis
            out.append((2 * p.n_particles * (M * M + 2 * M) * item,
                        f"slam.n_particles={p.n_particles} Hilbert maps of slam.n_basis={M}^2 {p.dtype}"))
        if "fastslam_grid" in methods and "odometry" in input_dirs:
            try:
                t = read_artifact(input_dirs["odometry"] / "odometry.parquet", "odometry", columns=["x", "y"])
                xy = np.column_stack([t["x"].to_numpy(), t["y"].to_numpy()])
            except (OSError, SchemaError):  # not estimated: the stage itself then says what is wrong
                xy = np.zeros((0, 2))
            if len(xy) and np.all(np.isfinite(xy)):
                half, _ = domain_from_trajectory(xy, p.domain_padding)
                cells = float(np.prod(np.ceil(2 * half / p.grid_resolution)))
                out.append((int(2 * p.n_particles * cells * 4),
                            f"slam.n_particles={p.n_particles} grids of {cells:.3g} cells at "
                            f"slam.grid_resolution={p.grid_resolution} m"))
        return max(out) if out else None

    def run(self, ctx: StageContext) -> None:
        p: SlamParams = ctx.params
        cfg = p.config()
        base_from_radar = read_calibration(ctx)
        scans, t_ns, odo, inc_cov = read_odometry(ctx)
        point_scan, xyz = read_radar(ctx)
        samples = beam_samples_by_scan(point_scan, xyz, scans, base_from_radar, p)
        ctx.stats["radar_points_used"] = int(sum(len(o.endpoints) for o in samples))
        half, centre = domain_from_trajectory(odo[:, :2], p.domain_padding)
        basis = hm.make_basis(half, centre, p.n_basis, "tensor")
        device, note = resolve_device(p.backend, p.device)
        if note:
            ctx.console.print(f"[yellow]slam: {note}[/]")
        ctx.stats.update({"backend": p.backend, "device": device, **({"device_note": note} if note else {})})
        n_samples = np.array([s.n for s in samples])
        ctx.stats.update({
            "scans": len(scans), "scans_with_samples": int(np.sum(n_samples > 0)),
            "samples_per_scan_mean": float(n_samples.mean()) if len(n_samples) else 0.0,
            "samples_per_scan_max": int(n_samples.max()) if len(n_samples) else 0,
            "beams_per_scan_mean": float(np.mean([len(s.endpoints) for s in samples])) if samples else 0.0,
            "domain": {"L1": float(half[0]), "L2": float(half[1]), "cx": float(centre[0]), "cy": float(centre[1])},
            "lengthscale_m": cfg.lengthscale_m,
        })
        methods = [p.method, *[m for m in dict.fromkeys(p.methods) if m != p.method]]
        tracker = MapTracker(basis, cfg, p, samples, scans, t_ns, ctx)
        results: dict[str, MethodResult] = {}
        graphs: dict[str, GraphResult] = {}
        with ctx.progress(len(methods) * len(scans), "methods") as advance:
            for m in methods:
                obs = tracker.observe if (m == p.method and m in HILBERT_METHODS) else None
                if m in GRAPH_METHODS:
                    endpoints = graph_endpoints_by_scan(point_scan, xyz, scans, base_from_radar, p)
                    res, graph = run_graph(ctx, p, odo, inc_cov, t_ns, endpoints)
                    graphs[m] = graph
                    advance(len(scans))
                else:
                    res = run_method(m, odo, samples, basis, cfg, p.seed, observer=obs, on_step=advance)
                results[m] = res
                write_trajectory(ctx.output(f"trajectory_{m}.parquet"), scans, t_ns, res)
                ctx.stats.setdefault("methods", {})[m] = {
                    "seconds": round(res.seconds, 3),
                    "seconds_per_scan": round(res.seconds / max(len(scans), 1), 5),
                    "resamplings": res.resampled,
                    "n_eff_median": float(np.median(res.n_eff)) if len(res.n_eff) else None,
                    "map_form": res.form,
                    **({"device": res.device} if m in HILBERT_METHODS else {}),
                }
                ctx.console.print(f"[dim]slam: {m}: {res.seconds:.1f} s ({res.seconds / max(len(scans), 1):.3f} "
                                  f"s/scan), {res.resampled} resamplings[/]")
                if m in GRAPH_METHODS:
                    g = graphs[m]
                    ctx.stats["methods"][m].update({
                        "keyframes": len(g.keyframes), "loops_proposed": g.count("loop"),
                        "loops_accepted": g.count("loop", True), "loops_rejected": g.count("loop", False)})
                    ctx.console.print(f"slam: {m}: {len(g.keyframes)} keyframes, loop closures "
                                      f"{g.count('loop')} proposed / "
                                      f"{g.count('loop', True)} accepted / {g.count('loop', False)} rejected")
                    for w in g.warnings:
                        ctx.warn(f"{m}: {w}")
                    write_graph(ctx, g, scans, t_ns)
                elif m != "odometry":
                    dev = heading_deviation(odo, res.poses, inc_cov)
                    ctx.stats["methods"][m]["heading_deviation_sigmas"] = round(dev.sigmas, 2)
                    if dev.sigmas > p.deviation_warn_sigmas:
                        ctx.warn(f"{m}'s heading left the odometry's by {dev.degrees:.1f} deg at scan "
                                 f"{int(scans[dev.index])}, {dev.sigmas:.1f} sigma of the odometry's own accumulated "
                                 f"heading uncertainty ({dev.sigma_degrees:.2f} deg): it corrected a drift or it "
                                 f"diverged; compare trajectory_{m}.parquet with trajectory_odometry.parquet")
        main = results[p.method]
        write_trajectory(ctx.output("trajectory.parquet"), scans, t_ns, main)
        if main.theta is None or main.cov is None:
            theta, cov = tracker.replay(main.poses)
        else:
            theta, cov = main.theta, main.cov
        write_posterior(ctx.output("map_posterior.parquet"), basis, theta, cov, p, int(scans[-1]) if len(scans) else -1)
        grid = query_grid(basis, theta, cov, p.grid_spacing, cfg)
        write_artifact(grid, ctx.output("map_grid.parquet"), "map_grid", metadata={"grid_spacing": str(p.grid_spacing)})
        tracker.write(ctx.output("map_stats.parquet"))
        log_recording(ctx, scans, t_ns, results, p.method, tracker)
        for g in graphs.values():
            log_graph(ctx, g, scans, t_ns)


# -- reading -----------------------------------------------------------------------------------------------------


def read_calibration(ctx: StageContext) -> F64:
    path = ctx.input("ingest", "calibration.json")
    try:
        T = np.asarray(json.loads(path.read_text())["base_from_radar"], dtype=np.float64)
    except (KeyError, json.JSONDecodeError, ValueError, TypeError) as exc:
        raise UserError(f"{path}: no readable 'base_from_radar' 4x4 ({exc}); rerun "
                        f"`pipeline run ingest --seq {ctx.seq.name} --force`") from exc
    if T.shape != (4, 4):
        raise UserError(f"{path}: 'base_from_radar' has shape {T.shape}, expected 4x4")
    return T


def read_odometry(ctx: StageContext) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F64, F64]:
    """Scan ids, times, (x, y, yaw) and increment covariances ``(T, 3, 3)`` of the valid odometry rows, in
    scan order."""
    return read_odometry_file(ctx.input("odometry", "odometry.parquet"), ctx.seq.name)


def read_odometry_file(path: Path, seq: str) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F64, F64]:
    """:func:`read_odometry` of an ``odometry.parquet`` (``seq`` names the rerun command of the error).

    The covariance of a kept row's increment is the sum of those of the rows since the previous kept row
    (skipped rows' increments are added up; their errors taken as independent)."""
    t = read_artifact(path, "odometry")
    scans = t["scan"].to_numpy().astype(np.int64)
    keep = np.ones(len(scans), dtype=bool)
    if "valid" in t.column_names:
        keep = t["valid"].to_numpy(zero_copy_only=False).astype(bool)
    poses = np.stack([t[c].to_numpy().astype(np.float64) for c in ("x", "y", "yaw")], axis=1)
    keep &= np.all(np.isfinite(poses), axis=1)
    cov = np.zeros((len(scans), 3, 3))
    for c, (i, j) in zip(ODOMETRY_COV_COLS, ODOMETRY_COV_IDX, strict=True):
        cov[:, i, j] = cov[:, j, i] = np.nan_to_num(t[c].to_numpy().astype(np.float64))
    order0 = np.argsort(scans, kind="stable")
    csum = np.cumsum(cov[order0], axis=0)  # in scan order: a kept row takes the sum since the previous kept one
    kept_sorted = keep[order0]
    at = np.flatnonzero(kept_sorted)
    acc = csum[at] - np.concatenate([np.zeros((1, 3, 3)), csum[at[:-1]]])
    acc[:1] = 0.0
    order = np.argsort(scans[keep], kind="stable")
    scans, t_ns, poses = scans[keep][order], t["t_ns"].to_numpy()[keep][order], poses[keep][order]
    if len(scans) < 2:
        raise UserError(f"{path}: {len(scans)} valid odometry poses; the slam stage needs at least 2 "
                        f"(rerun `pipeline run odometry --seq {seq} --force`)")
    return scans, t_ns.astype(np.int64), poses, acc


def read_radar(ctx: StageContext) -> tuple[npt.NDArray[np.int64], F64]:
    """The filtered radar points' scan numbers and radar-frame x, y, z."""
    t = read_artifact(ctx.input("filter", "radar_filtered.parquet"), "radar_filtered", columns=["scan", "x", "y", "z"])
    xyz = np.stack([t[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], axis=1)
    return t["scan"].to_numpy().astype(np.int64), xyz


def points_by_scan(point_scan: npt.NDArray[np.int64], xyz: F64, scans: npt.NDArray[np.int64],
                   base_from_radar: F64, p: SlamParams) -> list[tuple[F64, F64]]:
    """Each scan of ``scans``: its radar-frame points ``xyz`` (tagged ``point_scan``) in the 2D base frame inside
    the height gate, and the radar origin there."""
    order = np.argsort(point_scan, kind="stable")
    s, xyz = point_scan[order], xyz[order]
    lo = np.searchsorted(s, scans, side="left")
    hi = np.searchsorted(s, scans, side="right")
    return [radar_to_body_2d(xyz[a:b], base_from_radar, p.z_min, p.z_max) for a, b in zip(lo, hi, strict=True)]


def beam_samples_by_scan(point_scan: npt.NDArray[np.int64], xyz: F64, scans: npt.NDArray[np.int64],
                         base_from_radar: F64, p: SlamParams) -> list[BeamSamples]:
    """Body-frame beam samples of every scan in ``scans`` from radar-frame points ``xyz`` tagged ``point_scan``."""
    return [sample_beams(pts, origin, p.ray_step, p.max_range, p.min_range, p.free_clearance)
            for pts, origin in points_by_scan(point_scan, xyz, scans, base_from_radar, p)]


def graph_endpoints_by_scan(point_scan: npt.NDArray[np.int64], xyz: F64, scans: npt.NDArray[np.int64],
                            base_from_radar: F64, p: SlamParams) -> list[F64]:
    """radar_graph's input: each scan's points in the 2D base frame within ``graph_max_range`` of the radar (and
    beyond ``min_range``, inside the height gate)."""
    out = []
    for pts, origin in points_by_scan(point_scan, xyz, scans, base_from_radar, p):
        r = np.hypot(*(pts - origin).T) if len(pts) else np.zeros(0)
        out.append(pts[(r <= p.graph_max_range) & (r >= p.min_range)])
    return out


# -- radar_graph ---------------------------------------------------------------------------------------------------


def run_graph(ctx: StageContext, p: SlamParams, odo: F64, inc_cov: F64, t_ns: npt.NDArray[np.int64],
              endpoints: list[F64]) -> tuple[MethodResult, GraphResult]:
    """radar_graph on the stage's inputs (a one-line error for a log too short or GTSAM missing)."""
    t0 = time.perf_counter()
    try:
        g = optimise_graph(odo, inc_cov, (t_ns - t_ns[0]) * 1e-9, endpoints, p.graph_model())
    except ImportError as exc:
        raise UserError(f"slam.methods includes radar_graph: {exc} (or leave radar_graph out of slam.methods and "
                        "set slam.method to another method)") from None
    except ValueError as exc:
        raise UserError(f"{ctx.input('odometry', 'odometry.parquet')}: {exc}; lower slam.graph_keyframe_distance "
                        "or leave radar_graph out of slam.methods") from None
    res = MethodResult("radar_graph", g.poses, np.ones(len(g.poses)), time.perf_counter() - t0)
    return res, g


def write_graph(ctx: StageContext, g: GraphResult, scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64]
                ) -> None:
    """``graph_keyframes.parquet`` (the optimised keyframe poses and marginal covariances) and
    ``graph_edges.parquet`` (every factor between keyframes: kind, keyframes, measurement, inlier share, whether
    the optimiser kept it)."""
    k = g.keyframes
    pq.write_table(pa.table({
        "keyframe": pa.array(np.arange(len(k)), pa.int32()), "scan": pa.array(scans[k], pa.int32()),
        "t_ns": pa.array(t_ns[k], pa.int64()), "x": g.keyframe_poses[:, 0], "y": g.keyframe_poses[:, 1],
        "yaw": g.keyframe_poses[:, 2], "cov_xx": g.keyframe_cov[:, 0, 0], "cov_yy": g.keyframe_cov[:, 1, 1],
        "cov_yawyaw": g.keyframe_cov[:, 2, 2], "cov_xy": g.keyframe_cov[:, 0, 1],
        "cov_xyaw": g.keyframe_cov[:, 0, 2], "cov_yyaw": g.keyframe_cov[:, 1, 2], "yaw_rate_bias": g.bias,
    }), ctx.output("graph_keyframes.parquet"))
    e = g.edges
    pq.write_table(pa.table({
        "kind": pa.array([x.kind for x in e], pa.string()), "from_keyframe": pa.array([x.i for x in e], pa.int32()),
        "to_keyframe": pa.array([x.j for x in e], pa.int32()),
        "dx": pa.array([float(x.z[0]) for x in e], pa.float64()), "dy": pa.array([float(x.z[1]) for x in e],
                                                                             pa.float64()),
        "dyaw": pa.array([float(x.z[2]) for x in e], pa.float64()),
        "sigma_yaw_deg": pa.array([float(np.degrees(np.sqrt(x.cov[2, 2]))) for x in e], pa.float64()),
        "inliers": pa.array([x.inliers for x in e], pa.float64()),
        "accepted": pa.array([x.accepted for x in e], pa.bool_()),
    }), ctx.output("graph_edges.parquet"))


def log_graph(ctx: StageContext, g: GraphResult, scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64]) -> None:
    """Keyframes and loop-closure edges (accepted green, rejected red) on the ``scan`` timeline, each edge from
    the scan of its later keyframe on."""
    import rerun as rr

    rec = ctx.recording
    P = g.keyframe_poses
    k = g.keyframes
    xyz = np.column_stack([P[:, :2], np.zeros(len(P))])
    rec.points_over_time("world/slam/graph/keyframes", scans[k], t_ns[k], xyz, np.ones(len(k), dtype=np.int64),
                         radii=0.08)
    for e in g.edges:
        if e.kind != "loop":
            continue
        seg = np.array([[P[e.i, 0], P[e.i, 1], 0.0], [P[e.j, 0], P[e.j, 1], 0.0]])
        rec.log(f"world/slam/graph/{'loops' if e.accepted else 'rejected_loops'}/{e.i}_{e.j}",
                rr.LineStrips3D([seg], colors=[(40, 200, 80) if e.accepted else (230, 40, 40)]),
                scan=int(scans[k[e.j]]), t_ns=int(t_ns[k[e.j]]))


# -- map statistics and snapshots (Fig. 10, Rerun images) -------------------------------------------------------------


class MapTracker:
    """Per-scan uncertainty quartiles of the best particle's map and a few map snapshots."""

    def __init__(self, basis: hm.HilbertBasis, cfg: SlamConfig, p: SlamParams, samples: list[BeamSamples],
                 scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64], ctx: StageContext) -> None:
        self.basis, self.cfg, self.p, self.samples = basis, cfg, p, samples
        self.scans, self.t_ns = scans, t_ns
        lo, hi = basis.centre - basis.half_widths, basis.centre + basis.half_widths
        gx = np.arange(lo[0] + p.stats_spacing / 2, hi[0], p.stats_spacing)
        gy = np.arange(lo[1] + p.stats_spacing / 2, hi[1], p.stats_spacing)
        self.cells = np.stack(np.meshgrid(gx, gy, indexing="xy"), -1).reshape(-1, 2)
        self.prior_diag = hm.prior_variances(basis, cfg.lengthscale_m, cfg.signal_variance)
        self.cell_prior = hm.prior_variance_at(basis, self.prior_diag, self.cells)
        self.observed = np.zeros(len(self.cells), dtype=bool)
        self.rows: list[tuple[int, int, float, float, float, int, float]] = []
        T = len(scans)
        k = min(p.n_map_snapshots, T)
        self.snapshot_at = set(np.unique(np.linspace(0, T - 1, k).round().astype(int)).tolist()) if k else set()
        self.snapshots: list[tuple[int, int, F64, F64]] = []
        self.image_axes = (np.arange(lo[0] + p.image_spacing / 2, hi[0], p.image_spacing),
                           np.arange(lo[1] + p.image_spacing / 2, hi[1], p.image_spacing))

    def observe(self, i: int, f: Any, best: int) -> None:
        """At scan ``i`` of a Hilbert method's filter (``RBPF`` or ``TorchRBPF``): the best particle's pose
        (recorded in the history just before) and, every ``stats_every`` scans, its map."""
        assert hasattr(f.maps, "map_of")
        pose = f.history.best_pose[-1]
        last = i == len(self.scans) - 1
        if i % self.p.stats_every == 0 or last or i in self.snapshot_at:
            theta, cov = f.maps.map_of(best)
            self._observe_map(i, pose, theta, cov)
        else:
            self._observe_map(i, pose, None, None)

    def _observe_map(self, i: int, pose: F64, theta: F64 | None, cov: F64 | None) -> None:
        near = np.sum((self.cells - pose[:2]) ** 2, axis=1) <= self.p.max_range**2
        self.observed |= near
        last = i == len(self.scans) - 1
        if theta is None or cov is None:
            return
        if i % self.p.stats_every == 0 or last:
            idx = np.flatnonzero(self.observed)
            _, var, _ = hm.query(self.basis, theta.astype(np.float64), cov.astype(np.float64), self.cells[idx])
            u = var / np.maximum(self.cell_prior[idx], 1e-300)
            q = np.quantile(u, [0.25, 0.5, 0.75]) if len(u) else np.full(3, np.nan)
            self.rows.append((int(self.scans[i]), int(self.t_ns[i]), float(q[0]), float(q[1]), float(q[2]), len(idx),
                              float(np.mean(u)) if len(u) else float("nan")))
        if i in self.snapshot_at:
            gx, gy = self.image_axes
            g = np.stack(np.meshgrid(gx, gy, indexing="xy"), -1).reshape(-1, 2)
            _, var, occ = hm.query(self.basis, theta.astype(np.float64), cov.astype(np.float64), g)
            u = var / np.maximum(hm.prior_variance_at(self.basis, self.prior_diag, g), 1e-300)
            self.snapshots.append((int(self.scans[i]), int(self.t_ns[i]), occ.reshape(len(gy), len(gx)),
                                   u.reshape(len(gy), len(gx))))

    def replay(self, poses: F64) -> tuple[F64, F64]:
        """Statistics for a method without its own Hilbert maps: a map built along its poses (returned)."""
        theta, cov = hm.prior(self.basis, self.cfg.lengthscale_m, self.cfg.signal_variance)
        for i, (pose, s) in enumerate(zip(poses, self.samples, strict=True)):
            if s.n:
                phi = hm.features(self.basis, to_world(pose, s.points))
                theta, cov = hm.kalman_update(theta, cov, phi, s.labels, self.cfg.noise_variance, inplace=True)
            self._observe_map(i, pose, theta, cov)
        return theta, cov

    def write(self, path: Any) -> None:
        cols: list[Any] = list(zip(*self.rows, strict=True)) if self.rows else [[] for _ in range(7)]
        table = pa.table({
            "scan": pa.array(cols[0], pa.int32()), "t_ns": pa.array(cols[1], pa.int64()),
            "u_p25": pa.array(cols[2], pa.float64()), "u_p50": pa.array(cols[3], pa.float64()),
            "u_p75": pa.array(cols[4], pa.float64()), "n_cells": pa.array(cols[5], pa.int32()),
            "u_mean": pa.array(cols[6], pa.float64()),
        }).replace_schema_metadata({"description": "normalised predictive variance u(p) / u_prior(p) (eq. 33) of "
                                    "the best particle's map over the cells within max_range of its path so far"})
        pq.write_table(table, path)


# -- writing -------------------------------------------------------------------------------------------------


def write_trajectory(path: Any, scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64], res: MethodResult) -> None:
    write_artifact({"scan": scans.astype(np.int32), "t_ns": t_ns, "x": res.poses[:, 0], "y": res.poses[:, 1],
                    "yaw": res.poses[:, 2], "n_eff": res.n_eff}, path, "trajectory", metadata={"method": res.method})


def write_posterior(path: Any, basis: hm.HilbertBasis, theta: F64, cov: F64, p: SlamParams, last_scan: int) -> None:
    M = basis.M
    write_artifact({
        "theta": pa.array([np.asarray(theta, np.float64).tolist()], pa.list_(pa.float64())),
        "cov": pa.array([np.asarray(cov, np.float64).reshape(-1).tolist()], pa.list_(pa.float64())),
        "L1": [float(basis.half_widths[0])], "L2": [float(basis.half_widths[1])],
        "cx": [float(basis.centre[0])], "cy": [float(basis.centre[1])], "M": [M],
        "lengthscale": [p.lengthscale], "signal_variance": [p.signal_variance], "noise_variance": [p.noise_variance],
        "length_unit_m": [p.length_unit_m], "lengthscale_m": [p.lengthscale * p.length_unit_m],
        "basis_kind": [basis.kind], "method": [p.method], "scan": [last_scan],
    }, path, "map_posterior")


def query_grid(basis: hm.HilbertBasis, theta: F64, cov: F64, spacing: float, cfg: SlamConfig) -> dict[str, F64]:
    """The posterior on a regular grid over the domain (any spacing: the map is continuous)."""
    lo, hi = basis.centre - basis.half_widths, basis.centre + basis.half_widths
    gx = np.arange(lo[0] + spacing / 2, hi[0], spacing)
    gy = np.arange(lo[1] + spacing / 2, hi[1], spacing)
    g = np.stack(np.meshgrid(gx, gy, indexing="xy"), -1).reshape(-1, 2)
    mean, var, occ = hm.query(basis, np.asarray(theta, np.float64), np.asarray(cov, np.float64), g)
    u0 = hm.prior_variance_at(basis, hm.prior_variances(basis, cfg.lengthscale_m, cfg.signal_variance), g)
    return {"x": g[:, 0], "y": g[:, 1], "occupancy": occ, "variance": var, "mean": mean, "prior_variance": u0}


def _colormap(values: F64, name: str, vmin: float, vmax: float) -> npt.NDArray[np.uint8]:
    from matplotlib import colormaps

    v = np.clip((np.nan_to_num(values, nan=vmin) - vmin) / (vmax - vmin), 0.0, 1.0)
    return (colormaps[name](v)[..., :3] * 255).astype(np.uint8)


def log_recording(ctx: StageContext, scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64],
                  results: dict[str, MethodResult], main: str, tracker: MapTracker) -> None:
    import rerun as rr

    rec = ctx.recording
    colors = {"odometry": (70, 130, 255), "radar_graph": (250, 250, 80), "fastslam_grid": (60, 200, 90),
              "rich_slam": (230, 50, 50),
              "rich_slam_no_et": (170, 80, 220), "rich_slam_mean_only": (240, 160, 40)}
    for m, res in results.items():
        xyz = np.column_stack([res.poses[:, :2], np.zeros(len(res.poses))])
        entity = "world/slam/trajectory" if m == main else f"world/slam/methods/{m}"
        rec.trajectory(entity, scans, t_ns, xyz, color=colors.get(m, (255, 255, 255)))
    res = results[main]
    if res.particles is not None and len(res.particles):
        T, Np = res.particles.shape[:2]
        pts = np.concatenate([res.particles[..., :2], np.zeros((T, Np, 1))], axis=-1).reshape(-1, 3)
        rec.points_over_time("world/slam/particles", scans, t_ns, pts, np.full(T, Np), radii=0.03)
        rec.scalars("metrics/slam/n_eff", scans, t_ns, res.n_eff)
    for scan, t, occ, u in tracker.snapshots:
        # image rows run from +y (top) down
        rec.log("world/slam/map/occupancy", rr.Image(_colormap(occ[::-1], "viridis", 0.0, 1.0)), scan=scan, t_ns=t)
        rec.log("world/slam/map/uncertainty", rr.Image(_colormap(u[::-1], "magma", 0.0, 1.0)), scan=scan, t_ns=t)


STAGE = SlamStage()
