"""``pipeline train``: build the training set from `patches` runs, train, write checkpoint and curve.

Kept apart from ``pipeline/cli.py`` so that the CLI imports torch only when this command runs. ``--set``
overrides apply to every sequence; ``--train-set`` overrides only to the training sequences (e.g.
``patches.a=16``, the paper's a_train, while held-out sequences keep the workflow's a = 4, its a_test).
"""

from __future__ import annotations

import importlib.util
import json
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from pipeline.config import Overrides, Workflow, merge_overrides
from pipeline.errors import UserError
from pipeline.paths import PROJECT_ROOT
from pipeline.sequences import SequenceInfo, expand_sequences, load_registry
from pipeline.stage import Stage
from stages.complete.data import Patch, read_patches, split_by_sequence


@dataclass
class TrainRequest:
    """Everything ``pipeline train`` was asked to do."""

    seqs: str
    test_seqs: str | None
    runs_dir: Path
    registry: dict[str, Stage]
    workflow: Workflow
    overrides: Overrides
    train_overrides: Overrides
    out: Path
    train_kwargs: dict[str, Any]
    threads: int | None = None
    half: bool = False
    #: read the finished `patches` runs as they are instead of bringing them up to date first
    cached_only: bool = False


def _git_commit() -> str:
    try:
        res = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=PROJECT_ROOT, capture_output=True,
                             text=True, timeout=5)
        return res.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def split(req: TrainRequest) -> tuple[list[SequenceInfo], list[SequenceInfo]]:
    """(train, held-out) sequences: ``--test-seqs`` if given ('none' for no held-out set), else RMap's rule."""
    registry = load_registry()
    pool = expand_sequences(req.seqs, registry)
    if req.test_seqs is not None:
        test = [] if req.test_seqs.lower() == "none" else expand_sequences(req.test_seqs, registry)
        test_names = {s.name for s in test}
        train = [s for s in pool if s.name not in test_names]
    else:
        tr_names, te_names = split_by_sequence([(s.name, s.run or s.name) for s in pool])
        train = [s for s in pool if s.name in tr_names]
        test = [s for s in pool if s.name in te_names]
    if not train:
        raise UserError(f"--seqs {req.seqs}: no training sequence left after holding out the test sequences")
    return train, test


def collect(req: TrainRequest, seqs: list[SequenceInfo], overrides: Overrides, console: Console,
            provenance: dict[str, Any]) -> list[Patch]:
    """Bring the `patches` stage of every sequence up to date (unless ``cached_only``) and read its patch pairs."""
    from pipeline.runner import Runner
    from pipeline.store import RunStore

    out: list[Patch] = []
    for info in seqs:
        if req.cached_only:
            store = RunStore(req.runs_dir, info.name)
            manifest = store.read_manifest("patches")
            if manifest is None:
                raise UserError(f"{store.stage_dir('patches')}: no finished patches run; run without --cached-only")
        else:
            runner = Runner(info, req.runs_dir, req.registry, req.workflow, overrides, console)
            runner.run(["patches"])
            store = runner.store
            manifest = store.read_manifest("patches") or {}
        got = read_patches(store.stage_dir("patches") / "patches.parquet", info.name, need_lidar=True)
        params = manifest.get("params", {})
        voxel = store.read_manifest("voxel") or {}
        provenance[info.name] = {"patches_key": manifest.get("key"), "patches_params": params,
                                 "voxel_params": voxel.get("params", {}), "n_patches": len(got)}
        console.print(f"  {info.name}: {len(got)} patches (a = {params.get('a', '?')})")
        out.extend(got)
    return out


def run_training(req: TrainRequest, console: Console) -> dict[str, Any]:
    """The whole ``pipeline train`` command; returns a summary."""
    for mod in ("torch", "safetensors"):
        if importlib.util.find_spec(mod) is None:
            raise UserError(f"`pipeline train` needs {mod}: pip install 'radar-pipeline[learn]'")
    import torch

    from stages.complete.checkpoint import save_checkpoint
    from stages.complete.infer import resolve_device
    from stages.complete.train import TrainConfig, plot_curve, train

    try:
        cfg = TrainConfig(**req.train_kwargs)
        cfg.model_config()
    except (TypeError, ValueError) as exc:
        raise UserError(f"pipeline train: {exc}") from exc
    if req.out.suffix not in (".safetensors", ".pt"):
        raise UserError(f"--out {req.out}: the checkpoint must end in .safetensors or .pt")
    if req.threads is not None:
        torch.set_num_threads(req.threads)
    device = resolve_device(cfg.device)
    train_seqs, test_seqs = split(req)
    train_names = [s.name for s in train_seqs]
    console.print(f"training sequences: {', '.join(train_names)}; "
                  f"held out: {', '.join(s.name for s in test_seqs) or 'none'}")
    provenance: dict[str, Any] = {}
    tr = collect(req, train_seqs, merge_overrides(req.overrides, req.train_overrides), console, provenance)
    te = collect(req, test_seqs, req.overrides, console, provenance) if test_seqs else []
    if not tr:
        raise UserError("the training sequences produced no patches with radar and lidar points")
    record = {
        "train_seqs": [s.name for s in train_seqs],
        "test_seqs": [s.name for s in test_seqs],
        "overrides": req.overrides,
        "train_overrides": req.train_overrides,
        "cached_only": req.cached_only,
        "patches": provenance,
        "command": shlex.join(["pipeline", *sys.argv[1:]]) if sys.argv and "train" in sys.argv else "",
        "git_commit": _git_commit(),
        "threads": torch.get_num_threads(),
    }
    t0 = time.perf_counter()
    with Progress(TextColumn("[bold blue]train[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=True,
                  disable=not console.is_terminal) as prog:
        task = prog.add_task(f"{cfg.size} model, {len(tr)} patches", total=cfg.epochs * len(tr))

        def on_epoch(row: dict[str, Any]) -> None:
            val = f", held-out CD-l1 {row['val_cd_l1_m']:.3f} m" if "val_cd_l1_m" in row else ""
            console.print(f"epoch {row['epoch']:>3}: loss {row['train_loss']:.5f}{val} ({row['seconds']:.0f} s)")

        result = train(tr, te, cfg, device, advance=lambda n: prog.advance(task, n), on_epoch=on_epoch,
                       record=record)
    ckpt = save_checkpoint(req.out, result.model, result.meta, half=req.half)
    curve = plot_curve(result.history, req.out.with_name(req.out.stem + "_curve.png"),
                       title=f"{cfg.size} model on {', '.join(train_names)}")
    hist = req.out.with_name(req.out.stem + "_history.json")
    hist.write_text(json.dumps({"meta": result.meta.train, "history": result.history}, indent=2) + "\n")
    return {
        "checkpoint": str(ckpt),
        "checkpoint_mb": ckpt.stat().st_size / 2**20,
        "curve": str(curve),
        "history": str(hist),
        "n_train_patches": len(tr),
        "n_test_patches": len(te),
        "epochs": len(result.history),
        "seconds": time.perf_counter() - t0,
        "final": result.history[-1] if result.history else {},
    }
