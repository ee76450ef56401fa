"""``pipeline train``: build the training set from `patches` runs or a published map set (``--maps``), train,
write the checkpoint, its curve and history after every epoch, resumable (``--resume``).

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

from core.errors import UserError
from core.paths import PROJECT_ROOT
from core.stage import Stage
from pipeline.config import Overrides, Workflow, merge_overrides
from pipeline.sequences import SequenceInfo, expand_sequences, load_registry
from stages.complete.data import Patch, read_patches, split_by_sequence


@dataclass
class TrainRequest:
    """Everything ``pipeline train`` was asked to do."""

    seqs: str | None
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
    #: a published map set (``<root>/index.json``, ``<root>/<scene>/{radar,lidar_filtered}.parquet``)
    maps: Path | None = None
    a_train: float = 16.0
    a_val: float = 4.0
    #: validation scenes (comma-separated train scenes); None = one per environment (maps.validation_scenes)
    val_scenes: str | None = None
    resume: bool = False
    #: resumable training state; None = ``<out>.state.pt``
    state: Path | None = None


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
    if req.seqs is None:
        raise UserError("pipeline train: give --seqs (patches runs) or --maps (a map set)")
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


def _check_env(req: TrainRequest) -> None:
    for mod in ("torch", "safetensors"):
        if importlib.util.find_spec(mod) is None:
            raise UserError(f"`pipeline train` needs {mod}, not installed (the 'learn' extra: pip install -e "
                            "'.[learn]', or make demo)")
    if req.out.suffix not in (".safetensors", ".pt"):
        raise UserError(f"--out {req.out}: the checkpoint must end in .safetensors or .pt")


def collect_maps(req: TrainRequest, console: Console) -> tuple[list[Patch], dict[str, Any], dict[str, Any]]:
    """Training patches (a_train) of the map set's train scenes, the validation scenes (patches at a_val and
    their ground truth) and the split record. Test scenes are not read."""
    from sources.mapset import read_index
    from stages.complete.maps import map_split, read_scene, scene_patches

    assert req.maps is not None
    scenes = read_index(req.maps)
    val = None if req.val_scenes is None else [v.strip() for v in req.val_scenes.split(",") if v.strip()]
    sp = map_split(scenes, val)
    if not sp.train:
        raise UserError(f"--maps {req.maps}: no train scene left after taking out the validation scenes")
    seed = int(req.train_kwargs.get("seed", 0))
    train: list[Patch] = []
    counts: dict[str, int] = {}
    for name in sp.train:
        radar, gt = read_scene(req.maps, name)
        got = scene_patches(radar, gt, name, req.a_train, seed)
        counts[name] = len(got)
        train.extend(got)
    console.print(f"train scenes ({len(sp.train)}): {len(train)} patches at a = {req.a_train:g}")
    val_data: dict[str, Any] = {}
    for name in sp.val:
        radar, gt = read_scene(req.maps, name)
        val_data[name] = (scene_patches(radar, gt, name, req.a_val, seed), gt, radar)
        counts[name] = len(val_data[name][0])
    console.print(f"validation scenes ({len(sp.val)}): {', '.join(sp.val)}; "
                  f"{sum(len(v[0]) for v in val_data.values())} patches at a = {req.a_val:g}")
    record = {
        "maps": str(req.maps), "train_scenes": sp.train, "val_scenes": sp.val,
        "val_rule": "given" if val is not None else "per environment the train scene with the highest run number",
        "test_scenes_not_used": sp.test, "a_train": req.a_train, "a_val": req.a_val, "patch_counts": counts,
        "ground_truth": "lidar_filtered",
        "gt_rebuilt": sorted(n for n in sp.train + sp.val if scenes[n].gt_source != "map"),
    }
    return train, val_data, record


def run_training(req: TrainRequest, console: Console) -> dict[str, Any]:
    """The whole ``pipeline train`` command; returns a summary."""
    _check_env(req)
    import torch

    from stages.complete.checkpoint import save_checkpoint
    from stages.complete.infer import resolve_device
    from stages.complete.train import Selection, TrainConfig, TrainResult, Validator, plot_curve, train

    try:
        cfg = TrainConfig(**req.train_kwargs)
        cfg.model_config()
    except (TypeError, ValueError) as exc:
        raise UserError(f"pipeline train: {exc}") from exc
    if req.threads is not None:
        torch.set_num_threads(req.threads)
    device = resolve_device(cfg.device)
    state_path = req.state or req.out.with_name(req.out.name + ".state.pt")
    if req.resume and not state_path.exists():
        raise UserError(f"{state_path}: no training state to resume from; start without --resume")
    record: dict[str, Any] = {}
    validator: Validator | None = None
    select: Selection | None = None
    te: list[Patch] = []
    if req.maps is not None:
        tr, val_data, record = collect_maps(req, console)
        validator = _map_validator(val_data, device)
        select = Selection("val_map_cd_l2")
        title = f"{cfg.size} model on {len(record['train_scenes'])} map scenes"
    else:
        train_seqs, test_seqs = split(req)
        train_names = [s.name for s in train_seqs]
        console.print(f"training sequences: {', '.join(train_names)}; "
                      f"held out: {', '.join(s.name for s in test_seqs) or 'none'}")
        provenance: dict[str, Any] = {}
        tr = collect(req, train_seqs, merge_overrides(req.overrides, req.train_overrides), console, provenance)
        te = collect(req, test_seqs, req.overrides, console, provenance) if test_seqs else []
        record = {
            "train_seqs": [s.name for s in train_seqs],
            "test_seqs": [s.name for s in test_seqs],
            "overrides": req.overrides,
            "train_overrides": req.train_overrides,
            "cached_only": req.cached_only,
            "patches": provenance,
        }
        title = f"{cfg.size} model on {', '.join(train_names)}"
    if not tr:
        raise UserError("the training data produced no patches with radar and lidar points")
    record.update({
        "command": shlex.join(["pipeline", *sys.argv[1:]]) if sys.argv and "train" in sys.argv else "",
        "git_commit": _git_commit(),
        "threads": torch.get_num_threads(),
    })
    curve_path = req.out.with_name(req.out.stem + "_curve.png")
    hist_path = req.out.with_name(req.out.stem + "_history.json")
    written: dict[str, Any] = {}

    def on_checkpoint(res: TrainResult, improved: bool) -> None:
        # the selected (or last) model whenever it changes, the history and the curve after every epoch
        if select is None or improved or not req.out.exists():
            save_checkpoint(req.out, res.model, res.meta, half=req.half)
            written["epoch"] = res.epoch
        _write_json(hist_path, {"meta": res.meta.train, "history": res.history})
        plot_curve(res.history, curve_path, title=title)

    t0 = time.perf_counter()
    n_step = min(len(tr), cfg.patches_per_epoch or len(tr))
    with Progress(TextColumn("[bold blue]train[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=True,
                  disable=not console.is_terminal) as prog:
        task = prog.add_task(f"{cfg.size} model, {len(tr)} patches ({n_step} an epoch)", total=cfg.epochs * n_step)
        if req.resume:
            prog.update(task, completed=min(_epochs_done(state_path), cfg.epochs) * n_step)

        def on_epoch(row: dict[str, Any]) -> None:
            val = f", held-out CD-l1 {row['val_cd_l1_m']:.3f} m" if "val_cd_l1_m" in row else ""
            if "val_map_cd_l2" in row:
                val += (f", val map CD-l1 {row['val_map_cd_l1']:.3f} CD-l2 {row['val_map_cd_l2']:.3f} "
                        f"F {row['val_map_fscore_0.15']:.3f}")
            console.print(f"epoch {row['epoch']:>3}: loss {row['train_loss']:.5f}{val} ({row['seconds']:.0f} s)")

        seen = {"n": 0, "t0": time.perf_counter()}
        every = max(1, n_step // 10)

        def advance(n: int) -> None:
            prog.advance(task, n)
            if console.is_terminal:
                return
            # a log file gets a line every tenth of an epoch instead of the bar
            before, seen["n"] = seen["n"], seen["n"] + n
            if before // every != seen["n"] // every:
                console.print(f"  {seen['n'] % n_step or n_step}/{n_step} patches of this epoch, "
                              f"{time.perf_counter() - seen['t0']:.0f} s since start")

        result = train(tr, te, cfg, device, advance=advance, on_epoch=on_epoch,
                       record=record, state_path=state_path, resume=req.resume, validator=validator,
                       select=select, on_checkpoint=on_checkpoint)
    ckpt = save_checkpoint(req.out, result.model, result.meta, half=req.half)
    curve = plot_curve(result.history, curve_path, title=title)
    _write_json(hist_path, {"meta": result.meta.train, "history": result.history})
    return {
        "checkpoint": str(ckpt),
        "checkpoint_mb": ckpt.stat().st_size / 2**20,
        "curve": str(curve),
        "history": str(hist_path),
        "state": str(state_path),
        "n_train_patches": len(tr),
        "n_test_patches": len(te),
        "epochs": len(result.history),
        "checkpoint_epoch": result.epoch,
        "stopped_early": bool(result.meta.train.get("stopped_early")),
        "seconds": time.perf_counter() - t0,
        "final": result.history[-1] if result.history else {},
    }


def _epochs_done(state_path: Path) -> int:
    from stages.complete.train import load_state

    return len(load_state(state_path)["history"])


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(obj, indent=2) + "\n")
    tmp.replace(path)


def _map_validator(val_data: dict[str, Any], device: Any) -> Any:
    """Map-level validation: complete every validation scene, score it, average the scene rows."""
    from stages.complete.checkpoint import CheckpointMeta
    from stages.complete.map_eval import complete_map, mean_rows, score
    from stages.complete.model import UpPoinTr

    def validate(model: UpPoinTr, scale: float) -> dict[str, float]:
        meta = CheckpointMeta(model.cfg, scale)
        rows = []
        for patches, gt, _ in val_data.values():
            pred, _ = complete_map(model, meta, patches, device)
            rows.append(score(pred, gt))
        return {f"map_{k}": v for k, v in mean_rows(rows).items()}

    return validate


@dataclass
class VoxelTrainRequest:
    """``pipeline train --model voxel``: the voxel U-Net on a published map set's train scenes."""

    maps: Path
    out: Path
    #: VoxelTrainConfig fields (time_limit, seed, batch_size, lr, jitter, coverage_weight, ...)
    config: dict[str, Any]
    device: str = "auto"
    threads: int | None = None
    resume: bool = False
    init: Path | None = None


def parse_options(options: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` pairs (VALUE as JSON, else a string; ``a,b,c`` of integers as a tuple)."""
    out: dict[str, Any] = {}
    for item in options:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise UserError(f"--option {item!r}: expected KEY=VALUE, e.g. --option jitter=4.5")
        try:
            value: Any = json.loads(raw)
        except json.JSONDecodeError:
            value = tuple(int(v) for v in raw.split(",")) if raw.replace(",", "").isdigit() else raw
        out[key.strip().replace("-", "_")] = value
    return out


def run_voxel_training(req: VoxelTrainRequest, console: Console) -> dict[str, Any]:
    """Validate the settings, train (resumable), return the summary of :func:`train_voxel`."""
    import torch
    from pydantic import ValidationError

    from stages.complete.train_voxel import VoxelTrainConfig, train_voxel
    from stages.complete.voxel_grid import Band

    unknown = sorted(set(req.config) - set(VoxelTrainConfig.model_fields))
    if unknown:
        raise UserError(f"--option {unknown[0]}: not a voxel training setting; choose from "
                        f"{', '.join(VoxelTrainConfig.model_fields)}")
    try:
        cfg = VoxelTrainConfig(**req.config)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise UserError(f"--option {'.'.join(map(str, err['loc']))}: {err['msg']}") from None
    device = req.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"--device {device}: torch sees no CUDA device here; use --device cpu")
    if not (req.maps / "index.json").is_file():
        raise UserError(f"--maps {req.maps}: no index.json there; give a map set folder "
                        "(index.json + <scene>/{radar,lidar_filtered}.parquet)")
    torch.set_num_threads(req.threads or 1)
    req.out.parent.mkdir(parents=True, exist_ok=True)
    return train_voxel(req.maps, req.out, cfg, Band(), req.resume, log=console.log, device=device, init=req.init)
