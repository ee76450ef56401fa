"""Completion network: torch point ops against references, inference seconds per patch, and (full mode)
the held-out map comparison of RMap Table III on a simulated sequence.

- Chamfer (8192 x 8192, one patch): the torch brute-force backend and the cKDTree backend against
  scipy's ``cKDTree`` on both directions (the reference), same inputs, same run;
- FPS (8192 -> 2048): the torch loop against ``fpsample`` (reference);
- inference s/patch on this machine's CPU for the shipped small checkpoint (else a random small model)
  and, in full mode, the paper size; batch 1 and 8, best of ``repeat``;
- full mode: `complete` on the held-out sequence(s) with the shipped checkpoint, input radar map and
  completed map each scored against the lidar map (``stages.evaluate.map_metrics``).

``python -m benchmarks.bench_complete --heldout sim_hallway_loop`` prints only the held-out comparison.
Needs torch (the ``learn`` extra); without it the benchmark returns nothing.
"""

from __future__ import annotations

import importlib.util
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import Result, best_time

AREA = "complete"
HELDOUT = ("sim_hallway_loop",)


def _ops_results(quick: bool) -> list[Result]:
    import fpsample
    import torch
    from scipy.spatial import cKDTree

    from stages.complete.ops import chamfer_l2, fps

    rng = np.random.default_rng(0)
    p = rng.normal(size=(8192, 3)).astype(np.float32)
    g = rng.normal(size=(8192, 3)).astype(np.float32)
    pt, gt = torch.from_numpy(p)[None], torch.from_numpy(g)[None]

    def ref_chamfer() -> float:
        d1 = cKDTree(g).query(p)[0]
        d2 = cKDTree(p).query(g)[0]
        return float((d1**2).mean() + (d2**2).mean())

    repeat = 2 if quick else 3
    t_ref = best_time(ref_chamfer, repeat)
    out = []
    for backend in ("torch", "kdtree"):
        got = float(chamfer_l2(pt, gt, backend=backend))
        assert abs(got - ref_chamfer()) < 1e-4 * ref_chamfer(), (backend, got)
        t = best_time(partial(chamfer_l2, pt, gt, backend=backend), repeat)
        out.append(Result(AREA, f"chamfer 8192x8192 ({backend})", t * 1e3, "ms", "scipy cKDTree both ways",
                          t / t_ref, note="forward only"))
    t_ref = best_time(lambda: fpsample.fps_sampling(g, 2048, start_idx=0), repeat)
    t = best_time(lambda: fps(gt, 2048, backend="torch"), repeat)
    out.append(Result(AREA, "fps 8192->2048 (torch loop)", t * 1e3, "ms", "fpsample.fps_sampling", t / t_ref))
    return out


def _model(size: str) -> tuple[Any, Any, str]:
    from stages.complete.checkpoint import CheckpointMeta, load_checkpoint
    from stages.complete.model import SIZES, UpPoinTr
    from stages.complete.stage import DEFAULT_CHECKPOINT, resolve_checkpoint

    path = resolve_checkpoint(DEFAULT_CHECKPOINT)
    if size == "small" and path.exists():
        model, meta = load_checkpoint(path)
        return model, meta, "shipped checkpoint"
    return UpPoinTr(SIZES[size]).eval(), CheckpointMeta(SIZES[size], 1.0), "random weights"


def _inference_results(quick: bool) -> list[Result]:
    import torch

    from stages.complete.model import count_parameters
    from stages.complete.synthetic import make_patches

    out = []
    sizes = ["small"] if quick else ["small", "paper"]
    for size in sizes:
        model, _, what = _model(size)
        x = torch.from_numpy(np.stack([p.radar for p in make_patches(8, seed=0)])).float()
        for batch in (1, 8):
            xb = x[:batch]
            with torch.no_grad():
                model(xb)  # warm-up
                t = best_time(partial(model, xb), 2 if quick or size == "paper" else 3)
            out.append(Result(AREA, f"inference {size} batch {batch} (CPU, {torch.get_num_threads()} threads)",
                              t / batch, "s/patch",
                              note=f"{what}, {count_parameters(model) / 1e6:.2f} M parameters, 2048 -> 8192"))
    return out


def heldout_comparison(seqs: tuple[str, ...] = HELDOUT, runs_dir: Path | None = None,
                       overrides: dict[str, dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """Run `complete` on ``seqs`` and score the input radar map and the completed map against the lidar map."""
    from rich.console import Console

    from pipeline.config import load_workflow
    from pipeline.paths import default_runs_dir
    from pipeline.registry import load_stages
    from pipeline.runner import Runner
    from pipeline.sequences import get_sequence
    from schemas import read_artifact
    from stages.evaluate.map_metrics import map_metrics

    def cloud(path: Path, schema: str) -> np.ndarray:
        t = read_artifact(path, schema, columns=["x", "y", "z"])
        return np.stack([t.column(c).to_numpy().astype(np.float64) for c in "xyz"], axis=1)

    rows = []
    for name in seqs:
        runner = Runner(get_sequence(name), runs_dir or default_runs_dir(), load_stages(), load_workflow("default"),
                        overrides or {}, Console(stderr=True))
        runner.run(["complete"])
        store = runner.store
        lidar = cloud(store.stage_dir("voxel") / "lidar_map.parquet", "lidar_map")
        radar = cloud(store.stage_dir("voxel") / "radar_map.parquet", "radar_map")
        done = cloud(store.stage_dir("complete") / "completed_map.parquet", "completed_map")
        import json

        stats = json.loads((store.stage_dir("complete") / "manifest.json").read_text()).get("stats", {})
        for method, pred in (("input radar map", radar), ("completed map", done)):
            rows.append({"seq": name, "method": method, **map_metrics(pred, lidar),
                         "seconds_per_patch": stats.get("seconds_per_patch") if method == "completed map" else None,
                         "n_patches": stats.get("n_patches")})
    return rows


def _heldout_results() -> list[Result]:
    out = []
    for row in heldout_comparison():
        for metric, unit in (("cd_l1", "m"), ("cd_l2", "m^2"), ("fscore_0.15", ""), ("ddist_p50", "m"),
                             ("ddist_p95", "m")):
            out.append(Result(AREA, f"{row['seq']} {row['method']} {metric}", row[metric], unit,
                              note=f"{int(row['n_pred'])} points vs {int(row['n_gt'])} lidar"))
    return out


def run(quick: bool = False) -> list[Result]:
    if importlib.util.find_spec("torch") is None:
        return []
    import torch

    torch.manual_seed(0)
    results = _ops_results(quick) + _inference_results(quick)
    if not quick:
        results += _heldout_results()
    return results


def _print_heldout(seqs: tuple[str, ...]) -> None:
    t0 = time.perf_counter()
    rows = heldout_comparison(seqs)
    cols = ("cd_l1", "cd_l2", "fscore_0.15", "ddist_p50", "ddist_p75", "ddist_p90", "ddist_p95", "cd_x", "cd_y",
            "cd_z", "n_pred", "n_gt")
    print("| seq | map | " + " | ".join(cols) + " |")
    print("|" + "---|" * (len(cols) + 2))
    for r in rows:
        print(f"| {r['seq']} | {r['method']} | " + " | ".join(f"{r[c]:.4g}" for c in cols) + " |")
    sp = [r["seconds_per_patch"] for r in rows if r["seconds_per_patch"] is not None]
    print(f"\ncomplete: {rows[-1]['n_patches']} patches, {sp[-1]:.3f} s/patch; total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    args = sys.argv[1:]
    if args and args[0] == "--heldout":
        _print_heldout(tuple(args[1].split(",")) if len(args) > 1 else HELDOUT)
    else:
        for r in run(quick="--quick" in args):
            print(r)
