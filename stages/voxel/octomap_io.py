"""Optional OctoMap ``.bt`` export through the ``octomap`` Python binding (dev extra: octomap-python).

The stage must not need the binding: :func:`available` says whether it imports. The ``.bt`` format is
OctoMap's maximum-likelihood binary tree (occupied / free per voxel, log-odds dropped).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.voxel.voxel_map import SensorModel, key_to_coord


def available() -> bool:
    """True when ``import octomap`` would succeed."""
    return importlib.util.find_spec("octomap") is not None


def make_octree(resolution: float, model: SensorModel) -> Any:
    """An empty ``octomap.OcTree`` with the sensor model's probabilities and clamping thresholds."""
    import octomap

    tree = octomap.OcTree(resolution)
    tree.setProbHit(model.prob_hit)
    tree.setProbMiss(model.prob_miss)
    tree.setClampingThresMin(model.clamp_min)
    tree.setClampingThresMax(model.clamp_max)
    tree.setOccupancyThres(model.occupancy_threshold)
    return tree


def to_octree(keys: npt.ArrayLike, log_odds: npt.ArrayLike, resolution: float, model: SensorModel) -> Any:
    """An ``octomap.OcTree`` holding the given voxels with their log-odds (one bulk update per distinct value)."""
    tree = make_octree(resolution, model)
    centres = key_to_coord(keys, resolution)
    values = np.asarray(log_odds, dtype=np.float32)
    distinct, inverse = np.unique(values, return_inverse=True)
    for i, v in enumerate(distinct):
        tree.updateNodes(centres[inverse == i], float(v), lazy_eval=True)
    tree.updateInnerOccupancy()
    return tree


def write_bt(path: str | Path, keys: npt.ArrayLike, log_odds: npt.ArrayLike, resolution: float,
             model: SensorModel) -> Path:
    """Write voxels (keys with log-odds, free ones included) as an OctoMap binary ``.bt`` file."""
    tree = to_octree(keys, log_odds, resolution, model)
    path = Path(path)
    if not tree.writeBinary(str(path).encode()):
        raise OSError(f"{path}: octomap could not write the .bt file")
    return path
