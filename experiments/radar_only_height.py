"""The radar-only maps before and after a change of the odometry.

Reads the ``sweep_metrics.parquet`` of two runs of ``pipeline sweep sweep_radar_only`` (or a sweep with the same
points) on the same sequences, e.g. without and with the odometry's mount state and level prior, and gives, per
sequence and trajectory, the completed map's CD-l2 over the one built along ground truth (the issue's 1.5x
target), as a Markdown table and a bar chart (log scale, the target drawn).

Usage: ``python -m experiments.radar_only_height BEFORE.parquet AFTER.parquet --labels before after
[--sources odometry rich_slam] [--out figure.png]``
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from stages.evaluate.radar_only import radar_only_rows

TARGET = 1.5


def ratios(path: Path) -> dict[tuple[str, str], dict[str, Any]]:
    """(sequence, source) -> the radar-only row (:func:`radar_only_rows`) of one sweep's metrics."""
    import pyarrow.parquet as pq

    if not path.exists():
        raise SystemExit(f"{path}: missing; run `pipeline sweep sweep_radar_only --seq ...` first")
    return {(r["seq"], r["source"]): r for r in radar_only_rows(pq.read_table(path).to_pylist())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--labels", nargs=2, default=["before", "after"])
    ap.add_argument("--sources", nargs="+", default=["odometry", "rich_slam"])
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    runs = [ratios(a.before), ratios(a.after)]
    seqs = sorted({s for s, _ in runs[0]} & {s for s, _ in runs[1]})
    print("| sequence | built along | " + " | ".join(f"{lab}: completed CD-l2 / along GT" for lab in a.labels)
          + " | " + " | ".join(f"{lab}: yaw RMSE, no alignment (deg)" for lab in a.labels) + " |")
    print("|---|---|" + "---|" * 4)
    bars: list[tuple[str, list[list[float]]]] = []  # per source: the ratios per sweep (before, after), per sequence
    for src in a.sources:
        per_run: list[list[float]] = [[], []]
        for s in seqs:
            rows = [r.get((s, src), {}) for r in runs]
            rat = [r.get("ratio_cd_l2") or float("nan") for r in rows]
            yaw = [r.get("traj.ate_yaw_rmse_anchored_deg", float("nan")) for r in rows]
            print(f"| {s} | {src} | " + " | ".join(f"{v:.2f}" for v in rat) + " | "
                  + " | ".join(f"{v:.2f}" for v in yaw) + " |")
            for j, v in enumerate(rat):
                per_run[j].append(v)
        bars.append((src, per_run))
    if a.out is None:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.5))
    n = len(seqs)
    width = 0.8 / (2 * len(a.sources))
    x = np.arange(n)
    k = 0
    for src, per_run in bars:
        for j, lab in enumerate(a.labels):
            ax.bar(x + (k - len(a.sources) + 0.5) * width, per_run[j], width, label=f"along {src}, {lab}",
                   alpha=0.55 if j == 0 else 1.0, hatch="//" if j == 0 else None)
            k += 1
    ax.axhline(TARGET, color="k", ls="--", lw=1, label=f"target {TARGET}x")
    ax.set_yscale("log")
    ax.set_xticks(x, [s.replace("coloradar_", "CR").replace("_twin", " twin") for s in seqs])
    ax.set_ylabel("completed CD-l2 / along ground truth")
    ax.set_title("radar-only maps on the twins: the map along each trajectory against the map along ground truth")
    ax.legend(fontsize=8, ncol=2)
    ax.grid(axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=90)
    print(f"figure: {a.out}")


if __name__ == "__main__":
    main()
