"""Synthetic patch pairs for tests and benchmarks (no simulator needed): a floor, a wall corner and a box
sampled densely as the lidar target, and sparsely, with noise, missing sectors and outliers, as the radar
input. Pure numpy, seeded.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stages.complete.data import F64, Patch


def _sample_rect(rng: np.random.Generator, n: int, origin: F64, u: F64, v: F64) -> F64:
    a, b = rng.random((2, n, 1))
    return origin + a * u + b * v


def scene_surface(rng: np.random.Generator, n: int, radius: float = 3.0) -> F64:
    """``n`` points on a random floor + wall corner + box, around the origin."""
    r = radius
    yaw = rng.uniform(0, 2 * np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    h = rng.uniform(1.5, 2.5)
    wx, wy = rng.uniform(0.5, 1.5, 2)
    bx, by = rng.uniform(-1.0, 0.5, 2)
    bs = rng.uniform(0.4, 0.9)
    rects = [
        (np.array([-r, -r, -1.0]), np.array([2 * r, 0, 0]), np.array([0, 2 * r, 0])),  # floor
        (np.array([wx, -r, -1.0]), np.array([0, 2 * r, 0]), np.array([0, 0, h])),  # wall x = wx
        (np.array([-r, wy, -1.0]), np.array([2 * r, 0, 0]), np.array([0, 0, h])),  # wall y = wy
        (np.array([bx, by, -1.0]), np.array([bs, 0, 0]), np.array([0, 0, bs])),  # box faces
        (np.array([bx, by, -1.0]), np.array([0, bs, 0]), np.array([0, 0, bs])),
        (np.array([bx, by, -1.0 + bs]), np.array([bs, 0, 0]), np.array([0, bs, 0])),
    ]
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v in rects])
    counts = rng.multinomial(n, areas / areas.sum())
    pts = np.concatenate([_sample_rect(rng, k, o, u, v) for k, (o, u, v) in zip(counts, rects, strict=True)])
    return pts[rng.permutation(len(pts))] @ rot.T


def make_patch(rng: np.random.Generator, n_radar: int = 2048, n_lidar: int = 8192, noise: float = 0.08,
               outliers: float = 0.1, seed_xyz: F64 | None = None, seq: str = "synthetic", index: int = 0) -> Patch:
    """One patch pair: dense surface samples (target) and sparse noisy incomplete samples (input)."""
    seed = np.zeros(3) if seed_xyz is None else np.asarray(seed_xyz, dtype=np.float64)
    lidar = scene_surface(np.random.default_rng(rng.integers(1 << 31)), n_lidar)
    surf = scene_surface(np.random.default_rng(rng.integers(1 << 31)), 4 * n_radar)
    # radar-like: a missing angular sector, Gaussian range noise, a few spurious points
    ang = np.arctan2(surf[:, 1], surf[:, 0])
    start = rng.uniform(-np.pi, np.pi)
    keep = ((ang - start) % (2 * np.pi)) > 1.2
    surf = surf[keep]
    n_out = int(outliers * n_radar)
    radar = surf[rng.choice(len(surf), n_radar - n_out, replace=False)] + rng.normal(0, noise, (n_radar - n_out, 3))
    radar = np.concatenate([radar, rng.uniform(-3, 3, (n_out, 3))])
    return Patch(seq, index, seed, radar + seed, lidar + seed)


def make_patches(n: int, seed: int = 0, **kw: Any) -> list[Patch]:
    """``n`` independent patch pairs with seeds spread along a line (world coordinates)."""
    rng = np.random.default_rng(seed)
    return [make_patch(rng, seed_xyz=np.array([4.0 * i, 1.0, 0.5]), index=i, **kw) for i in range(n)]


def patches_table(patches: list[Patch]) -> dict[str, Any]:
    """Columns of a ``patches.parquet`` artifact holding ``patches`` (radar and lidar rows)."""
    cols: dict[str, list[Any]] = {k: [] for k in ("patch", "kind", "x", "y", "z", "seed_x", "seed_y", "seed_z")}
    for p in patches:
        for kind, pts in (("radar", p.radar), ("lidar", p.lidar)):
            n = len(pts)
            cols["patch"].append(np.full(n, p.patch, np.int32))
            cols["kind"].append(np.full(n, kind, dtype=object))
            for j, c in enumerate("xyz"):
                cols[c].append(pts[:, j].astype(np.float32))
            for j, c in enumerate(("seed_x", "seed_y", "seed_z")):
                cols[c].append(np.full(n, p.seed[j], np.float32))
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}
