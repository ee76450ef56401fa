"""Completion network: torch point ops against references, inference seconds per patch, and (full mode)
the held-out map comparison of RMap Table III on a simulated sequence.

- Chamfer (8192 x 8192, one patch): the torch brute-force backend and the cKDTree backend against
  scipy's ``cKDTree`` on both directions (the reference), same inputs, same run;
- FPS (8192 -> 2048): the torch loop against ``fpsample`` (reference);
- inference s/patch on this machine's CPU for the shipped small checkpoint (else a random small model)
  and the paper size (random weights; quick mode: batch 1 only); batch 1 and 8, best of ``repeat``; each
  as a ratio to a reference measured in the same run with the same torch threads: one float32
  2048 x 2048 matrix product (``torch.mm``), so that the ratio follows the model, not the machine's load;
- full mode: `complete` on the held-out sequence(s) with the shipped checkpoint, input radar map and
  completed map each scored against the lidar map (``core.map_metrics``).

``python -m benchmarks.bench_complete --heldout sim_hallway_loop [--runs-dir DIR] [--cached-only]`` prints
only the held-out comparison (as a markdown table).
Needs torch (the ``learn`` extra); without it the benchmark returns nothing.
"""

from __future__ import annotations

import importlib.util
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import Result, best_time

AREA = "complete"
#: torch threads of the 18-scene voxel inference (the target runs on 2 CPU cores)
INFERENCE_THREADS = 2
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
    a = torch.randn(2048, 2048, generator=torch.Generator().manual_seed(0))
    torch.mm(a, a)
    t_ref = best_time(partial(torch.mm, a, a), 5)
    ref = f"torch.mm 2048x2048 float32 ({t_ref * 1e3:.1f} ms)"
    x = torch.from_numpy(np.stack([p.radar for p in make_patches(8, seed=0)])).float()
    for size in ("small", "paper"):
        model, _, what = _model(size)
        for batch in (1,) if quick and size == "paper" else (1, 8):
            xb = x[:batch]
            with torch.no_grad():
                model(xb)  # warm-up
                t = best_time(partial(model, xb), 2 if quick or size == "paper" else 3)
            out.append(Result(AREA, f"inference {size} batch {batch} (CPU, {torch.get_num_threads()} threads)",
                              t / batch, "s/patch", ref, t / batch / t_ref,
                              note=f"{what}, {count_parameters(model) / 1e6:.2f} M parameters, 2048 -> 8192"))
    return out


def _voxel_results(quick: bool) -> list[Result]:
    """The voxel model: one tile's forward pass in Mvoxel/s and, in full mode with the shared map set
    present, the whole-map inference of the 18 present Table III test scenes on :data:`INFERENCE_THREADS`
    threads (target: < 56 s, the paper's GPU time for 1262 patches; the note gives the ratio to it), each as a
    ratio to a same-run ``torch.mm`` reference (for the scenes: at the same threads, before and after)."""
    import os

    import torch

    from stages.complete.stage import VOXEL_CHECKPOINT, resolve_checkpoint
    from stages.complete.voxel_net import VoxelUNet, n_parameters

    path = resolve_checkpoint(VOXEL_CHECKPOINT)
    if path.exists():
        from stages.complete.voxel_checkpoint import load_voxel_checkpoint

        model, _ = load_voxel_checkpoint(path)
        what = "shipped checkpoint"
    else:
        model, what = VoxelUNet().eval(), "random weights"
        model = model.to(memory_format=torch.channels_last_3d)  # type: ignore[call-overload]  # as the loader does
    a = torch.randn(2048, 2048, generator=torch.Generator().manual_seed(0))
    torch.mm(a, a)
    t_mm = best_time(partial(torch.mm, a, a), 5)
    ref = f"torch.mm 2048x2048 float32 ({2 * 2048**3 / t_mm / 1e9:.1f} GFLOP/s)"
    halo = model.receptive_radius() + (-model.receptive_radius()) % model.stride()
    side = 128 + 2 * halo
    x = torch.zeros(1, 5, side, side, 64).contiguous(memory_format=torch.channels_last_3d)
    from stages.complete.voxel_net import reuse_freed_memory

    with torch.no_grad(), reuse_freed_memory():  # as predict_tiles runs it
        model(x)
        t = best_time(partial(model, x), 1 if quick else 2)
    mvox = side * side * 64 / t / 1e6
    out = [Result(AREA, f"voxel model forward {side}x{side}x64 (CPU, {torch.get_num_threads()} threads)", mvox,
                  "Mvoxel/s", ref, t / t_mm, note=f"{what}, {n_parameters(model) / 1e6:.2f} M parameters, freed "
                  "memory reused as in predict_tiles; ratio = seconds per tile / seconds per torch.mm")]
    root = Path(os.environ.get("RMAP_ROOT", "../shared/data/coloradar_maps"))
    if not quick and path.exists() and (root / "index.json").is_file():
        from experiments.rmap_voxel_table3 import PAPER_SECONDS, mm_gflops, output_row, run_table
        from stages.complete.voxel_grid import Band

        threads = torch.get_num_threads()
        torch.set_num_threads(INFERENCE_THREADS)  # the target's 2 cores
        try:
            gf = mm_gflops()  # the same-run reference at these threads, before and after the 18 scenes
            table = run_table(root, "test", path, Band(), log=lambda *_: None)
            gf_after = mm_gflops()
        finally:
            torch.set_num_threads(threads)
        secs = table["inference_seconds"]
        mm_s = 2 * 2048**3 / (gf * 1e9)  # seconds of one 2048^2 torch.mm at the rate before the scenes
        row = output_row(table)
        o = table["overall"][row]
        out.append(Result(
            AREA, f"voxel model, {len(table['scenes'])} test scenes whole-map inference ({INFERENCE_THREADS} threads)",
            secs, "s", f"torch.mm 2048x2048 float32 at {INFERENCE_THREADS} threads ({gf:.1f} GFLOP/s before, "
            f"{gf_after:.1f} after)", secs / mm_s, target=f"< {PAPER_SECONDS:g} s (RMap: 1262 patches on an RTX 6000)",
            note=f"{secs / PAPER_SECONDS:.2f}x the paper's {PAPER_SECONDS:g} s; {table['voxels_run'] / 1e6:.1f} M "
                 f"voxels run; features {table['feature_seconds']:.1f} s, network {table['model_seconds']:.1f} s; "
                 f"Overall CD-l1 {o['cd_l1']:.3f}, CD-l2 {o['cd_l2']:.3f}, F exact {o['fscore_0.15']:.3f} "
                 f"(the checkpoint's output: {row}); "
                 "ratio = seconds / seconds per torch.mm"))
    return out


def _run_complete_on_existing(store: Any, params: dict[str, Any], out_dir: Path) -> dict[str, Any]:
    """The `complete` stage on a run store's finished `patches` and `voxel` folders, without the runner."""
    from rich.console import Console

    from core.stage import StageContext
    from pipeline.sequences import get_sequence
    from stages.complete.stage import STAGE

    for stage in ("patches", "voxel"):
        if store.read_manifest(stage) is None:
            raise RuntimeError(f"{store.stage_dir(stage)}: no finished run")
    out_dir.mkdir(parents=True, exist_ok=True)
    ctx = StageContext(stage="complete", seq=get_sequence(store.seq), params=STAGE.Params(**params), out_dir=out_dir,
                       input_dirs={s: store.stage_dir(s) for s in ("patches", "voxel")},
                       console=Console(stderr=True))
    try:
        STAGE.run(ctx)
    finally:
        ctx.close()
    return ctx.stats


def heldout_comparison(seqs: tuple[str, ...] = HELDOUT, runs_dir: Path | None = None,
                       overrides: dict[str, dict[str, Any]] | None = None,
                       cached_only: bool = False) -> list[dict[str, Any]]:
    """Run `complete` on ``seqs`` and score the input radar map and the completed map against the lidar map.

    ``cached_only``: use the run store's finished `voxel` and `patches` results as they are (the stage runs
    on them directly and writes into ``<seq>/complete_heldout/``) instead of bringing them up to date.
    """
    import json

    from rich.console import Console

    from core.map_metrics import map_metrics
    from core.paths import default_runs_dir
    from pipeline.config import load_workflow
    from pipeline.registry import load_stages
    from pipeline.runner import Runner
    from pipeline.sequences import get_sequence
    from pipeline.store import RunStore
    from schemas import read_artifact

    def cloud(path: Path, schema: str) -> np.ndarray:
        t = read_artifact(path, schema, columns=["x", "y", "z"])
        return np.stack([t.column(c).to_numpy().astype(np.float64) for c in "xyz"], axis=1)

    rows = []
    runs = runs_dir or default_runs_dir()
    for name in seqs:
        if cached_only:
            store = RunStore(Path(runs), name)
            out_dir = store.seq_dir / "complete_heldout"
            stats = _run_complete_on_existing(store, (overrides or {}).get("complete", {}), out_dir)
        else:
            runner = Runner(get_sequence(name), runs, load_stages(), load_workflow("default"), overrides or {},
                            Console(stderr=True))
            runner.run(["complete"])
            store = runner.store
            out_dir = store.stage_dir("complete")
            stats = json.loads((out_dir / "manifest.json").read_text()).get("stats", {})
        lidar = cloud(store.stage_dir("voxel") / "lidar_map.parquet", "lidar_map")
        radar = cloud(store.stage_dir("voxel") / "radar_map.parquet", "radar_map")
        done = cloud(out_dir / "completed_map.parquet", "completed_map")
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
    results = _ops_results(quick) + _inference_results(quick) + _voxel_results(quick)
    if not quick:
        results += _heldout_results()
    return results


def _print_heldout(seqs: tuple[str, ...], runs_dir: Path | None, cached_only: bool,
                   checkpoint: str | None = None) -> None:
    t0 = time.perf_counter()
    overrides = {"complete": {"checkpoint": checkpoint}} if checkpoint else None
    rows = heldout_comparison(seqs, runs_dir, overrides, cached_only=cached_only)
    cols = ("cd_l1", "cd_l2", "fscore_0.15", "ddist_p50", "ddist_p75", "ddist_p90", "ddist_p95", "cd_x", "cd_y",
            "cd_z", "n_pred", "n_gt")
    print("| seq | map | " + " | ".join(cols) + " |")
    print("|" + "---|" * (len(cols) + 2))
    for r in rows:
        print(f"| {r['seq']} | {r['method']} | " + " | ".join(f"{r[c]:.4g}" for c in cols) + " |")
    sp = [r["seconds_per_patch"] for r in rows if r["seconds_per_patch"] is not None]
    print(f"\ncomplete: {rows[-1]['n_patches']} patches, {sp[-1]:.3f} s/patch; total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heldout", help="comma-separated held-out sequences: print only their map comparison")
    ap.add_argument("--runs-dir", type=Path, default=None)
    ap.add_argument("--cached-only", action="store_true", help="use the finished voxel/patches runs as they are")
    ap.add_argument("--checkpoint", help="checkpoint for the held-out comparison (default: complete.checkpoint)")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    if args.heldout:
        _print_heldout(tuple(args.heldout.split(",")), args.runs_dir, args.cached_only, args.checkpoint)
    else:
        for r in run(quick=args.quick):
            print(r)
