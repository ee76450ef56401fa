"""Tables of the evaluation (markdown): RICH-SLAM Table III, the AUC table of Fig. 6, RMap Tables I/III/IV.

Input is the long metrics table as records ``{seq, method, metric, value, features}``; the same
functions format one sequence (``report.md``) and many (``pipeline report``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from stages.evaluate.rich_slam_paper import PAPER_METHODS, TABLE_III, paper_sequence

Record = Mapping[str, Any]

TRAJECTORY_METHODS = ("odometry", "fastslam_grid", "rich_slam_no_et", "rich_slam_mean_only", "rich_slam",
                      "radar_graph")
AUC_METHODS = ("hilbert_gp", "rff", "sparse", "nystrom")
DDIST = ("ddist_p50", "ddist_p75", "ddist_p90", "ddist_p95")
RMAP_COLUMNS = (("cd_l1", "CD-l1 [m]"), ("cd_l2", "CD-l2 [m²]"), ("fscore_0.15", "F-score@0.15"),
                ("ddist", "D-Dist 50/75/90/95 [m]"), ("cd_x", "CD^x"), ("cd_y", "CD^y"), ("cd_z", "CD^z"),
                ("lr_ratio", "L/R"), ("n_pred", "points"))


def fmt(v: Any, digits: int = 3) -> str:
    """A number for a table cell; '–' for missing or NaN."""
    if v is None:
        return "–"
    if isinstance(v, float) and math.isnan(v):
        return "–"
    if isinstance(v, int) or (isinstance(v, float) and v.is_integer() and abs(v) >= 1000):
        return f"{int(v)}"
    if v != 0 and abs(v) < 0.5 * 10**-digits:
        return f"{v:.{max(digits - 1, 1)}e}"  # too small for the fixed-point digits: keep it visible
    return f"{v:.{digits}f}"


def markdown(headers: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A GitHub-flavoured markdown table."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join(" --- " for _ in headers) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def lookup(records: Iterable[Record]) -> dict[tuple[str, str, str, int], float]:
    """(seq, method, metric, 0) -> value (the last index is kept for callers that add a variant)."""
    return {(str(r["seq"]), str(r["method"]), str(r["metric"]), 0): float(r["value"]) for r in records}


def ordered(names: Iterable[str], preferred: Sequence[str]) -> list[str]:
    names = list(dict.fromkeys(names))
    return [n for n in preferred if n in names] + sorted(n for n in names if n not in preferred)


#: the title of :func:`trajectory_table` (``report.md`` and ``pipeline report``)
TRAJECTORY_TITLE = ("Trajectories (RICH-SLAM Table III): position RMSE [m] / yaw RMSE [deg]; whole: SE(2) "
                    "alignment on the whole trajectory (= evo_ape --align in the plane, the headline); paper: the "
                    "paper's protocol, SE(2) alignment on the first N matched frames")


def trajectory_table(records: Sequence[Record]) -> tuple[list[str], list[list[str]]]:
    """Table III: rows are methods, columns sequences, cells 'position RMSE [m] / yaw RMSE [deg]'.

    Two columns a sequence when the records have the whole-trajectory errors (``ate_*_whole_*``): ``<seq>:
    whole`` (SE(2) alignment on every matched frame, first: the headline) and ``<seq>: paper, first N`` (the
    paper's protocol, ``ate_pos_rmse_m`` / ``ate_yaw_rmse_deg``); one, the paper's protocol, for records
    written before them. The paper's own rows (ColoRadar twins) sit under the paper-protocol columns."""
    d = lookup(records)
    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    methods = ordered((m for (_, m, k, _) in d if k in ("ate_pos_rmse_m", "ate_pos_rmse_whole_m")),
                      TRAJECTORY_METHODS)
    whole = {s for (s, _, k, _) in d if k == "ate_pos_rmse_whole_m"}
    n_aligned = {s: {int(v) for (s2, _, k, _), v in d.items() if s2 == s and k == "aligned_frames"} for s in seqs}

    def paper_header(s: str) -> str:
        n = n_aligned[s]
        return f"{s}: paper, first {min(n)}" if len(n) == 1 else f"{s}: paper"

    # (sequence, alignment) per column: the whole trajectory first where the records have it
    cols = [(s, a) for s in seqs for a in (("whole", "paper") if s in whole else ("paper",))]
    headers = ["method", *(f"{s}: whole" if a == "whole" else paper_header(s) if s in whole else s for s, a in cols)]
    keys = {"whole": ("ate_pos_rmse_whole_m", "ate_yaw_rmse_whole_deg"),
            "paper": ("ate_pos_rmse_m", "ate_yaw_rmse_deg")}
    rows = []
    length = ["length / duration"]
    for s, a in cols:
        L, T = d.get((s, "groundtruth", "length_m", 0)), d.get((s, "groundtruth", "duration_s", 0))
        length.append(f"{L:.1f} m, {T:.0f} s" if L is not None and T is not None and (a == "whole" or s not in whole)
                      else "–")
    if any(c != "–" for c in length[1:]):
        rows.append(length)
    for m in methods:
        row = [m]
        for s, a in cols:
            pos, yaw = (d.get((s, m, k, 0)) for k in keys[a])
            row.append("–" if pos is None else f"{fmt(pos, 2)} / {fmt(yaw, 2)}")
        rows.append(row)
    paper_cols = [paper_sequence(s) if a == "paper" else None for s, a in cols]
    if any(paper_cols):  # the ColoRadar twins (or logs): the paper's own rows for the same sequences beside ours
        for m in PAPER_METHODS:
            rows.append([f"paper {m}", *("–" if c is None else "{:.2f} / {:.2f}".format(*TABLE_III[c][m])
                                         for c in paper_cols)])
    return headers, rows


def split_method(method: str) -> tuple[str, int]:
    """``"rff@256"`` -> ("rff", 256); a name without ``@`` -> (name, 0)."""
    name, _, count = method.partition("@")
    return name, int(count) if count.isdigit() else 0


def auc_table(records: Sequence[Record]) -> tuple[list[str], list[list[str]]]:
    """Fig. 6 as a table: rows (sequence, method), columns feature counts (methods ``<name>@<count>``)."""
    d = lookup(records)
    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    per = {(s, *split_method(m)): v for (s, m, k, _), v in d.items() if k == "auc" and "@" in m}
    counts = sorted({c for (_, _, c) in per})
    methods = ordered((m for (_, m, _) in per), AUC_METHODS)
    multi = len(seqs) > 1
    headers = (["sequence"] if multi else []) + ["method \\ features", *[f"{c}" for c in counts]]
    rows = []
    for s in seqs:
        for m in methods:
            cells = [fmt(per.get((s, m, c))) for c in counts]
            if all(c == "–" for c in cells):
                continue
            rows.append(([s] if multi else []) + [m, *cells])
    return headers, rows


def headline_auc_table(records: Sequence[Record]) -> tuple[list[str], list[list[str]]]:
    """AUC per method at the slam stage's feature count (methods without ``@``), sequences as columns."""
    d = lookup(records)
    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    methods = ordered((m for (_, m, k, _) in d if k == "auc" and "@" not in m), (*AUC_METHODS, "grid"))
    headers = ["method", *seqs]
    rows = [[m, *[fmt(d.get((s, m, "auc", 0))) for s in seqs]] for m in methods]
    return headers, rows


def rmap_table(records: Sequence[Record]) -> tuple[list[str], list[list[str]]]:
    """RMap Tables I/III/IV: one row per (sequence, map) against the lidar map."""
    d = lookup(records)
    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    maps = ordered((m for (_, m, k, _) in d if k == "cd_l1"), ("radar_map", "completed_map"))
    multi = len(seqs) > 1
    headers = (["sequence"] if multi else []) + ["map", *[h for _, h in RMAP_COLUMNS]]
    rows = []
    for s in seqs:
        for m in maps:
            if (s, m, "cd_l1", 0) not in d:
                continue
            cells = []
            for key, _ in RMAP_COLUMNS:
                if key == "ddist":
                    cells.append(", ".join(fmt(d.get((s, m, k, 0))) for k in DDIST))
                elif key == "n_pred":
                    v = d.get((s, m, key, 0))
                    cells.append("–" if v is None else str(int(v)))
                else:
                    cells.append(fmt(d.get((s, m, key, 0))))
            rows.append(([s] if multi else []) + [m, *cells])
    return headers, rows
