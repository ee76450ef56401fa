"""Radar-only maps: the RMap maps built along ground truth, the odometry and each SLAM method.

The records are a sweep's (``workflows/sweep_radar_only.toml``): one point per trajectory the voxel stage
built its radar map along (``voxel.trajectory.source`` and ``voxel.trajectory.slam_method`` in the point's
``params``), each with the evaluate stage's map metrics (``radar_map``, ``completed_map`` against the lidar map
built along ground truth) and trajectory metrics. A row pairs a point's maps with the errors of the trajectory they were
built along: without alignment (``*_anchored``: every estimate starts at the ground-truth pose, so these are
the errors the maps inherit) and under RICH-SLAM's Table III protocol. Pure functions on records.
"""

from __future__ import annotations

import json
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from stages.evaluate import figures
from stages.evaluate.tables import fmt

MAP_METRICS = ("cd_l1", "cd_l2", "fscore_0.15", "ddist_p50", "ddist_p95")
TRAJ_METRICS = ("ate_pos_rmse_anchored_m", "ate_yaw_rmse_anchored_deg", "ate_pos_rmse_m", "ate_yaw_rmse_deg")
MAPS = ("radar_map", "completed_map")


def source_of(params: str | Mapping[str, Any]) -> str | None:
    """The trajectory a point's maps were built along: 'groundtruth', 'odometry', a SLAM method's name
    ('slam' for the default method's file), with ' (level)' for ``voxel.trajectory.attitude = level``; None when the
    point does not set ``voxel.trajectory.source``."""
    p = json.loads(params) if isinstance(params, str) else dict(params)
    traj = p.get("voxel.trajectory.source")
    if traj is None:
        return None
    name = str(p.get("voxel.trajectory.slam_method") or "slam") if traj == "slam" else str(traj)
    return f"{name} (level)" if traj != "groundtruth" and p.get("voxel.trajectory.attitude") == "level" else name


def radar_only_rows(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (sequence, source): ``seq``, ``source`` and ``<map>.<metric>`` / ``traj.<metric>`` values;
    ``ratio_cd_l2``: the completed map's CD-l2 over the one built along ground truth (same sequence)."""
    by_key: dict[tuple[str, str], dict[str, Any]] = {}
    for r in records:
        src = source_of(r.get("params") or "{}")
        if src is None:
            continue
        row = by_key.setdefault((str(r["seq"]), src), {"seq": str(r["seq"]), "source": src})
        method, metric = str(r["method"]), str(r["metric"])
        if method in MAPS and metric in MAP_METRICS:
            row[f"{method}.{metric}"] = float(r["value"])
        elif metric in TRAJ_METRICS and method == src.removesuffix(" (level)"):
            row[f"traj.{metric}"] = float(r["value"])
    rows = list(by_key.values())
    for row in rows:
        if row["source"] == "groundtruth":
            for m in TRAJ_METRICS:
                row[f"traj.{m}"] = 0.0
        ref = by_key.get((row["seq"], "groundtruth"), {}).get("completed_map.cd_l2")
        mine = row.get("completed_map.cd_l2")
        row["ratio_cd_l2"] = mine / ref if ref and mine is not None else None
    order = {"groundtruth": 0, "odometry": 1}
    seq_rank = {s: i for i, s in enumerate(dict.fromkeys(r["seq"] for r in rows))}  # first-seen order
    rows.sort(key=lambda r: (seq_rank[r["seq"]], order.get(r["source"], 2), r["source"]))
    return rows


def radar_only_table(records: Sequence[Mapping[str, Any]]) -> tuple[str, list[str], list[list[str]]] | None:
    """The radar-only map table (title, headers, rows), or None when the records hold no such sweep."""
    every = radar_only_rows(records)
    rows = [r for r in every if any(k.startswith(MAPS) for k in r)]
    skipped = list(dict.fromkeys(r["seq"] for r in every if r["seq"] not in {x["seq"] for x in rows}))
    if not every:
        return None
    headers = ["sequence", "built along", "ATE pos / yaw, no alignment (m / deg)",
               "ATE pos / yaw, Table III (m / deg)",
               "radar map CD-l1 / CD-l2 / F@0.15", "completed CD-l1 / CD-l2 / F@0.15",
               "completed D-Dist p50 / p95 (m)", "completed CD-l2 / along ground truth"]

    def trio(r: Mapping[str, Any], prefix: str, keys: Sequence[str]) -> str:
        return " / ".join(fmt(r.get(f"{prefix}.{k}")) for k in keys)

    body = [[r["seq"], r["source"],
             trio(r, "traj", ("ate_pos_rmse_anchored_m", "ate_yaw_rmse_anchored_deg")),
             trio(r, "traj", ("ate_pos_rmse_m", "ate_yaw_rmse_deg")),
             trio(r, "radar_map", ("cd_l1", "cd_l2", "fscore_0.15")),
             trio(r, "completed_map", ("cd_l1", "cd_l2", "fscore_0.15")),
             trio(r, "completed_map", ("ddist_p50", "ddist_p95")),
             fmt(r.get("ratio_cd_l2"), 2)] for r in rows]
    title = ("Radar-only maps: radar and completed maps built along each trajectory, against the lidar map built "
             "along ground truth (CD-l2 in m², the rest in m)")
    if skipped:
        title += f"; skipped, no lidar map to score against: {', '.join(skipped)}"
    return title, headers, body


def wide_span(values: Sequence[float], factor: float = 20.0) -> bool:
    """Whether the positive values span more than ``factor`` (then a logarithmic axis shows them all)."""
    positive = [v for v in values if v > 0]
    return bool(positive) and max(positive) > factor * min(positive)


def plot_map_vs_trajectory(path: Path, records: Sequence[Mapping[str, Any]], title: str = "") -> Path:
    """CD-l2 of the completed (filled) and radar (open) maps against the yaw RMSE (no alignment) of the
    trajectory they were built along; a colour per sequence, a marker per source. The CD-l2 axis is
    logarithmic when the values span more than a factor of 20 (one diverged trajectory would otherwise
    flatten every other point onto the axis)."""
    plt = figures._plt()
    rows = radar_only_rows(records)
    fig, ax = plt.subplots(figsize=(7.5, 4.8), constrained_layout=True)
    seqs = list(dict.fromkeys(r["seq"] for r in rows))
    markers = "osD^v<>p*hX"
    sources = list(dict.fromkeys(r["source"] for r in rows))
    values: list[float] = []
    for i, seq in enumerate(seqs):
        colour = f"C{i % 10}"
        for key, filled in (("completed_map.cd_l2", True), ("radar_map.cd_l2", False)):
            for r in rows:
                a, c = r.get("traj.ate_yaw_rmse_anchored_deg"), r.get(key)
                if r["seq"] != seq or a is None or c is None:
                    continue
                ax.plot(a, c, markers[sources.index(r["source"]) % len(markers)], color=colour,
                        mfc=colour if filled else "none", ms=7)
                values.append(float(c))
        ax.plot([], [], "-", color=colour, lw=5, label=seq)
    for j, src in enumerate(sources):
        ax.plot([], [], markers[j % len(markers)], color="grey", label=f"along {src}")
    ax.plot([], [], "o", color="grey", mfc="grey", label="completed map")
    ax.plot([], [], "o", color="grey", mfc="none", label="radar map")
    if wide_span(values):
        ax.set_yscale("log")
    ax.set_xlabel("yaw RMSE of the trajectory, no alignment (deg)")
    ax.set_ylabel("CD-l2 against the lidar map (m²)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    # a sweep's description can be longer than the axes are wide: wrapped, not clipped
    ax.set_title(textwrap.fill(title or "Radar-only maps: map quality against trajectory error", 80), fontsize=10)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
