"""RICH-SLAM Table III over several seeds: every method on run folders' cached inputs, resumable.

The slam stage runs one seed per run; Table III with a spread needs several, and 200-particle runs take
hours on a CPU, so this runner appends one JSON line per (sequence, method, seed) to ``--out`` as each
finishes and skips the ones already there: stop it at any point and run the same command again.

    pipeline run odometry --seq SEQ ...                       # ingest, filter, odometry (and ground truth)
    python -m experiments.slam_table3 RUNS/SEQ [RUNS/SEQ ...] --methods odometry,fastslam_grid,rich_slam \\
        --seeds 0,1,2 --set n_particles=200 --out table3.jsonl
    python -m experiments.slam_table3 --table table3.jsonl         # the markdown tables: mean, spread, seeds
    python -m experiments.slam_table3 --table a.jsonl b.jsonl      # rows of several runs in one table
    python -m experiments.slam_table3 --table table3.jsonl --figure table3.png   # and the figure (one panel a sequence)
    python -m experiments.slam_table3 --table table3.jsonl --paper               # beside the paper's Table III
    python -m experiments.slam_table3 --table table3.jsonl --targets             # radar_graph's targets per sequence

Errors are position RMSE [m] / yaw RMSE [deg] after an SE(2) alignment (the evaluate stage's
``evaluate_trajectory``), two ways, both in every row: on the whole trajectory (``pos_rmse_whole_m``,
``yaw_rmse_whole_deg``; equal to ``evo_ape --align`` in the plane; the headline table and the figure's
default) and the paper's protocol, on the first 100 matched frames (``pos_rmse_m``, ``yaw_rmse_deg``; the
paper's own rows are beside these). Rows written before the whole-trajectory errors have the protocol's
only. ``--set`` takes the slam stage's parameters (JSON values).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from core import hilbert_map as hm
from core.stage import flatten_params, nest_params
from experiments.slam_unit_study import read_run_folder
from stages.evaluate.rich_slam_paper import (
    COUNTERPART,
    PAPER_METHODS,
    PAPER_SEQUENCES,
    TABLE_III,
    paper_sequence,
)
from stages.evaluate.trajectory import anchored_errors, evaluate_trajectory, evaluate_trajectory_whole, quat_to_yaw
from stages.slam.beam_sampling import BeamSamples
from stages.slam.method_names import GRAPH_METHODS, METHODS
from stages.slam.methods import DOMAIN_PADDING, MethodResult, domain_from_trajectory, run_method
from stages.slam.params import SlamParams
from stages.slam.pose_graph import optimise_graph
from stages.slam.stage import beam_samples_by_scan, graph_endpoints_by_scan, read_odometry_file

F64 = npt.NDArray[np.floating[Any]]


Truth = tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], npt.NDArray[np.float64]]

#: how a row's errors were aligned: the whole trajectory, the paper's protocol (first 100 frames), none (anchored)
Alignment = Literal["whole", "paper", "anchored"]
#: the (position, yaw) keys of a row per alignment
KEYS: dict[str, tuple[str, str]] = {"whole": ("pos_rmse_whole_m", "yaw_rmse_whole_deg"),
                                    "paper": ("pos_rmse_m", "yaw_rmse_deg"),
                                    "anchored": ("pos_rmse_anchored_m", "yaw_rmse_anchored_deg")}
#: the title of each alignment's table
TITLES = {"whole": "Whole-trajectory SE(2) alignment (= evo_ape --align in the plane)",
          "paper": "The paper's protocol: SE(2) alignment on the first 100 matched frames",
          "anchored": "Without alignment (anchored at the ground truth)"}


def slam_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``[slam.]KEY=VALUE`` strings as slam parameter overrides: VALUE as JSON, else the string itself.
    Raises ``ValueError`` naming the first item without ``=``."""
    overrides: dict[str, Any] = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE")
        try:
            overrides[key.removeprefix("slam.")] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key.removeprefix("slam.")] = value
    return overrides


def load_inputs(run_dir: Path, p: SlamParams
                ) -> tuple[npt.NDArray[np.int64], F64, list[BeamSamples], Truth, F64]:
    """Scan times, odometry poses (valid rows, scan order), beam samples, ground truth and the odometry's
    increment covariance ``(T, 3, 3)`` of a run folder."""
    gt, calib, radar = read_run_folder(run_dir)
    scans, t_ns, poses, inc_cov = read_odometry_file(run_dir / "odometry" / "odometry.parquet", run_dir.name)
    xyz = np.stack([radar[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], 1)
    samples = beam_samples_by_scan(radar["scan"].to_numpy().astype(np.int64), xyz, scans, calib, p)
    truth: Truth = (gt["t_ns"].astype(np.int64), np.stack([gt["x"], gt["y"]], 1).astype(np.float64),
                    quat_to_yaw(gt["qx"], gt["qy"], gt["qz"], gt["qw"]))
    return t_ns, poses, samples, truth, inc_cov


def error_fields(t_ns: npt.NDArray[np.int64], est: npt.NDArray[np.float64], truth: Truth) -> dict[str, float]:
    """A row's errors: the paper's protocol (SE(2) alignment on the first 100 frames) and the whole-trajectory
    alignment (= evo_ape --align in the plane)."""
    e = evaluate_trajectory(t_ns, est[:, :2], est[:, 2], truth[0], truth[1], truth[2], n_align=100)
    w = evaluate_trajectory_whole(t_ns, est[:, :2], est[:, 2], truth[0], truth[1], truth[2])
    return {"pos_rmse_m": e.pos_rmse_m, "yaw_rmse_deg": e.yaw_rmse_deg, "pos_rmse_whole_m": w.pos_rmse_m,
            "yaw_rmse_whole_deg": w.yaw_rmse_deg}


def say_row(row: dict[str, Any], tail: str) -> None:
    """The progress line of a written row."""
    print(f"{row['seq']} {row['method']} seed {row['seed']}: whole {row['pos_rmse_whole_m']:.3f} m / "
          f"{row['yaw_rmse_whole_deg']:.2f} deg, paper protocol {row['pos_rmse_m']:.3f} m / "
          f"{row['yaw_rmse_deg']:.2f} deg ({tail})", flush=True)


def groundtruth_anchored(run_dir: Path) -> bool:
    """Whether the run's odometry (and so every filter started from it) is in the ground truth's frame."""
    import pyarrow.parquet as pq

    meta = pq.read_schema(run_dir / "odometry" / "odometry.parquet").metadata or {}
    return meta.get(b"anchor") == b"groundtruth"


def done_keys(out: Path) -> set[tuple[str, str, int, str]]:
    if not out.exists():
        return set()
    rows = [json.loads(line) for line in out.read_text().splitlines() if line.strip()]
    return {(r["seq"], r["method"], int(r["seed"]), r.get("config", "")) for r in rows}


def default_params() -> dict[str, Any]:
    """The slam stage's defaults under their dotted names (``graph.bias_walk``), as rows' configs name them."""
    return flatten_params(SlamParams().model_dump())


#: slam parameters that change how a run executes, not what it computes (left out when rows are compared)
EXECUTION_KEYS = ("workers", "device", "torch_threads")


def config_key(config: str, defaults: dict[str, Any] | None = None) -> str:
    """A row's ``config`` reduced to what sets its numbers: execution-only keys (:data:`EXECUTION_KEYS`) and
    values equal to the stage's current defaults (``defaults``: :func:`default_params` when not given)
    are dropped, so ``{"n_particles": 200, "workers": 0}`` and ``{"workers": 2}`` are one configuration. (A row
    written under an older default cannot be told apart from one under today's: its file's name and the README
    say which stop wrote it.)"""
    given = json.loads(config) if config else {}
    if defaults is None:
        defaults = default_params()
    kept = {k: v for k, v in given.items() if k not in EXECUTION_KEYS and (k not in defaults or defaults[k] != v)}
    return json.dumps(kept, sort_keys=True)


#: the odometry row's errors that identify the odometry a results file's filters ran on
ODOMETRY_SIGNATURE = ("pos_rmse_m", "yaw_rmse_deg", "pos_rmse_whole_m", "yaw_rmse_whole_deg")


def read_rows(paths: Sequence[Path], by_config: bool = False) -> tuple[list[dict[str, Any]], list[str]]:
    """The rows of several results files, for one table: a (sequence, method, seed) row that a later file
    repeats is replaced by it; where a later file's odometry row of a sequence differs from an earlier file's
    (the odometry was run again with other code or parameters), every row of that sequence in the earlier file
    is dropped, since its filters ran on the other odometry; likewise a (sequence, method) cell's rows in an earlier
    file are dropped where a later file has that cell in another configuration (:func:`config_key`: a default
    changed between them); a cell whose rows in one file were made with different configurations is refused,
    naming both, since its mean would mix them; with ``by_config`` each configuration is a method of its own
    instead (``"radar_graph {\"graph.bias_walk\": 0.001}"``; the defaults' is the bare method). Returns the rows
    and notes (replacements, dropped rows). Raises ``ValueError`` with the file and line for a line that is not
    a JSON row."""
    defaults = default_params()
    # per file: (seq, method, seed), the row, its file:line and its configuration (config_key; "" for odometry)
    per_file: list[list[tuple[tuple[str, str, int], dict[str, Any], str, str]]] = []
    odometry: dict[tuple[int, str], tuple[float, ...]] = {}  # (file, seq) -> the odometry's errors there
    cell_config: dict[tuple[str, str], tuple[int, str]] = {}  # (seq, method) -> the last file with rows, config
    for f, path in enumerate(paths):
        if not path.is_file():
            raise ValueError(f"{path}: no such results file (write one with --out)")
        per_file.append([])
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if not line.strip():
                continue
            try:
                r = json.loads(line)
                key = (str(r["seq"]), str(r["method"]), int(r["seed"]))
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"{path}:{i}: not a table3 row ({exc}); each line is one JSON object with seq, "
                                 "method and seed") from None
            config = ""
            if key[1] == "odometry":
                odometry[(f, key[0])] = tuple(float(r.get(k, math.nan)) for k in ODOMETRY_SIGNATURE)
            else:
                try:
                    config = config_key(r.get("config", ""), defaults)
                except json.JSONDecodeError as exc:
                    raise ValueError(f"{path}:{i}: its config is not JSON ({exc})") from None
                if by_config and config != "{}":
                    key = (key[0], f"{key[1]} {config}", key[2])
                    r = {**r, "method": key[1]}
                cell_config[key[:2]] = (f, config)
            per_file[-1].append((key, r, f"{path}:{i}", config))
    latest = {seq: f for f, seq in sorted(odometry)}  # seq -> the last file with an odometry row of it
    whole, paper = ODOMETRY_SIGNATURE.index("yaw_rmse_whole_deg"), ODOMETRY_SIGNATURE.index("yaw_rmse_deg")
    rows: dict[tuple[str, str, int], dict[str, Any]] = {}
    source: dict[tuple[str, str, int], tuple[str, str]] = {}  # file:line and configuration of each kept row
    notes: list[str] = []
    for f, (path, items) in enumerate(zip(paths, per_file, strict=True)):
        stale = set()
        for seq, g in sorted(latest.items()):
            was, now = odometry.get((f, seq)), odometry[(g, seq)]
            if g <= f or was is None or np.allclose(was, now, rtol=0, atol=1e-9, equal_nan=True):
                continue
            stale.add(seq)
            yaw = whole if not (math.isnan(was[whole]) or math.isnan(now[whole])) else paper
            notes.append(f"{seq}: the rows of {path} are dropped: its odometry differs from that of {paths[g]} (yaw "
                         f"RMSE {was[yaw]:.2f} against {now[yaw]:.2f} deg), so its filters ran on another odometry")
        superseded: set[tuple[str, str]] = set()
        for key, r, where, config in items:
            if key[0] in stale:
                continue
            g, c = cell_config.get(key[:2], (f, config))
            if g > f and config != c:
                superseded.add(key[:2])
                continue
            if key in rows:
                notes.append(f"{key[0]} {key[1]} seed {key[2]}: the row of {path} replaces an earlier one")
            rows[key], source[key] = r, (where, config)
        notes.extend(f"{seq} {method}: the rows of {path} are dropped: {paths[cell_config[(seq, method)][0]]} has "
                     "this cell in another configuration" for seq, method in sorted(superseded))
    configs: dict[tuple[str, str], tuple[str, str]] = {}
    for (seq, method, _), (where, c) in source.items():
        if method == "odometry":
            continue
        first = configs.setdefault((seq, method), (c, where))
        if first[0] != c:
            raise ValueError(f"{seq} {method}: rows of different configurations in one cell, {first[0]} "
                             f"({first[1]}) and {c} ({where}); tabulate them separately")
    return list(rows.values()), notes


def append_row(out: Path, row: dict[str, Any]) -> None:
    """One JSON line, flushed and synced (a killed run loses at most the row being computed)."""
    with out.open("a") as f:
        f.write(json.dumps(row) + "\n")
        f.flush()
        os.fsync(f.fileno())


def run(runs: Sequence[Path], methods: Sequence[str], seeds: Sequence[int], overrides: dict[str, Any],
        out: Path, keep: Path | None = None) -> None:
    """Append a row per (run, method, seed) not yet in ``out``; ``keep``: also save each row's trajectory there
    (:func:`save_trajectory`)."""
    p = SlamParams.model_validate(nest_params(overrides))
    config = json.dumps(overrides, sort_keys=True)
    done = done_keys(out)
    for run_dir in runs:
        todo = [(m, s) for s in seeds for m in methods if (run_dir.name, m, s, config) not in done]
        if not todo:
            continue
        t_ns, odo, samples, truth, inc_cov = load_inputs(run_dir, p)
        half, centre = domain_from_trajectory(odo[:, :2], DOMAIN_PADDING)
        basis = hm.make_basis(half, centre, p.map.n_basis, "tensor")
        anchored = groundtruth_anchored(run_dir)
        for m, s in todo:
            t0 = time.perf_counter()
            graph_counts: dict[str, int] = {}
            if m in GRAPH_METHODS:
                res, graph_counts = run_graph_method(run_dir, p, t_ns, odo, inc_cov)
            else:
                res = run_method(m, odo, samples, basis, p.model_copy(update={"seed": s}))
            seconds = time.perf_counter() - t0
            est = np.asarray(res.poses, np.float64)
            row = {"seq": run_dir.name, "method": m, "seed": s, "config": config,
                   **error_fields(t_ns, est, truth), "s_per_scan": seconds / len(odo),
                   "resamplings": res.resampled, "scans": len(odo), **graph_counts}
            if anchored:  # beside the Table III protocol: no alignment (every filter starts at the anchor)
                row["pos_rmse_anchored_m"], row["yaw_rmse_anchored_deg"] = anchored_errors(
                    t_ns, est[:, :2], est[:, 2], truth[0], truth[1], truth[2])
            if keep is not None:
                save_trajectory(keep, run_dir.name, m, s, config, t_ns, est, truth)
            append_row(out, row)
            say_row(row, f"{row['s_per_scan']:.3f} s/scan")


def run_graph_method(run_dir: Path, p: SlamParams, t_ns: npt.NDArray[np.int64], odo: F64,
                     inc_cov: F64) -> tuple[MethodResult, dict[str, int]]:
    """radar_graph on a run folder, as the slam stage runs it (endpoints to ``graph.max_range``): its result and
    the loop-closure counts of the row."""
    _, calib, radar = read_run_folder(run_dir)
    scans = read_odometry_file(run_dir / "odometry" / "odometry.parquet", run_dir.name)[0]
    xyz = np.stack([radar[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], 1)
    endpoints = graph_endpoints_by_scan(radar["scan"].to_numpy().astype(np.int64), xyz, scans, calib, p)
    g = optimise_graph(odo, inc_cov, (t_ns - t_ns[0]) * 1e-9, endpoints, p.graph)
    counts = {"keyframes": len(g.keyframes), "loops_proposed": g.count("loop"),
              "loops_accepted": g.count("loop", True), "loops_rejected": g.count("loop", False)}
    return MethodResult("radar_graph", g.poses, np.ones(len(g.poses)), 0.0), counts


def trajectory_file(keep: Path, seq: str, label: str, seed: int, config: str) -> Path:
    """Where :func:`save_trajectory` puts a row's trajectory: one file per (sequence, label, seed, config)."""
    import hashlib

    tag = hashlib.sha1(config.encode()).hexdigest()[:8]
    return keep / seq / f"{label.replace(', ', '__')}_seed{seed}_{tag}.npz"


def save_trajectory(keep: Path, seq: str, label: str, seed: int, config: str, t_ns: npt.NDArray[np.int64],
                    est: F64, truth: Truth) -> Path:
    """Save a row's trajectory (scan stamps, x, y, yaw) with the ground truth and the row's config, written to
    a temporary name and renamed, so that estimators can be studied after the filter run."""
    path = trajectory_file(keep, seq, label, seed, config)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, t_ns=t_ns, pose=est, truth_t_ns=truth[0], truth_xy=truth[1], truth_yaw=truth[2],
             config=np.array(config), label=np.array(label), seed=np.array(seed))
    os.replace(tmp, path)
    return path


def by_sequence(rows: Sequence[dict[str, Any]], anchored: bool = False, alignment: Alignment = "paper"
                ) -> dict[str, dict[str, list[tuple[float, float]]]]:
    """``{sequence: {method: [(position RMSE, yaw RMSE) per seed]}}`` (odometry once): sequences in the rows'
    order, the ColoRadar twins last in the paper's column order (the table's and the figure's order).

    ``alignment``: the errors of the paper's protocol (``pos_rmse_m``, ``yaw_rmse_deg``), of the whole-trajectory
    alignment (``pos_rmse_whole_m``, ``yaw_rmse_whole_deg``) or without alignment (``anchored``, or
    ``anchored=True``: ``pos_rmse_anchored_m``, ``yaw_rmse_anchored_deg``, runs whose odometry is anchored at the
    ground truth); rows without those keys are left out."""
    keys = KEYS["anchored" if anchored else alignment]
    out: dict[str, dict[str, list[tuple[float, float]]]] = {}
    for r in rows:
        if keys[0] not in r:
            continue
        cell = out.setdefault(r["seq"], {}).setdefault(r["method"], [])
        if not (r["method"] == "odometry" and cell):  # the odometry does not depend on the seed
            cell.append((float(r[keys[0]]), float(r[keys[1]])))
    return dict(sorted(out.items(), key=lambda kv: _paper_rank(kv[0])))


def cell(seeds: Sequence[tuple[float, float]], method: str) -> str:
    """One table cell: mean position / yaw RMSE over the seeds, +- half the range, and the seed count."""
    v = np.asarray(seeds, dtype=np.float64).reshape(-1, 2)
    if not len(v):
        return "–"
    if len(v) == 1:
        return f"{v[0, 0]:.2f} / {v[0, 1]:.2f}" + ("" if method == "odometry" else " (1 seed)")
    h = (v.max(0) - v.min(0)) / 2
    return f"{v[:, 0].mean():.2f} ± {h[0]:.2f} / {v[:, 1].mean():.2f} ± {h[1]:.2f} ({len(v)})"


def table(rows: Sequence[dict[str, Any]], methods: Sequence[str] = (), anchored: bool = False,
          alignment: Alignment = "paper") -> str:
    """Markdown: per method and sequence, mean position / yaw RMSE over seeds, +- half the range, seeds; the
    errors of one ``alignment`` (:func:`by_sequence`)."""
    d = by_sequence(rows, anchored, alignment)
    seqs = list(d)
    key = KEYS["anchored" if anchored else alignment][0]
    ms = list(dict.fromkeys([*methods, *(r["method"] for r in rows if key in r)]))
    lines = ["| method | " + " | ".join(seqs) + " |", "|---|" + "---|" * len(seqs)]
    for m in ms:
        lines.append(f"| {m} | " + " | ".join(cell(d[s].get(m, []), m) for s in seqs) + " |")
    return "\n".join(lines)


#: the targets: an odometry whose whole-trajectory yaw RMSE is below this (deg) must not be made worse
GOOD_ODOMETRY_DEG = 5.0
#: and on a drifting sequence (its name ends so) the method's yaw RMSE must be this fraction of the odometry's or less
DRIFT_FACTOR = 0.7


def targets(rows: Sequence[dict[str, Any]], method: str = "radar_graph",
            against: str = "rich_slam") -> tuple[str, dict[str, tuple[int, int]]]:
    """The default method's targets per sequence, whole-trajectory alignment, a markdown table and the counts
    ``{target: (met, of)}``: **no worse** than the odometry in yaw and position where its yaw RMSE is below
    :data:`GOOD_ODOMETRY_DEG`, within the spread over seeds (the cell's mean minus half its range at most the
    odometry's); on the drifting sequences (``*_drift``) the mean yaw **30 % below** the odometry's
    (:data:`DRIFT_FACTOR`) and **below** ``against``'s mean yaw. A sequence without a ``method`` or odometry row
    is left out; one without an ``against`` row counts that target as not met (``no row``)."""
    d = by_sequence(rows, alignment="whole")
    counts = {"no worse": [0, 0], "30 % below": [0, 0], f"below {against}": [0, 0], "both drifting": [0, 0]}
    lines = [f"| sequence | odometry | {method} | {against} | no worse (odometry < {GOOD_ODOMETRY_DEG:g}°) | "
             "30 % below (drifting) | below the other (drifting) |", "|---|---|---|---|---|---|---|"]
    mark = {True: "✓", False: "✗", None: ""}
    for seq, cells in d.items():
        odo, mine = cells.get("odometry"), cells.get(method)
        if not odo or not mine:
            continue
        v = np.asarray(mine, np.float64).reshape(-1, 2)
        mean, half = v.mean(0), (v.max(0) - v.min(0)) / 2
        o = np.asarray(odo[0], np.float64)
        other = cells.get(against)
        no_worse = bool(np.all(mean - half <= o + 1e-9)) if o[1] < GOOD_ODOMETRY_DEG else None
        drifting = seq.endswith("_drift")
        below30 = bool(mean[1] <= DRIFT_FACTOR * o[1]) if drifting else None
        below_other = (bool(other) and bool(mean[1] < np.mean(np.asarray(other)[:, 1]))) if drifting else None
        for name, ok in (("no worse", no_worse), ("30 % below", below30), (f"below {against}", below_other)):
            if ok is not None:
                counts[name][0] += ok
                counts[name][1] += 1
        if drifting:
            counts["both drifting"][0] += bool(below30 and below_other)
            counts["both drifting"][1] += 1
        gain = f" ({100 * (mean[1] / o[1] - 1):+.0f} %)" if drifting and o[1] > 0 else ""
        lines.append(f"| {seq} | {cell(odo, 'odometry')} | {cell(mine, method)} | "
                     f"{cell(other, against) if other else 'no row'} | {mark[no_worse]} | {mark[below30]}{gain} | "
                     f"{mark[below_other]} |")
    totals = {k: (v[0], v[1]) for k, v in counts.items()}
    lines.append("\n" + "; ".join(f"{k}: {m} of {n}" for k, (m, n) in totals.items()))
    return "\n".join(lines), totals


def paper_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown, a line per sequence that Table III has (the ColoRadar twins): our methods' cells under the
    paper's protocol, then the paper's rows for the same sequence (``stages.evaluate.rich_slam_paper``). When
    the rows have the whole-trajectory errors, those come first (``<method>, whole``) and the protocol's are
    ``<method>, paper``. Empty when no sequence has a Table III column."""
    twins = [(col, s, cells) for s, cells in by_sequence(rows).items()  # already in the paper's order
             if (col := paper_sequence(s)) is not None]
    if not twins:
        return ""
    whole = by_sequence(rows, alignment="whole")
    seen = dict.fromkeys(m for _, _, cells in twins for m in cells)
    ms = sorted(seen, key=lambda m: METHODS.index(m) if m in METHODS else len(METHODS))
    both = any(s in whole for _, s, _ in twins)
    ours = [f"{m}, whole" for m in ms] + [f"{m}, paper" for m in ms] if both else ms
    head = ["sequence", *ours, *(f"paper {m}" for m in PAPER_METHODS)]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---|" * (len(head) - 1)]
    for col, s, cells in twins:
        paper = [f"{p:.2f} / {y:.2f}" for p, y in (TABLE_III[col][m] for m in PAPER_METHODS)]
        mine = [cell(cells.get(m, []), m) for m in ms]
        if both:
            mine = [cell(whole.get(s, {}).get(m, []), m) for m in ms] + mine
        lines.append(f"| {col} ({s}) | " + " | ".join([*mine, *paper]) + " |")
    return "\n".join(lines)


def _paper_rank(seq: str) -> int:
    """Sort key: sequences without a Table III column first (stable), then the paper's column order."""
    col = paper_sequence(seq)
    return -1 if col is None else PAPER_SEQUENCES.index(col)


def paper_marks(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, tuple[float, float]]]:
    """``{sequence: {our method: the paper's (position, yaw) for it}}`` for the figure's marks."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for s, cells in by_sequence(rows).items():
        col = paper_sequence(s)
        if col is not None:
            out[s] = {m: TABLE_III[col][COUNTERPART[m]] for m in cells if m in COUNTERPART}
    return out


def tabulate(a: argparse.Namespace) -> int:
    """``--table``: print the tables (and draw the figure) of the results files ``a.table``; the exit code."""
    try:
        rows, notes = read_rows(a.table, by_config=a.by_config)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for n in notes:
        print(f"note: {n}", file=sys.stderr)
    if a.labels:
        keep = [lab.strip() for lab in a.labels.split(";") if lab.strip()]
        have = {r["method"] for r in rows}
        missing = [lab for lab in keep if lab not in have]
        if missing:
            print(f"error: --labels: no row is labelled {missing[0]!r}; the rows have {', '.join(sorted(have))}",
                  file=sys.stderr)
            return 2
        rows = [r for r in rows if r["method"] in keep]
    has_whole = any(KEYS["whole"][0] in r for r in rows)
    if has_whole:  # the headline first
        print(f"{TITLES['whole']}:\n\n{table(rows, alignment='whole')}\n")
    print(f"{TITLES['paper']}:\n\n{table(rows)}")
    if a.anchored:
        print(f"\n{TITLES['anchored']}:\n")
        print(table(rows, anchored=True) if any("pos_rmse_anchored_m" in r for r in rows)
              else "(no row has errors without alignment)")
    if a.paper:
        print("\n" + (paper_table(rows) or "(no sequence of the paper's Table III in these rows)"))
    if a.targets:
        method, _, other = a.targets.partition(";")
        if not has_whole or method.strip() not in {r["method"] for r in rows}:
            print(f"error: --targets: no row of {method.strip()!r} with the whole-trajectory errors",
                  file=sys.stderr)
            return 2
        print(f"\nTargets, {method.strip()} (whole-trajectory alignment; mean ± half range over "
              f"seeds):\n\n{targets(rows, method.strip(), other.strip() or 'rich_slam')[0]}")
    if a.figure:
        from stages.evaluate.figures import plot_table3

        drawn: Alignment = "whole" if a.alignment == "whole" and has_whole else "paper"
        if drawn != a.alignment:
            print("(no row has the whole-trajectory errors: the figure draws the paper's protocol)")
        tmp = a.figure.with_name(a.figure.name + ".tmp.png")
        marks = "; black line: the paper's value, its protocol" if a.paper else ""
        title = (f"Table III, {TITLES[drawn][0].lower()}{TITLES[drawn][1:]}: yaw RMSE (bar: mean over seeds, "
                 f"dots: seeds; text: position RMSE{marks})")
        plot_table3(tmp, by_sequence(rows, alignment=drawn), paper=paper_marks(rows) if a.paper else None,
                    title=title)
        os.replace(tmp, a.figure)
        print(f"wrote {a.figure}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("runs", nargs="*", type=Path, help="run folders <runs>/<seq> with ingest/, filter/, odometry/")
    ap.add_argument("--methods", default="odometry,radar_graph,fastslam_grid,rich_slam")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--set", action="append", default=[], metavar="PARAM=JSON", help="a slam stage parameter")
    ap.add_argument("--out", type=Path, default=Path("table3.jsonl"))
    ap.add_argument("--keep", type=Path, help="also save each row's trajectory (and the ground truth) in this "
                    "folder, one .npz per row: <keep>/<seq>/<method>_seed<S>_<config hash>.npz")
    ap.add_argument("--table", type=Path, nargs="+", help="print the markdown table of these results files and "
                    "exit (several: one table; a row repeated in a later file replaces the earlier one; cells that "
                    "mix configurations are refused)")
    ap.add_argument("--figure", type=Path, help="with --table: also draw it into this PNG")
    ap.add_argument("--write", type=Path, help="with --table: write the tables (markdown) to this file, headed by the "
                    "command that regenerates it, instead of printing them")
    ap.add_argument("--by-config", action="store_true", help="with --table: each configuration of a method is a row "
                    "of its own, labelled by what differs from the defaults (a calibration grid)")
    ap.add_argument("--labels", help="with --table: only the rows of these methods, as the rows label them, "
                    "separated by ';' (e.g. 'odometry;radar_graph;rich_slam'); default: every row")
    ap.add_argument("--paper", action="store_true", help="with --table: also the ColoRadar twins beside the paper's "
                    "Table III (a line per twin; in the figure, a mark at the paper's value of each method)")
    ap.add_argument("--targets", metavar="METHOD;OTHER", nargs="?", const="radar_graph;rich_slam",
                    help="with --table: the targets per sequence for METHOD against the odometry and OTHER "
                    "(default 'radar_graph;rich_slam'), whole-trajectory alignment")
    ap.add_argument("--anchored", action="store_true", help="with --table: also the errors without alignment "
                    "(rows of runs whose odometry is anchored at the ground truth)")
    ap.add_argument("--alignment", choices=("whole", "paper"), default="whole", help="with --figure: the "
                    "errors drawn (whole: the whole-trajectory alignment, where the rows have it; paper: the paper's "
                    "protocol)")
    a = ap.parse_args(argv)
    if a.table and a.write:
        import contextlib
        import io
        import shlex

        from pipeline.store import write_text_atomic

        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            code = tabulate(a)
        if code == 0:
            args = " ".join(shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:]))
            head = f"<!-- written by `python -m experiments.slam_table3 {args}`; do not edit -->\n\n"
            write_text_atomic(a.write, head + buf.getvalue())
            print(f"wrote {a.write}")
        else:
            sys.stdout.write(buf.getvalue())
        return code
    if a.table:
        return tabulate(a)
    try:
        overrides = slam_overrides(a.set)
    except ValueError as exc:
        ap.error(str(exc))
    missing = [r for r in a.runs if not (r / "odometry" / "odometry.parquet").exists()]
    if missing:
        ap.error(f"{missing[0]}: no odometry/odometry.parquet; run `pipeline run odometry --seq "
                 f"{missing[0].name}` first")
    unknown = [m for m in a.methods.split(",") if m not in METHODS]
    if unknown:
        ap.error(f"--methods: unknown {unknown[0]!r}; one of {', '.join(METHODS)}")
    run(a.runs, a.methods.split(","), [int(s) for s in a.seeds.split(",")], overrides, a.out, a.keep)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
