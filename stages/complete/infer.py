"""Running a trained completion network over the radar patches of a map (RMap Sec. III, Fig. 2 E-G)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from core.errors import UserError
from stages.complete.checkpoint import CheckpointMeta
from stages.complete.data import F64, Patch, denormalize, normalize, resample
from stages.complete.model import UpPoinTr


def resolve_device(name: str) -> torch.device:
    """``cpu``, ``cuda`` (error when absent) or ``auto`` (cuda when available)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise UserError("device 'cuda' requested but torch sees no CUDA device; use device=cpu or auto")
    if name not in ("cpu", "cuda"):
        raise UserError(f"unknown device {name!r}; use cpu, cuda or auto")
    return torch.device(name)


@dataclass
class Completion:
    """Predicted patches in world coordinates and the time the network took per batch."""

    points: list[F64]
    batch_seconds: list[float]
    batch_sizes: list[int]

    @property
    def model_seconds(self) -> float:
        return float(sum(self.batch_seconds))

    @property
    def seconds_per_patch(self) -> float:
        """Network seconds per patch, leaving out the first (warm-up) batch when there are more."""
        s, n = self.batch_seconds, self.batch_sizes
        if len(s) > 1:
            s, n = s[1:], n[1:]
        return float(sum(s) / sum(n)) if n and sum(n) else 0.0


def prepare_inputs(patches: Sequence[Patch], n_input: int, scale: float, rng: np.random.Generator) -> F64:
    """Normalised radar inputs ``(P, n_input, 3)``: each patch resampled to ``n_input`` points."""
    if not patches:
        return np.zeros((0, n_input, 3))
    return np.stack([normalize(resample(p.radar, n_input, rng), p.seed, scale) for p in patches])


@torch.no_grad()
def complete_patches(
    model: UpPoinTr,
    meta: CheckpointMeta,
    patches: Sequence[Patch],
    device: torch.device,
    batch_size: int = 8,
    seed: int = 0,
    advance: Callable[[int], None] | None = None,
) -> Completion:
    """The network's finest cloud for every patch, put back in world coordinates."""
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    x = prepare_inputs(patches, meta.config.n_input, meta.norm_scale, rng)
    model.eval()
    out: list[F64] = []
    seconds: list[float] = []
    sizes: list[int] = []
    for s in range(0, len(patches), batch_size):
        xb = torch.from_numpy(x[s : s + batch_size]).to(device=device, dtype=torch.float32)
        t0 = time.perf_counter()
        pred = model(xb)[-1]
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds.append(time.perf_counter() - t0)
        sizes.append(len(xb))
        pred_np = pred.cpu().numpy().astype(np.float64)
        for j, p in enumerate(patches[s : s + batch_size]):
            out.append(denormalize(pred_np[j], p.seed, meta.norm_scale))
        if advance is not None:
            advance(len(xb))
    return Completion(out, seconds, sizes)
