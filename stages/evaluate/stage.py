"""`evaluate` stage: the papers' tables and figures for one sequence.

Sections (parameter ``sections``):

- ``trajectory`` (RICH-SLAM Table III, Fig. 11): every trajectory of the run (odometry and each slam
  method) against ground truth after an SE(2) alignment, two ways: on the whole trajectory
  (``ate_pos_rmse_whole_m``, ``ate_yaw_rmse_whole_deg``: equal to ``evo_ape --align`` in the plane, the
  report's headline) and, the paper's protocol, on the first ``n_align`` matched frames (``ate_pos_rmse_m``,
  ``ate_yaw_rmse_deg``); without alignment too (``*_anchored``) when the odometry is anchored at ground truth;
- ``mapping`` (Q1/Q2, Fig. 6): occupancy AUC with ground-truth poses on held-out scans for HILBERT-GP
  (Kalman update) and the SGD Hilbert-map baselines at several feature counts, plus a count grid;
  writes ``gt_map_grid.parquet`` (the HILBERT-GP map trained on the training scans);
- ``uncertainty`` (Fig. 10): quartiles of the normalised predictive uncertainty over the mapped area
  while that map is built;
- ``rmap`` (RMap Tables I/III/IV): the radar map (and the completed map when the ``complete`` stage
  ran) against the lidar map with ``map_metrics.py``.

Writes ``metrics.parquet`` (seq, method, metric, value; plus ``features`` and ``section``),
``report.md`` and PNG figures beside it, and logs every scalar to Rerun under ``metrics/``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from core import hilbert_map as hm
from core.errors import UserError
from core.stage import Stage, StageContext, StageParams, StageReport, blas_threads, flatten_params, parquet_rows
from schemas import read_artifact, write_artifact
from stages.evaluate import figures, tables
from stages.evaluate.params import EvaluateParams
from stages.evaluate.trajectory import (
    anchored_errors,
    evaluate_trajectory,
    evaluate_trajectory_whole,
    path_length,
    quat_to_yaw,
)

if TYPE_CHECKING:
    from sources.sequence import SequenceInfo

F64 = npt.NDArray[np.float64]
#: sections that read the log's ground truth (the map metrics compare maps only)
GT_SECTIONS = frozenset({"trajectory", "mapping", "uncertainty"})

#: parameters of the slam stage this stage falls back to (name in slam's manifest -> default)
SLAM_FALLBACKS = {"beams.max_range": 5.0}


class EvaluateStage(Stage):
    name = "evaluate"
    description = "the papers' tables and figures"
    inputs = ("ingest", "filter", "odometry", "slam", "voxel")
    optional_inputs = ("complete", "patches")
    Params = EvaluateParams
    version = "1"
    outputs = ("metrics.parquet", "report.md")

    def input_stages(self, params: StageParams) -> tuple[str, ...]:
        assert isinstance(params, EvaluateParams)
        s = set(params.sections)
        need = ["ingest"] if s & GT_SECTIONS else []
        if "mapping" in s or "uncertainty" in s:
            need += ["filter"] if params.mapping.auc_points == "filtered" else []
        if "trajectory" in s:
            need += ["odometry"]
        if s & {"trajectory", "mapping", "uncertainty"}:
            need += ["slam"]
        if "rmap" in s:
            need += ["voxel"]
        return tuple(n for n in self.inputs if n in need)

    def optional_input_stages(self, params: StageParams) -> tuple[str, ...]:
        """The completed map and its patches: only the RMap section reads them."""
        assert isinstance(params, EvaluateParams)
        return self.optional_inputs if "rmap" in params.sections else ()

    def skip_reason_for_inputs(self, seq: SequenceInfo, params: StageParams,
                               input_dirs: Mapping[str, Path]) -> str | None:
        assert isinstance(params, EvaluateParams)
        if set(params.sections) & GT_SECTIONS and "ingest" in input_dirs:
            n = parquet_rows(input_dirs["ingest"] / "groundtruth.parquet")
            if n is not None and n < 2:
                return (f"the log has {'no' if n == 0 else 'one'} ground-truth pose{'s' if n == 0 else ''}; "
                        f"evaluate.sections {', '.join(sorted(set(params.sections) & GT_SECTIONS))} need it")
        return None

    def report(self) -> StageReport:
        from stages.evaluate.report import EvaluationReport

        return EvaluationReport()

    def run(self, ctx: StageContext) -> None:
        with blas_threads(ctx.params.blas_threads):
            Evaluation().run(ctx)


class Evaluation:
    """One evaluation: the metric records, figures and notes collected while the sections run."""

    def __init__(self) -> None:
        self.records: list[dict[str, Any]] = []
        self.figures: dict[str, str] = {}
        self.notes: dict[str, list[str]] = {}

    def run(self, ctx: StageContext) -> None:
        p: EvaluateParams = ctx.params
        t_start = time.perf_counter()
        gt = self._groundtruth(ctx) if set(p.sections) & GT_SECTIONS else {}
        if "trajectory" in p.sections:
            self._trajectories(ctx, gt)
        if "mapping" in p.sections or "uncertainty" in p.sections:
            self._mapping(ctx, gt)
        if "rmap" in p.sections:
            self._rmap(ctx)
        self._write(ctx)
        ctx.stats["seconds"] = round(time.perf_counter() - t_start, 3)

    # -- helpers ------------------------------------------------------------------------------------------------
    def add(self, section: str, method: str, metric: str, value: float, features: int = 0) -> None:
        self.records.append({"section": section, "method": method, "metric": metric, "value": float(value),
                             "features": int(features)})

    def note(self, section: str, text: str) -> None:
        self.notes.setdefault(section, []).append(text)

    @staticmethod
    def _slam_params(ctx: StageContext) -> dict[str, Any]:
        if not ctx.has_input("slam"):
            return {}
        path = ctx.input_dirs["slam"] / "manifest.json"
        try:
            return flatten_params(json.loads(path.read_text()).get("params", {}))
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    def _groundtruth(self, ctx: StageContext) -> dict[str, Any]:
        path = ctx.input("ingest", "groundtruth.parquet")
        t = read_artifact(path, "groundtruth")
        if t.num_rows < 2:
            raise UserError(f"{path}: {t.num_rows} ground-truth poses; evaluation needs ground truth (the "
                            "sequence's /lidar_ground_truth topic or groundtruth/ folder)")
        c = {k: t[k].to_numpy().astype(np.float64) for k in ("x", "y", "z", "qx", "qy", "qz", "qw")}
        order = np.argsort(t["t_ns"].to_numpy(), kind="stable")
        out = {k: v[order] for k, v in c.items()}
        out["t_ns"] = t["t_ns"].to_numpy()[order]
        out["yaw"] = quat_to_yaw(out["qx"], out["qy"], out["qz"], out["qw"])
        return out

    # -- trajectories (Table III, Fig. 11) ------------------------------------------------------------------------
    def _trajectory_files(self, ctx: StageContext) -> list[tuple[str, Path, str]]:
        files: list[tuple[str, Path, str]] = []
        odo = ctx.input_dirs.get("odometry")
        if odo is not None and (odo / "odometry.parquet").exists():
            files.append(("odometry", odo / "odometry.parquet", "odometry"))
        slam = ctx.input_dirs.get("slam")
        if slam is not None:
            for f in sorted(slam.glob("trajectory_*.parquet")):
                method = f.stem.removeprefix("trajectory_")
                if all(m != method for m, _, _ in files):  # the odometry stage's file wins over a copy
                    files.append((method, f, "trajectory"))
            # trajectory.parquet is slam.method's trajectory: counted once, under that method's name (without a
            # manifest naming it, only when no per-method file exists)
            method = _manifest(slam).get("params", {}).get("method")
            listed = any(s == "trajectory" for _, _, s in files)
            if (slam / "trajectory.parquet").exists() and (method is not None or not listed) \
                    and not any(m == method for m, _, _ in files):
                files.append((str(method or "slam"), slam / "trajectory.parquet", "trajectory"))
        return files

    def _trajectories(self, ctx: StageContext, gt: dict[str, Any]) -> None:
        p: EvaluateParams = ctx.params
        gt_xy = np.stack([gt["x"], gt["y"]], 1)
        files = self._trajectory_files(ctx)
        if not files:
            ctx.warn("no trajectories to evaluate (odometry.parquet, trajectory_*.parquet)")
            return
        aligned: dict[str, F64] = {}
        span: tuple[int, int] | None = None
        odo_file = next((f for m, f, s in files if s == "odometry"), None)
        anchored = odo_file is not None and _anchor_of(odo_file) == "groundtruth"
        for method, path, schema in files:
            t = read_artifact(path, schema)
            est_t = t["t_ns"].to_numpy()
            xy = np.stack([t["x"].to_numpy(), t["y"].to_numpy()], 1)
            try:
                err = evaluate_trajectory(est_t, xy, t["yaw"].to_numpy(), gt["t_ns"], gt_xy, gt["yaw"],
                                          p.trajectory.n_align, int(p.trajectory.max_gt_gap_s * 1e9))
                whole = evaluate_trajectory_whole(est_t, xy, t["yaw"].to_numpy(), gt["t_ns"], gt_xy, gt["yaw"],
                                                  int(p.trajectory.max_gt_gap_s * 1e9))
            except ValueError as exc:
                ctx.warn(f"{path.name}: {exc}; skipped")
                continue
            self.add("trajectory", method, "ate_pos_rmse_whole_m", whole.pos_rmse_m)
            self.add("trajectory", method, "ate_yaw_rmse_whole_deg", whole.yaw_rmse_deg)
            self.add("trajectory", method, "ate_pos_rmse_m", err.pos_rmse_m)
            self.add("trajectory", method, "ate_yaw_rmse_deg", err.yaw_rmse_deg)
            self.add("trajectory", method, "matched_frames", err.n_matched)
            self.add("trajectory", method, "aligned_frames", err.n_aligned)
            if anchored:  # every estimate starts at the ground-truth pose: its errors without alignment (the maps
                # built along it live in that frame, so these are the errors the radar-only maps inherit)
                pos_a, yaw_a = anchored_errors(est_t, xy, t["yaw"].to_numpy(), gt["t_ns"], gt_xy, gt["yaw"],
                                               int(p.trajectory.max_gt_gap_s * 1e9))
                self.add("trajectory", method, "ate_pos_rmse_anchored_m", pos_a)
                self.add("trajectory", method, "ate_yaw_rmse_anchored_deg", yaw_a)
            final = float(np.linalg.norm(err.xy_aligned[-1] - err.xy_gt[-1]))
            self.add("trajectory", method, "final_pos_error_m", final)
            ctx.stats.setdefault("alignment", {})[method] = {
                "rotation_deg": round(err.rotation_deg, 4), "translation_m": [round(v, 4) for v in err.translation],
                "aligned_on": err.n_aligned, "matched": err.n_matched, "of": len(est_t),
                "whole": {"rotation_deg": round(whole.rotation_deg, 4),
                          "translation_m": [round(v, 4) for v in whole.translation]}}
            aligned[method] = whole.xy_aligned
            lo, hi = int(err.t_ns[0]), int(err.t_ns[-1])
            span = (lo, hi) if span is None else (min(span[0], lo), max(span[1], hi))
        if span is not None:
            m = (gt["t_ns"] >= span[0]) & (gt["t_ns"] <= span[1])
            self.add("trajectory", "groundtruth", "length_m", path_length(gt_xy[m]))
            self.add("trajectory", "groundtruth", "duration_s", (span[1] - span[0]) / 1e9)
            figures.plot_trajectories(ctx.output("trajectories.png"), gt_xy[m], aligned,
                                      f"{ctx.seq.name}: SE(2)-aligned on the whole trajectory")
            self.figures["trajectory"] = "trajectories.png"

    # -- mapping (Fig. 6, 7, 10) -----------------------------------------------------------------------------------
    def _mapping(self, ctx: StageContext, gt: dict[str, Any]) -> None:
        from stages.evaluate import mapping as mp
        from stages.evaluate.occupancy import hilbert_maps_samples, split_scans_by_block
        from stages.evaluate.world import gt_interpolator, radar_beams_world

        p: EvaluateParams = ctx.params
        rng = np.random.default_rng(p.seed)
        slam_params = self._slam_params(ctx)
        post = self._posterior_meta(ctx)
        mp_ = p.mapping
        max_range = mp_.max_range or float(slam_params.get("beams.max_range") or SLAM_FALLBACKS["beams.max_range"])
        z_min = mp_.z_min if mp_.z_min is not None else slam_params.get("beams.z_min")
        z_max = mp_.z_max if mp_.z_max is not None else slam_params.get("beams.z_max")
        padding = mp_.domain_padding if mp_.domain_padding is not None else hm.DOMAIN_PADDING

        stage, fname, schema = (("filter", "radar_filtered.parquet", "radar_filtered") if mp_.auc_points == "filtered"
                                else ("ingest", "radar.parquet", "radar"))
        radar_path = ctx.input(stage, fname)
        radar = read_artifact(radar_path, schema, columns=["scan", "t_ns", "x", "y", "z"])
        calib = self._calibration(ctx)
        interp = gt_interpolator(gt, int(p.trajectory.max_gt_gap_s * 1e9))
        beams = radar_beams_world(radar, calib, interp, max_range, z_min, z_max)
        ctx.stats["auc_beams"] = beams.stats
        if len(beams.scan) < 10:
            raise UserError(f"{radar_path}: only {len(beams.scan)} radar points fall within ground truth and "
                            f"max_range {max_range} m; the AUC protocol needs radar scans with ground-truth poses")
        samples = hilbert_maps_samples(beams.origin, beams.end, beams.scan, rng, p.mapping.free_per_metre)
        # the Hilbert domain: ground-truth envelope plus the slam stage's padding
        env = np.stack([gt["x"], gt["y"]], 1)[interp.span_mask(gt["t_ns"])]
        lo, hi = env.min(0) - padding, env.max(0) + padding
        half, centre = (hi - lo) / 2.0, (hi + lo) / 2.0
        inside = np.all(np.abs(samples.points - centre) < half, axis=1)
        samples = samples.select(inside)
        test_mask = split_scans_by_block(samples.scan, p.mapping.test_fraction, p.mapping.split_block_scans, rng)
        train, test = samples.select(~test_mask), samples.select(test_mask)
        n_scans = len(np.unique(samples.scan))
        ctx.stats["auc_samples"] = {"train": len(train), "test": len(test), "outside_domain": int((~inside).sum()),
                                    "scans": n_scans, "test_scans": len(np.unique(test.scan)),
                                    "occupied_share_test": float(np.mean(test.labels > 0)) if len(test) else None}
        gp_cfg = mp.GPConfig(
            (float(half[0]), float(half[1])), (float(centre[0]), float(centre[1])),
            lengthscale_m=p.gp.lengthscale_m or post["lengthscale"] * post["length_unit_m"],
            signal_variance=p.gp.signal_variance or post["signal_variance"],
            noise_variance=p.gp.noise_variance or post["noise_variance"],
            basis_kind=post["basis_kind"])
        for k, v in (("lengthscale_m", gp_cfg.lengthscale_m), ("signal_variance", gp_cfg.signal_variance),
                     ("noise_variance", gp_cfg.noise_variance)):
            self.add("mapping", "hilbert_gp", k, v)
        ctx.stats["gp"] = {"half_widths": list(gp_cfg.half_widths), "centre": list(gp_cfg.centre),
                           "lengthscale_m": gp_cfg.lengthscale_m, "signal_variance": gp_cfg.signal_variance,
                           "noise_variance": gp_cfg.noise_variance, "M": post["M"], "basis": gp_cfg.basis_kind}
        self.note("mapping", f"{len(train)} training and {len(test)} held-out samples from {n_scans} scans "
                  f"({p.mapping.test_fraction:.0%} of the scans held out in blocks of "
                  f"{p.mapping.split_block_scans}, seed {p.seed}); "
                  f"ground-truth poses; HILBERT-GP l = {gp_cfg.lengthscale_m:g} m, "
                  f"sf2 = {gp_cfg.signal_variance:g}, "
                  f"sn2 = {gp_cfg.noise_variance:g} on {2 * half[0]:.1f} m x {2 * half[1]:.1f} m; baselines "
                  f"l = {p.baselines.lengthscale_m:g} m, SGD alpha = {p.baselines.alpha:g}, "
                  f"{p.baselines.epochs} epoch(s)")

        t_scan = {int(s): int(t) for s, t in zip(beams.scan, beams.t_ns, strict=True)}
        M = int(post["M"])
        fit = None
        if p.mapping.headline or "uncertainty" in p.sections:
            # the headline map: HILBERT-GP at the slam stage's M, tracking the uncertainty over the mapped area
            track = None
            if "uncertainty" in p.sections:
                pos = np.stack([gt["x"], gt["y"]], 1)[interp.span_mask(gt["t_ns"])]
                track = mp.observed_cells(lo, hi, max(p.mapping.grid_spacing, 0.5), pos, max_range)
            with ctx.progress(len(np.unique(train.scan)), f"HILBERT-GP M={M} (Kalman, ground-truth poses)") as adv:
                fit = mp.fit_hilbert_gp(train, gp_cfg, M, track, p.uncertainty.every, on_scan=adv)
        if "mapping" in p.sections:
            self._auc(ctx, mp, train, test, gp_cfg, fit if p.mapping.headline else None, M)
            if fit is not None and p.mapping.headline:
                self._gt_map(ctx, fit, gp_cfg, lo, hi, gt, interp, train)
        if "uncertainty" in p.sections and fit is not None:
            self._uncertainty(ctx, fit, t_scan, gt)
        if "uncertainty" in p.sections:
            self._query_resolutions(ctx)

    def _query_resolutions(self, ctx: StageContext) -> None:
        """Fig. 9: the slam stage's map posterior (one set of weights) queried at several grid spacings."""
        d = ctx.input_dirs.get("slam")
        if d is None or not (d / "map_posterior.parquet").exists() or not ctx.params.uncertainty.query_spacings:
            return
        from core.map_field import field_from_posterior, grid_axes

        field = field_from_posterior(read_artifact(d / "map_posterior.parquet", "map_posterior"))
        basis, theta, cov, M = field.basis, field.theta, field.cov, field.basis.M
        panels: list[tuple[float, F64, F64, F64]] = []
        for spacing in sorted(ctx.params.uncertainty.query_spacings, reverse=True):
            gx, gy = grid_axes(field.lo, field.hi, spacing)
            if len(gx) == 0 or len(gy) == 0:
                continue
            pts = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
            occ = np.asarray(hm.query(basis, theta, cov, pts)[2], np.float64).reshape(len(gx), len(gy))
            panels.append((float(spacing), gx, gy, occ))
        if not panels:
            return
        figures.plot_query_resolutions(ctx.output("query_resolutions.png"), panels,
                                       f"{ctx.seq.name}: the slam map (M = {M} weights) queried at "
                                       + ", ".join(f"{sp:g} m" for sp, *_ in panels))
        self.figures["resolutions"] = "query_resolutions.png"

    def _auc(self, ctx: StageContext, mp: Any, train: Any, test: Any, gp_cfg: Any, fit: Any, M: int) -> None:
        """AUC rows: ``<method>@<count>`` per feature count, ``<method>`` at the slam's M (``fit`` given)."""
        from stages.evaluate.occupancy import roc_auc

        p: EvaluateParams = ctx.params
        base = p.baselines
        counts = sorted(set(p.mapping.feature_counts) | ({M} if fit is not None else set()))
        feature_methods = [m for m in p.mapping.methods if m != "grid"]
        rows = []
        with ctx.progress(len(feature_methods) * len(counts), "AUC: methods x feature counts") as adv:
            if "hilbert_gp" in p.mapping.methods:
                hg_counts = list(counts)
                if fit is not None:
                    t0 = time.perf_counter()
                    rows.append(mp.AucRow("hilbert_gp", M, roc_auc(test.labels, fit.query(test.points)[2]),
                                          time.perf_counter() - t0))
                    hg_counts.remove(M)
                    adv(1)
                if hg_counts:
                    rows += mp.auc_suite(train, test, gp_cfg, base, hg_counts, ["hilbert_gp"], p.seed,
                                         on_fit=lambda *_: adv(1))
            rest = [m for m in p.mapping.methods if m != "hilbert_gp"]
            if rest and (counts or "grid" in rest):
                rows += mp.auc_suite(train, test, gp_cfg, base, counts, rest, p.seed, on_fit=lambda *_: adv(1))
        fig_rows = []
        ref: dict[str, float] = {}
        for r in rows:
            if r.method == "grid":
                self.add("mapping", "grid", "auc", r.auc)
                self.add("mapping", "grid", "fit_seconds", r.seconds)
                ref["grid"] = r.auc
                continue
            if r.features in p.mapping.feature_counts:
                self.add("mapping", f"{r.method}@{r.features}", "auc", r.auc, r.features)
                self.add("mapping", f"{r.method}@{r.features}", "fit_seconds", r.seconds, r.features)
                fig_rows.append((r.method, r.features, r.auc, 0.0))
            if r.features == M and fit is not None:
                self.add("mapping", r.method, "auc", r.auc, r.features)
        if not fig_rows:
            return
        figures.plot_auc_vs_features(ctx.output("auc_vs_features.png"), fig_rows,
                                     f"{ctx.seq.name}: occupancy AUC, ground-truth poses", ref)
        self.figures["mapping"] = "auc_vs_features.png"

    def _gt_map(self, ctx: StageContext, fit: Any, gp_cfg: Any, lo: F64, hi: F64, gt: dict[str, Any],
                interp: Any, train: Any) -> None:
        p: EvaluateParams = ctx.params
        gx = np.arange(lo[0] + p.mapping.grid_spacing / 2, hi[0], p.mapping.grid_spacing)
        gy = np.arange(lo[1] + p.mapping.grid_spacing / 2, hi[1], p.mapping.grid_spacing)
        pts = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
        mean, var, occ = fit.query(pts)

        u0 = hm.prior_variance_at(fit.basis, fit.prior_diag, pts)
        write_artifact({"x": pts[:, 0], "y": pts[:, 1], "occupancy": occ, "variance": var, "mean": mean,
                        "prior_variance": u0}, ctx.output("gt_map_grid.parquet"), "map_grid")
        shape = (len(gx), len(gy))
        traj = np.stack([gt["x"], gt["y"]], 1)[interp.span_mask(gt["t_ns"])]
        auc = next((r["value"] for r in self.records if r["method"] == "hilbert_gp" and r["metric"] == "auc"), None)
        title = (f"{ctx.seq.name}: HILBERT-GP on ground-truth poses, M={fit.basis.M}, l={gp_cfg.lengthscale_m:g} m, "
                 f"sf2={gp_cfg.signal_variance:g}" + (f", AUC {auc:.3f}" if auc is not None else ""))
        figures.plot_map_pair(ctx.output("gt_map.png"), gx, gy, occ.reshape(shape),
                              (var / np.maximum(u0, 1e-300)).reshape(shape), title, traj,
                              train.points[train.labels > 0])
        self.figures["gt_map"] = "gt_map.png"

    def _uncertainty(self, ctx: StageContext, fit: Any, t_scan: dict[int, int], gt: dict[str, Any]) -> None:
        rows = fit.uncertainty
        curves: dict[str, F64] = {}
        if len(rows):
            t0 = min(t_scan.values())
            ts = np.array([(t_scan.get(int(s), t0) - t0) / 1e9 for s in rows[:, 0]])
            curves["HILBERT-GP, ground-truth poses (training scans)"] = np.column_stack([ts, rows[:, 1:]])
            scans = rows[:, 0].astype(np.int64)
            t_ns = np.array([t_scan.get(int(s), t0) for s in scans], np.int64)
            for j, q in enumerate(("p25", "p50", "p75")):
                ctx.recording.scalars(f"metrics/uncertainty/{q}", scans, t_ns, rows[:, 1 + j])
            self.add("uncertainty", "hilbert_gp", "uncertainty_p50_final", rows[-1, 2])
            self.add("uncertainty", "hilbert_gp", "uncertainty_iqr_final", rows[-1, 3] - rows[-1, 1])
            self.add("uncertainty", "hilbert_gp", "uncertainty_p50_first", rows[0, 2])
        online = self._slam_uncertainty(ctx)
        if online is not None:
            curves["RICH-SLAM online map (slam stage)"] = online
            self.add("uncertainty", "rich_slam", "uncertainty_p50_final", online[-1, 2])
        if curves:
            figures.plot_uncertainty(ctx.output("uncertainty.png"), curves,
                                     f"{ctx.seq.name}: normalised predictive uncertainty (median, 25-75 %)")
            self.figures["uncertainty"] = "uncertainty.png"
            self.note("uncertainty", "normalised uncertainty u(p) / u_prior(p) (eq. 33 over the prior) on "
                      "the cells within max_range of the ground-truth path; quartiles after each "
                      f"{ctx.params.uncertainty.every}th training scan" +
                      ("; the slam stage's per-scan statistics are drawn as well" if online is not None else
                       "; the slam stage wrote no map_stats.parquet, so only the ground-truth-pose map is shown"))

    @staticmethod
    def _slam_uncertainty(ctx: StageContext) -> F64 | None:
        """Rows (t_s, p25, p50, p75) from the slam stage's ``map_stats.parquet`` when it wrote one."""
        d = ctx.input_dirs.get("slam")
        if d is None or not (d / "map_stats.parquet").exists():
            return None
        import pyarrow.parquet as pq

        t = pq.read_table(d / "map_stats.parquet")
        names = set(t.column_names)
        cols = next(((a, b, c) for a, b, c in (("u_p25", "u_p50", "u_p75"), ("p25", "p50", "p75"),
                                               ("uncertainty_p25", "uncertainty_p50", "uncertainty_p75"))
                     if {a, b, c} <= names), None)
        if cols is None or "t_ns" not in names or t.num_rows == 0:
            return None
        tn = t["t_ns"].to_numpy()
        return np.column_stack([(tn - tn[0]) / 1e9, *[t[c].to_numpy().astype(np.float64) for c in cols]])

    def _posterior_meta(self, ctx: StageContext) -> dict[str, Any]:
        path = ctx.input("slam", "map_posterior.parquet")
        cols = ["L1", "L2", "cx", "cy", "M", "lengthscale", "signal_variance", "noise_variance"]
        t = read_artifact(path, "map_posterior", columns=cols)
        import pyarrow.parquet as pq

        names = pq.read_schema(path).names
        extra = [c for c in ("length_unit_m", "basis_kind") if c in names]
        row = {c: t[c][0].as_py() for c in cols}
        if extra:
            e = pq.read_table(path, columns=extra)
            row.update({c: e[c][0].as_py() for c in extra})
        row.setdefault("length_unit_m", 1.0)
        row["length_unit_m"] = float(row.get("length_unit_m") or 1.0)
        row.setdefault("basis_kind", "tensor")
        row["basis_kind"] = row.get("basis_kind") or "tensor"
        return row

    @staticmethod
    def _calibration(ctx: StageContext) -> F64:
        path = ctx.input("ingest", "calibration.json")
        try:
            T = np.asarray(json.loads(path.read_text())["base_from_radar"], np.float64)
        except (KeyError, json.JSONDecodeError, ValueError) as exc:
            raise UserError(f"{path}: no readable base_from_radar 4x4 ({exc}); rerun `pipeline run ingest "
                            f"--seq {ctx.seq.name} --force`") from exc
        if T.shape != (4, 4):
            raise UserError(f"{path}: base_from_radar has shape {T.shape}, expected 4x4")
        return T

    # -- RMap (Tables I, III, IV) -----------------------------------------------------------------------------------
    def _rmap(self, ctx: StageContext) -> None:
        from core.map_metrics import MapComparison, comparison_metrics, lr_ratio, recall_by_path_distance

        p: EvaluateParams = ctx.params

        def cloud(stage: str, fname: str, schema: str) -> F64:
            t = read_artifact(ctx.input(stage, fname), schema, columns=["x", "y", "z"])
            return np.stack([t[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], 1)

        lidar = cloud("voxel", "lidar_map.parquet", "lidar_map")
        if len(lidar) == 0:
            ctx.warn("the lidar map is empty (no lidar in the log?): no map metrics")
            return
        maps = {"radar_map": cloud("voxel", "radar_map.parquet", "radar_map")}
        d = ctx.input_dirs.get("complete")
        per_model = _complete_models(d) if d is not None else {}
        if d is not None and (d / BAND_MAP).exists():  # the pre-filtered input (complete.prefilter.mode = band)
            maps[BAND_METHOD] = cloud("complete", BAND_MAP, "completed_map")
        if d is not None and (d / "completed_map.parquet").exists():
            maps["completed_map"] = cloud("complete", "completed_map.parquet", "completed_map")
        elif "complete" in ctx.input_dirs:
            ctx.warn("the complete stage's folder has no completed_map.parquet; only the radar map is scored")
            per_model = {}
        for model, fname in per_model.items():  # the other models of complete.models, each its own method
            if fname != "completed_map.parquet":
                maps[f"completed_map_{model}"] = cloud("complete", fname, "completed_map")
        path = (cloud("voxel", "map_trajectory.parquet", "map_trajectory")
                if (ctx.input_dirs["voxel"] / "map_trajectory.parquet").exists() else np.zeros((0, 3)))
        scored: dict[str, dict[str, float]] = {}
        for name, pts in maps.items():
            cmp = MapComparison(pts, lidar)
            scored[name] = {**comparison_metrics(cmp, p.fscore_threshold), "lr_ratio": lr_ratio(len(lidar), len(pts)),
                            **recall_by_path_distance(cmp, path, p.fscore_threshold)}
        for model, fname in per_model.items():  # the configured model: the rows of completed_map, not scored twice
            if fname == "completed_map.parquet":
                scored[f"completed_map_{model}"] = dict(scored["completed_map"])
        for name, m in scored.items():
            for k, v in m.items():
                self.add("rmap", name, k, v)
        self.add("rmap", "lidar_map", "n_points", len(lidar))
        self._map_set_rows(ctx)
        self.note("rmap", f"against the lidar map ({len(lidar)} voxel centres); F-score at {p.fscore_threshold:g} m; "
                  "CD-l2 and CD^x/y/z in m², the others in m (x1000 values are in metrics.parquet as *_x1000)")
        figures.plot_maps_top(ctx.output("maps_top.png"), {"lidar_map": lidar, **maps},
                              f"{ctx.seq.name}: voxel maps, top view (colour: z)", seed=p.seed)
        self.figures["rmap"] = "maps_top.png"

    def _map_set_rows(self, ctx: StageContext) -> None:
        """Map sequences: whether the ground truth was rebuilt, and the patch count, ``a`` and inference time of
        the completion (from the voxel, patches and complete manifests) for the paper's Tables III and VI."""
        voxel = _manifest(ctx.input_dirs["voxel"])
        ms = voxel.get("stats", {}).get("map_set")
        if not isinstance(ms, dict):
            return
        rebuilt = ms.get("lidar_filtered_source") != "map"
        self.add("rmap", "lidar_map", "gt_rebuilt", float(rebuilt))
        if rebuilt:
            self.note("rmap", f"ground truth rebuilt: lidar_filtered is {ms.get('lidar_filtered_detail') or 'rebuilt'}"
                      " (not the authors' map file)")
        if "complete" in ctx.input_dirs:
            stats = _manifest(ctx.input_dirs["complete"]).get("stats", {})
            for key in ("n_patches", "seconds_per_patch", "model_seconds", "n_parameters"):
                if isinstance(stats.get(key), int | float):
                    self.add("rmap", "completed_map", key, float(stats[key]))
            models = stats.get("models")
            for model, info in (models.items() if isinstance(models, dict) else ()):
                for key in ("n_patches", "model_seconds", "n_parameters"):
                    if isinstance(info, dict) and isinstance(info.get(key), int | float):
                        self.add("rmap", f"completed_map_{model}", key, float(info[key]))
        if "patches" in ctx.input_dirs:
            a = _manifest(ctx.input_dirs["patches"]).get("params", {}).get("a")
            if isinstance(a, int | float):
                self.add("rmap", "completed_map", "patches_a", float(a))

    # -- outputs --------------------------------------------------------------------------------------------------
    def _write(self, ctx: StageContext) -> None:
        seq = ctx.seq.name
        recs = [{"seq": seq, **r} for r in self.records]
        write_artifact({
            "seq": [r["seq"] for r in recs], "method": [r["method"] for r in recs],
            "metric": [r["metric"] for r in recs], "value": np.array([r["value"] for r in recs], np.float64),
            "features": np.array([r["features"] for r in recs], np.int32),
            "section": [r["section"] for r in recs],
        }, ctx.output("metrics.parquet"), "metrics")
        ctx.output("report.md").write_text(render_report(seq, recs, self.figures, self.notes))
        import rerun as rr

        for r in recs:
            if np.isfinite(r["value"]):
                method = r["method"].replace("@", "/features_")  # rff@64 -> metrics/rff/features_64/auc
                ctx.recording.log(f"metrics/{method}/{r['metric']}", rr.Scalars([r["value"]]), static=True)
        ctx.stats["metrics"] = len(recs)


def _anchor_of(odometry_file: Path) -> str:
    """The odometry artifact's ``anchor`` metadata ('groundtruth' or 'origin'; '' when unrecorded)."""
    import pyarrow.parquet as pq

    meta = pq.read_schema(odometry_file).metadata or {}
    return meta.get(b"anchor", b"").decode()


#: the complete stage's band-filtered radar map and its method name in metrics.parquet
BAND_MAP, BAND_METHOD = "radar_map_band.parquet", "radar_map_band"


def _complete_models(stage_dir: Path) -> dict[str, str]:
    """model -> map file of every model the complete stage ran (``stats.models``; empty when it ran one)."""
    models = _manifest(stage_dir).get("stats", {}).get("models")
    if not isinstance(models, dict):
        return {}
    return {str(m): str(info["file"]) for m, info in models.items()
            if isinstance(info, dict) and isinstance(info.get("file"), str) and (stage_dir / info["file"]).is_file()}


def _manifest(stage_dir: Path) -> dict[str, Any]:
    try:
        doc = json.loads((stage_dir / "manifest.json").read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return doc if isinstance(doc, dict) else {}


def render_report(seq: str, records: list[dict[str, Any]], figs: dict[str, str], notes: dict[str, list[str]]) -> str:
    """``report.md``: the tables of each section with their figures."""
    out = [f"# Evaluation of `{seq}`", ""]

    def section(title: str, key: str, tabs: list[tuple[list[str], list[list[str]]]], fig_keys: list[str]) -> None:
        recs = [r for r in records if r["section"] == key]
        if not recs and not any(k in figs for k in fig_keys):
            return
        out.extend([f"## {title}", ""])
        for n in notes.get(key, []):
            out.extend([n, ""])
        for headers, rows in tabs:
            if rows:
                out.extend([tables.markdown(headers, rows), ""])
        for k in fig_keys:
            if k in figs:
                out.extend([f"![{k}]({figs[k]})", ""])

    traj = [r for r in records if r["section"] == "trajectory"]
    section(tables.TRAJECTORY_TITLE, "trajectory", [tables.trajectory_table(traj)], ["trajectory"])
    mapping = [r for r in records if r["section"] == "mapping"]
    section("Mapping: occupancy AUC on held-out scans (RICH-SLAM Fig. 6)", "mapping",
            [tables.headline_auc_table(mapping), tables.auc_table(mapping)], ["mapping", "gt_map"])
    unc = [r for r in records if r["section"] == "uncertainty"]
    section("Predictive uncertainty over time (RICH-SLAM Fig. 10)", "uncertainty",
            [(["method", "metric", "value"], [[r["method"], r["metric"], tables.fmt(r["value"])] for r in unc])],
            ["uncertainty"])
    section("Resolution-independent querying (RICH-SLAM Fig. 9): one posterior, several grid spacings", "resolutions",
            [], ["resolutions"])
    rm = [r for r in records if r["section"] == "rmap"]
    section("Maps against the lidar map (RMap Tables I, III, IV)", "rmap", [tables.rmap_table(rm)], ["rmap"])
    return "\n".join(out).rstrip() + "\n"


STAGE = EvaluateStage()
