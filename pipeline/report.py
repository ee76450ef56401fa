"""``pipeline report``: gather the ``evaluate`` results of several runs into one comparison.

Reads ``runs/<seq>/evaluate/metrics.parquet`` for every sequence asked for and prints (or writes as
markdown) the tables of ``stages/evaluate/tables.py``: RICH-SLAM Table III (position / yaw RMSE per
method and sequence), the occupancy AUC per method (at the slam stage's feature count and per feature
count) and the RMap map metrics.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from rich.table import Table

from pipeline.errors import UserError
from pipeline.store import RunStore

METRICS_FILE = "metrics.parquet"

#: (title, table builder name in stages.evaluate.tables, metric sections it reads)
TABLES = (
    ("Trajectories (RICH-SLAM Table III): position RMSE [m] / yaw RMSE [deg]", "trajectory_table", "trajectory"),
    ("Occupancy AUC at the slam stage's feature count (ground-truth poses, held-out scans)", "headline_auc_table",
     "mapping"),
    ("Occupancy AUC per number of map features (RICH-SLAM Fig. 6)", "auc_table", "mapping"),
    ("Maps against the lidar map (RMap Tables I, III, IV)", "rmap_table", "rmap"),
)


def metrics_path(runs_dir: Path, seq: str, stage: str = "evaluate") -> Path:
    return RunStore(Path(runs_dir), seq).stage_dir(stage) / METRICS_FILE


def resolve_sequences(spec: str | Sequence[str], runs_dir: Path) -> list[str]:
    """Names from ``a,b`` or globs (``sim_*``) matched against the sequences that have a run folder."""
    items = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip()]
    present = sorted(p.name for p in Path(runs_dir).glob("*") if p.is_dir() and not p.name.startswith("."))
    out: list[str] = []
    for item in items:
        if any(ch in item for ch in "*?["):
            hits = [n for n in present if fnmatch.fnmatchcase(n, item)]
            if not hits:
                raise UserError(f"--seqs {item}: no run folders match in {runs_dir} (present: "
                                f"{', '.join(present) or 'none'})")
            out += hits
        else:
            out.append(item)
    return list(dict.fromkeys(out))


def read_records(path: Path) -> list[dict[str, Any]]:
    """Records of one ``metrics.parquet`` (validated)."""
    from schemas import read_artifact

    return read_artifact(path, "metrics").to_pylist()


def gather(runs_dir: Path, seqs: Iterable[str], stage: str = "evaluate") -> tuple[list[dict[str, Any]], list[str]]:
    """All metric records of the sequences that have them, and the names of those that do not."""
    records: list[dict[str, Any]] = []
    missing: list[str] = []
    for seq in seqs:
        path = metrics_path(runs_dir, seq, stage)
        if not path.exists():
            missing.append(seq)
            continue
        recs = read_records(path)
        for r in recs:
            r["seq"] = seq  # the run folder names the sequence (a --source run may carry another name)
        records += recs
    return records, missing


def _section(records: Sequence[dict[str, Any]], section: str) -> list[dict[str, Any]]:
    out = []
    for r in records:
        s = r.get("section")
        if s is None:  # files without the section column: infer from the metric name
            m = str(r["metric"])
            s = "trajectory" if m.startswith("ate_") or r["method"] == "groundtruth" else \
                "mapping" if m in ("auc", "fit_seconds") else "uncertainty" if m.startswith("uncertainty") else "rmap"
        if s == section:
            out.append(r)
    return out


def build_tables(records: Sequence[dict[str, Any]]) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, headers, rows) for every table that has rows."""
    from stages.evaluate import tables

    out = []
    for title, fn, section in TABLES:
        headers, rows = getattr(tables, fn)(_section(records, section))
        if rows:
            out.append((title, headers, rows))
    return out


def rich_table(title: str, headers: Sequence[str], rows: Sequence[Sequence[str]]) -> Table:
    t = Table(title=title, title_justify="left")
    for i, h in enumerate(headers):
        t.add_column(h, justify="left" if i == 0 or h in ("sequence", "map", "method") else "right")
    for r in rows:
        t.add_row(*r)
    return t


def comparison_table(runs: Path, seqs: Sequence[str]) -> Any:
    """The comparison printed after a multi-sequence ``pipeline run`` (None when nothing was evaluated)."""
    from rich.console import Group

    records, _ = gather(Path(runs), seqs)
    if not records:
        return None
    return Group(*[rich_table(*t) for t in build_tables(records)])


def to_markdown(records: Sequence[dict[str, Any]], title: str = "Comparison") -> str:
    from stages.evaluate import tables

    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    out = [f"# {title}", "", f"Sequences: {', '.join(seqs)}", ""]
    for t, headers, rows in build_tables(records):
        out += [f"## {t}", "", tables.markdown(headers, rows), ""]
    return "\n".join(out).rstrip() + "\n"


def write_outputs(records: Sequence[dict[str, Any]], out: Path, title: str) -> list[Path]:
    """``out`` (markdown) and the combined long table beside it (``<out>.parquet``)."""
    import numpy as np

    from schemas import write_artifact

    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(to_markdown(records, title))
    cols: dict[str, Any] = {k: [r.get(k) for r in records] for k in ("seq", "method", "metric")}
    cols["value"] = np.array([r["value"] for r in records], np.float64)
    cols["features"] = np.array([int(r.get("features") or 0) for r in records], np.int32)
    cols["section"] = [str(r.get("section") or "") for r in records]
    pq_path = out.with_suffix(".parquet")
    write_artifact(cols, pq_path, "metrics")
    return [out, pq_path]


def uncertainty_curves(runs_dir: Path, seqs: Sequence[str]) -> dict[str, Any]:
    """Per sequence, rows (t_s, p25, p50, p75) of the slam stage's ``map_stats.parquet`` (Fig. 10, right)."""
    import numpy as np
    import pyarrow.parquet as pq

    out: dict[str, Any] = {}
    for seq in seqs:
        path = RunStore(Path(runs_dir), seq).stage_dir("slam") / "map_stats.parquet"
        if not path.exists():
            continue
        t = pq.read_table(path)
        if t.num_rows == 0 or not {"t_ns", "u_p25", "u_p50", "u_p75"} <= set(t.column_names):
            continue
        tn = t["t_ns"].to_numpy()
        out[seq] = np.column_stack([(tn - tn[0]) / 1e9, *[t[c].to_numpy() for c in ("u_p25", "u_p50", "u_p75")]])
    return out


def write_figures(runs_dir: Path, records: Sequence[dict[str, Any]], out: Path) -> list[Path]:
    """Figures across sequences beside ``out``: Fig. 6 (AUC per feature count, one panel per sequence) and
    Fig. 10 right (the slam map's median and 25-75 % uncertainty over time, one curve per sequence)."""
    from pipeline.sweep import plot_auc_vs_features
    from stages.evaluate import figures

    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    written = []
    with_auc = [s for s in seqs if any(r["seq"] == s and r["metric"] == "auc" and "@" in str(r["method"])
                                       for r in records)]
    if with_auc:
        written.append(plot_auc_vs_features(out.with_name(out.stem + "_auc.png"), records, with_auc,
                                            "occupancy AUC vs number of map features (ground-truth poses)"))
    curves = uncertainty_curves(runs_dir, seqs)
    if curves:
        written.append(figures.plot_uncertainty(out.with_name(out.stem + "_uncertainty.png"), curves,
                                                "RICH-SLAM map: normalised predictive uncertainty (median, 25-75 %)"))
    return written


def report_sequences(runs_dir: Path, spec: str) -> tuple[list[dict[str, Any]], list[str]]:
    """Resolve ``--seqs`` and gather; a clear error when nothing was evaluated."""
    seqs = resolve_sequences(spec, runs_dir)
    if not seqs:
        raise UserError("--seqs: no sequence names given (e.g. --seqs demo,sim_hallway_loop)")
    records, missing = gather(runs_dir, seqs)
    if not records:
        hint = ",".join(seqs)
        raise UserError(f"no evaluation results for {', '.join(seqs)} in {runs_dir}; run "
                        f"`pipeline run evaluate --seq {hint}` first")
    return records, missing


# -- sweeps -----------------------------------------------------------------------------------------------------
def sweep_records(runs_dir: Path, name: str, seqs: str | None = None) -> list[dict[str, Any]]:
    """Records of ``runs/sweeps/<name>/sweep_metrics.parquet`` (optionally only some sequences)."""
    from pipeline.sweep import sweep_root

    path = sweep_root(runs_dir, name) / "sweep_metrics.parquet"
    if not path.exists():
        raise UserError(f"{path}: no gathered sweep; run `pipeline sweep {name} --seq <seq>` first")
    records = read_records(path)
    if seqs:
        wanted = set(resolve_sequences(seqs, runs_dir)) | {s.strip() for s in seqs.split(",")}
        records = [r for r in records if r["seq"] in wanted]
    if not records:
        raise UserError(f"{path}: no rows for --seqs {seqs}")
    return records


def sweep_tables(records: Sequence[dict[str, Any]]) -> list[tuple[str, list[str], list[list[str]]]]:
    """AUC per point and method (the sweep's point names as rows), and Fig. 6 means over the points."""
    from pipeline.sweep import auc_by_features
    from stages.evaluate.tables import fmt

    out = []
    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    head = [r for r in records if r["metric"] == "auc" and "@" not in str(r["method"])]
    if head:
        methods = list(dict.fromkeys(str(r["method"]) for r in head))
        points = list(dict.fromkeys(str(r.get("point", "")) for r in head))
        d = {(r["seq"], r.get("point", ""), r["method"]): r["value"] for r in head}
        rows = [[s, p, *[fmt(d.get((s, p, m))) for m in methods]] for s in seqs for p in points
                if any((s, p, m) in d for m in methods)]
        out.append(("AUC per sweep point", ["sequence", "point", *methods], rows))
    for s in seqs:
        agg = auc_by_features(records, s)
        if agg:
            counts = sorted({a[1] for a in agg})
            methods = list(dict.fromkeys(a[0] for a in agg))
            cell = {(a[0], a[1]): f"{a[2]:.3f}±{a[3]:.3f}" for a in agg}
            n = max(a[4] for a in agg)
            out.append((f"{s}: AUC per number of map features, mean ± std over {n} point(s)",
                        ["method", *map(str, counts)], [[m, *[cell.get((m, c), "–") for c in counts]]
                                                        for m in methods]))
    return out
