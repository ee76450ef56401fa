"""Can the scans' consistency score be trusted on a run? Its answer to perturbations the truth can judge.

The fused estimate's scale is chosen by :func:`map_consistency.map_consistency` without ground truth. This tool
perturbs a run's odometry two ways whose right answer the ground truth knows: its positions
scaled about the start (:func:`map_consistency.scaled_positions`; the odometry's scale is nearly right on every
simulated run, so an unbiased score is lowest near 1) and its heading given a linear ramp
(:func:`map_consistency.heading_ramp`; the truth says which ramp undoes the odometry's drift). Per run and
perturbation: the score relative to the odometry's, the share of points with a counterpart within the cap
(:func:`map_consistency.consistency_parts`), the mean square distance of the points matched under every
perturbation of that kind (:func:`map_consistency.common_support_scores`, the ``common`` criterion), and the
whole-trajectory yaw and position RMSE against the ground truth. A score that keeps falling as the path
contracts rewards overlap, not agreement (stages/slam/README.md, stop 52). Run folders need the odometry stage
and a ground truth.

With ``--kept DIR`` the perturbation is instead the fused estimate's own scale (kind ``alpha``): for each
smoothed trajectory that ``table3 --keep DIR`` kept for the run, the fusion's heading correction of the odometry
scaled by every ``--alphas`` value (the search of ``slam.fusion_alpha_*``), with the three criteria's values and
the true errors at each: which scale each criterion picks, and the best any criterion of this family could pick
(stages/slam/README.md, stop 53). Usage::

    python -m stages.slam.consistency_sweep RUN [RUN ...] [--scales 0.94,1,1.06] [--ramps=-0.1,0,0.1] [--out F.jsonl]
    python -m stages.slam.consistency_sweep RUN [RUN ...] --kept KEPT [--alphas 0,0.5,1,1.5] [--out F.jsonl]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.slam.heading_fusion import fuse_heading, recompose
from stages.slam.map_consistency import (
    MapConsistency,
    common_support_scores,
    consistency_parts,
    heading_ramp,
    scaled_positions,
    stacked_endpoints,
)
from stages.slam.stage import SlamParams
from stages.slam.table3 import Truth, error_fields, kept_fusion, kept_smoothed, load_inputs, slam_overrides

F64 = npt.NDArray[np.floating[Any]]

SCALES = (0.94, 0.97, 1.0, 1.03, 1.06)
RAMPS = (-0.2, -0.1, -0.05, 0.0, 0.05, 0.1, 0.2)


def sweep_run(run_dir: Path, params: SlamParams, scales: Sequence[float] = SCALES,
              ramps: Sequence[float] = RAMPS) -> list[dict[str, Any]]:
    """One row per perturbation of ``run_dir``'s odometry: ``kind`` (``scale`` or ``ramp``), ``value``, the score,
    its parts, the common points' mean square (``common_ms``, over the perturbations of that kind) and the
    whole-trajectory errors against the run's ground truth; ``score_rel`` is the score minus the unperturbed
    odometry's."""
    t_ns, odo, scans, truth, motion = load_inputs(run_dir, params)
    t = np.cumsum(motion.dt)
    points, scan = stacked_endpoints(scans)
    if len(points) == 0:
        raise ValueError(f"{run_dir}: no scan has endpoints; the score has nothing to compare")
    consistency: MapConsistency = params.config().consistency
    base = consistency_parts(odo, points, scan, t, consistency).score
    rows: list[dict[str, Any]] = []
    for kind, values in (("scale", scales), ("ramp", ramps)):
        estimates = [scaled_positions(odo, v) if kind == "scale" else heading_ramp(odo, t, v) for v in values]
        rows += _scored(kind, values, estimates, points, scan, t, consistency, base, t_ns, truth,
                        {"seq": run_dir.name}, reference=odo)
    return rows


def _scored(kind: str, values: Sequence[float], estimates: Sequence[F64],
            points: F64, scan: npt.NDArray[np.int64], t: F64,
            consistency: MapConsistency, base: float, t_ns: npt.NDArray[np.int64], truth: Truth,
            head: dict[str, Any], reference: F64 | None = None) -> list[dict[str, Any]]:
    """One row per estimate: the score (minus ``base``), its parts, the common points' mean square over these
    estimates (and ``reference``, if given: the points are then thinned on it, else on the first estimate) and the
    whole-trajectory errors."""
    pool = list(estimates) if reference is None else [reference, *estimates]
    common, share = common_support_scores(pool, points, scan, t, consistency)
    common = common if reference is None else common[1:]
    rows = []
    for v, est, common_ms in zip(values, estimates, common, strict=True):
        parts = consistency_parts(est, points, scan, t, consistency)
        row: dict[str, Any] = {**head, "kind": kind, "value": float(v), "score": parts.score,
                               "score_rel": parts.score - base, "matched": parts.matched,
                               "matched_ms": parts.matched_ms, "common_ms": float(common_ms), "common_share": share}
        e = error_fields(t_ns, np.asarray(est, np.float64), truth)
        rows.append(row | {k: e[k] for k in ("yaw_rmse_whole_deg", "pos_rmse_whole_m")})
    return rows


def profile_kept(run_dir: Path, keep: Path, params: SlamParams, alphas: Sequence[float] | None = None,
                 method: str = "rich_slam") -> list[dict[str, Any]]:
    """Rows of kind ``alpha`` for every smoothed trajectory of ``method`` kept for ``run_dir`` in ``keep``: the
    fusion's heading correction (as ``table3 --from-kept`` computes it, with ``params``' fusion settings) scaled
    by each of ``alphas`` (default: the grid ``params``' fused estimate searches) and composed with the odometry's
    increments; ``seed`` and ``kept`` name the file."""
    if alphas is None:
        alphas = [float(v) for v in params.consistency_model().scales()]
    kept_runs = kept_smoothed(keep, run_dir.name, method)
    if not kept_runs:
        raise ValueError(f"{keep / run_dir.name}: no smoothed {method} trajectory kept (table3 --keep)")
    t_ns, odo, scans, _, motion = load_inputs(run_dir, params)
    t = np.cumsum(motion.dt)
    points, scan = stacked_endpoints(scans)
    if len(points) == 0:
        raise ValueError(f"{run_dir}: no scan has endpoints; the score has nothing to compare")
    fusion_keys = {k: v for k, v in params.model_dump().items() if k.startswith("fusion_")}
    rows: list[dict[str, Any]] = []
    base_scores: dict[MapConsistency, float] = {}  # the odometry's score, once per score setting
    for path, kept, base in kept_runs:
        if not np.array_equal(t_ns, kept["t_ns"]):
            raise ValueError(f"{path}: its scan stamps are not those of {run_dir}/odometry")
        model, _, consistency = kept_fusion(method, SlamParams(**{**base, **fusion_keys}), odo, lambda: scans)
        correction = fuse_heading(t, odo[:, 2], kept["pose"][:, 2], motion.cov[:, 2, 2], model).correction
        estimates = [recompose(odo, a * correction) for a in alphas]
        truth: Truth = (kept["truth_t_ns"], kept["truth_xy"], kept["truth_yaw"])
        if consistency not in base_scores:
            base_scores[consistency] = consistency_parts(odo, points, scan, t, consistency).score
        base_score = base_scores[consistency]
        head = {"seq": run_dir.name, "method": f"{method}, fused", "seed": int(kept["seed"]), "kept": path.name}
        rows += _scored("alpha", alphas, estimates, points, scan, t, consistency, base_score, t_ns, truth, head)
    return rows


def summary(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Per kind: the value the score picks (lowest), the one the matched points' mean square picks
    (``slam.fusion_alpha_criterion = matched``), the one the common points' picks (``common``) and the one the
    truth picks (lowest yaw RMSE for a ramp or a fused scale ``alpha``, lowest position RMSE for a scale). Rows of
    one run and (for ``alpha``) one kept trajectory."""
    out: dict[str, Any] = {}
    for kind, err in (("scale", "pos_rmse_whole_m"), ("ramp", "yaw_rmse_whole_deg"), ("alpha", "yaw_rmse_whole_deg")):
        sel = [r for r in rows if r["kind"] == kind]
        if not sel:
            continue
        out[f"{kind}_by_score"] = min(sel, key=lambda r: r["score"])["value"]
        out[f"{kind}_by_matched"] = min(sel, key=lambda r: r["matched_ms"] if r["matched"] > 0 else np.inf)["value"]
        out[f"{kind}_by_common"] = min(sel, key=lambda r: np.nan_to_num(r["common_ms"], nan=np.inf))["value"]
        out[f"{kind}_by_truth"] = min(sel, key=lambda r: r[err])["value"]
    return out


def table(rows: Sequence[dict[str, Any]]) -> str:
    """A markdown table of one run's rows."""
    lines = ["| perturbation | score - odometry's | matched share | matched mean square, m^2 | common mean square, "
             "m^2 | yaw RMSE, deg | position RMSE, m |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['kind']} {r['value']:+g} | {r['score_rel']:+.4f} | {r['matched']:.3f} | "
                     f"{r['matched_ms']:.4f} | {r['common_ms']:.4f} | {r['yaw_rmse_whole_deg']:.2f} | "
                     f"{r['pos_rmse_whole_m']:.2f} |")
    return "\n".join(lines)


def _floats(text: str, name: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--{name} {text!r}: give comma-separated numbers, e.g. 0.94,1,1.06") from None
    if not values:
        raise ValueError(f"--{name} is empty: give comma-separated numbers")
    return values


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m stages.slam.consistency_sweep",
                                 description=(__doc__ or "").splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders with an odometry (pipeline run odometry)")
    ap.add_argument("--scales", default=",".join(map(str, SCALES)), help="position scales about the start")
    ap.add_argument("--ramps", default=",".join(map(str, RAMPS)),
                    help="heading ramps over the run, rad (write --ramps=-0.1,0,0.1: a leading minus needs the =)")
    ap.add_argument("--kept", type=Path, help="instead: the fused estimate's scale, on the smoothed trajectories "
                    "that table3 --keep kept in this folder")
    ap.add_argument("--alphas", help="scales of the fused correction (with --kept; default: the grid the fused "
                    "estimate searches, slam.fusion_alpha_max in steps of 0.125)")
    ap.add_argument("--method", default="rich_slam", help="whose kept trajectories (with --kept)")
    ap.add_argument("--set", action="append", default=[], metavar="PARAM=JSON",
                    help="a slam parameter (the beam sampling's), as table3 takes it")
    ap.add_argument("--out", type=Path, help="also write the rows here (JSON lines, replaced whole)")
    a = ap.parse_args(argv)
    try:
        scales, ramps = _floats(a.scales, "scales"), _floats(a.ramps, "ramps")
        params = SlamParams(**slam_overrides(a.set))
        if a.kept is not None:
            alphas = (_floats(a.alphas, "alphas") if a.alphas is not None
                      else [float(v) for v in params.consistency_model().scales()])
            if not alphas:
                raise ValueError("slam.fusion_alpha_max is 0: no scale is searched; give --alphas or set it above 0")
            results = []
            for run in a.runs:
                rows = profile_kept(run, a.kept, params, alphas, a.method)
                files = sorted({(r["seed"], r["kept"]) for r in rows})  # one table per kept file
                results += [(f"{run.name} seed {seed} ({name})", [r for r in rows if r["kept"] == name])
                            for seed, name in files]
        else:
            results = [(run.name, sweep_run(run, params, scales, ramps)) for run in a.runs]
    except (OSError, ValueError, KeyError) as e:
        print(f"consistency_sweep: {e}", file=sys.stderr)
        return 2
    every: list[dict[str, Any]] = []
    for name, rows in results:
        s = summary(rows)
        picks = ", ".join(f"{k.replace('_', ' ')} {v:+g}" for k, v in s.items())
        print(f"\n{name}: {picks}\n{table(rows)}")
        every.extend(rows)
    if a.out is not None:
        tmp = a.out.with_name(a.out.name + ".tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in every))
        tmp.replace(a.out)
        print(f"\nwrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
