"""``pipeline report``: gather the ``evaluate`` results of several runs into one comparison.

Reads ``runs/<seq>/evaluate/metrics.parquet`` for every sequence asked for (:mod:`pipeline.results`) and
hands the records to the evaluate stage's report (``load_stages()["evaluate"].report()``, a
:class:`core.stage.StageReport`, in ``stages/evaluate/report.py``), which builds the tables and
figures: RICH-SLAM Table III, the occupancy AUC per method, the RMap map metrics and, for map
sequences, the RMap paper's tables side by side. This module only gathers, prints and writes files.
"""

from __future__ import annotations

import fnmatch
import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from rich.table import Table

from core.errors import UserError
from pipeline.registry import stage_report
from pipeline.results import METRICS_FILE, gather, metrics_path, read_records
from pipeline.store import RunStore, write_text_atomic

__all__ = ["METRICS_FILE", "build_tables", "comparison_table", "gather", "metrics_path", "read_records",
           "report_sequences", "resolve_sequences", "rich_table", "sequence_context", "stage_report", "sweep_records",
           "sweep_tables", "to_markdown", "uncertainty_curves", "write_figures", "write_outputs",
           "write_sweep_markdown"]


def sequence_context(seqs: Iterable[str], runs_dir: Path | None = None) -> dict[str, dict[str, Any]]:
    """Per sequence ``{"kind", "scene", "split", "environment"}``: from the registry, else (``--source`` runs)
    from the map set recorded in the run's voxel manifest; ``{}`` for what neither knows."""
    from pipeline.sequences import load_registry

    try:
        registry = load_registry()
    except UserError:
        registry = {}
    out: dict[str, dict[str, Any]] = {}
    for s in seqs:
        info = registry.get(s)
        ctx: dict[str, Any] = {}
        if info is not None:
            ctx = {"kind": info.kind, "scene": info.scene or "", "split": info.split,
                   "environment": info.environment}
        if runs_dir is not None and (info is None or info.kind == "rmap"):
            path = RunStore(Path(runs_dir), s).stage_dir("voxel") / "manifest.json"
            try:
                recorded = json.loads(path.read_text()).get("stats", {}).get("map_set")
            except (OSError, json.JSONDecodeError):
                recorded = None
            if isinstance(recorded, dict):
                ctx = {"kind": "rmap", **{k: v for k, v in recorded.items() if v not in (None, "")},
                       **{k: v for k, v in ctx.items() if v not in (None, "")}}
        out[s] = ctx
    return out


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


def build_tables(records: Sequence[dict[str, Any]], sequences: Mapping[str, Mapping[str, Any]] | None = None,
                 runs_dir: Path | None = None) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, headers, rows) for every table that has rows (the evaluate stage's report)."""
    if sequences is None:
        sequences = sequence_context(dict.fromkeys(str(r["seq"]) for r in records), runs_dir)
    return stage_report().tables(records, sequences)


def rich_table(title: str, headers: Sequence[str], rows: Sequence[Sequence[str]]) -> Table:
    """The table for the terminal; text printed as written (``[m]`` is a unit, not rich markup)."""
    from rich.markup import escape

    t = Table(title=escape(title), title_justify="left")
    for i, h in enumerate(headers):
        t.add_column(escape(h), justify="left" if i == 0 or h in ("sequence", "map", "method") else "right")
    for r in rows:
        t.add_row(*map(escape, r))
    return t


def comparison_table(runs: Path, seqs: Sequence[str]) -> Any:
    """The comparison printed after a multi-sequence ``pipeline run`` (None when nothing was evaluated)."""
    from rich.console import Group

    records, _ = gather(Path(runs), seqs)
    if not records:
        return None
    return Group(*[rich_table(*t) for t in build_tables(records, runs_dir=Path(runs))])


def to_markdown(records: Sequence[dict[str, Any]], title: str = "Comparison",
                sequences: Mapping[str, Mapping[str, Any]] | None = None, runs_dir: Path | None = None) -> str:
    if sequences is None:
        sequences = sequence_context(dict.fromkeys(str(r["seq"]) for r in records), runs_dir)
    return stage_report().markdown(records, title, sequences)


def stale_rows(runs_dir: Path, seqs: Iterable[str], stage: str = "evaluate") -> dict[str, str]:
    """Per sequence whose ``stage`` result no longer matches what is in its run folder: why, in one line.

    A result is stale when a stage it was computed from (directly or further up) has been rerun since, or is
    gone: its manifest's recorded input keys differ from the inputs' manifests now."""
    out: dict[str, str] = {}
    for seq in seqs:
        store = RunStore(Path(runs_dir), seq)
        rerun: dict[str, str] = {}
        gone: list[str] = []
        todo, seen = [stage], set()
        while todo:
            name = todo.pop()
            if name in seen:
                continue
            seen.add(name)
            manifest = store.read_manifest(name)
            if manifest is None:
                continue
            for dep, key in sorted(manifest.get("inputs", {}).items()):
                now = store.read_manifest(dep)
                if now is None:
                    gone.append(dep)
                elif now.get("key") != key:
                    rerun[dep] = str(now.get("timings", {}).get("finished_at", ""))
                else:
                    todo.append(dep)
        reasons = []
        if rerun:
            names = sorted(rerun, key=lambda n: rerun[n])
            reasons.append(f"computed from {', '.join(repr(n) for n in names)} result(s) rerun since "
                           f"(last at {max(rerun.values())})")
        if gone:
            reasons.append(f"the {', '.join(repr(n) for n in sorted(set(gone)))} result(s) it used are gone")
        if reasons:
            out[seq] = "; ".join(reasons)
    return out


def command_line(argv: Sequence[str]) -> str:
    """The first line of a written report: the command that regenerates it (a markdown comment)."""
    import shlex

    return f"<!-- written by `pipeline {shlex.join(argv)}`; regenerate rather than edit -->\n\n"


def write_outputs(records: Sequence[dict[str, Any]], out: Path, title: str,
                  runs_dir: Path | None = None, stale: Mapping[str, str] | None = None,
                  command: str = "") -> list[Path]:
    """``out`` (markdown headed by ``command``, with a list of the stale rows under the title) and the combined
    long table beside it (``<out>.parquet``), each written to a temporary name and renamed into place."""
    import numpy as np

    from schemas import write_artifact

    out.parent.mkdir(parents=True, exist_ok=True)
    text = to_markdown(records, title, runs_dir=runs_dir)
    if stale:
        lines = [f"- **{seq}**: {why}; refresh with `pipeline run evaluate --seq {seq}`"
                 for seq, why in stale.items()]
        head, _, rest = text.partition("\n")
        text = "\n".join([head, "", "Stale rows (computed from results that have been replaced since):", "", *lines,
                          "", rest.lstrip("\n")])
    write_text_atomic(out, command + text)
    cols: dict[str, Any] = {k: [r.get(k) for r in records] for k in ("seq", "method", "metric")}
    cols["value"] = np.array([r["value"] for r in records], np.float64)
    cols["features"] = np.array([int(r.get("features") or 0) for r in records], np.int32)
    cols["section"] = [str(r.get("section") or "") for r in records]
    pq_path = out.with_suffix(".parquet")
    write_artifact(cols, pq_path, "metrics")
    return [out, pq_path]


def write_sweep_markdown(records: Sequence[dict[str, Any]], out: Path, title: str,
                         command: str = "") -> list[Path]:
    """``out``: the sweep's tables (one row per point, as printed) as markdown headed by ``command``, not the
    pooled per-sequence tables, which would mix the points."""
    lines = [command + f"# {title}", ""]
    for name, headers, rows in sweep_tables(records):
        lines += [f"## {name}", "", "| " + " | ".join(headers) + " |", "|" + " --- |" * len(headers)]
        lines += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
        lines.append("")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, "\n".join(lines) + "\n")
    return [out]


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
    """Figures across sequences beside ``out`` (the evaluate stage's report draws them): Fig. 6 and Fig. 10
    right from the slam stages' ``map_stats.parquet``; for map sequences the top views of the maps in the runs."""
    seqs = list(dict.fromkeys(str(r["seq"]) for r in records))
    return stage_report().figures(records, out, uncertainty_curves(runs_dir, seqs), runs_dir=runs_dir)


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
    """AUC per point and method, and Fig. 6 means over the points (the evaluate stage's report)."""
    return stage_report().sweep_tables(records)
