"""Completing a whole map and scoring it (RMap Sec. IV-B): every radar patch through the network, the
predicted patches merged and assembled at the map resolution (the paper's mean per voxel, or the
voxel centres), the map metrics against the ground-truth lidar map. The same path as the `complete` stage, on arrays.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from core.map_metrics import map_metrics
from core.rmap_paper import MAP_KEYS
from stages.complete.checkpoint import CheckpointMeta
from stages.complete.data import F64, Patch, voxel_downsample
from stages.complete.infer import complete_patches
from stages.complete.model import UpPoinTr


def predict_map(model: UpPoinTr, meta: CheckpointMeta, patches: Sequence[Patch], device: torch.device,
                batch_size: int = 8, seed: int = 0) -> tuple[F64, float]:
    """(merged predicted patches in world coordinates, network seconds per patch), before assembly."""
    with torch.random.fork_rng(devices=[]):
        res = complete_patches(model, meta, patches, device, batch_size, seed)
    merged = np.concatenate(res.points) if res.points else np.zeros((0, 3))
    return merged, res.seconds_per_patch


def complete_map(model: UpPoinTr, meta: CheckpointMeta, patches: Sequence[Patch], device: torch.device,
                 resolution: float = 0.15, batch_size: int = 8, seed: int = 0) -> tuple[F64, float]:
    """(completed map, network seconds per patch): merged predictions assembled at ``resolution``
    (:func:`stages.complete.data.voxel_downsample`, the paper's mean per voxel)."""
    merged, spp = predict_map(model, meta, patches, device, batch_size, seed)
    down, _ = voxel_downsample(merged, resolution)
    return down, spp


#: the metrics :func:`score` returns besides Table III's (both F-score forms, with precision and recall)
EXTRA_KEYS = ("precision_0.15", "recall_0.15", "fscore_0.15_robust", "precision_0.15_robust",
              "recall_0.15_robust")


def score(pred: F64, gt: F64) -> dict[str, float]:
    """The Table III metrics of a map against ground truth (``core.map_metrics``), plus the
    robust F-score and both forms' precision and recall."""
    m = map_metrics(pred, gt)
    return {k: float(m[k]) for k in (*MAP_KEYS, *EXTRA_KEYS)} | {"n_points": float(len(pred))}


def mean_rows(rows: Sequence[dict[str, float]]) -> dict[str, float]:
    """Table III's Overall row: the mean of the per-scene rows."""
    keys = [k for k in rows[0] if all(k in r for r in rows)] if rows else []
    return {k: float(np.mean([r[k] for r in rows])) for k in keys}
