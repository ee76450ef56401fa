"""Vectorised voxel traversal of many rays at once (OctoMap's ``computeRayKeys``, all rays together).

OctoMap walks each ray with the 3D-DDA of Amanatides & Woo and returns the keys of the voxels from the
origin's voxel up to, but excluding, the end point's voxel (empty when both are the same voxel). The
set of voxels a segment passes through is the origin voxel plus the voxel entered at every crossing
of a voxel boundary plane. The crossings on axis ``a`` are the ``|key_end[a] - key_origin[a]|`` planes
between the two keys; the voxel entered at a crossing has, on axis ``a``, the key beyond that plane and,
on the other axes, the key of the crossing point. So every crossing is computed independently
(no sequential stepping, no sort), which vectorises over all rays and crossings of a scan. The end
voxel can only be entered by the last crossing of some axis, so only those are checked against it.

The order of visits is not needed: a scan updates every voxel at most once. Differences to OctoMap's
DDA arise only where a ray passes within ~1e-6 m of a voxel edge or corner (the two implementations may
then pick different neighbours of the edge).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from stages.voxel.voxel_map import coord_to_key, key_to_coord

IntArray = npt.NDArray[np.integer[Any]]


def ray_keys(origins: npt.ArrayLike, ends: npt.ArrayLike, resolution: float) -> IntArray:
    """Keys (M, 3) of the voxels traversed by the segments ``origins[i] -> ends[i]`` (end voxel excluded).

    ``origins`` is (3,) for a common origin or (N, 3). Duplicates across rays are kept. The result is
    column-major (``keys.T`` is contiguous), which the map's rasteriser reads fastest.
    """
    inv = 1.0 / resolution
    e = np.asarray(ends, dtype=np.float64).reshape(-1, 3) * inv  # voxel units from here on
    o = np.broadcast_to(np.asarray(origins, dtype=np.float64).reshape(-1, 3) * inv, e.shape)
    ko = np.floor(o).astype(np.int32)
    ke = np.floor(e).astype(np.int32)
    valid = np.any(ko != ke, axis=1)
    if not np.any(valid):
        return np.zeros((0, 3), np.int32)
    o, e, ko, ke = o[valid], e[valid], ko[valid], ke[valid]
    D = e - o
    parts = [ko.T]
    for a in range(3):
        n = np.abs(ke[:, a] - ko[:, a])
        total = int(n.sum())
        if total == 0:
            continue
        nz = n > 0
        ends_cum = np.cumsum(n)
        j = np.arange(1, total + 1, dtype=np.int32) - np.repeat((ends_cum - n).astype(np.int32), n)
        r_o, r_D, r_ko = o[nz], D[nz], ko[nz]
        step = np.where(r_D[:, a] > 0, 1, -1).astype(np.int32)
        # the j-th crossing on axis a enters key ko + step * j through the plane ko + step * j + (step < 0),
        # at ray parameter lam_j = lam_1 + (j - 1) / |D_a| (the DDA's tMax += tDelta)
        d_lam = 1.0 / np.abs(r_D[:, a])
        lam0 = (r_ko[:, a] + step + (step < 0) - r_o[:, a]) / r_D[:, a] - d_lam
        keys = np.empty((3, total), np.int32)
        keys[a] = np.repeat(r_ko[:, a], n[nz]) + np.repeat(step, n[nz]) * j
        jf = j.astype(np.float64)
        for b in range(3):
            if b != a:
                c0 = r_o[:, b] + lam0 * r_D[:, b]
                c1 = d_lam * r_D[:, b]
                u = np.repeat(c1, n[nz])
                u *= jf
                u += np.repeat(c0, n[nz])
                keys[b] = np.floor(u, out=u)
        last = ends_cum[nz] - 1  # the only crossings that may enter the end voxel
        at_end = np.all(keys[:, last] == ke[nz].T, axis=0)
        if np.any(at_end):
            keys = np.delete(keys, last[at_end], axis=1)
        parts.append(keys)
    return np.ascontiguousarray(np.concatenate(parts, axis=1)).T


def scan_update_keys(
    points: npt.ArrayLike,
    origin: npt.ArrayLike,
    resolution: float,
    max_range: float = -1.0,
    discretize: bool = False,
) -> tuple[IntArray, IntArray]:
    """Free and hit keys of one range scan, as OctoMap's ``insertPointCloud`` (``computeUpdate``).

    ``points`` are end points in the world frame, ``origin`` the sensor position. A point within
    ``max_range`` (or any point when ``max_range < 0``) marks the voxels on its ray as free and its own
    voxel as hit; a point beyond it marks only the ray truncated at ``max_range`` as free. With
    ``discretize`` the end points are first replaced by the centres of their distinct voxels
    (``computeDiscreteUpdate``). Hits win over misses; the map applies both once per voxel.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    org = np.asarray(origin, dtype=np.float64).reshape(3)
    if discretize and len(pts):
        pts = key_to_coord(np.unique(coord_to_key(pts, resolution), axis=0), resolution)
    if max_range >= 0:
        d = pts - org
        rng = np.linalg.norm(d, axis=1)
        far = rng > max_range
        ends = pts.copy()
        ends[far] = org + d[far] * (max_range / rng[far])[:, None]
        hits = pts[~far]
    else:
        ends, hits = pts, pts
    return ray_keys(org, ends, resolution), coord_to_key(hits, resolution)
