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
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq

from core.errors import UserError
from core.stage import Stage, StageContext, StageParams

if TYPE_CHECKING:
    from sources.sequence import SequenceInfo

from core import hilbert_map as hm
from schemas.artifacts import ODOMETRY_COV_COLS, ODOMETRY_COV_IDX
from schemas.io import SchemaError, read_artifact, write_artifact
from stages.slam.backend import resolve_device
from stages.slam.beam_sampling import BeamSamples, radar_to_body_2d, sample_beams, to_world
from stages.slam.divergence import heading_deviation
from stages.slam.method_names import GRAPH_METHODS, HILBERT_METHODS
from stages.slam.methods import DOMAIN_PADDING, MethodResult, domain_from_trajectory, run_method
from stages.slam.params import MapParams, SlamParams
from stages.slam.pose_graph import GraphResult, optimise_graph

F64 = npt.NDArray[np.floating[Any]]
#: warn when a filter's heading leaves the odometry's by more than this many sigma of the odometry's accumulated
#: heading uncertainty (:mod:`stages.slam.divergence`; the value is in the manifest either way)
DEVIATION_WARN_SIGMAS = 3.0
#: map_grid.parquet's query spacing (m)
GRID_SPACING = 0.25
#: map_stats.parquet: uncertainty quartiles every this many scans, over cells of this size (m)
STATS_EVERY, STATS_SPACING = 5, 1.0
#: occupancy / uncertainty images logged to Rerun, and their pixel size (m)
MAP_SNAPSHOTS, IMAGE_SPACING = 8, 0.25


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
        item = 4 if p.map.dtype == "float32" else 8
        out: list[tuple[int, str]] = []
        if methods & set(HILBERT_METHODS):
            M = p.map.n_basis
            out.append((2 * p.n_particles * (M * M + 2 * M) * item,
                        f"slam.n_particles={p.n_particles} Hilbert maps of slam.map.n_basis={M}^2 {p.map.dtype}"))
        if "fastslam_grid" in methods and "odometry" in input_dirs:
            try:
                t = read_artifact(input_dirs["odometry"] / "odometry.parquet", "odometry", columns=["x", "y"])
                xy = np.column_stack([t["x"].to_numpy(), t["y"].to_numpy()])
            except (OSError, SchemaError):  # not estimated: the stage itself then says what is wrong
                xy = np.zeros((0, 2))
            if len(xy) and np.all(np.isfinite(xy)):
                half, _ = domain_from_trajectory(xy, DOMAIN_PADDING)
                cells = float(np.prod(np.ceil(2 * half / p.grid.resolution)))
                out.append((int(2 * p.n_particles * cells * 4),
                            f"slam.n_particles={p.n_particles} grids of {cells:.3g} cells at "
                            f"slam.grid.resolution={p.grid.resolution} m"))
        return max(out) if out else None

    def run(self, ctx: StageContext) -> None:
        p: SlamParams = ctx.params
        base_from_radar = read_calibration(ctx)
        scans, t_ns, odo, inc_cov = read_odometry(ctx)
        point_scan, xyz = read_radar(ctx)
        samples = beam_samples_by_scan(point_scan, xyz, scans, base_from_radar, p)
        ctx.stats["radar_points_used"] = int(sum(len(o.endpoints) for o in samples))
        half, centre = domain_from_trajectory(odo[:, :2], DOMAIN_PADDING)
        basis = hm.make_basis(half, centre, p.map.n_basis, "tensor")
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
            "lengthscale_m": p.map.lengthscale_m,
        })
        methods = [p.method, *[m for m in dict.fromkeys(p.methods) if m != p.method]]
        tracker = MapTracker(basis, p, samples, scans, t_ns, ctx)
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
                    res = run_method(m, odo, samples, basis, p, observer=obs, on_step=advance)
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
                    if dev.sigmas > DEVIATION_WARN_SIGMAS:
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
        grid = query_grid(basis, theta, cov, GRID_SPACING, p.map)
        write_artifact(grid, ctx.output("map_grid.parquet"), "map_grid", metadata={"grid_spacing": str(GRID_SPACING)})
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
    b = p.beams
    return [radar_to_body_2d(xyz[i:j], base_from_radar, b.z_min, b.z_max) for i, j in zip(lo, hi, strict=True)]


def beam_samples_by_scan(point_scan: npt.NDArray[np.int64], xyz: F64, scans: npt.NDArray[np.int64],
                         base_from_radar: F64, p: SlamParams) -> list[BeamSamples]:
    """Body-frame beam samples of every scan in ``scans`` from radar-frame points ``xyz`` tagged ``point_scan``."""
    return [sample_beams(pts, origin, p.beams.ray_step, p.beams.max_range)
            for pts, origin in points_by_scan(point_scan, xyz, scans, base_from_radar, p)]


def graph_endpoints_by_scan(point_scan: npt.NDArray[np.int64], xyz: F64, scans: npt.NDArray[np.int64],
                            base_from_radar: F64, p: SlamParams) -> list[F64]:
    """radar_graph's input: each scan's points in the 2D base frame within ``graph_max_range`` of the radar (and
    beyond ``min_range``, inside the height gate)."""
    out = []
    for pts, origin in points_by_scan(point_scan, xyz, scans, base_from_radar, p):
        r = np.hypot(*(pts - origin).T) if len(pts) else np.zeros(0)
        out.append(pts[r <= p.graph.max_range])
    return out


# -- radar_graph ---------------------------------------------------------------------------------------------------


def run_graph(ctx: StageContext, p: SlamParams, odo: F64, inc_cov: F64, t_ns: npt.NDArray[np.int64],
              endpoints: list[F64]) -> tuple[MethodResult, GraphResult]:
    """radar_graph on the stage's inputs (a one-line error for a log too short or GTSAM missing)."""
    t0 = time.perf_counter()
    try:
        g = optimise_graph(odo, inc_cov, (t_ns - t_ns[0]) * 1e-9, endpoints, p.graph)
    except ImportError as exc:
        raise UserError(f"slam.methods includes radar_graph: {exc} (or leave radar_graph out of slam.methods and "
                        "set slam.method to another method)") from None
    except ValueError as exc:
        raise UserError(f"{ctx.input('odometry', 'odometry.parquet')}: {exc}; lower slam.graph.keyframe_distance "
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

    def __init__(self, basis: hm.HilbertBasis, p: SlamParams, samples: list[BeamSamples],
                 scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64], ctx: StageContext) -> None:
        self.basis, self.m, self.p, self.samples = basis, p.map, p, samples
        self.scans, self.t_ns = scans, t_ns
        lo, hi = basis.centre - basis.half_widths, basis.centre + basis.half_widths
        gx = np.arange(lo[0] + STATS_SPACING / 2, hi[0], STATS_SPACING)
        gy = np.arange(lo[1] + STATS_SPACING / 2, hi[1], STATS_SPACING)
        self.cells = np.stack(np.meshgrid(gx, gy, indexing="xy"), -1).reshape(-1, 2)
        self.prior_diag = hm.prior_variances(basis, p.map.lengthscale_m, p.map.signal_variance)
        self.cell_prior = hm.prior_variance_at(basis, self.prior_diag, self.cells)
        self.observed = np.zeros(len(self.cells), dtype=bool)
        self.rows: list[tuple[int, int, float, float, float, int, float]] = []
        T = len(scans)
        k = min(MAP_SNAPSHOTS, T)
        self.snapshot_at = set(np.unique(np.linspace(0, T - 1, k).round().astype(int)).tolist()) if k else set()
        self.snapshots: list[tuple[int, int, F64, F64]] = []
        self.image_axes = (np.arange(lo[0] + IMAGE_SPACING / 2, hi[0], IMAGE_SPACING),
                           np.arange(lo[1] + IMAGE_SPACING / 2, hi[1], IMAGE_SPACING))

    def observe(self, i: int, f: Any, best: int) -> None:
        """At scan ``i`` of a Hilbert method's filter (``RBPF`` or ``TorchRBPF``): the best particle's pose
        (recorded in the history just before) and, every ``stats_every`` scans, its map."""
        assert hasattr(f.maps, "map_of")
        pose = f.history.best_pose[-1]
        last = i == len(self.scans) - 1
        if i % STATS_EVERY == 0 or last or i in self.snapshot_at:
            theta, cov = f.maps.map_of(best)
            self._observe_map(i, pose, theta, cov)
        else:
            self._observe_map(i, pose, None, None)

    def _observe_map(self, i: int, pose: F64, theta: F64 | None, cov: F64 | None) -> None:
        near = np.sum((self.cells - pose[:2]) ** 2, axis=1) <= self.p.beams.max_range**2
        self.observed |= near
        last = i == len(self.scans) - 1
        if theta is None or cov is None:
            return
        if i % STATS_EVERY == 0 or last:
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
        theta, cov = hm.prior(self.basis, self.m.lengthscale_m, self.m.signal_variance)
        for i, (pose, s) in enumerate(zip(poses, self.samples, strict=True)):
            if s.n:
                phi = hm.features(self.basis, to_world(pose, s.points))
                theta, cov = hm.kalman_update(theta, cov, phi, s.labels, self.m.noise_variance, inplace=True)
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
        "lengthscale": [p.map.lengthscale_m], "signal_variance": [p.map.signal_variance],
        "noise_variance": [p.map.noise_variance], "length_unit_m": [1.0], "lengthscale_m": [p.map.lengthscale_m],
        "basis_kind": [basis.kind], "method": [p.method], "scan": [last_scan],
    }, path, "map_posterior")


def query_grid(basis: hm.HilbertBasis, theta: F64, cov: F64, spacing: float, m: MapParams) -> dict[str, F64]:
    """The posterior on a regular grid over the domain (any spacing: the map is continuous)."""
    lo, hi = basis.centre - basis.half_widths, basis.centre + basis.half_widths
    gx = np.arange(lo[0] + spacing / 2, hi[0], spacing)
    gy = np.arange(lo[1] + spacing / 2, hi[1], spacing)
    g = np.stack(np.meshgrid(gx, gy, indexing="xy"), -1).reshape(-1, 2)
    mean, var, occ = hm.query(basis, np.asarray(theta, np.float64), np.asarray(cov, np.float64), g)
    u0 = hm.prior_variance_at(basis, hm.prior_variances(basis, m.lengthscale_m, m.signal_variance), g)
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
