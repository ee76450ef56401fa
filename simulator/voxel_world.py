"""A simulator world made from a voxel map: ray casting against occupied voxels (the ColoRadar twins).

The map is a set of occupied voxel centres (e.g. the RMap authors' 0.15 m lidar OctoMap of a real scene).
It is stored as a dense boolean occupancy grid plus, per free cell, its *clearance*: the chessboard
(L-infinity) distance in voxels to the nearest occupied cell (``scipy.ndimage.distance_transform_cdt``).

Rays march all at once (numpy over rays, a Python loop over march steps only):

- a ray in a cell of clearance ``k >= 2`` jumps ``(k - 1) / max|d_i|`` voxels along itself: every point
  of that jump lies in a cell at most ``k - 1`` cells from the current one, which is free (empty-space
  skipping as in sphere tracing, with the L-infinity distance);
- a ray next to an occupied cell (``k = 1``) takes one exact 3D-DDA step (Amanatides and Woo, 1987) to the
  next cell boundary, so the first occupied cell is never skipped;
- a ray stops at the first occupied cell (range = where it enters that cell, the normal = the crossed face)
  or when it leaves the grid or its maximum range.

``simulator.raycast.cast`` hands a :class:`VoxelScene` to its own ``cast_fan``. The cell a ray starts in
is never a hit (a sensor inside a voxel of the map still sees out of it).
:func:`cast_voxels_brute` is the per-voxel reference used by the tests (slab intersection with every
occupied voxel's box).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from simulator.raycast import Hits, directions
from simulator.world import KIND_CEILING, KIND_FLOOR, KIND_NONE, KIND_SEGMENT, Scene

#: clearance stored as uint8 (jumps of at most 254 voxels)
MAX_CLEARANCE = 255
#: safety margin of a jump, in voxels (floating point)
JUMP_MARGIN = 1e-3


@dataclass(frozen=True)
class VoxelGrid:
    """A dense occupancy grid: cell ``(i, j, k)`` spans ``origin + res * [(i, j, k), (i, j, k) + 1)``."""

    origin: np.ndarray  # (3,) world position of the grid's corner, metres
    resolution: float  # edge length of a cell, metres
    occupied: np.ndarray  # bool (nx, ny, nz)
    clearance: np.ndarray  # uint8 (nx, ny, nz): chessboard distance (cells) to the nearest occupied cell, 0 if occupied

    @property
    def shape(self) -> tuple[int, int, int]:
        s = self.occupied.shape
        return int(s[0]), int(s[1]), int(s[2])

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """Integer cell indices (N, 3) of world points (N, 3) (may lie outside the grid)."""
        return np.floor((np.asarray(points, np.float64) - self.origin) / self.resolution).astype(np.int64)

    def centres(self, cells: np.ndarray) -> np.ndarray:
        return self.origin + (np.asarray(cells, np.float64) + 0.5) * self.resolution

    def inside(self, cells: np.ndarray) -> np.ndarray:
        return np.all((cells >= 0) & (cells < np.asarray(self.shape)), axis=-1)


def grid_from_points(points: np.ndarray, resolution: float = 0.15, pad: int = 2) -> VoxelGrid:
    """The occupancy grid of voxel centres ``points`` (N, 3) on a lattice of spacing ``resolution``.

    The grid is aligned so that each centre lies in the middle of its cell; ``pad`` free cells surround the
    map on every side.
    """
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError("a voxel map needs at least one (x, y, z) point")
    if not np.isfinite(pts).all():
        raise ValueError("a voxel map holds non-finite coordinates")
    res = float(resolution)
    # lattice phase from the first point: centres sit at phase + (n + 1/2) res
    phase = pts[0] - res * (np.round(pts[0] / res - 0.5) + 0.5)
    lo = np.floor((pts.min(0) - phase) / res) - pad
    origin = phase + lo * res
    cells = np.floor((pts - origin) / res + 1e-6).astype(np.int64)
    shape = tuple(int(v) for v in cells.max(0) + pad + 1)
    occ = np.zeros(shape, dtype=bool)
    occ[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    dist = ndimage.distance_transform_cdt(~occ, metric="chessboard")
    clearance = np.clip(dist, 0, MAX_CLEARANCE).astype(np.uint8)
    return VoxelGrid(origin=origin, resolution=res, occupied=occ, clearance=clearance)


@dataclass(frozen=True)
class GridHits:
    """First occupied cells along rays (flat arrays, one entry per ray)."""

    range: np.ndarray  # (R,) metres to the entry point of the first occupied cell (inf: none)
    axis: np.ndarray  # (R,) int8 axis of the crossed face (0 x, 1 y, 2 z; -1: no hit)
    cell: np.ndarray  # (R, 3) int64 the hit cell (-1 when none)
    steps: int  # march iterations used


def cast_rays(grid: VoxelGrid, origins: np.ndarray, directions: np.ndarray, max_range: float = np.inf,
              max_iterations: int = 100_000) -> GridHits:
    """March rays ``origins`` (R, 3) along unit ``directions`` (R, 3) through ``grid`` (see the module doc)."""
    res = grid.resolution
    o = (np.asarray(origins, np.float64) - grid.origin) / res  # cell units
    d = np.asarray(directions, np.float64)
    n = len(o)
    shape = np.asarray(grid.shape)
    t_max = min(float(max_range) / res, float(np.sum(shape)) * 2.0)  # a ray leaves the grid before this
    rng = np.full(n, np.inf)
    axis_out = np.full(n, -1, np.int8)
    cell_out = np.full((n, 3), -1, np.int64)
    if n == 0:
        return GridHits(rng, axis_out, cell_out, 0)
    step = np.sign(d).astype(np.int64)
    with np.errstate(divide="ignore"):
        inv = np.where(d != 0.0, 1.0 / d, np.inf)
    dmax = np.abs(d).max(1)
    v = np.floor(o).astype(np.int64)
    t = np.zeros(n)
    # rays starting outside the grid: advance to where they enter its box (or miss)
    outside = ~grid.inside(v)
    if outside.any():
        with np.errstate(invalid="ignore"):
            t0 = np.where(np.isfinite(inv), (np.where(d > 0, 0.0, shape) - o) * inv, -np.inf)
            t1 = np.where(np.isfinite(inv), (np.where(d > 0, shape, 0.0) - o) * inv, np.inf)
        # an axis with d = 0 constrains nothing when the origin is within its slab
        slab_ok = np.where(np.isfinite(inv), True, (o >= 0) & (o < shape))
        t_in = np.maximum(t0.max(1), 0.0)
        t_out = t1.min(1)
        enter = outside & slab_ok.all(1) & (t_in < t_out) & (t_in < t_max)
        t[enter] = t_in[enter] + 1e-9
        v[enter] = np.clip(np.floor(o[enter] + t[enter, None] * d[enter]).astype(np.int64), 0, shape - 1)
    active = np.nonzero(~outside | enter)[0] if outside.any() else np.arange(n)
    started = np.zeros(n, bool)  # the first cell of each ray is never a hit
    started[outside] = True  # ... unless the ray entered the grid from outside
    last_axis = np.full(n, -1, np.int8)
    it = 0
    while len(active) and it < max_iterations:
        it += 1
        va = v[active]
        occ = grid.occupied[va[:, 0], va[:, 1], va[:, 2]] & started[active]
        if occ.any():
            h = active[occ]
            rng[h] = t[h] * res
            axis_out[h] = last_axis[h]
            cell_out[h] = v[h]
            active = active[~occ]
            va = va[~occ]
            if not len(active):
                break
        started[active] = True
        k = grid.clearance[va[:, 0], va[:, 1], va[:, 2]].astype(np.float64)
        jump = k >= 2
        if jump.any():
            j = active[jump]
            t[j] += (k[jump] - 1.0 - JUMP_MARGIN) / dmax[j]
            v[j] = np.floor(o[j] + t[j, None] * d[j]).astype(np.int64)
        walk = active[~jump]
        if len(walk):
            vw = v[walk]
            with np.errstate(invalid="ignore"):
                tn = (vw + (step[walk] > 0) - o[walk]) * inv[walk]
            tn = np.where(np.isfinite(tn), tn, np.inf)
            ax = np.argmin(tn, axis=1)
            rows = np.arange(len(walk))
            t[walk] = np.maximum(tn[rows, ax], t[walk])
            vw[rows, ax] += step[walk][rows, ax]
            v[walk] = vw
            last_axis[walk] = ax.astype(np.int8)
        keep = grid.inside(v[active]) & (t[active] <= t_max)
        active = active[keep]
    miss = rng * 1.0 > max_range
    rng[miss] = np.inf
    axis_out[miss] = -1
    cell_out[miss] = -1
    return GridHits(rng, axis_out, cell_out, it)


def cast_voxels_brute(grid: VoxelGrid, origins: np.ndarray, directions: np.ndarray,
                      max_range: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Reference: per ray, the nearest occupied voxel box it enters (slab test against every voxel).

    Returns (range, cell index (R, 3)); the box containing the origin is skipped as in :func:`cast_rays`.
    Quadratic in rays x voxels: only for tiny grids (tests).
    """
    cells = np.argwhere(grid.occupied)
    lo = grid.origin + cells * grid.resolution
    hi = lo + grid.resolution
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        ta = (lo[None] - o[:, None]) * inv[:, None]
        tb = (hi[None] - o[:, None]) * inv[:, None]
    # d = 0 on an axis: inside the slab -> (-inf, inf), outside -> empty
    zero = d[:, None, :] == 0
    inside = (o[:, None] >= lo[None]) & (o[:, None] < hi[None])
    t_near = np.where(zero, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb)).max(-1)
    t_far = np.where(zero, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb)).min(-1)
    own = np.all(inside, axis=-1)
    ok = (t_near <= t_far) & (t_far > 0) & ~own & (t_near >= 0)
    t_hit = np.where(ok, t_near, np.inf)
    best = np.argmin(t_hit, axis=1) if len(cells) else np.zeros(len(o), np.int64)
    r = t_hit[np.arange(len(o)), best] if len(cells) else np.full(len(o), np.inf)
    r = np.where(r <= max_range, r, np.inf)
    cell = np.where(np.isfinite(r)[:, None], cells[best] if len(cells) else -1, -1)
    return r, cell


@dataclass(frozen=True)
class VoxelScene(Scene):
    """A :class:`~simulator.world.Scene` with no primitives whose geometry is a voxel grid.

    :func:`simulator.raycast.cast` dispatches to :func:`cast_scene` for it. One material (``voxel``) for
    every surface: the maps carry no material.
    """

    grid: VoxelGrid
    #: the radar's occlusion test allows a hit this much in front of a scatterer (a surface voxel's depth)
    occlusion_slack: float

    def cast_fan(self, origins: np.ndarray, headings: np.ndarray, slopes: np.ndarray,
                 max_range: float = np.inf) -> Hits:
        """What :func:`simulator.raycast.cast` calls for this scene."""
        return cast_scene(self, origins, headings, slopes, max_range)


def voxel_scene(name: str, grid: VoxelGrid, radar_db: float = 0.0, specular: float = 0.5,
                lidar_reflectivity: float = 0.5) -> VoxelScene:
    """The scene of a voxel grid (one material; floor = the bottom of the occupied cells, no ceiling)."""
    z0 = float(grid.origin[2] + grid.resolution * np.argwhere(grid.occupied.any((0, 1)))[0, 0])
    e2 = np.zeros((0, 2))
    e1 = np.zeros(0)
    ei = np.zeros(0, np.int64)
    return VoxelScene(
        name=name, seg_a=e2, seg_b=e2, seg_z=e2, seg_mat=ei, cyl_c=e2, cyl_r=e1, cyl_z=e2, cyl_mat=ei,
        rect_c=e2, rect_half=e2, rect_cs=e2, rect_z=e1, rect_mat=ei, disc_c=e2, disc_r=e1, disc_z=e1,
        disc_mat=ei, floor=z0, ceiling=None, floor_mat=0, ceiling_mat=0, material_names=("voxel",),
        radar_db=np.array([radar_db]), specular=np.array([specular]),
        lidar_reflectivity=np.array([lidar_reflectivity]), grid=grid, occlusion_slack=grid.resolution,
    )


def cast_scene(scene: VoxelScene, origins: np.ndarray, headings: np.ndarray, slopes: np.ndarray,
               max_range: float = np.inf) -> Hits:
    """:func:`simulator.raycast.cast` for a voxel scene: fans of rays, first occupied voxel per ray."""
    o = np.asarray(origins, np.float64)
    g = len(o)
    m = np.broadcast_to(np.asarray(slopes, np.float64), (g, np.shape(slopes)[-1]))
    e = m.shape[1]
    dirs = directions(headings, m)  # (G, E, 3)
    flat = cast_rays(scene.grid, np.repeat(o, e, axis=0), dirs.reshape(-1, 3), max_range)
    rng = flat.range.reshape(g, e)
    ax = flat.axis.reshape(g, e)
    hit = np.isfinite(rng)
    kind = np.full((g, e), KIND_NONE, np.int8)
    kind[hit & (ax < 2)] = KIND_SEGMENT  # a vertical face
    kind[hit & (ax == 2) & (dirs[..., 2] < 0)] = KIND_FLOOR  # an upward-facing face
    kind[hit & (ax == 2) & (dirs[..., 2] > 0)] = KIND_CEILING
    cos_inc = np.where(hit, np.abs(np.take_along_axis(dirs, np.maximum(ax, 0)[..., None].astype(np.int64),
                                                      axis=-1)[..., 0]), 0.0)
    nxy = np.zeros((g, e, 2))
    for a in (0, 1):
        sel = hit & (ax == a)
        nxy[..., a] = np.where(sel, -np.sign(dirs[..., a]), 0.0)
    material = np.where(hit, 0, -1).astype(np.int64)
    return Hits(range=rng, kind=kind, material=material, cos_incidence=cos_inc, normal_xy=nxy)

