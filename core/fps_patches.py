"""FPS based patch generation (RMap Algorithm 1, Sec. III-B) on numpy arrays.

1. Outlier pre-removal on the radar map: statistical outlier removal (the mean distance of each point
   to its ``k`` nearest neighbours; points above ``mean + std_ratio * std`` of that statistic over the
   map are dropped), the "points too deviated from the centre of each small region" of Sec. III-B.
2. ``t = floor(a * n_R / N_R)`` seeds (at least 1) by farthest point sampling over the cleaned radar
   map (``fpsample.fps_sampling``, exact vanilla FPS, from a seeded random start point). ``n_R`` counts
   the radar points after step 1. Algorithm 1 leaves the rounding open; rounding down reproduces Table VI:
   over the 21 test scenes of the published maps the totals are 307 / 624 / 1263 / 2540 / 5089 / 10186
   for a = 1 / 2 / 4 / 8 / 16 / 32 against the paper's 307 / 624 / 1262 / 2532 / 5075 / 10160, while
   rounding up gives 328 / 645 / 1284 / ... (``shared/data/coloradar_maps/README.md``;
   ``tests/test_rmap_paper.py``).
3. For every seed the ``N_R`` nearest radar and ``N_L`` nearest lidar map points (``cKDTree``), nearest
   first, so the first radar point of a patch is its seed.
4. Padding when a map holds fewer than ``N`` points: all of them (nearest first), then the missing
   ``N - n`` drawn with replacement from those ``n`` with the seeded generator; padded rows are marked.
5. Normalisation for the network: ``(p - centre) / scale`` with the seed as centre (the first input
   point, as in the UpPoinTr ColoRadar inference script) and ``scale`` either fixed or the largest
   distance of the radar patch's points from the seed (the same script); both are stored per patch so
   that normalised predictions go back to world coordinates with ``p * scale + centre``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import fpsample
import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


def statistical_outliers(points: npt.ArrayLike, k: int, std_ratio: float) -> npt.NDArray[np.bool_]:
    """Mask of inliers: mean distance to the ``k`` nearest neighbours <= mean + std_ratio * std."""
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    if k <= 0 or n <= k:
        return np.ones(n, bool)
    d, _ = cKDTree(pts).query(pts, k=k + 1, workers=-1)  # the first neighbour is the point itself
    mean_d = d[:, 1:].mean(axis=1)
    return np.asarray(mean_d <= mean_d.mean() + std_ratio * mean_d.std())


def n_seeds(n_radar: int, n_patch_radar: int, a: float) -> int:
    """Number of seeds ``t = floor(a * n_R / N_R)`` (Algorithm 1, Table VI's counts), at least 1 for a non-empty map."""
    if n_radar == 0:
        return 0
    return max(1, math.floor(a * n_radar / n_patch_radar))


def farthest_point_sampling(points: npt.ArrayLike, n: int, start: int) -> I64:
    """Indices of ``n`` farthest points (vanilla FPS from index ``start``; fpsample, exact)."""
    pts = np.ascontiguousarray(points, dtype=np.float32)
    n = min(n, len(pts))
    if n <= 0:
        return np.zeros(0, np.int64)
    if n == 1:
        return np.array([start], np.int64)
    return np.asarray(fpsample.fps_sampling(pts, n, start_idx=int(start)), dtype=np.int64)


def knn_padded(
    tree: cKDTree, n_points: int, seeds: npt.ArrayLike, k: int, rng: np.random.Generator
) -> tuple[I64, npt.NDArray[np.bool_]]:
    """(t, k) indices of the ``k`` nearest points of every seed, nearest first, padded by resampling."""
    s = np.asarray(seeds, dtype=np.float64).reshape(-1, 3)
    if n_points == 0:
        raise ValueError("cannot build patches from an empty map")
    kk = min(k, n_points)
    _, idx = tree.query(s, k=kk, workers=-1)
    idx = np.asarray(idx, np.int64).reshape(len(s), kk)
    padded = np.zeros((len(s), k), bool)
    if kk < k:
        extra = idx[np.arange(len(s))[:, None], rng.integers(0, kk, size=(len(s), k - kk))]
        idx = np.concatenate([idx, extra], axis=1)
        padded[:, kk:] = True
    return idx, padded


@dataclass(frozen=True)
class Patches:
    """Patches of both maps; row ``i`` of ``radar_idx``/``lidar_idx`` is patch ``i``."""

    seeds: F64  # (t, 3) seed points (world)
    radar_idx: I64  # (t, N_R) indices into the cleaned radar map
    radar_padded: npt.NDArray[np.bool_]
    lidar_idx: I64  # (t, N_L) indices into the lidar map
    lidar_padded: npt.NDArray[np.bool_]
    scale: F64  # (t,) normalisation scale per patch
    radar_inliers: npt.NDArray[np.bool_]  # mask over the input radar map
    seed_idx: I64  # (t,) seed indices into the cleaned radar map


def make_patches(
    radar: npt.ArrayLike,
    lidar: npt.ArrayLike,
    a: float = 4.0,
    n_radar: int = 2048,
    n_lidar: int = 8192,
    outlier_neighbors: int = 20,
    outlier_std_ratio: float = 2.0,
    norm_scale: float = 0.0,
    seed: int = 0,
) -> Patches:
    """Algorithm 1 with outlier pre-removal, padding and normalisation (see the module docstring)."""
    rng = np.random.default_rng(seed)
    radar_all = np.asarray(radar, dtype=np.float64).reshape(-1, 3)
    lid = np.asarray(lidar, dtype=np.float64).reshape(-1, 3)
    inliers = statistical_outliers(radar_all, outlier_neighbors, outlier_std_ratio)
    rad = radar_all[inliers]
    t = n_seeds(len(rad), n_radar, a)
    if t == 0:
        raise ValueError(f"cannot build patches: {len(rad)} radar map points")
    seed_idx = farthest_point_sampling(rad, t, int(rng.integers(len(rad))))
    seeds = rad[seed_idx]
    r_idx, r_pad = knn_padded(cKDTree(rad), len(rad), seeds, n_radar, rng)
    if len(lid):
        l_idx, l_pad = knn_padded(cKDTree(lid), len(lid), seeds, n_lidar, rng)
    else:  # a radar + IMU log: radar patches to complete, no lidar patches to train or score on
        l_idx, l_pad = np.zeros((t, 0), np.int64), np.zeros((t, 0), bool)
    if norm_scale > 0:
        scale = np.full(len(seeds), float(norm_scale))
    else:
        scale = np.linalg.norm(rad[r_idx] - seeds[:, None, :], axis=2).max(axis=1)
        scale = np.where(scale > 0, scale, 1.0)
    return Patches(seeds, r_idx, r_pad, l_idx, l_pad, scale, inliers, seed_idx)


def normalise(points: npt.ArrayLike, centre: npt.ArrayLike, scale: float | npt.ArrayLike) -> F64:
    """World -> patch coordinates: ``(p - centre) / scale``."""
    return (np.asarray(points, np.float64) - np.asarray(centre, np.float64)) / np.asarray(scale, np.float64)


def denormalise(points: npt.ArrayLike, centre: npt.ArrayLike, scale: float | npt.ArrayLike) -> F64:
    """Patch -> world coordinates: ``p * scale + centre``."""
    return np.asarray(points, np.float64) * np.asarray(scale, np.float64) + np.asarray(centre, np.float64)
