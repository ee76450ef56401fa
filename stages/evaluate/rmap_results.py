"""Per-scene RMap results collected from run folders, for :mod:`stages.evaluate.rmap_tables`.

Reads, for ``runs/<seq>/``: ``evaluate/metrics.parquet`` (long table seq, method, metric, value; map
methods ``radar_map`` / ``completed_map`` / ``lidar_map``), ``patches/manifest.json`` (``params.a``,
``stats.n_seeds``) and ``complete/manifest.json`` (``stats.n_patches``, ``stats.model_seconds``,
``stats.device``). Optionally it reads the maps themselves (``voxel/{radar,lidar}_map.parquet``,
``complete/completed_map.parquet``) for the ground-truth distances that pooled D-Dist needs.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Collection, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import UserError
from core.map_metrics import MapComparison, comparison_metrics, lr_ratio, nearest
from schemas import read_artifact
from stages.evaluate.rmap_figures import plot_top_views
from stages.evaluate.rmap_tables import BAND, COMPLETED, F64, INPUT, LIDAR, MODEL_PREFIX, SceneResult, scene_name

MAP_METHODS = (INPUT, COMPLETED, LIDAR, BAND)
#: a metric of method ``lidar_map`` that marks rebuilt ground truth (1.0), if the evaluate stage writes it
REBUILT_METRIC = "gt_rebuilt"


def _manifest(path: Path) -> dict[str, Any]:
    if not path.is_file():
        return {}
    try:
        return dict(json.loads(path.read_text()))
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: unreadable manifest ({exc}); rerun the stage with --force") from exc


def _cloud(path: Path, schema: str) -> F64:
    t = read_artifact(path, schema, columns=["x", "y", "z"])
    return np.stack([t[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], 1)


def read_map_metrics(path: Path) -> dict[str, dict[str, float]]:
    """method -> metric -> value of the map methods in an evaluate ``metrics.parquet``."""
    t = read_artifact(path, "metrics", columns=["method", "metric", "value"])
    out: dict[str, dict[str, float]] = {}
    for method, metric, value in zip(t["method"].to_pylist(), t["metric"].to_pylist(), t["value"].to_pylist(),
                                     strict=True):
        if method in MAP_METHODS or method.startswith(MODEL_PREFIX):
            out.setdefault(method, {})[metric] = float(value)
    return out


def collect_scene_result(seq_dir: Path, rebuilt: bool = False, with_distances: bool = False) -> SceneResult | None:
    """One sequence's :class:`SceneResult`; None (with a warning) when it has no evaluate metrics yet."""
    seq_dir = Path(seq_dir)
    seq = seq_dir.name
    mpath = seq_dir / "evaluate" / "metrics.parquet"
    if not mpath.is_file():
        warnings.warn(f"{mpath}: missing, {seq} left out of the RMap tables; run `pipeline run all --seq {seq}`",
                      stacklevel=2)
        return None
    metrics = read_map_metrics(mpath)
    if INPUT not in metrics:
        warnings.warn(f"{mpath}: no radar_map metrics (evaluate without the rmap section?); {seq} left out",
                      stacklevel=2)
        return None
    patches = _manifest(seq_dir / "patches" / "manifest.json")
    complete = _manifest(seq_dir / "complete" / "manifest.json")
    p_stats, c_stats = patches.get("stats", {}), complete.get("stats", {})
    a = patches.get("params", {}).get("a")
    n_patches = c_stats.get("n_patches", p_stats.get("n_seeds"))
    seconds = c_stats.get("model_seconds")
    distances: dict[str, F64] = {}
    if with_distances:
        gt = _cloud(seq_dir / "voxel" / "lidar_map.parquet", "lidar_map")
        distances[INPUT] = nearest(gt, _cloud(seq_dir / "voxel" / "radar_map.parquet", "radar_map"))[0]
        cpath = seq_dir / "complete" / "completed_map.parquet"
        if COMPLETED in metrics and cpath.is_file():
            distances[COMPLETED] = nearest(gt, _cloud(cpath, "completed_map"))[0]
    flagged = metrics.get(LIDAR, {}).get(REBUILT_METRIC, 0.0) > 0
    return SceneResult(
        scene=scene_name(seq), seq=seq, metrics=metrics, rebuilt=rebuilt or flagged,
        a_test=float(a) if a is not None else None, n_patches=int(n_patches) if n_patches is not None else None,
        inference_s=float(seconds) if seconds is not None else None, device=str(c_stats.get("device", "")),
        distances=distances,
    )


def collect_scene_results(runs_dir: Path, seqs: Iterable[str] | None = None, rebuilt: Collection[str] = (),
                          with_distances: bool = False) -> list[SceneResult]:
    """:class:`SceneResult` of every sequence in ``seqs`` (default: every ``rmap_*`` folder of ``runs_dir``).

    ``rebuilt``: scene names (``arpg_lab_run0``) or sequence names whose ground truth was rebuilt
    (:func:`sources.mapset.rebuilt_scenes` of the map set's index). Sequences without evaluate metrics are
    skipped with a warning.
    """
    runs_dir = Path(runs_dir)
    if seqs is None:
        seqs = sorted(p.name for p in runs_dir.glob("rmap_*") if p.is_dir()) if runs_dir.is_dir() else []
    marks = {scene_name(s) for s in rebuilt}
    out = []
    for seq in seqs:
        r = collect_scene_result(runs_dir / seq, scene_name(seq) in marks, with_distances)
        if r is not None:
            out.append(r)
    return out


def load_scene_maps(seq_dir: Path) -> dict[str, F64]:
    """The maps of one run for the top-view figure: ``radar_map``, ``lidar_map``, (when run) ``completed_map``
    and, when the complete stage ran several models, ``completed_map_<model>`` for each (the configured model's
    is the same array as ``completed_map``)."""
    seq_dir = Path(seq_dir)
    maps = {INPUT: _cloud(seq_dir / "voxel" / "radar_map.parquet", "radar_map"),
            LIDAR: _cloud(seq_dir / "voxel" / "lidar_map.parquet", "lidar_map")}
    cpath = seq_dir / "complete" / "completed_map.parquet"
    if cpath.is_file():
        maps[COMPLETED] = _cloud(cpath, "completed_map")
    models = _manifest(seq_dir / "complete" / "manifest.json").get("stats", {}).get("models")
    for model, info in (models.items() if isinstance(models, dict) else ()):
        fname = info.get("file") if isinstance(info, dict) else None
        path = seq_dir / "complete" / str(fname)
        if isinstance(fname, str) and path.is_file():
            maps[MODEL_PREFIX + model] = maps[COMPLETED] if fname == cpath.name and COMPLETED in maps else \
                _cloud(path, "completed_map")
    return maps


def score_maps(scene: str, maps: Mapping[str, F64], rebuilt: bool = False, d: float = 0.15,
               with_distances: bool = True) -> SceneResult:
    """A :class:`SceneResult` computed directly from the maps (``radar_map``, ``lidar_map`` = ground truth,
    optionally ``completed_map``), as the evaluate stage scores them (``map_metrics``)."""
    gt = np.asarray(maps[LIDAR], np.float64)
    metrics: dict[str, dict[str, float]] = {LIDAR: {"n_points": float(len(gt))}}
    distances: dict[str, F64] = {}
    for method in (INPUT, COMPLETED):
        if method not in maps:
            continue
        pred = np.asarray(maps[method], np.float64)
        cmp = MapComparison(pred, gt)
        metrics[method] = {**comparison_metrics(cmp, d), "lr_ratio": lr_ratio(len(gt), len(pred))}
        if with_distances:
            distances[method] = cmp.d_gp
    return SceneResult(scene=scene_name(scene), seq=scene, metrics=metrics, rebuilt=rebuilt, distances=distances)


#: the three scenes of the top-view figure by default (one lab, one hallway, one outdoor scene)
FIGURE_SEQS = ("rmap_arpg_lab_run0", "rmap_ec_hallways_run0", "rmap_outdoors_run0")
#: the columns when both completion models ran (complete.models)
MODEL_COLUMNS = ((INPUT, "input radar map"), (MODEL_PREFIX + "uppointr", "UpPoinTr"),
                 (MODEL_PREFIX + "voxel", "voxel U-Net"), (LIDAR, "lidar map"))


def plot_run_top_views(runs_dir: Path, path: Path, seqs: Sequence[str] = FIGURE_SEQS, z_max: float | None = None,
                       seed: int = 0) -> Path | None:
    """Fig. 3-style top views of ``seqs`` that have voxel maps in ``runs_dir``: input, completed, lidar; or,
    when every shown scene has both models' maps, input, UpPoinTr, voxel U-Net, lidar (:data:`MODEL_COLUMNS`).

    Sequences without maps are left out with a warning; None (and a warning) when none has them.
    """
    scenes = {}
    for seq in seqs:
        d = Path(runs_dir) / seq
        if not (d / "voxel" / "radar_map.parquet").is_file() or not (d / "voxel" / "lidar_map.parquet").is_file():
            warnings.warn(f"{d / 'voxel'}: no radar/lidar map, {seq} left out of the top-view figure; run "
                          f"`pipeline run all --seq {seq}`", stacklevel=2)
            continue
        scenes[scene_name(seq)] = load_scene_maps(d)
    if not scenes:
        warnings.warn("no sequence of the top-view figure has maps; figure not written", stacklevel=2)
        return None
    if all(all(m in maps for m, _ in MODEL_COLUMNS) for maps in scenes.values()):
        return plot_top_views(path, scenes, "input radar map, UpPoinTr, voxel U-Net and lidar map (top view, colour: "
                              "height)", columns=MODEL_COLUMNS, z_max=z_max, seed=seed)
    return plot_top_views(path, scenes, "input radar, completed and lidar maps (top view, colour: height)",
                          z_max=z_max, seed=seed)
