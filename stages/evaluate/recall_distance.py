"""Recall by horizontal distance from the path: how far from the trajectory each map reaches the lidar's walls.

The evaluate stage's ``rmap`` section records, per map, ``recall_path_<bin>`` and the bin's lidar point count
``n_gt_path_<bin>`` (:func:`core.map_metrics.recall_by_path_distance`). Over several sequences a bin's recall is
pooled: the hits of all sequences over their points. Pure functions on records.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from core.map_metrics import PATH_BINS_M, path_bin_names
from stages.evaluate import figures
from stages.evaluate.tables import fmt, ordered

Table = tuple[str, list[str], list[list[str]]]
#: the far field of the table's last column: every bin at or beyond this many metres
FAR_M = 5.0
MAP_ORDER = ("radar_map", "radar_map_band", "completed_map", "completed_map_uppointr", "completed_map_voxel")


def pooled_recall(records: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, tuple[float, float]]]:
    """``{map: {bin: (recall, points)}}`` pooled over the sequences among ``records``."""
    hits: dict[tuple[str, str], float] = {}
    counts: dict[tuple[str, str], float] = {}
    by = {(str(r["seq"]), str(r["method"]), str(r["metric"])): float(r["value"]) for r in records
          if str(r.get("metric", "")).startswith(("recall_path_", "n_gt_path_"))}
    for (seq, method, metric), value in by.items():
        if not metric.startswith("recall_path_") or not np.isfinite(value):
            continue
        name = metric.removeprefix("recall_path_")
        n = by.get((seq, method, f"n_gt_path_{name}"), 0.0)
        hits[(method, name)] = hits.get((method, name), 0.0) + value * n
        counts[(method, name)] = counts.get((method, name), 0.0) + n
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for (method, name), n in counts.items():
        out.setdefault(method, {})[name] = (hits[(method, name)] / n if n else float("nan"), n)
    return out


def far_bins() -> list[str]:
    names = path_bin_names()
    return [n for n, lo in zip(names, PATH_BINS_M, strict=True) if lo >= FAR_M]


def recall_table(records: Sequence[Mapping[str, Any]]) -> Table | None:
    """One row per map: the pooled recall per bin, the far field's (>= :data:`FAR_M`) and the share of the
    lidar points in each bin (a row of its own); None without the metrics."""
    pooled = pooled_recall(records)
    if not pooled:
        return None
    names = path_bin_names()
    far = far_bins()
    rows = []
    for method in ordered(pooled, MAP_ORDER):
        cells = pooled[method]
        n_far = sum(cells.get(b, (0.0, 0.0))[1] for b in far)
        r_far = sum(cells[b][0] * cells[b][1] for b in far if b in cells and cells[b][1]) / n_far if n_far else None
        rows.append([method, *[fmt(cells.get(b, (None, 0))[0]) for b in names], fmt(r_far)])
    any_map = pooled[next(iter(pooled))]
    total = sum(n for _, n in any_map.values()) or 1.0
    share = [fmt(any_map.get(b, (0.0, 0.0))[1] / total) for b in names]
    rows.append(["(share of lidar points)", *share, fmt(sum(any_map.get(b, (0.0, 0.0))[1] for b in far) / total)])
    n_seq = len({str(r["seq"]) for r in records if str(r.get("metric", "")).startswith("recall_path_")})
    return (f"Recall by horizontal distance from the path (F-score threshold, pooled over {n_seq} sequence(s))",
            ["map", *names, f">={FAR_M:g}m"], rows)


def plot_recall_by_distance(path: Path, records: Sequence[Mapping[str, Any]], title: str = "") -> Path | None:
    """Pooled recall against the distance bin, a line per map; None without the metrics."""
    pooled = pooled_recall(records)
    if not pooled:
        return None
    plt = figures._plt()
    names = path_bin_names()
    fig, ax = plt.subplots(figsize=(7.0, 4.0), constrained_layout=True)
    for method in ordered(pooled, MAP_ORDER):
        ax.plot(range(len(names)), [pooled[method].get(b, (np.nan, 0))[0] for b in names], "o-", label=method)
    ax.set_xticks(range(len(names)), names)
    ax.set_xlabel("horizontal distance of the lidar voxel from the path")
    ax.set_ylabel("recall")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.set_title(title or "Recall by distance from the path", fontsize=10)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
