"""The voxel lattice of a published map set and the voxel model's inputs, as pure numpy functions.

RMap's radar and ``lidar_filtered`` maps are occupied voxel centres on one 0.15 m lattice (every coordinate
is ``(k + 1/2) * res``), so completion can be posed as a per-voxel occupancy prediction. Here:

- :func:`lattice_keys` / :func:`key_centres`: integer voxel keys of a map and back (a one-line error when
  a map is not on the lattice);
- :func:`trajectory_band`: the radar pre-filter (RMap Sec. VI names pre-filtering as future work): keep
  voxels within ``radius`` horizontally and ``z_below..z_above`` in height of the recorded trajectory;
- :func:`voxel_features`: the network's input channels on a box of the lattice: radar occupancy, local
  radar density at two scales, horizontal distance to and height over the trajectory. Only what the
  published maps hold (radar map, trajectory). Every channel of a voxel depends only on the radar voxels
  within :data:`FEATURE_HALO` of it and on the trajectory, so features of a tile equal those of the whole
  map on the same voxels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
F32 = npt.NDArray[np.float32]

#: input channels of the voxel model, in order
CHANNELS = ("radar", "density_r2", "density_r5", "traj_dist", "traj_height")
#: box radii (voxels) of the two density channels
DENSITY_RADII = (2, 5)
#: how far (voxels) a feature looks at other radar voxels
FEATURE_HALO = max(DENSITY_RADII)
#: feature scales (m): distance and height are divided by these and clipped to [-CLIP, CLIP]
DIST_SCALE, HEIGHT_SCALE, CLIP = 7.0, 4.0, 2.0
#: tolerance (in voxels) of the lattice check
LATTICE_TOL = 1e-6


class LatticeError(ValueError):
    """A map's coordinates are not voxel centres of the lattice."""


@dataclass(frozen=True)
class Band:
    """The trajectory band of the pre-filter: horizontal radius and height range (m) around the trajectory.

    Defaults fixed on RMap's 23 train scenes only (``data/models/README.md``): pooled over their
    ``lidar_filtered`` voxels, the 99.9th percentile of the horizontal distance to the trajectory (6.83 m)
    and the 0.2 / 99.9th percentiles of the height over its horizontally nearest point (-2.73 / +4.44 m),
    rounded outwards to 0.5 m.
    """

    radius: float = 7.0
    z_below: float = -3.0
    z_above: float = 4.5


def lattice_keys(points: F64, res: float, what: str = "map") -> I64:
    """Integer keys ``k`` with ``points = (k + 1/2) * res`` (``(N, 3)`` int64); :class:`LatticeError` if off."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise LatticeError(f"the {what} must be an (N, 3) array, got shape {pts.shape}")
    k = pts / res - 0.5
    keys = np.rint(k)
    if len(pts) and float(np.abs(k - keys).max()) > LATTICE_TOL * max(1.0, float(np.abs(k).max())):
        worst = int(np.argmax(np.abs(k - keys).max(axis=1)))
        raise LatticeError(f"the {what} is not on the {res:g} m voxel lattice (point {pts[worst].tolist()} is "
                           f"not a voxel centre (k + 1/2) * {res:g})")
    return keys.astype(np.int64)


def key_centres(keys: I64, res: float, decimals: int = 6) -> F64:
    """Voxel centres ``(k + 1/2) * res`` of integer keys, rounded to ``decimals`` like the published files."""
    return np.round((np.asarray(keys, np.float64) + 0.5) * res, decimals)


def band_distance_height(points: F64, trajectory: F64) -> tuple[F64, F64]:
    """Horizontal distance of each point to the trajectory and its height over the horizontally nearest
    trajectory point (m)."""
    pts = np.asarray(points, np.float64)
    traj = np.asarray(trajectory, np.float64)
    if len(traj) == 0:
        raise ValueError("the trajectory is empty")
    if len(pts) == 0:
        return np.zeros(0), np.zeros(0)
    d, i = cKDTree(traj[:, :2]).query(pts[:, :2], k=1)
    return np.asarray(d, np.float64), pts[:, 2] - traj[np.asarray(i), 2]


def in_band(points: F64, trajectory: F64, band: Band) -> npt.NDArray[np.bool_]:
    """Mask of the points inside the trajectory band (the pre-filter)."""
    d, h = band_distance_height(points, trajectory)
    return (d <= band.radius) & (h >= band.z_below) & (h <= band.z_above)


def trajectory_band(points: F64, trajectory: F64, band: Band) -> F64:
    """The radar pre-filter: the points of a map within ``band`` of the recorded trajectory."""
    return np.asarray(points, np.float64)[in_band(points, trajectory, band)]


def _axis_slice(axis: int, start: int | None, stop: int | None) -> tuple[slice, ...]:
    return tuple(slice(start, stop) if i == axis else slice(None) for i in range(axis + 1))


def box_sum(occ: npt.NDArray[np.generic], r: int) -> F32:
    """Sum of ``occ`` over the ``(2r+1)^3`` box around every voxel of the inner region (``occ`` is padded by
    ``r`` on every side; the result is ``r`` smaller on every side). Exact for 0/1 inputs (integer sums: one
    running sum per axis)."""
    w = 2 * r + 1
    a = np.asarray(occ)
    for axis in (2, 1, 0):  # z (the shortest) first: the later running sums see smaller arrays
        shape = list(a.shape)
        shape[axis] += 1
        c = np.zeros(shape, np.int32)
        np.cumsum(a, axis=axis, dtype=np.int32, out=c[_axis_slice(axis, 1, None)])
        a = c[_axis_slice(axis, w, None)] - c[_axis_slice(axis, None, -w)]
    return a.astype(np.float32)


def occupancy(keys: I64, lo: npt.ArrayLike, shape: tuple[int, int, int],
              dtype: npt.DTypeLike = np.float32) -> npt.NDArray[Any]:
    """Dense 0/1 grid of ``shape`` (float32 unless ``dtype``) whose voxel ``(0, 0, 0)`` has key ``lo``."""
    lo_a = np.asarray(lo, np.int64)
    grid = np.zeros(shape, dtype)
    if len(keys) == 0:
        return grid
    k = keys - lo_a
    inside = np.all((k >= 0) & (k < np.asarray(shape)), axis=1)
    k = k[inside]
    grid[k[:, 0], k[:, 1], k[:, 2]] = 1
    return grid


def trajectory_columns(lo: npt.ArrayLike, shape: tuple[int, int], trajectory: F64, res: float) -> tuple[F64, F64]:
    """Per voxel column of a box (``(nx, ny)`` from key ``lo``): horizontal distance to the trajectory and the
    height of its horizontally nearest point (m)."""
    lo_a = np.asarray(lo, np.int64)
    nx, ny = shape[0], shape[1]
    xs = (lo_a[0] + np.arange(nx) + 0.5) * res
    ys = (lo_a[1] + np.arange(ny) + 0.5) * res
    xy = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    d, i = cKDTree(np.asarray(trajectory, np.float64)[:, :2]).query(xy, k=1)
    tz = np.asarray(trajectory, np.float64)[np.asarray(i), 2].reshape(nx, ny)
    return np.asarray(d, np.float64).reshape(nx, ny), tz


def _z_centres(lo: npt.ArrayLike, nz: int, res: float) -> F64:
    return np.asarray((int(np.asarray(lo, np.int64)[2]) + np.arange(nz) + 0.5) * res, np.float64)


def trajectory_grids(lo: npt.ArrayLike, shape: tuple[int, int, int], trajectory: F64, res: float,
                     columns: tuple[F64, F64] | None = None) -> tuple[F64, F64]:
    """Horizontal distance (``(nx, ny)``) and height over the trajectory (``(nx, ny, nz)``) of a box's voxels;
    ``columns``: the box's :func:`trajectory_columns`, when already computed."""
    dist, tz = columns if columns is not None else trajectory_columns(lo, (shape[0], shape[1]), trajectory, res)
    return dist, _z_centres(lo, shape[2], res)[None, None, :] - tz[:, :, None]


def band_grid(lo: npt.ArrayLike, shape: tuple[int, int, int], trajectory: F64, res: float,
              band: Band, columns: tuple[F64, F64] | None = None) -> npt.NDArray[np.bool_]:
    """Boolean grid: voxels of the box inside the trajectory band (``columns`` as in :func:`trajectory_grids`)."""
    dist, height = trajectory_grids(lo, shape, trajectory, res, columns)
    return (dist[:, :, None] <= band.radius) & (height >= band.z_below) & (height <= band.z_above)


def voxel_features(radar_keys: I64, trajectory: F64, lo: npt.ArrayLike, shape: tuple[int, int, int],
                   res: float, columns: tuple[F64, F64] | None = None) -> F32:
    """The input channels (:data:`CHANNELS`, ``(C, nx, ny, nz)`` float32) on the box of ``shape`` at key ``lo``
    (``columns`` as in :func:`trajectory_grids`).

    radar: 0/1 occupancy; density_r*: share of occupied voxels in the ``(2r+1)^3`` box; traj_dist: horizontal
    distance to the trajectory / :data:`DIST_SCALE`; traj_height: height over the horizontally nearest
    trajectory point / :data:`HEIGHT_SCALE` (both clipped to +-:data:`CLIP`).
    """
    lo_a = np.asarray(lo, np.int64)
    h = FEATURE_HALO
    padded = occupancy(radar_keys, lo_a - h, (shape[0] + 2 * h, shape[1] + 2 * h, shape[2] + 2 * h), np.uint8)
    out = np.empty((len(CHANNELS), *shape), np.float32)
    out[0] = padded[h:h + shape[0], h:h + shape[1], h:h + shape[2]]
    for c, r in enumerate(DENSITY_RADII, start=1):
        o = h - r
        sub = padded[o:o + shape[0] + 2 * r, o:o + shape[1] + 2 * r, o:o + shape[2] + 2 * r]
        out[c] = box_sum(sub, r) / float((2 * r + 1) ** 3)
    dist, height = trajectory_grids(lo_a, shape, trajectory, res, columns)
    out[3] = np.clip(dist / DIST_SCALE, -CLIP, CLIP)[:, :, None]
    height /= HEIGHT_SCALE
    out[4] = np.clip(height, -CLIP, CLIP, out=height)
    return out
