"""Training the completion network on patch pairs (RMap Sec. III-D): Chamfer at every level (eq. 1-2),
AdamW with the paper's settings as defaults, a training-curve figure.

The ground truth of level i is the lidar patch downsampled by FPS to that level's size (eq. 1). Training
draws every random number from seeded generators (numpy for resampling and augmentation, torch for the
weights and batch order), so a run is repeatable on the same device and thread count.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from stages.complete.checkpoint import CheckpointMeta
from stages.complete.data import Patch, crop_target, normalize, patch_scale, resample
from stages.complete.infer import prepare_inputs
from stages.complete.model import SIZES, ModelConfig, UpPoinTr, count_parameters
from stages.complete.ops import chamfer_l1, chamfer_l2, fps, gather_points


@dataclass(frozen=True)
class TrainConfig:
    """Training settings; the defaults are the paper's (AdamW, lr 1e-5, wd 5e-5, batch 16, 100 epochs,
    lr x0.9 every 20 epochs)."""

    size: str = "small"
    epochs: int = 100
    batch_size: int = 16
    lr: float = 1e-5
    weight_decay: float = 5e-5
    lr_decay: float = 0.9
    decay_every: int = 20
    grad_clip: float = 10.0
    loss: Literal["l2", "l1"] = "l2"
    augment: bool = True
    seed: int = 0
    device: str = "cpu"
    norm_scale: float | None = None
    crop_target: bool = True
    time_limit_s: float | None = None
    #: training patches per epoch, a seeded random subset drawn anew every epoch (None = all)
    patches_per_epoch: int | None = None
    #: checkpoint whose weights start the run (fine-tuning; same model config), None = random weights
    init: str | None = None

    def model_config(self) -> ModelConfig:
        if self.size not in SIZES:
            raise ValueError(f"unknown model size {self.size!r} ({' | '.join(SIZES)})")
        return SIZES[self.size]


@dataclass
class PatchTensors:
    """Normalised inputs ``x (P, n_input, 3)``, targets ``g (P, n_output, 3)`` and the FPS order of ``g``."""

    x: Tensor
    g: Tensor
    #: FPS indices of every target, ``(P, max level size below n_output)``; prefixes give each level's G_i
    fps_idx: Tensor

    def __len__(self) -> int:
        return int(self.x.shape[0])


def build_tensors(patches: Sequence[Patch], cfg: ModelConfig, scale: float, rng: np.random.Generator) -> PatchTensors:
    """Inputs resampled to ``n_input``, targets to ``n_output`` points, normalised by seed and ``scale``."""
    x = prepare_inputs(patches, cfg.n_input, scale, rng)
    g = np.stack([normalize(resample(p.lidar, cfg.n_output, rng), p.seed, scale).astype(np.float32)
                  for p in patches]) if patches else np.zeros((0, cfg.n_output, 3), np.float32)
    gt = torch.from_numpy(g)
    below = [s for s in cfg.level_sizes() if s < cfg.n_output]
    n_fps = max(below) if below else 1
    # FPS is greedy from a fixed start, so the first n samples of a longer run are FPS(G, n) for every n
    idx = torch.cat([fps(gt[s : s + 64], n_fps) for s in range(0, len(gt), 64)]) if len(gt) else torch.zeros(0, n_fps)
    return PatchTensors(torch.from_numpy(x).float(), gt, idx.long())


def level_targets(g: Tensor, fps_idx: Tensor, sizes: Sequence[int]) -> list[Tensor]:
    """G_i for every level: the target itself at full size, else its first ``size`` FPS samples."""
    return [g if s >= g.shape[1] else gather_points(g, fps_idx[:, :s]) for s in sizes]


def random_rotation_z(n: int, rng: np.random.Generator, mirror: bool = True) -> Tensor:
    """``n`` random rotations about the vertical axis, each mirrored in y with probability 1/2."""
    a = rng.uniform(0.0, 2.0 * math.pi, n)
    c, s = np.cos(a), np.sin(a)
    r = np.zeros((n, 3, 3))
    r[:, 0, 0], r[:, 0, 1], r[:, 1, 0], r[:, 1, 1], r[:, 2, 2] = c, -s, s, c, 1.0
    if mirror:
        flip = rng.random(n) < 0.5
        r[flip, :, 1] *= -1.0
    return torch.from_numpy(r).float()


def level_losses(pred: Sequence[Tensor], targets: Sequence[Tensor], loss: str) -> list[Tensor]:
    """CD_i of every level, each averaged over the batch (eq. 1)."""
    fn = chamfer_l2 if loss == "l2" else chamfer_l1
    return [fn(p, t).mean() for p, t in zip(pred, targets, strict=True)]


@torch.no_grad()
def evaluate(model: UpPoinTr, data: PatchTensors, scale: float, device: torch.device,
             batch_size: int = 8) -> dict[str, float]:
    """Patch-level CD-l1 (m) and CD-l2 (m^2) of the finest level against the full target."""
    model.eval()
    l1, l2 = [], []
    for s in range(0, len(data), batch_size):
        pred = model(data.x[s : s + batch_size].to(device))[-1]
        g = data.g[s : s + batch_size].to(device)
        l1.append(chamfer_l1(pred, g).cpu() * scale)
        l2.append(chamfer_l2(pred, g).cpu() * scale**2)
    if not l1:
        return {}
    return {"cd_l1_m": float(torch.cat(l1).mean()), "cd_l2_m2": float(torch.cat(l2).mean())}


@dataclass
class TrainResult:
    model: UpPoinTr
    meta: CheckpointMeta
    history: list[dict[str, Any]] = field(default_factory=list)
    #: epoch whose weights ``model`` holds (the last one, or the best on ``select`` when given)
    epoch: int = 0


#: a function scoring the model on the validation data after an epoch: ``(model, norm_scale) -> metrics``
Validator = Callable[[UpPoinTr, float], dict[str, float]]


@dataclass
class Selection:
    """Pick the epoch whose validation metric ``key`` (a key of the epoch rows) is lowest."""

    key: str

    def better(self, value: float, best: float | None) -> bool:
        return math.isfinite(value) and (best is None or value < best)


STATE_VERSION = 1


def _state_dict_copy(model: UpPoinTr) -> dict[str, Tensor]:
    return {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}


def save_state(path: Path, state: dict[str, Any]) -> None:
    """The resumable training state (``torch.save``, written to a temp file and renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def load_state(path: Path) -> dict[str, Any]:
    """A state written by :func:`save_state`; a one-line error when it is not one."""
    from core.errors import UserError

    if not path.exists():
        raise UserError(f"{path}: no training state to resume from; start without --resume")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any unreadable file is the same user error
        raise UserError(f"{path}: not a readable training state ({type(exc).__name__}); delete it or start "
                        "without --resume") from exc
    if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
        raise UserError(f"{path}: not a training state of version {STATE_VERSION}; start without --resume")
    return state


def _resume_compatible(state: dict[str, Any], cfg: TrainConfig, n_train: int, path: Path) -> None:
    from core.errors import UserError

    old = dict(state["config"])
    new = asdict(cfg)
    # what may change between resumed runs: the epoch budget, the time limit and the device
    for k in ("epochs", "time_limit_s", "device"):
        old.pop(k, None)
        new.pop(k, None)
    diff = sorted(k for k in new if old.get(k) != new[k])
    if diff:
        raise UserError(f"{path}: the saved run used other settings ({', '.join(diff)}); resume with the same "
                        "settings or start a new run")
    if state["n_train_patches"] != n_train:
        raise UserError(f"{path}: the saved run had {state['n_train_patches']} training patches, this data has "
                        f"{n_train}; resume on the same data")


def _load_init(model: UpPoinTr, path: Path) -> None:
    """Start from the weights of the checkpoint at ``path`` (its model config must be the run's)."""
    from core.errors import UserError
    from stages.complete.checkpoint import load_checkpoint

    init, meta = load_checkpoint(path)
    if meta.config != model.cfg:
        raise UserError(f"--init {path}: its model config is not the one of --size; pick the matching size")
    model.load_state_dict(init.state_dict())


def train(
    train_patches: Sequence[Patch],
    val_patches: Sequence[Patch],
    cfg: TrainConfig,
    device: torch.device,
    advance: Callable[[int], None] | None = None,
    on_epoch: Callable[[dict[str, Any]], None] | None = None,
    record: dict[str, Any] | None = None,
    state_path: Path | None = None,
    resume: bool = False,
    validator: Validator | None = None,
    select: Selection | None = None,
    on_checkpoint: Callable[[TrainResult, bool], None] | None = None,
) -> TrainResult:
    """Train (from scratch, or from ``state_path`` when ``resume``); returns the final or the selected model.

    After every epoch the full state (weights, optimiser, scheduler, generators, history) goes to
    ``state_path`` so that ``resume`` continues exactly where the run stopped: on the same device and thread
    count a resumed run equals an uninterrupted one. ``validator`` adds map-level validation metrics to
    every epoch row; with ``select`` the returned model is the epoch with the lowest ``select.key`` (the
    choice is made on validation data only). ``on_checkpoint(result, improved)`` runs after every epoch.
    ``cfg.patches_per_epoch`` draws a seeded random subset of the training patches for every epoch.
    ``cfg.time_limit_s`` counts this run's time: the run stops after the epoch that passes it.
    """
    if not train_patches:
        raise ValueError("no training patches")
    mcfg = cfg.model_config()
    torch.manual_seed(cfg.seed)
    if cfg.crop_target:
        train_patches = [crop_target(p) for p in train_patches]
        val_patches = [crop_target(p) for p in val_patches]
    scale = cfg.norm_scale or patch_scale(train_patches)
    t_prep = time.perf_counter()
    tr = build_tensors(train_patches, mcfg, scale, np.random.default_rng(cfg.seed))
    va = build_tensors(val_patches, mcfg, scale, np.random.default_rng(cfg.seed + 1)) if val_patches else None
    prep_s = time.perf_counter() - t_prep
    rng = np.random.default_rng([cfg.seed, 1])  # batch order, subsets, augmentation
    torch.manual_seed(cfg.seed)
    model = UpPoinTr(mcfg).to(device)
    if cfg.init is not None and not resume:
        _load_init(model, Path(cfg.init))
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: cfg.lr_decay ** (e // cfg.decay_every))
    sizes = mcfg.level_sizes()
    history: list[dict[str, Any]] = []
    best: dict[str, Any] = {"epoch": 0, "value": None, "weights": None}
    seconds_before = 0.0
    if resume:
        if state_path is None:
            raise ValueError("resume needs a state path")
        state = load_state(state_path)
        _resume_compatible(state, cfg, len(tr), state_path)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        rng.bit_generator.state = state["numpy_rng"]
        torch.set_rng_state(state["torch_rng"])
        history = list(state["history"])
        best = dict(state["best"])
        seconds_before = float(state["train_seconds"])
        scale = float(state["norm_scale"])
    n_step = min(len(tr), cfg.patches_per_epoch or len(tr))
    t0 = time.perf_counter()
    stopped_early = False

    def result(final: bool) -> TrainResult:
        info = {
            "config": asdict(cfg),
            "n_parameters": count_parameters(model),
            "n_train_patches": len(tr),
            "patches_per_epoch": n_step,
            "n_val_patches": len(va) if va is not None else 0,
            "epochs_run": len(history),
            "stopped_early": stopped_early,
            "prep_seconds": prep_s,
            "train_seconds": seconds_before + time.perf_counter() - t0,
            "device": str(device),
            "torch": torch.__version__,
            "final": history[-1] if history else {},
            "selection": ({"key": select.key, "rule": "lowest on the validation data", "epoch": best["epoch"],
                           "value": best["value"]} if select is not None else None),
            **(record or {}),
        }
        out = UpPoinTr(mcfg)
        if select is not None and best["weights"] is not None:
            out.load_state_dict(best["weights"])
            epoch = int(best["epoch"])
        else:
            out.load_state_dict(_state_dict_copy(model))
            epoch = len(history)
        return TrainResult(out.eval(), CheckpointMeta(mcfg, scale, info), list(history), epoch)

    for epoch in range(len(history), cfg.epochs):
        model.train()
        te = time.perf_counter()
        order = torch.from_numpy(rng.permutation(len(tr))[:n_step])
        sums = np.zeros(len(sizes))
        n_batches = 0
        for s in range(0, n_step, cfg.batch_size):
            idx = order[s : s + cfg.batch_size]
            x, g = tr.x[idx], tr.g[idx]
            if cfg.augment:
                rot = random_rotation_z(len(idx), rng)
                x, g = x @ rot.transpose(1, 2), g @ rot.transpose(1, 2)
            x, g = x.to(device), g.to(device)
            targets = level_targets(g, tr.fps_idx[idx].to(device), sizes)
            losses = level_losses(model(x), targets, cfg.loss)
            total = torch.stack(losses).sum()  # eq. 2
            opt.zero_grad(set_to_none=True)
            total.backward()
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            sums += np.array([v.item() for v in losses])
            n_batches += 1
            if advance is not None:
                advance(len(idx))
        sched.step()
        row: dict[str, Any] = {
            "epoch": epoch + 1,
            "lr": opt.param_groups[0]["lr"],
            "train_loss": float(sums.sum() / n_batches),
            "train_levels": (sums / n_batches).tolist(),
            "seconds": time.perf_counter() - te,
        }
        if va is not None and len(va):
            row.update({f"val_{k}": v for k, v in evaluate(model, va, scale, device).items()})
        if validator is not None:
            tv = time.perf_counter()
            row.update({f"val_{k}": v for k, v in validator(model.eval(), scale).items()})
            row["val_seconds"] = time.perf_counter() - tv
        history.append(row)
        improved = False
        if select is not None and select.better(float(row.get(select.key, math.nan)), best["value"]):
            best = {"epoch": epoch + 1, "value": float(row[select.key]), "weights": _state_dict_copy(model)}
            improved = True
        out_of_time = (cfg.time_limit_s is not None and time.perf_counter() - t0 > cfg.time_limit_s
                       and epoch + 1 < cfg.epochs)
        stopped_early = out_of_time
        if state_path is not None:
            save_state(state_path, {
                "version": STATE_VERSION, "config": asdict(cfg), "n_train_patches": len(tr),
                "model": _state_dict_copy(model), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                "numpy_rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                "history": history, "best": best, "norm_scale": scale,
                "train_seconds": seconds_before + time.perf_counter() - t0,
            })
        if on_epoch is not None:
            on_epoch(row)
        if on_checkpoint is not None:
            on_checkpoint(result(False), improved)
        if out_of_time:
            break
    return result(True)


def plot_curve(history: Sequence[dict[str, Any]], path: str | Path, title: str = "") -> Path:
    """Training loss per level (eq. 1) and held-out patch CD-l1 against the epoch."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    epochs = [h["epoch"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    ax = axes[0]
    ax.plot(epochs, [h["train_loss"] for h in history], "k-", lw=2, label="J = sum CD_i (eq. 2)")
    levels = np.array([h["train_levels"] for h in history])
    for i in range(levels.shape[1] if levels.ndim == 2 else 0):
        ax.plot(epochs, levels[:, i], lw=1, label=f"CD level {i}")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("training loss (normalised units)")
    ax.legend(fontsize=8)
    ax = axes[1]
    if history and "val_map_cd_l2" in history[0]:
        ax.plot(epochs, [h["val_map_cd_l1"] for h in history], "b-", label="validation map CD-l1 (m)")
        ax.plot(epochs, [h["val_map_cd_l2"] for h in history], "r-", label="validation map CD-l2 (m^2)")
        ax.set_ylabel("map metric on the validation scenes")
        ax.legend(fontsize=8)
    elif history and "val_cd_l1_m" in history[0]:
        ax.plot(epochs, [h["val_cd_l1_m"] for h in history], "b-", label="held-out patch CD-l1 (m)")
        ax.set_ylabel("CD-l1 (m)")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no held-out patches", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("epoch")
    fig.suptitle(title or "completion network training")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
