"""The evaluate stage's reports over many runs: ``pipeline report`` and the sweeps' tables and figures.

The orchestration layer gathers the metric records of several runs (``pipeline/report.py``,
``pipeline/sweep.py``) and reaches this module through the stage registry
(``load_stages()["evaluate"].report()``, :class:`core.stage.StageReport`); everything that formats
or draws those records lives here, beside the code that computes them.

Map sequences (``rmap_<scene>``): :meth:`EvaluationReport.tables` adds the paper's Tables III, IV, VI and I
side by side with ours (:mod:`stages.evaluate.rmap_tables`), built from the gathered records alone
(:func:`map_set_results`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from stages.evaluate import figures, tables
from stages.evaluate.tables import fmt, split_method

Table = tuple[str, list[str], list[list[str]]]

#: (title, table builder name in stages.evaluate.tables, metric sections it reads)
TABLES = (
    (tables.TRAJECTORY_TITLE, "trajectory_table", "trajectory"),
    ("Occupancy AUC at the slam stage's feature count (ground-truth poses, held-out scans)", "headline_auc_table",
     "mapping"),
    ("Occupancy AUC per number of map features (RICH-SLAM Fig. 6)", "auc_table", "mapping"),
    ("Maps against the lidar map (RMap Tables I, III, IV)", "rmap_table", "rmap"),
)


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


def build_tables(records: Sequence[dict[str, Any]],
                 sequences: Mapping[str, Mapping[str, Any]] | None = None) -> list[Table]:
    """(title, headers, rows) for every table that has rows; ``sequences`` describes each sequence (kind,
    scene, split, environment) for the map-set tables."""
    out: list[Table] = []
    for title, fn, section in TABLES:
        headers, rows = getattr(tables, fn)(_section(records, section))
        if rows:
            out.append((title, headers, rows))
    out += [(t.title, list(t.headers), [list(map(str, row)) for row in t.rows])
            for t in map_set_tables(records, sequences or {})]
    from stages.evaluate.recall_distance import recall_table

    recall = recall_table(records)
    return out + ([recall] if recall is not None else [])


def map_set_results(records: Sequence[Mapping[str, Any]], sequences: Mapping[str, Mapping[str, Any]]) -> list[Any]:
    """One ``rmap_tables.SceneResult`` per map sequence among ``records``, built from the records alone.

    The evaluate stage's ``rmap`` section of a map sequence carries everything the paper's tables need:
    the ``radar_map`` / ``completed_map`` / ``lidar_map`` metrics, ``lidar_map gt_rebuilt`` (1 = ground
    truth rebuilt from published patches) and ``completed_map`` ``patches_a``, ``n_patches`` and
    ``model_seconds`` (network seconds over all patches). Empty when ``stages.evaluate.rmap_tables`` is absent.
    """
    try:
        from stages.evaluate import rmap_tables as rt  # type: ignore[attr-defined, unused-ignore]
    except ImportError:
        return []
    map_seqs = [s for s, info in sequences.items() if info.get("kind") == "rmap"]
    out = []
    for seq in map_seqs:
        metrics: dict[str, dict[str, float]] = {}
        for r in records:
            if r.get("seq") == seq and (r.get("section") in (None, "rmap")):
                metrics.setdefault(str(r["method"]), {})[str(r["metric"])] = float(r["value"])
        if "radar_map" not in metrics:
            continue
        done = metrics.get("completed_map", {})
        a, n, secs = (done.pop(k, None) for k in ("patches_a", "n_patches", "model_seconds"))
        done.pop("seconds_per_patch", None)
        out.append(rt.SceneResult(
            scene=str(sequences[seq].get("scene") or rt.scene_name(seq)), seq=seq, metrics=metrics,
            rebuilt=metrics.get("lidar_map", {}).get("gt_rebuilt", 0.0) > 0, a_test=a,
            n_patches=int(n) if n is not None else None, inference_s=secs))
    return out


def map_set_tables(records: Sequence[Mapping[str, Any]], sequences: Mapping[str, Mapping[str, Any]]) -> list[Any]:
    """The RMap paper's Tables III, IV, VI and I side by side with ours (``rmap_tables.Table``: title, headers,
    rows, notes) for the map sequences among ``records``; nothing without map sequences."""
    results = map_set_results(records, sequences)
    if not results:
        return []
    from stages.evaluate import rmap_tables as rt  # type: ignore[attr-defined, unused-ignore]

    if rt.model_methods(results):  # several completion models ran (complete.models): one row per map
        tables = [rt.table_iii_models(results), rt.table_iv_models(results)]
    else:
        tables = [rt.table_iii(results), rt.table_iv(results)]
    if any(r.a_test is not None for r in results):
        tables.append(rt.table_vi(results))
    tables.append(rt.table_i(results))
    return tables


def to_markdown(records: Sequence[dict[str, Any]], title: str = "Comparison",
                sequences: Mapping[str, Mapping[str, Any]] | None = None) -> str:
    """The tables as markdown; the RMap tables with the notes under them (rebuilt scenes, coverage, errata)."""
    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    out = [f"# {title}", "", f"Sequences: {', '.join(seqs)}", ""]
    notes = {t.title: list(t.notes) for t in map_set_tables(records, sequences or {})}
    for t, headers, rows in build_tables(records, sequences):
        out += [f"## {t}", "", tables.markdown(headers, rows), ""]
        out += [f"- {n}" for n in notes.get(t, [])] + ([""] if notes.get(t) else [])
    return "\n".join(out).rstrip() + "\n"


def write_figures(records: Sequence[dict[str, Any]], out: Path, curves: Mapping[str, Any],
                  runs_dir: Path | None = None) -> list[Path]:
    """Figures across sequences beside ``out``: Fig. 6 (AUC per feature count, one panel per sequence),
    Fig. 10 right (the slam map's median and 25-75 % uncertainty over time, one curve per sequence) and, with
    ``runs_dir``, RMap's top views (``<out>_top.png``: input, UpPoinTr, voxel U-Net and lidar maps when both
    models ran) of the figure's scenes among the records (``rmap_results.FIGURE_SEQS``) and each run's trajectories
    (``<out>_<seq>_trajectories.png``), and the maps' recall by distance from the path (``<out>_recall.png``)."""
    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    written = []
    if runs_dir is not None:
        from stages.evaluate.rmap_results import FIGURE_SEQS, plot_run_top_views

        shown = [s for s in FIGURE_SEQS if s in seqs]
        if shown:
            top = plot_run_top_views(runs_dir, out.with_name(out.stem + "_top.png"), shown)
            written += [top] if top is not None else []
    if runs_dir is not None:  # each run's trajectory figure (whole-trajectory alignment), named by its sequence
        import shutil

        for s in seqs:
            src = runs_dir / s / "evaluate" / "trajectories.png"
            if src.is_file() and any(r["seq"] == s and str(r["metric"]).startswith("ate_") for r in records):
                dst = out.with_name(f"{out.stem}_{s}_trajectories.png")
                shutil.copyfile(src, dst)
                written.append(dst)
    from stages.evaluate.recall_distance import plot_recall_by_distance

    recall = plot_recall_by_distance(out.with_name(out.stem + "_recall.png"), records,
                                     f"Recall by distance from the path, pooled over {len(seqs)} sequence(s)")
    written += [recall] if recall is not None else []
    with_auc = [s for s in seqs if any(r["seq"] == s and r["metric"] == "auc" and "@" in str(r["method"])
                                       for r in records)]
    if with_auc:
        written.append(plot_auc_vs_features(out.with_name(out.stem + "_auc.png"), records, with_auc,
                                            "occupancy AUC vs number of map features (ground-truth poses)"))
    if curves:
        written.append(figures.plot_uncertainty(out.with_name(out.stem + "_uncertainty.png"), curves,
                                                "RICH-SLAM map: normalised predictive uncertainty (median, 25-75 %)"))
    return written


# -- sweeps -----------------------------------------------------------------------------------------------------
def sweep_tables(records: Sequence[dict[str, Any]]) -> list[tuple[str, list[str], list[list[str]]]]:
    """Table III over seeds when the points vary ``slam.seed``, the radar-only map table when they vary the
    voxel stage's trajectory, AUC per point and method (the sweep's point names as rows) and Fig. 6 means over
    the points."""
    from stages.evaluate.radar_only import radar_only_table
    from stages.evaluate.seed_table import seed_tables

    out = seed_tables(records)
    ro = radar_only_table(records)
    if ro is not None:
        out.append(ro)
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


def auc_by_features(records: Sequence[Mapping[str, Any]],
                    seq: str | None = None) -> list[tuple[str, int, float, float, int]]:
    """(method, features, mean, std, n) of ``<method>@<count>`` AUC rows over all points (seeds)."""
    groups: dict[tuple[str, int], list[float]] = {}
    for r in records:
        if r["metric"] != "auc" or "@" not in str(r["method"]) or (seq is not None and r["seq"] != seq):
            continue
        m, n = split_method(str(r["method"]))
        groups.setdefault((m, n), []).append(float(r["value"]))
    return [(m, n, float(np.mean(v)), float(np.std(v)), len(v)) for (m, n), v in sorted(groups.items())]


def sweep_figures(kind: str, root: Path, name: str, description: str, points: Sequence[Any], seqs: Sequence[str],
                  records: Sequence[Mapping[str, Any]], meta: Mapping[str, Any]) -> list[Path]:
    """The sweep figure ``kind`` (``[workflow] figure``) for the points under ``root``."""
    if kind == "auc_vs_features":
        return [plot_auc_vs_features(root / f"{name}.png", records, seqs, description)]
    if kind == "hyperparameter_grid":
        return [plot_hyperparameter_grid(root / f"{name}_{seq}.png", root, points, seq,
                                         str(meta.get("figure_method", "hilbert_gp")), records) for seq in seqs]
    if kind == "map_vs_trajectory":
        from stages.evaluate.radar_only import plot_map_vs_trajectory

        return [plot_map_vs_trajectory(root / f"{name}.png", records, description)]
    if kind == "seed_spread":
        from stages.evaluate.seed_table import plot_seed_spread

        return [plot_seed_spread(root / f"{name}.png", records, description)]
    raise ValueError(f"unknown sweep figure {kind!r}; known: {', '.join(SWEEP_FIGURES)}")


SWEEP_FIGURES = ("auc_vs_features", "hyperparameter_grid", "map_vs_trajectory", "seed_spread")


def plot_auc_vs_features(path: Path, records: Sequence[Mapping[str, Any]], seqs: Sequence[str],
                         title: str = "") -> Path:
    """Fig. 6: one panel per sequence, AUC (mean and +-1 std over the points) against the feature count."""
    plt = figures._plt()
    n = len(seqs)
    fig, axes = plt.subplots(1, n, figsize=(5.5 * n, 4.2), squeeze=False, constrained_layout=True, sharey=True)
    for ax, seq in zip(axes[0], seqs, strict=True):
        rows = auc_by_features(records, seq)
        for m in dict.fromkeys(r[0] for r in rows):
            sel = [r for r in rows if r[0] == m]
            x = np.array([r[1] for r in sel], float)
            y = np.array([r[2] for r in sel])
            s = np.array([r[3] for r in sel])
            ax.plot(x, y, "o-", color=figures.colour(m), label=figures.label(m))
            ax.fill_between(x, y - s, y + s, color=figures.colour(m), alpha=0.15)
        ax.set_title(seq)
        ax.set_xlabel("number of map features")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("AUC (held-out scans), mean ± std over seeds")
    axes[0][0].legend(fontsize=8)
    if title:
        import textwrap

        fig.suptitle(textwrap.fill(title, 30 + 45 * n), fontsize=10)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_hyperparameter_grid(path: Path, root: Path, points: Sequence[Any], seq: str, method: str,
                             records: Sequence[Mapping[str, Any]]) -> Path:
    """Fig. 7: the ground-truth-pose map of every point, rows = first swept key, columns = second, AUC in titles."""
    from schemas import read_artifact
    plt = figures._plt()
    keys = list(points[0].values()) if points else []
    rows_vals = list(dict.fromkeys(json.dumps(p.values()[keys[0]]) for p in points)) if keys else [""]
    cols_vals = list(dict.fromkeys(json.dumps(p.values()[keys[1]]) for p in points)) if len(keys) > 1 else [""]
    auc = {r["point"]: r["value"] for r in records
           if r["seq"] == seq and r["method"] == method and r["metric"] == "auc"}
    ell = {r["point"]: r["value"] for r in records
           if r["seq"] == seq and r["method"] == method and r["metric"] == "lengthscale_m"}
    fig, axes = plt.subplots(len(rows_vals), len(cols_vals), figsize=(4.2 * len(cols_vals), 3.4 * len(rows_vals)),
                             squeeze=False, constrained_layout=True)
    im = None
    for p in points:
        v = p.values()
        i = rows_vals.index(json.dumps(v[keys[0]])) if keys else 0
        j = cols_vals.index(json.dumps(v[keys[1]])) if len(keys) > 1 else 0
        ax = axes[i][j]
        grid_path = root / p.name / seq / "evaluate" / "gt_map_grid.parquet"
        if grid_path.exists():
            t = read_artifact(grid_path, "map_grid", columns=["x", "y", "occupancy"])
            x, y, o = (t[c].to_numpy() for c in ("x", "y", "occupancy"))
            gx, gy = np.unique(x), np.unique(y)
            img = np.full((len(gx), len(gy)), np.nan)
            img[np.searchsorted(gx, x), np.searchsorted(gy, y)] = o
            im = ax.imshow(img.T, origin="lower", extent=(gx[0], gx[-1], gy[0], gy[-1]), cmap="viridis",
                           vmin=0, vmax=1, interpolation="nearest")
        else:
            ax.text(0.5, 0.5, "no map", ha="center", va="center", transform=ax.transAxes)
        label = ", ".join(f"{k.split('.', 1)[1]}={val}" for k, val in v.items())
        a, lm = auc.get(p.name), ell.get(p.name)
        sub = ", ".join(s for s in (f"l = {lm:g} m" if lm is not None else "",
                                    f"AUC {a:.3f}" if a is not None else "") if s)
        ax.set_title(label + ("\n" + sub if sub else ""), fontsize=9)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.6, label="occupancy probability")
    fig.suptitle(f"{seq}: {method} maps on ground-truth poses", fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def summary_rows(records: Sequence[Mapping[str, Any]], metric: str = "auc") -> list[list[str]]:
    """(seq, point, method, value) rows of one metric, for printing."""
    return [[str(r["seq"]), str(r["point"]), str(r["method"]), fmt(float(r["value"]))]
            for r in records if r["metric"] == metric]


class EvaluationReport:
    """The evaluate stage's :class:`core.stage.StageReport` (what ``pipeline report`` and sweeps call)."""

    metrics_file = "metrics.parquet"
    sweep_figure_kinds: Sequence[str] = SWEEP_FIGURES

    def tables(self, records: Sequence[dict[str, Any]],
               sequences: Mapping[str, Mapping[str, Any]] | None = None) -> list[Table]:
        return build_tables(records, sequences)

    def markdown(self, records: Sequence[dict[str, Any]], title: str,
                 sequences: Mapping[str, Mapping[str, Any]] | None = None) -> str:
        return to_markdown(records, title, sequences)

    def figures(self, records: Sequence[dict[str, Any]], out: Path, curves: Mapping[str, Any],
                runs_dir: Path | None = None) -> list[Path]:
        return write_figures(records, out, curves, runs_dir)

    def sweep_tables(self, records: Sequence[dict[str, Any]]) -> list[Table]:
        return sweep_tables(records)

    def sweep_figures(self, kind: str, root: Path, name: str, description: str, points: Sequence[Any],
                      seqs: Sequence[str], records: Sequence[Mapping[str, Any]],
                      meta: Mapping[str, Any]) -> list[Path]:
        return sweep_figures(kind, root, name, description, points, seqs, records, meta)

    def summary_rows(self, records: Sequence[Mapping[str, Any]], metric: str = "auc") -> list[list[str]]:
        return summary_rows(records, metric)

    def auc_by_features(self, records: Sequence[Mapping[str, Any]],
                        seq: str | None = None) -> list[tuple[str, int, float, float, int]]:
        return auc_by_features(records, seq)

