"""Completing a whole map and scoring it (RMap Sec. IV-B): every radar patch through the network, the
predicted patches merged and downsampled to the map resolution (mean per voxel), the map metrics against
the ground-truth lidar map. The same path as the `complete` stage, on arrays.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from stages.complete.checkpoint import CheckpointMeta
from stages.complete.data import F64, Patch, voxel_downsample
from stages.complete.infer import complete_patches
from stages.complete.model import UpPoinTr
from stages.evaluate.map_metrics import map_metrics
from stages.evaluate.rmap_paper import MAP_KEYS


def complete_map(model: UpPoinTr, meta: CheckpointMeta, patches: Sequence[Patch], device: torch.device,
                 resolution: float = 0.15, batch_size: int = 8, seed: int = 0) -> tuple[F64, float]:
    """(completed map, network seconds per patch): merged predictions downsampled at ``resolution``."""
    with torch.random.fork_rng(devices=[]):
        res = complete_patches(model, meta, patches, device, batch_size, seed)
    merged = np.concatenate(res.points) if res.points else np.zeros((0, 3))
    down, _ = voxel_downsample(merged, resolution)
    return down, res.seconds_per_patch


def score(pred: F64, gt: F64) -> dict[str, float]:
    """The Table III metrics of a map against ground truth (``stages.evaluate.map_metrics``)."""
    m = map_metrics(pred, gt)
    return {k: float(m[k]) for k in MAP_KEYS} | {"n_points": float(len(pred))}


def mean_rows(rows: Sequence[dict[str, float]]) -> dict[str, float]:
    """Table III's Overall row: the mean of the per-scene rows."""
    keys = [k for k in rows[0] if all(k in r for r in rows)] if rows else []
    return {k: float(np.mean([r[k] for r in rows])) for k in keys}
