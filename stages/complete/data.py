"""Patch handling for the completion network on numpy arrays (no torch): reading ``patches.parquet``,
normalising patches around their seed, resampling to fixed sizes, merging and voxel downsampling
(RMap Sec. III-B/D, IV-B), and the paper's train/test split by sequence (Sec. III-C).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from core.errors import UserError

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Patch:
    """One patch pair in world coordinates: radar input, lidar target (may be empty) and its FPS seed."""

    seq: str
    patch: int
    seed: F64  # (3,)
    radar: F64  # (n, 3)
    lidar: F64  # (m, 3)


def read_patches(path: str | Path, seq: str, need_lidar: bool = False) -> list[Patch]:
    """The patches of a ``patches.parquet`` artifact, in patch order.

    ``need_lidar``: raise when a patch has radar points but no lidar target (training needs both).
    """
    from schemas import read_artifact

    table = read_artifact(path, "patches", columns=["patch", "kind", "x", "y", "z", "seed_x", "seed_y", "seed_z"])
    patch = table.column("patch").to_numpy()
    kind = np.asarray(table.column("kind").to_pylist(), dtype=object)
    xyz = np.stack([table.column(c).to_numpy().astype(np.float64) for c in ("x", "y", "z")], axis=1)
    seed = np.stack([table.column(c).to_numpy().astype(np.float64) for c in ("seed_x", "seed_y", "seed_z")], axis=1)
    unknown = set(np.unique(kind).tolist()) - {"radar", "lidar"}
    if unknown:
        raise UserError(f"{path}: column 'kind' holds {sorted(unknown)}; expected 'radar' or 'lidar'")
    order = np.argsort(patch, kind="stable")
    patch, kind, xyz, seed = patch[order], kind[order], xyz[order], seed[order]
    ids, starts = np.unique(patch, return_index=True)
    ends = np.r_[starts[1:], len(patch)]
    out: list[Patch] = []
    for pid, s, e in zip(ids.tolist(), starts.tolist(), ends.tolist(), strict=True):
        k = kind[s:e]
        radar = xyz[s:e][k == "radar"]
        lidar = xyz[s:e][k == "lidar"]
        if len(radar) == 0:
            continue
        if need_lidar and len(lidar) == 0:
            raise UserError(f"{path}: patch {pid} has no lidar points; training needs lidar targets")
        out.append(Patch(seq, int(pid), seed[s], radar, lidar))
    return out


def normalize(points: npt.ArrayLike, seed: npt.ArrayLike, scale: float) -> F64:
    """Patch coordinates: ``(p - seed) / scale`` (float64)."""
    return (np.asarray(points, dtype=np.float64) - np.asarray(seed, dtype=np.float64)) / float(scale)


def denormalize(points: npt.ArrayLike, seed: npt.ArrayLike, scale: float) -> F64:
    """World coordinates of normalised patch points: ``q * scale + seed`` (the inverse of :func:`normalize`)."""
    return np.asarray(points, dtype=np.float64) * float(scale) + np.asarray(seed, dtype=np.float64)


def resample(points: F64, n: int, rng: np.random.Generator) -> F64:
    """Exactly ``n`` points: a random subset when there are more, all plus random repeats when fewer."""
    m = len(points)
    if m == 0:
        raise ValueError("cannot resample an empty point set")
    if m == n:
        return points
    if m > n:
        return points[np.sort(rng.choice(m, n, replace=False))]
    return np.concatenate([points, points[rng.integers(0, m, n - m)]])


def crop_target(patch: Patch, min_points: int = 256) -> Patch:
    """The patch with its lidar target cut to the ball the radar input spans around the seed.

    Algorithm 1 takes the N_L = 4 N_R nearest lidar points, which covers the radar patch's region when the
    lidar map holds about 4x the radar map's points (RMap's L/R ~ 4, Table I). With a denser radar map the
    lidar patch reaches far beyond the radar input and the network would be taught to extrapolate; the
    target is therefore limited to lidar points within the radar patch's largest seed distance (at least
    the ``min_points`` nearest, so a target never vanishes).
    """
    if len(patch.lidar) == 0:
        return patch
    r = np.sqrt(((patch.radar - patch.seed) ** 2).sum(1)).max()
    d = np.sqrt(((patch.lidar - patch.seed) ** 2).sum(1))
    keep = d <= r
    if keep.sum() < min(min_points, len(d)):
        keep = np.zeros(len(d), bool)
        keep[np.argsort(d, kind="stable")[:min_points]] = True
    return Patch(patch.seq, patch.patch, patch.seed, patch.radar, patch.lidar[keep])


def patch_scale(patches: Sequence[Patch], quantile: float = 0.5) -> float:
    """A normalisation length (m): the ``quantile`` over patches of the largest lidar (else radar) radius."""
    radii = []
    for p in patches:
        pts = p.lidar if len(p.lidar) else p.radar
        radii.append(float(np.sqrt(((pts - p.seed) ** 2).sum(1).max())))
    if not radii:
        raise ValueError("no patches to derive a normalisation scale from")
    return float(np.quantile(radii, quantile))


def voxel_downsample(points: npt.ArrayLike, resolution: float) -> tuple[F64, npt.NDArray[np.int64]]:
    """The completed map from the merged predicted patches (RMap Sec. IV-B, V: merge, then downsample to the map
    resolution by averaging the points in each voxel): one point per occupied voxel ``floor(p / res)``, the mean of
    its points, sorted by key; ``counts`` is the number of predicted points in each."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if resolution <= 0:
        raise ValueError(f"resolution must be > 0, got {resolution}")
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    keys = np.floor(pts / resolution).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.stack([np.bincount(inverse, weights=pts[:, j], minlength=len(counts)) for j in range(3)], axis=1)
    return sums / counts[:, None], counts.astype(np.int64)


_RUN = re.compile(r"^(?P<env>.+?)_run(?P<idx>\d+)$")


def split_by_sequence(runs: Iterable[tuple[str, str]]) -> tuple[list[str], list[str]]:
    """RMap's split (Sec. III-C): per environment with runs run0..runX, run0..run(floor(X/2)) are test.

    ``runs``: (sequence name, run name) pairs, e.g. ``("coloradar_5", "12_21_2020_arpg_lab_run0")``; the
    environment is the run name up to ``_runN`` without a leading date. Returns (train, test) names.
    """
    groups: dict[str, list[tuple[int, str]]] = {}
    for name, run in runs:
        m = _RUN.match(run)
        if m is None:
            raise UserError(f"sequence '{name}': run name '{run}' does not end in _run<N>; pass --test-seqs explicitly")
        env = re.sub(r"^\d+_\d+_\d+_", "", m.group("env"))
        groups.setdefault(env, []).append((int(m.group("idx")), name))
    train: list[str] = []
    test: list[str] = []
    for members in groups.values():
        x = max(i for i, _ in members)
        for i, name in sorted(members):
            (test if i <= x // 2 else train).append(name)
    return train, test
