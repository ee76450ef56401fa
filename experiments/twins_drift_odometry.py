"""EKF-RIO drift on the (drifting) ColoRadar twins beside RICH-SLAM Table III's real RIO.

For each sequence named, after ``pipeline run ingest filter odometry --seq S``: the
odometry stage's own drift against ground truth (``stats.drift`` of its manifest: the estimate anchored at
the first ground-truth pose, no alignment) and the vertical drift (the odometry's z minus the ground truth's
at the same stamps, both taken relative to their first matched pose: RMSE and final value), with the EKF's
update counts. Table III's OPT-RIO and EKF-RIO (real ColoRadar) beside each twin.

Usage: ``python -m experiments.twins_drift_odometry --runs-dir RUNS coloradar_1_twin_drift ...``; prints Markdown.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

#: RICH-SLAM Table III on ColoRadar 1-6: horizontal position RMSE (m), yaw RMSE (deg)
PAPER_RIO: dict[int, dict[str, tuple[float, float]]] = {
    1: {"OPT-RIO": (1.28, 7.69), "EKF-RIO": (3.26, 79.53)},
    2: {"OPT-RIO": (2.78, 25.41), "EKF-RIO": (1.60, 91.98)},
    3: {"OPT-RIO": (6.54, 15.36), "EKF-RIO": (3.72, 97.11)},
    4: {"OPT-RIO": (4.70, 16.90), "EKF-RIO": (0.89, 96.45)},
    5: {"OPT-RIO": (3.31, 26.34), "EKF-RIO": (2.76, 79.15)},
    6: {"OPT-RIO": (5.95, 9.00), "EKF-RIO": (3.26, 86.98)},
}


def z_drift(odo_t: np.ndarray, odo_z: np.ndarray, gt_t: np.ndarray, gt_z: np.ndarray) -> dict[str, float]:
    """Vertical error of the odometry against ground truth (interpolated at the odometry's stamps inside the
    ground truth's span), both relative to their first matched pose: RMSE and final value, metres."""
    inside = (odo_t >= gt_t[0]) & (odo_t <= gt_t[-1])
    if inside.sum() < 2:
        return {"z_rmse_m": float("nan"), "z_final_m": float("nan")}
    t = odo_t[inside].astype(np.float64)
    ref = np.interp(t, gt_t.astype(np.float64), gt_z)
    e = (odo_z[inside] - odo_z[inside][0]) - (ref - ref[0])
    return {"z_rmse_m": float(np.sqrt(np.mean(e**2))), "z_final_m": float(e[-1])}


def row(run: Path) -> dict[str, Any]:
    """Drift numbers of one sequence's odometry run folder."""
    import pyarrow.parquet as pq

    st = json.loads((run / "odometry" / "manifest.json").read_text())["stats"]
    odo = pq.read_table(run / "odometry" / "odometry.parquet").to_pandas()
    gt = pq.read_table(run / "ingest" / "groundtruth.parquet").to_pandas()
    odo = odo[odo["valid"]]
    out: dict[str, Any] = dict(st["drift"])
    out |= z_drift(odo["t_ns"].to_numpy(), odo["z"].to_numpy(), gt["t_ns"].to_numpy(), gt["z"].to_numpy())
    ekf = st.get("ekf", {})
    out["updates"] = f"{ekf.get('velocity_updates', '')}/{ekf.get('velocity_rejected', '')}"
    out["recoveries"] = ekf.get("recoveries", "")
    out["standstill"] = "yes" if ekf.get("standstill") else "no"
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.twins_drift_odometry", description=__doc__)
    ap.add_argument("--runs-dir", type=Path, default=Path("runs"))
    ap.add_argument("seqs", nargs="+")
    a = ap.parse_args(argv)
    lines = ["| sequence | path m | duration s | yaw RMSE deg | final yaw err deg | pos RMSE m | drift % | "
             "z RMSE m | final z err m | upd/rej | recoveries | standstill | paper OPT-RIO m / deg | "
             "paper EKF-RIO m / deg |", "|" + "---|" * 14]
    for s in a.seqs:
        r = row(a.runs_dir / s)
        m = re.match(r"coloradar_(\d)_twin", s)
        paper = PAPER_RIO.get(int(m.group(1)), {}) if m else {}
        opt, ekf = (" / ".join(f"{v:.2f}" for v in paper[k]) if k in paper else "" for k in ("OPT-RIO", "EKF-RIO"))
        lines.append(f"| {s} | {r['path_length_m']:.2f} | {r['duration_s']:.1f} | {r['rmse_yaw_deg']:.2f} | "
                     f"{r['final_yaw_error_deg']:.2f} | {r['rmse_position_m']:.2f} | "
                     f"{r['drift_pct_of_distance']:.2f} | "
                     f"{r['z_rmse_m']:.3f} | {r['z_final_m']:.3f} | {r['updates']} | {r['recoveries']} | "
                     f"{r['standstill']} | {opt} | {ekf} |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
