"""The occupancy-AUC protocol of Hilbert maps (Ramos and Ott 2016) used by RICH-SLAM Sec. V-B1.

Pure numpy. Beams run from the sensor origin to each detection (both in the world, placed with
ground-truth poses). Each endpoint is an occupied sample (+1); each beam of length ``d`` also gives
``max(1, floor(d / 2))`` free samples (-1) drawn uniformly in ``[0, d - 0.1]`` along it. Scans are
split into training and held-out sets by contiguous blocks, and the AUC is the area under the ROC
curve of the held-out samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class LabelledSamples:
    """Occupancy samples: positions, labels in {-1, +1}, the scan each came from."""

    points: F64  # (N, 2)
    labels: F64  # (N,)
    scan: npt.NDArray[np.int64]  # (N,)

    def __len__(self) -> int:
        return int(self.labels.size)

    def select(self, mask: npt.NDArray[np.bool_]) -> LabelledSamples:
        return LabelledSamples(self.points[mask], self.labels[mask], self.scan[mask])


def hilbert_maps_samples(
    origins: F64, endpoints: F64, scan: npt.ArrayLike, rng: np.random.Generator,
    free_per_metre: float = 0.5, gap: float = 0.1,
) -> LabelledSamples:
    """Endpoints (+1) and ``max(1, floor(d * free_per_metre))`` free samples per beam in ``[0, d - gap]``.

    ``origins`` and ``endpoints`` are (B, 2) per beam, ``scan`` (B,) the scan of each beam. The
    samples of a scan stay contiguous and in scan order (free samples first, then the endpoints).
    """
    o = np.asarray(origins, np.float64).reshape(-1, 2)
    e = np.asarray(endpoints, np.float64).reshape(-1, 2)
    scan = np.asarray(scan, np.int64).reshape(-1)
    d_vec = e - o
    d = np.linalg.norm(d_vec, axis=1)
    n_free = np.maximum(1, np.floor(d * free_per_metre)).astype(np.int64)
    beam = np.repeat(np.arange(len(e)), n_free)
    t = rng.uniform(0.0, 1.0, size=beam.size) * np.maximum(d[beam] - gap, 0.0)
    unit = d_vec / np.where(d > 0, d, 1.0)[:, None]
    free = o[beam] + unit[beam] * t[:, None]
    pts = np.concatenate([free, e])
    lab = np.concatenate([-np.ones(len(free)), np.ones(len(e))])
    sc = np.concatenate([scan[beam], scan])
    order = np.argsort(sc, kind="stable")
    return LabelledSamples(pts[order], lab[order], sc[order])


def split_scans_by_block(
    scans: npt.ArrayLike, test_fraction: float, block: int, rng: np.random.Generator
) -> npt.NDArray[np.bool_]:
    """Held-out mask over ``scans``: consecutive blocks of ``block`` scans, ``test_fraction`` of them drawn.

    Blocks keep near-identical neighbouring scans on one side of the split. At least one block is
    held out and at least one kept for training (when there are two or more blocks).
    """
    scans = np.asarray(scans)
    uniq = np.unique(scans)
    block_of = np.searchsorted(uniq, scans) // max(1, block)
    n_blocks = int(block_of.max()) + 1 if len(scans) else 0
    if n_blocks == 0:
        return np.zeros(0, bool)
    n_test = round(test_fraction * n_blocks)
    n_test = min(max(n_test, 1), max(n_blocks - 1, 1)) if test_fraction > 0 else 0
    test_blocks = rng.choice(n_blocks, size=n_test, replace=False)
    return np.isin(block_of, test_blocks)


def roc_auc(labels: npt.ArrayLike, scores: npt.ArrayLike) -> float:
    """Area under the ROC curve by the Mann-Whitney rank statistic (mid-ranks for ties).

    ``labels`` are positive when > 0. NaN when a class is empty.
    """
    y = np.asarray(labels).reshape(-1) > 0
    s = np.asarray(scores, np.float64).reshape(-1)
    n_pos = int(y.sum())
    n_neg = y.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    order = np.argsort(s, kind="mergesort")
    s_sorted = s[order]
    # mid-ranks: every run of equal scores gets the mean of its ranks (1-based)
    starts = np.flatnonzero(np.r_[True, s_sorted[1:] != s_sorted[:-1]])
    ends = np.r_[starts[1:], s.size]
    mid = 0.5 * (starts + ends + 1)
    ranks = np.empty(s.size)
    ranks[order] = np.repeat(mid, ends - starts)
    return float((ranks[y].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


GridModel = tuple[F64, npt.NDArray[np.int64], F64, F64]


def grid_counts_fit(train: LabelledSamples, resolution: float) -> GridModel:
    """Hit and free counts per cell: returns (origin, shape, hits, frees) with dense count arrays."""
    lo = np.asarray(train.points.min(0) - resolution, np.float64)
    idx = np.floor((train.points - lo) / resolution).astype(np.int64)
    shape = np.asarray(idx.max(0) + 2, np.int64)
    flat = idx[:, 0] * shape[1] + idx[:, 1]
    hits = np.bincount(flat, weights=(train.labels > 0).astype(np.float64), minlength=int(shape.prod()))
    frees = np.bincount(flat, weights=(train.labels <= 0).astype(np.float64), minlength=int(shape.prod()))
    return lo, shape, hits.astype(np.float64), frees.astype(np.float64)


def grid_counts_predict(model: GridModel, points: F64, resolution: float) -> F64:
    """``hits / (hits + frees)`` per query cell, 0.5 where no sample fell."""
    lo, shape, hits, frees = model
    idx = np.floor((np.asarray(points, np.float64) - lo) / resolution).astype(np.int64)
    inside = np.all((idx >= 0) & (idx < shape), axis=1)
    out = np.full(len(idx), 0.5)
    flat = idx[inside, 0] * shape[1] + idx[inside, 1]
    n = hits[flat] + frees[flat]
    out[inside] = np.where(n > 0, hits[flat] / np.where(n > 0, n, 1.0), 0.5)
    return out
