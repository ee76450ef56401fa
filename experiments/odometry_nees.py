"""The NEES check of the odometry's increment covariance, on finished odometry runs.

Usage: ``python -m experiments.odometry_nees RUNS_DIR SEQ [SEQ ...] [--calibrate CAL [CAL ...]]``. For each
sequence, the normalised estimation error squared of the body-frame increments against the ground truth
(:func:`core.trajectory_metrics.increment_nees`; chi-square(3): mean 3, median 2.37). ``--calibrate`` names
runs (never evaluated ones) whose pooled mean NEES gives the factor ``increment_cov_scale`` that makes it 3;
the table is then also given with that factor. ``--windows``: also the heading NEES over windows of 1, 10, 100
and 300 increments (:func:`core.trajectory_metrics.heading_window_nees`; 1 at every window when the increments'
errors are independent). ``--speed``: also the distance the odometry moves in 10 s over the truth's
(:func:`core.trajectory_metrics.distance_ratio`: a speed scale error). Runs come from
``pipeline run odometry --seq SEQ --runs-dir RUNS_DIR``; the covariances are divided by the factor each run was
made with, so the factor is chosen on the EKF's own covariance.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from core.errors import UserError
from core.geometry import interpolate_poses, yaw_of
from core.trajectory_metrics import (
    NEES_TOLERANCE,
    NEES_WINDOWS,
    distance_ratio,
    heading_window_nees,
    increment_nees,
)
from schemas.io import read_artifact
from stages.odometry.stage import _COV_IDX, COV_COLS, POSE_COLS

F64 = npt.NDArray[np.float64]


def load(run: Path) -> tuple[F64, F64, F64, npt.NDArray[np.bool_], F64]:
    """Estimated and true (x, y, yaw) at the scans, the EKF's own increment covariance, the usable rows and the
    scans' times (s from the first)."""
    path = run / "odometry" / "odometry.parquet"
    if not path.exists():
        raise UserError(f"{path}: no odometry run (pipeline run odometry --seq {run.name} --runs-dir {run.parent})")
    odo = read_artifact(path, "odometry")
    params = json.loads((run / "odometry" / "manifest.json").read_text())["params"]
    scale = params.get("covariance", {}).get("scale", 1.0)
    gt = read_artifact(run / "ingest" / "groundtruth.parquet", "groundtruth")
    if gt.num_rows < 2:
        raise UserError(f"{run / 'ingest' / 'groundtruth.parquet'}: no ground truth; the NEES check needs it")
    t = odo["t_ns"].to_numpy()
    T, inside = interpolate_poses(gt["t_ns"].to_numpy(), np.stack([gt[c].to_numpy() for c in POSE_COLS], 1), t)
    ref = np.stack([T[:, 0, 3], T[:, 1, 3], yaw_of(T[:, :3, :3])], axis=1)
    est = np.stack([odo[c].to_numpy() for c in ("x", "y", "yaw")], axis=1)
    cov = np.zeros((len(t), 3, 3))
    for c, (i, j) in zip(COV_COLS, _COV_IDX, strict=True):
        cov[:, i, j] = cov[:, j, i] = odo[c].to_numpy() / scale
    return est, ref, cov, odo["valid"].to_numpy() & inside, (t - t[0]) * 1e-9


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs_dir", type=Path)
    ap.add_argument("seqs", nargs="+")
    ap.add_argument("--calibrate", nargs="*", default=[], help="runs that choose the factor (not evaluated)")
    ap.add_argument("--windows", action="store_true", help="also the heading NEES over windows of increments")
    ap.add_argument("--speed", action="store_true", help="also the odometry's distance over 10 s against the truth's")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    a = ap.parse_args(argv)
    overlap = set(a.seqs) & set(a.calibrate)
    if overlap:
        raise UserError(f"--calibrate: {', '.join(sorted(overlap))} also evaluated; calibrate on other runs")
    data = {s: load(a.runs_dir / s) for s in [*a.calibrate, *a.seqs]}
    scale = 1.0
    if a.calibrate:
        stats = [increment_nees(*data[s][:4]) for s in a.calibrate]
        n = sum(st["increments"] for st in stats)
        scale = sum(st["mean"] * st["increments"] for st in stats) / n / 3.0
        print(f"factor from {', '.join(a.calibrate)} ({n} increments): {scale:.3f}")
    rows: list[dict[str, Any]] = []
    print(f"tolerance: mean NEES within a factor {NEES_TOLERANCE:g} of 3")
    print("| sequence | role | increments | mean (factor 1) | median | < chi2 95 % | x, y, yaw | mean (factor) | ok |")
    print("|---|---|---|---|---|---|---|---|---|")
    for s, (est, ref, cov, ok, _) in data.items():
        st1 = increment_nees(est, ref, cov, ok)
        sts = increment_nees(est, ref, cov * scale, ok)
        role = "calibration" if s in a.calibrate else "evaluated"
        rows.append({"sequence": s, "role": role, "factor": round(scale, 4), "factor_1": st1, "scaled": sts})
        print(f"| {s} | {role} | {st1['increments']} | {st1['mean']} | {st1['median']} | "
              f"{st1['share_below_chi2_95']} | {', '.join(map(str, st1['axis_mean']))} | {sts['mean']} | "
              f"{'yes' if sts['within_tolerance'] else 'no'} |")
    if a.windows:
        print("\nheading change over windows of W increments, normalised by the summed increment variances "
              "(chi-square(1): 1 at every W when the increments' errors are independent):\n")
        print("| sequence | role | " + " | ".join(f"W = {w}" for w in NEES_WINDOWS) + " |")
        print("|---|---|" + "---|" * len(NEES_WINDOWS))
        for row, (s, (est, ref, cov, ok, _)) in zip(rows, data.items(), strict=True):
            wn = heading_window_nees(est[:, 2], ref[:, 2], cov[:, 2, 2] * scale, ok)
            row["heading_window_nees"] = {str(w): round(v, 4) for w, v in wn.items()}
            print(f"| {s} | {row['role']} | " + " | ".join(f"{v:.2f}" for v in wn.values()) + " |")
    if a.speed:
        print("\nthe odometry's straight-line distance over 10 s against the truth's, from every scan where the truth "
              "moves at least 3 m (1: no speed scale error):\n")
        print("| sequence | role | windows | median | 10 % | 90 % |\n|---|---|---|---|---|---|")
        for row, (s, (est, ref, _, ok, t)) in zip(rows, data.items(), strict=True):
            row["distance_ratio_10s"] = dr = distance_ratio(t, est[:, :2], ref[:, :2], ok)
            print(f"| {s} | {row['role']} | {dr['windows']} | {dr['median']:.4f} | {dr['p10']:.4f} | "
                  f"{dr['p90']:.4f} |")
    if a.json:
        a.json.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
