"""RICH-SLAM Table III over seeds: every trajectory's error per sequence, mean and spread over the seeds.

The records are a sweep's (``workflows/sweep_table3.toml``): one point per ``slam.seed``, each with the evaluate
stage's trajectory metrics. A cell is ``position m / yaw deg`` averaged over the seeds, with the yaw's standard
deviation when the seeds differ, under both alignments: the whole trajectory (``evo_ape --align`` in the plane)
and the paper's protocol (Sec. V-C: the first frames). Pure functions on records.
"""

from __future__ import annotations

import json
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from stages.evaluate import figures

Table = tuple[str, list[str], list[list[str]]]

#: (title, position metric, yaw metric)
ALIGNMENTS = (("whole-trajectory SE(2) alignment", "ate_pos_rmse_whole_m", "ate_yaw_rmse_whole_deg"),
              ("the paper's protocol (alignment on the first frames)", "ate_pos_rmse_m", "ate_yaw_rmse_deg"))


def seed_of(params: str | Mapping[str, Any]) -> int | None:
    """The point's ``slam.seed``; None when the point does not set it."""
    p = json.loads(params) if isinstance(params, str) else dict(params)
    seed = p.get("slam.seed")
    return None if seed is None else int(seed)


def errors_by_seed(records: Sequence[Mapping[str, Any]], metric: str
                   ) -> dict[tuple[str, str], dict[int, float]]:
    """``{(seq, method): {seed: value}}`` of one metric over the points that set ``slam.seed``."""
    out: dict[tuple[str, str], dict[int, float]] = {}
    for r in records:
        if r.get("metric") != metric or r.get("value") is None:
            continue
        seed = seed_of(r.get("params") or "{}")
        if seed is None:
            continue
        out.setdefault((str(r["seq"]), str(r["method"])), {})[seed] = float(r["value"])
    return out


def cell(pos: Sequence[float], yaw: Sequence[float]) -> str:
    """``pos / yaw`` means, ``± std`` of the yaw when the seeds differ, ``(n)`` seeds."""
    if not pos or not yaw:
        return "–"
    spread = f" ± {np.std(yaw):.2f}" if len(yaw) > 1 and np.ptp(yaw) > 0 else ""
    return f"{np.mean(pos):.2f} / {np.mean(yaw):.2f}{spread} ({len(yaw)})"


def seed_tables(records: Sequence[Mapping[str, Any]]) -> list[Table]:
    """One table per alignment: methods as rows, sequences as columns and their mean; empty when no point sets
    ``slam.seed``."""
    out: list[Table] = []
    for title, pos_metric, yaw_metric in ALIGNMENTS:
        pos, yaw = errors_by_seed(records, pos_metric), errors_by_seed(records, yaw_metric)
        if not yaw:
            continue
        seqs = list(dict.fromkeys(s for s, _ in yaw))
        methods = list(dict.fromkeys(m for _, m in yaw))
        rows = []
        for m in methods:
            cells = [cell(list(pos.get((s, m), {}).values()), list(yaw.get((s, m), {}).values())) for s in seqs]
            per_seq = [float(np.mean(list(yaw[(s, m)].values()))) for s in seqs if (s, m) in yaw]
            mean = f"{np.mean(per_seq):.2f} ({len(per_seq)} seq)" if per_seq else "–"
            rows.append([m, *cells, mean])
        out.append((f"Table III over seeds, {title}: position RMSE m / yaw RMSE deg, mean (± std of the yaw) over "
                    "the seeds", ["method", *seqs, "mean yaw"], rows))
    return out


def plot_seed_spread(path: Path, records: Sequence[Mapping[str, Any]], title: str = "") -> Path:
    """Yaw RMSE (whole-trajectory alignment) per sequence and method: each seed a dot, the mean a bar."""
    plt = figures._plt()
    yaw = errors_by_seed(records, ALIGNMENTS[0][2])
    seqs = list(dict.fromkeys(s for s, _ in yaw))
    methods = list(dict.fromkeys(m for _, m in yaw))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(seqs) * max(len(methods), 1) ** 0.5 + 3), 4.2),
                           constrained_layout=True)
    width = 0.8 / max(len(methods), 1)
    for j, m in enumerate(methods):
        xs = np.arange(len(seqs)) + (j - (len(methods) - 1) / 2) * width
        means = [np.mean(list(yaw[(s, m)].values())) if (s, m) in yaw else np.nan for s in seqs]
        ax.bar(xs, means, width * 0.9, label=m, alpha=0.6)
        for x, s in zip(xs, seqs, strict=True):
            vals = list(yaw.get((s, m), {}).values())
            ax.plot([x] * len(vals), vals, "k.", ms=3)
    ax.set_xticks(np.arange(len(seqs)), seqs, rotation=30, ha="right")
    ax.set_ylabel("yaw RMSE (deg), whole-trajectory alignment")
    ax.set_title("\n".join(textwrap.wrap(title or "Table III over seeds", 70)), fontsize=10)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
