"""The length-scale unit study (README): which unit makes Table II's l = 20 give the paper's maps.

For each candidate unit (metres per map unit) the paper's l = 20 becomes ``20 * unit`` metres. On a
run folder (ingest + filter) this measures, with ground-truth poses and the evaluate stage's Hilbert-maps
AUC protocol (held-out scan blocks, ``stages/evaluate``), the held-out occupancy AUC of HILBERT-GP at
M = 256, and two properties of the prior: how many of the 256 basis functions keep at least 1 % of the
largest prior variance, and the share of the SE kernel's variance sigma_f^2 that the truncated basis
represents at the domain centre (eq. 5 vs eq. 3).

    python -m experiments.slam_unit_study RUN_DIR [RUN_DIR ...] [--units 1,0.5,0.2,0.1,0.05] [--out table.md]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from core import hilbert_map as hm

F64 = npt.NDArray[np.float64]


def prior_properties(basis: hm.HilbertBasis, lengthscale_m: float, signal_variance: float) -> dict[str, float]:
    """Active basis functions (prior variance >= 1 % of the largest) and the share of sigma_f^2 at the centre."""
    lam = hm.prior_variances(basis, lengthscale_m, signal_variance)
    active = int(np.sum(lam >= 0.01 * lam.max())) if lam.max() > 0 else 0
    share = float(hm.prior_variance_at(basis, lam, basis.centre[None, :])[0] / signal_variance)
    return {"active_basis": active, "prior_share_centre": share}


def read_run_folder(run_dir: Path) -> tuple[dict[str, Any], F64, Any]:
    """Ground truth (columns sorted by time), ``base_from_radar`` and the filtered radar table of a run folder."""
    from schemas.io import read_artifact

    g = read_artifact(run_dir / "ingest" / "groundtruth.parquet", "groundtruth")
    gt = {k: g[k].to_numpy() for k in ("t_ns", "x", "y", "z", "qx", "qy", "qz", "qw")}
    order = np.argsort(gt["t_ns"], kind="stable")
    calib = np.asarray(json.loads((run_dir / "ingest" / "calibration.json").read_text())["base_from_radar"])
    radar = read_artifact(run_dir / "filter" / "radar_filtered.parquet", "radar_filtered",
                          columns=["scan", "t_ns", "x", "y", "z"])
    return {k: v[order] for k, v in gt.items()}, calib, radar


def study_run(run_dir: Path, units: list[float], lengthscale: float = 20.0, signal_variance: float = 16.0,
              noise_variance: float = 0.36, M: int = 256, padding: float = 10.0, max_range: float = 5.0,
              seed: int = 0) -> list[dict[str, Any]]:
    """AUC and prior properties per unit on one run folder (ground-truth poses)."""
    from stages.evaluate.mapping import GPConfig, fit_hilbert_gp
    from stages.evaluate.occupancy import hilbert_maps_samples, roc_auc, split_scans_by_block
    from stages.evaluate.world import gt_interpolator, radar_beams_world

    gt, calib, radar = read_run_folder(run_dir)
    interp = gt_interpolator(gt, int(0.5e9))
    beams = radar_beams_world(radar, calib, interp, max_range)
    rng = np.random.default_rng(seed)
    samples = hilbert_maps_samples(beams.origin, beams.end, beams.scan, rng)
    env = np.stack([gt["x"], gt["y"]], 1)
    lo, hi = env.min(0) - padding, env.max(0) + padding
    half, centre = (hi - lo) / 2, (hi + lo) / 2
    test_mask = split_scans_by_block(samples.scan, 0.2, 10, rng)
    train, test = samples.select(~test_mask), samples.select(test_mask)
    rows = []
    for unit in units:
        cfg = GPConfig((float(half[0]), float(half[1])), (float(centre[0]), float(centre[1])),
                       lengthscale * unit, signal_variance, noise_variance)
        fit = fit_hilbert_gp(train, cfg, M)
        _, _, occ = fit.query(test.points)
        rows.append({"run": run_dir.name, "unit_m": unit, "lengthscale_m": lengthscale * unit,
                     "auc": roc_auc(test.labels > 0, occ), "train": len(train), "test": len(test),
                     **prior_properties(fit.basis, lengthscale * unit, signal_variance)})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders <runs>/<seq> with ingest/ and filter/")
    ap.add_argument("--units", default="1,0.5,0.2,0.1,0.05", help="metres per map unit to compare")
    ap.add_argument("--lengthscale", type=float, default=20.0, help="length scale in map units (Table II)")
    ap.add_argument("--out", type=Path, help="write the table as markdown here")
    a = ap.parse_args(argv)
    units = [float(u) for u in a.units.split(",")]
    lines = ["| sequence | unit (m) | l (m) | AUC | active basis functions (>= 1 % of max) | "
             "prior share of sigma_f^2 at centre |", "|---|---|---|---|---|---|"]
    for run in a.runs:
        for r in study_run(run, units, a.lengthscale):
            lines.append(f"| {r['run']} | {r['unit_m']:g} | {r['lengthscale_m']:g} | {r['auc']:.3f} | "
                         f"{r['active_basis']} | {r['prior_share_centre']:.3f} |")
            print(lines[-1], flush=True)
    if a.out:
        a.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
