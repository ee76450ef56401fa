"""Training of the voxel completion model on a published map set:
``pipeline train --model voxel --maps ../shared/data/coloradar_maps --out data/models/rmap_voxel.safetensors``.

- Scenes: only ``split = train`` of the map set's ``index.json``; the validation part is fixed before training
  by :func:`stages.complete.maps.validation_scenes` (in every environment the train scene with the highest
  run number). Test scenes are never read.
- Crops: a random training scene, a random trajectory point (jittered in xy), an xy square of ``crop_xy``
  voxels and ``crop_z`` voxels in height around the point; the loss covers the band voxels of the central
  ``crop_xy - 2 * margin`` square. Augmented with the lattice's symmetries (90-degree rotations about z,
  mirror flips); the per-voxel features are invariant under them, so rotating the arrays rotates the world.
- Loss: weighted BCE (``pos_weight``) + soft Dice over the loss voxels (class imbalance: 3-12 % occupied),
  optionally + a coverage term (:func:`coverage_loss`, ``coverage_weight``): the BCE of each 0.6 m and 1.2 m
  cell's highest prediction against whether the cell holds a lidar voxel, for the regions that squared Chamfer
  distance punishes most: ground truth metres from any predicted voxel.
- Validation (fixed before training): every ``val_every`` steps, the same deterministic crops of the
  validation scenes; the voxel F1 (exact voxel matches) at every threshold of ``THRESHOLDS``; the selected
  checkpoint is the one with the highest F1 (its threshold stored with it).
- Resumable state (``<out>.state.pt``): weights, optimiser, generator, history, elapsed seconds; the
  learning rate follows a cosine over the time budget.
- Devices: ``--device cuda`` trains on a GPU; ``--workers N`` builds the crops in N worker processes (a GPU
  step is faster than one process builds a batch). With workers, worker ``i`` draws from a generator seeded
  by ``(seed, step at the loader's start, i)`` and batches arrive in worker order, so a run is repeatable for
  a given worker count; a resumed run restarts the workers at the step it resumes from.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from pydantic import BaseModel, Field

from core.errors import UserError
from stages.complete.voxel_checkpoint import VoxelMeta, save_voxel_checkpoint
from stages.complete.voxel_grid import (
    F32,
    F64,
    I64,
    Band,
    band_grid,
    lattice_keys,
    occupancy,
    trajectory_band,
    voxel_features,
)
from stages.complete.voxel_net import VoxelNetConfig, VoxelUNet, n_parameters

#: thresholds tried on the validation crops
THRESHOLDS = tuple(round(float(t), 2) for t in np.arange(0.05, 0.951, 0.05))


class VoxelTrainConfig(BaseModel):
    """Training settings of the voxel model (all fixed before training)."""

    resolution: float = Field(0.15, gt=0, description="lattice spacing (m) of the map set")
    crop_xy: int = Field(96, ge=16, description="crop side in x and y (voxels)")
    crop_z: int = Field(64, ge=8, description="crop height (voxels)")
    margin: int = Field(16, ge=0, description="xy border of the crop left out of the loss (voxels)")
    jitter: float = Field(3.0, ge=0, description="xy jitter of the crop centre around the trajectory point (m)")
    batch_size: int = Field(2, ge=1)
    lr: float = Field(1e-3, gt=0)
    weight_decay: float = Field(1e-4, ge=0)
    pos_weight: float = Field(2.0, gt=0, description="BCE weight of occupied voxels")
    dice_weight: float = Field(1.0, ge=0, description="weight of the soft Dice term")
    coverage_weight: float = Field(0.0, ge=0, description="weight of the coverage term (:func:`coverage_loss`): "
                                   "BCE of the max-pooled prediction against the max-pooled label per cell")
    coverage_cells: tuple[int, ...] = Field((4, 8), description="cell sides (voxels) of the coverage term")
    val_every: int = Field(100, ge=1, description="steps between validations")
    workers: int = Field(0, ge=0, description="crop-building worker processes (0: in the training process)")
    val_crops: int = Field(6, ge=1, description="validation crops per validation scene")
    time_limit: float = Field(3600.0, gt=0, description="training seconds (the cosine schedule's length)")
    seed: int = 0
    widths: tuple[int, ...] = (8, 24, 48, 64)
    bottom_convs: int = 2
    bottom_dilation: int = 2


@dataclass
class SceneData:
    """A scene on the lattice: pre-filtered radar keys, lidar keys, the trajectory."""

    name: str
    radar_keys: I64
    lidar_keys: I64
    trajectory: F64


def load_scene(root: Path, name: str, res: float, band: Band) -> SceneData:
    from sources.mapset import read_map_set

    m = read_map_set(root, name)
    return SceneData(name, lattice_keys(trajectory_band(m.radar, m.trajectory, band), res, f"{name} radar map"),
                     lattice_keys(m.lidar_filtered, res, f"{name} lidar map"), m.trajectory)


@dataclass
class Crop:
    features: F32  # (C, X, Y, Z)
    label: F32  # (X, Y, Z)
    mask: F32  # (X, Y, Z): loss voxels


def make_crop(scene: SceneData, centre: F64, cfg: VoxelTrainConfig, band: Band, stride: int) -> Crop:
    """The crop around ``centre`` (x, y, z in m) on the lattice, origin a multiple of ``stride``."""
    res = cfg.resolution
    c = np.floor(np.asarray(centre) / res).astype(np.int64)
    zc = int(np.floor((centre[2] + (band.z_below + band.z_above) / 2) / res))
    lo = np.array([c[0] - cfg.crop_xy // 2, c[1] - cfg.crop_xy // 2, zc - cfg.crop_z // 2])
    lo = (lo // stride) * stride
    shape = (cfg.crop_xy, cfg.crop_xy, cfg.crop_z)
    feats = voxel_features(scene.radar_keys, scene.trajectory, lo, shape, res)
    label = occupancy(scene.lidar_keys, lo, shape)
    mask = band_grid(lo, shape, scene.trajectory, res, band).astype(np.float32)
    m = cfg.margin
    if m:
        mask[:m] = 0
        mask[-m:] = 0
        mask[:, :m] = 0
        mask[:, -m:] = 0
    return Crop(feats, label, mask)


def random_crop(scenes: list[SceneData], rng: np.random.Generator, cfg: VoxelTrainConfig, band: Band,
                stride: int) -> Crop:
    s = scenes[int(rng.integers(len(scenes)))]
    p = s.trajectory[int(rng.integers(len(s.trajectory)))].copy()
    p[:2] += rng.uniform(-cfg.jitter, cfg.jitter, 2)
    return make_crop(s, p, cfg, band, stride)


def augment(crop: Crop, rng: np.random.Generator) -> Crop:
    """A random element of the lattice's xy symmetry group: rotation by k * 90 degrees about z, mirror in x."""
    k = int(rng.integers(4))
    flip = bool(rng.integers(2))

    def t(a: npt.NDArray[np.float32], off: int) -> npt.NDArray[np.float32]:
        a = np.rot90(a, k, axes=(off, off + 1))
        if flip:
            a = np.flip(a, axis=off)
        return np.ascontiguousarray(a)

    return Crop(t(crop.features, 1), t(crop.label, 0), t(crop.mask, 0))


def random_batch(scenes: list[SceneData], rng: np.random.Generator, cfg: VoxelTrainConfig, band: Band,
                 stride: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``cfg.batch_size`` augmented random crops stacked as (features, label, mask) tensors."""
    crops = [augment(random_crop(scenes, rng, cfg, band, stride), rng) for _ in range(cfg.batch_size)]
    return (torch.from_numpy(np.stack([c.features for c in crops])),
            torch.from_numpy(np.stack([c.label for c in crops])), torch.from_numpy(np.stack([c.mask for c in crops])))


class CropStream(torch.utils.data.IterableDataset):
    """Endless random batches for a ``DataLoader`` with workers: worker ``i`` seeds its own generator with
    ``(seed, start_step, i)``."""

    def __init__(self, scenes: list[SceneData], cfg: VoxelTrainConfig, band: Band, stride: int,
                 start_step: int) -> None:
        self.scenes, self.cfg, self.band, self.stride, self.start_step = scenes, cfg, band, stride, start_step

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        info = torch.utils.data.get_worker_info()
        rng = np.random.default_rng([self.cfg.seed, self.start_step, info.id if info else 0])
        while True:
            yield random_batch(self.scenes, rng, self.cfg, self.band, self.stride)


def validation_crops(scenes: list[SceneData], cfg: VoxelTrainConfig, band: Band, stride: int) -> list[Crop]:
    """``val_crops`` crops per validation scene at evenly spaced trajectory points (deterministic)."""
    out = []
    for s in scenes:
        idx = np.linspace(0, len(s.trajectory) - 1, cfg.val_crops + 2)[1:-1].round().astype(int)
        out += [make_crop(s, s.trajectory[i], cfg, band, stride) for i in idx]
    return out


def _masked_bce(logits: torch.Tensor, label: torch.Tensor, mask: torch.Tensor, pos_weight: float) -> torch.Tensor:
    """BCE with occupied voxels weighted ``pos_weight``, summed over ``mask`` and divided by its size."""
    w = mask * (1.0 + (pos_weight - 1.0) * label)
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, label, weight=w, reduction="sum")
    return bce / mask.sum().clamp(min=1.0)


def coverage_loss(logits: torch.Tensor, label: torch.Tensor, mask: torch.Tensor, cells: tuple[int, ...],
                  pos_weight: float) -> torch.Tensor:
    """Mean over ``cells`` of the weighted BCE between each cell's highest logit (over its loss voxels) and
    whether any of its loss voxels is occupied, over the cells that hold a loss voxel.

    The squared Chamfer term from the ground truth to the prediction is paid by whole regions the prediction
    leaves empty (a missed wall 2 m away costs 4 m^2 per voxel), which the per-voxel BCE weighs like any
    single voxel; this term asks for at least one confident voxel in every occupied cell of 0.6 m, 1.2 m
    (``cells`` = 4, 8 voxels) instead. Max-pooling the logits equals max-pooling the probabilities."""
    x = logits.unsqueeze(1).masked_fill(mask.unsqueeze(1) <= 0, -30.0)
    y = (label * mask).unsqueeze(1)
    m = mask.unsqueeze(1)
    total = logits.new_zeros(())
    for c in cells:
        xm, ym, mm = (torch.nn.functional.max_pool3d(a, c, c, ceil_mode=True) for a in (x, y, m))
        total = total + _masked_bce(xm, ym, mm, pos_weight)
    return total / max(len(cells), 1)


def loss_fn(logits: torch.Tensor, label: torch.Tensor, mask: torch.Tensor, pos_weight: float,
            dice_weight: float, coverage_weight: float = 0.0, coverage_cells: tuple[int, ...] = (4, 8)
            ) -> torch.Tensor:
    """Weighted BCE (mean over the loss voxels) + ``dice_weight`` * (1 - soft Dice) over the loss voxels
    (+ ``coverage_weight`` * :func:`coverage_loss`)."""
    bce = _masked_bce(logits, label, mask, pos_weight)
    p = torch.sigmoid(logits) * mask
    inter = (p * label).sum()
    dice = 1.0 - (2.0 * inter + 1.0) / (p.sum() + (label * mask).sum() + 1.0)
    out = bce + dice_weight * dice
    if coverage_weight > 0:
        out = out + coverage_weight * coverage_loss(logits, label, mask, coverage_cells, pos_weight)
    return out


def cfg_loss(logits: torch.Tensor, label: torch.Tensor, mask: torch.Tensor, cfg: VoxelTrainConfig) -> torch.Tensor:
    """:func:`loss_fn` with the weights of ``cfg``."""
    return loss_fn(logits, label, mask, cfg.pos_weight, cfg.dice_weight, cfg.coverage_weight, cfg.coverage_cells)


@torch.no_grad()
def validate(model: VoxelUNet, crops: list[Crop], cfg: VoxelTrainConfig,
             device: torch.device | None = None) -> dict[str, Any]:
    """Validation loss and voxel F1 / precision / recall at every threshold of :data:`THRESHOLDS`."""
    device = device or torch.device("cpu")
    model.eval()
    tp = np.zeros(len(THRESHOLDS))
    fp = np.zeros(len(THRESHOLDS))
    fn = np.zeros(len(THRESHOLDS))
    losses = []
    for c in crops:
        x = torch.from_numpy(c.features)[None].to(device).contiguous(memory_format=torch.channels_last_3d)
        lab, mask = torch.from_numpy(c.label)[None].to(device), torch.from_numpy(c.mask)[None].to(device)
        logit = model(x)
        losses.append(float(cfg_loss(logit, lab, mask, cfg)))
        prob = torch.sigmoid(logit)
        p = prob[0].float().cpu().numpy()[c.mask > 0]
        y = c.label[c.mask > 0] > 0
        for i, t in enumerate(THRESHOLDS):
            pred = p >= t
            tp[i] += np.sum(pred & y)
            fp[i] += np.sum(pred & ~y)
            fn[i] += np.sum(~pred & y)
    prec = tp / np.maximum(tp + fp, 1)
    rec = tp / np.maximum(tp + fn, 1)
    f1 = 2 * prec * rec / np.maximum(prec + rec, 1e-12)
    b = int(np.argmax(f1))
    model.train()
    return {"val_loss": float(np.mean(losses)), "val_f1": float(f1[b]), "val_threshold": THRESHOLDS[b],
            "val_precision": float(prec[b]), "val_recall": float(rec[b]), "val_f1_by_threshold": f1.round(4).tolist()}


def lr_at(cfg: VoxelTrainConfig, elapsed: float) -> float:
    """Cosine decay over the time budget (to 5 % of the base rate)."""
    f = min(max(elapsed / cfg.time_limit, 0.0), 1.0)
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * f)))


def write_curve(path: Path, history: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    steps = [h["step"] for h in history]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].plot(steps, [h["train_loss"] for h in history], label="train (mean since last validation)")
    ax[0].plot(steps, [h["val_loss"] for h in history], label="validation crops")
    ax[0].set_xlabel("step")
    ax[0].set_ylabel("BCE + Dice")
    ax[0].legend()
    ax[1].plot(steps, [h["val_f1"] for h in history], color="C2")
    ax[1].set_xlabel("step")
    ax[1].set_ylabel("validation voxel F1 (best threshold)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _rng_state(rng: np.random.Generator) -> str:
    return json.dumps(rng.bit_generator.state)


def train_voxel(root: Path, out: Path, cfg: VoxelTrainConfig, band: Band, resume: bool = False,
                log: Any = print, device: str | torch.device = "cpu", init: Path | None = None) -> dict[str, Any]:
    """Train, validate, write the selected checkpoint, history and curve; return the summary. ``init``: start
    from that voxel checkpoint's weights (a fresh optimiser and schedule; its config replaces the widths)."""
    from sources.mapset import read_index
    from stages.complete.maps import map_split

    split = map_split(read_index(root))
    res = cfg.resolution
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    init_record: dict[str, Any] | None = None
    if init is not None:
        from stages.complete.voxel_checkpoint import load_voxel_checkpoint

        model, init_meta = load_voxel_checkpoint(init)
        cfg = cfg.model_copy(update={"widths": model.config.widths, "bottom_convs": model.config.bottom_convs,
                                     "bottom_dilation": model.config.bottom_dilation})
        sel = init_meta.train.get("selected", {})
        init_record = {"checkpoint": str(init), "selected_step": sel.get("step"),
                       "elapsed_s": init_meta.train.get("total_elapsed_s", sel.get("elapsed_s")),
                       "device": init_meta.train.get("device", "cpu")}
    else:
        model = VoxelUNet(VoxelNetConfig(widths=cfg.widths, bottom_convs=cfg.bottom_convs,
                                         bottom_dilation=cfg.bottom_dilation))
    dev = torch.device(device)
    model = model.to(dev, memory_format=torch.channels_last_3d)  # type: ignore[call-overload]  # 1.6x faster conv3d
    stride = model.stride()
    if cfg.crop_xy % stride or cfg.crop_z % stride:
        raise UserError(f"crop_xy {cfg.crop_xy} and crop_z {cfg.crop_z} must be multiples of the stride {stride}")
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    state_path = out.with_name(out.name + ".state.pt")
    hist_path = out.with_name(out.stem + "_history.json")
    curve_path = out.with_name(out.stem + "_curve.png")
    history: list[dict[str, Any]] = []
    step, elapsed, best = 0, 0.0, -1.0
    if resume:
        if not state_path.is_file():
            raise UserError(f"{state_path}: no training state to resume from")
        st = torch.load(state_path, weights_only=True, map_location=dev)
        model.load_state_dict(st["model"])
        opt.load_state_dict(st["opt"])
        rng.bit_generator.state = json.loads(st["rng"])
        torch.set_rng_state(st["torch_rng"].cpu())
        history = json.loads(st["history"])
        step, elapsed, best = int(st["step"]), float(st["elapsed"]), float(st["best"])
        log(f"resumed at step {step}, {elapsed:.0f} s elapsed, best validation F1 {best:.4f}")
    log(f"train scenes ({len(split.train)}): {', '.join(split.train)}")
    log(f"validation scenes ({len(split.val)}): {', '.join(split.val)}")
    t_load = time.perf_counter()
    train_scenes = [load_scene(root, s, res, band) for s in split.train]
    val_scenes = [load_scene(root, s, res, band) for s in split.val]
    val = validation_crops(val_scenes, cfg, band, stride)
    log(f"loaded in {time.perf_counter() - t_load:.0f} s; {len(val)} validation crops; model "
        f"{n_parameters(model):,} parameters, receptive radius {model.receptive_radius()} voxels")
    record = {"maps": str(root), "train_scenes": split.train, "val_scenes": split.val,
              "validation_rule": "maps.validation_scenes: per environment the train scene with the highest run "
                                 "number; the checkpoint with the highest validation-crop voxel F1",
              "config": cfg.model_dump(mode="json"), "band": band.__dict__, "command": " ".join(sys.argv),
              "device": str(dev), "parameters": n_parameters(model), "init": init_record}
    model.train()
    losses: list[float] = []
    batches: Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = None
    cuda = dev.type == "cuda"  # pinned host batches, copied without blocking
    if cfg.workers:
        loader = torch.utils.data.DataLoader(CropStream(train_scenes, cfg, band, stride, step), batch_size=None,
                                             num_workers=cfg.workers, prefetch_factor=4, pin_memory=cuda)
        batches = iter(loader)
    t_start = time.perf_counter() - elapsed
    while elapsed < cfg.time_limit:
        for g in opt.param_groups:
            g["lr"] = lr_at(cfg, elapsed)
        xb, lab, mask = next(batches) if batches is not None else random_batch(train_scenes, rng, cfg, band, stride)
        x = xb.to(dev, non_blocking=cuda).contiguous(memory_format=torch.channels_last_3d)
        lab, mask = lab.to(dev, non_blocking=cuda), mask.to(dev, non_blocking=cuda)
        loss = cfg_loss(model(x), lab, mask, cfg)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        step += 1
        elapsed = time.perf_counter() - t_start
        if step % cfg.val_every == 0 or elapsed >= cfg.time_limit:
            v = validate(model, val, cfg, dev)
            elapsed = time.perf_counter() - t_start
            row = {"step": step, "elapsed_s": round(elapsed, 1), "lr": lr_at(cfg, elapsed),
                   "train_loss": float(np.mean(losses)), **v}
            history.append(row)
            losses = []
            improved = v["val_f1"] > best
            if improved:
                best = v["val_f1"]
                prior = float(init_record["elapsed_s"] or 0.0) if init_record else 0.0
                meta = VoxelMeta(model.config, res, v["val_threshold"], band,
                                 train={**record, "selected": row, "history_file": hist_path.name,
                                        "total_elapsed_s": round(prior + row["elapsed_s"], 1)})
                save_voxel_checkpoint(out, model, meta, half=True)
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "rng": _rng_state(rng),
                        "torch_rng": torch.get_rng_state(), "history": json.dumps(history), "step": step,
                        "elapsed": elapsed, "best": best}, state_path.with_suffix(".tmp"))
            state_path.with_suffix(".tmp").replace(state_path)
            hist_path.write_text(json.dumps({"record": record, "history": history}, indent=1))
            write_curve(curve_path, history)
            eta = max(cfg.time_limit - elapsed, 0.0)
            log(f"step {step} {elapsed / 60:.1f} min (ETA {eta / 60:.1f} min) lr {row['lr']:.2e} train "
                f"{row['train_loss']:.4f} val {v['val_loss']:.4f} F1 {v['val_f1']:.4f} @ {v['val_threshold']} "
                f"P {v['val_precision']:.3f} R {v['val_recall']:.3f}{'  * saved' if improved else ''}")
    return {"steps": step, "elapsed_s": elapsed, "best_val_f1": best, "out": str(out), "device": str(dev),
            "crops": step * cfg.batch_size}
