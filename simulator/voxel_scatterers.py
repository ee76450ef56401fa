"""Radar scatterers on the surfaces of a voxel map (the twins' counterpart of :mod:`simulator.scatterers`).

The same scatterer model as the built-in worlds, on the voxel surfaces:

- **surface scatterers**: every *surface voxel* (occupied, with a free face neighbour) holds a Poisson
  number of diffuse scatterers, ``scatterer_density * res^2`` on average, each with backscatter
  ``surface_sigma0_db + area`` and a once-drawn Rayleigh factor, falling as ``cos(incidence)**exponent``
  about the local surface normal. The normal is the least-variance axis of the occupied voxels in a
  ``(2 w + 1)^3`` box around the voxel (principal component analysis from box-filtered moments), pointed
  towards the voxel's free faces; the scatterer sits on the surface (half a voxel from the centre along
  the normal, with a random offset within the face);
- **edge scatterers** (strong): surface voxels where the neighbourhood is not planar (surface variation
  ``l_min / (l_0 + l_1 + l_2)`` above ``edge_variation``: edges, corners, furniture, clutter) hold a point
  scatterer of ``dihedral_rcs_db`` (+ the once-drawn spread) with probability ``edge_density * res``
  (``edge_density`` per metre of edge).

A surface scatterer is only returned towards a radar on the side its normal faces (a voxel map's thin
walls have two sides one voxel apart). No multipath ghosts: the voxel world has no mirror faces.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from simulator.params import RadarParams
from simulator.scatterers import KIND_CORNER, KIND_SURFACE, Returns, Scatterers
from simulator.voxel_world import VoxelGrid

_NEIGHBOURS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])


class VoxelScatterParams(BaseModel):
    """How scatterers are drawn on a voxel map."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    normal_window: int = Field(2, ge=1, le=4, description="half width w of the (2w+1)^3 voxel box of the normals")
    edge_variation: float = Field(0.12, gt=0, lt=1 / 3, description="surface variation above which a surface voxel "
                                                                    "is an edge or corner")
    edge_density: float = Field(1.0, ge=0, description="strong edge scatterers per metre of edge")


@dataclass(frozen=True)
class VoxelScatterers(Scatterers):
    """Scatterers of a voxel map; surface points are one-sided (see the module doc)."""

    pt_two_sided: np.ndarray  # (N,) bool: a surface point of a one-voxel-thin sheet, seen from both sides

    def returns(self, origin: np.ndarray, max_range: float) -> Returns:
        d = origin - self.pt_pos
        near = np.nonzero((np.abs(d) < max_range).all(1))[0]
        facing = ((self.pt_kind[near] != KIND_SURFACE) | self.pt_two_sided[near]
                  | ((d[near] * self.pt_normal[near]).sum(1) > 0))
        k = near[facing]
        sub = replace(self, pt_pos=self.pt_pos[k], pt_normal=self.pt_normal[k], pt_rcs_db=self.pt_rcs_db[k],
                      pt_kind=self.pt_kind[k], pt_wedge=self.pt_wedge[k], pt_specular=self.pt_specular[k],
                      pt_two_sided=self.pt_two_sided[k])
        return Scatterers.returns(sub, origin, max_range)


def surface_normals(grid: VoxelGrid, cells: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (N, 3) and surface variation (N,) at ``cells`` (N, 3) from the occupied voxels around them."""
    occ = grid.occupied.astype(np.float64)
    size = 2 * window + 1
    idx = np.indices(grid.shape, dtype=np.float64)
    sums: dict[tuple[int, ...], np.ndarray] = {}

    def box(a: np.ndarray) -> np.ndarray:
        f = ndimage.uniform_filter(a, size=size, mode="constant")
        return np.asarray(f[cells[:, 0], cells[:, 1], cells[:, 2]], np.float64)

    s0 = box(occ)
    for i in range(3):
        sums[(i,)] = box(occ * idx[i])
    for i in range(3):
        for j in range(i, 3):
            sums[(i, j)] = box(occ * idx[i] * idx[j])
    n = len(cells)
    cov = np.zeros((n, 3, 3))
    s0 = np.maximum(s0, 1e-12)
    for i in range(3):
        for j in range(i, 3):
            c = sums[(i, j)] / s0 - sums[(i,)] * sums[(j,)] / s0**2
            cov[:, i, j] = cov[:, j, i] = c
    w, v = np.linalg.eigh(cov)
    normal = v[:, :, 0]
    variation = w[:, 0] / np.maximum(w.sum(1), 1e-12)
    return normal, variation


def build_voxel_scatterers(grid: VoxelGrid, p: RadarParams, vp: VoxelScatterParams,
                           rng: np.random.Generator) -> VoxelScatterers:
    """Draw the scatterers of ``grid`` (deterministic for a given ``rng`` state)."""
    occ = grid.occupied
    cells = np.argwhere(occ)
    shape = np.asarray(grid.shape)
    free_dir = np.zeros((len(cells), 3))  # sum of the directions to free face neighbours
    surface = np.zeros(len(cells), bool)  # any free face neighbour (also when the directions cancel)
    for nb in _NEIGHBOURS:
        c = cells + nb
        ok = np.all((c >= 0) & (c < shape), axis=1)
        free = np.ones(len(cells), bool)
        free[ok] = ~occ[c[ok, 0], c[ok, 1], c[ok, 2]]
        free_dir += free[:, None] * nb
        surface |= free
    cells, free_dir = cells[surface], free_dir[surface]
    normal, variation = surface_normals(grid, cells, vp.normal_window)
    towards_free = (normal * free_dir).sum(1)
    normal *= np.where(towards_free < 0, -1.0, 1.0)[:, None]
    two_sided = np.abs(towards_free) < 0.5  # free on both sides along the normal: a thin sheet
    res = grid.resolution
    centre = grid.centres(cells)

    # diffuse surface scatterers
    count = rng.poisson(p.scatterer_density * res * res, len(cells))
    which = np.repeat(np.arange(len(cells)), count)
    nrm = normal[which]
    # a random point of the voxel's cross-section normal to n, moved onto the surface
    off = rng.uniform(-0.5, 0.5, (len(which), 3)) * res
    off -= (off * nrm).sum(1, keepdims=True) * nrm
    pos_s = centre[which] + np.where(two_sided[which], 0.0, 0.5 * res)[:, None] * nrm + off
    area_db = -10 * np.log10(p.scatterer_density)
    rcs_s = p.surface_sigma0_db + area_db + 10 * np.log10(np.maximum(rng.exponential(1.0, len(which)), 1e-12))

    # strong edge scatterers
    edge = np.nonzero((variation > vp.edge_variation) & (rng.random(len(cells)) < vp.edge_density * res))[0]
    pos_e = centre[edge] + 0.5 * res * normal[edge]
    rcs_e = p.dihedral_rcs_db + rng.normal(0.0, p.strong_rcs_spread_db, len(edge))

    n_s, n_e = len(which), len(edge)
    e3, e0 = np.zeros((0, 3)), np.zeros(0)
    return VoxelScatterers(
        pt_pos=np.concatenate([pos_s, pos_e]), pt_normal=np.concatenate([nrm, np.zeros((n_e, 3))]),
        pt_rcs_db=np.concatenate([rcs_s, rcs_e]),
        pt_kind=np.concatenate([np.full(n_s, KIND_SURFACE, np.int8), np.full(n_e, KIND_CORNER, np.int8)]),
        pt_wedge=np.full(n_s + n_e, -1, np.int64), pt_specular=np.concatenate([np.full(n_s, 0.5), np.zeros(n_e)]),
        line_a=e3, line_b=e3, line_radius=e0, line_rcs_db=e0, line_convex_rcs_db=e0,
        line_wedge=np.zeros(0, np.int64), line_kind=np.zeros(0, np.int8), wedge_v=np.zeros((0, 2)),
        wedge_e1=np.zeros((0, 2)), wedge_e2=np.zeros((0, 2)), incidence_exponent=p.incidence_exponent,
        tip_loss_db=p.tip_loss_db, pt_two_sided=np.concatenate([two_sided[which], np.zeros(n_e, bool)]),
    )

