"""Per-particle log-odds occupancy grids with a likelihood-field weight: the FastSLAM-Radar baseline.

Pure numpy. The same RBPF as RICH-SLAM drives it (:class:`GridParticleMaps` implements
``ParticleMaps``); only the map (a discrete grid, cells independent) and the weight differ. The weight
is the classic likelihood field (Thrun et al., Probabilistic Robotics 6.4) restricted to a window:
each endpoint scores ``z_hit N(d; 0, sigma^2) + z_rand`` with ``d`` the distance to the nearest
occupied cell, capped at ``max_dist`` (GMapping's windowed search is the same idea).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.slam.beam_sampling import BeamSamples, to_world

F64 = npt.NDArray[np.floating[Any]]


@dataclass(frozen=True)
class GridSpec:
    """A regular grid: cell (iy, ix) covers ``origin + [ix, ix+1) res`` x ``[iy, iy+1) res``."""

    origin: F64  # (2,) lower-left corner [m]
    resolution: float
    shape: tuple[int, int]  # (ny, nx)

    @property
    def n_cells(self) -> int:
        return self.shape[0] * self.shape[1]

    def cell_index(self, points: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
        """Flat cell index of points ``(..., 2)`` and whether they fall inside the grid."""
        p = np.asarray(points, dtype=np.float64)
        ij = np.floor((p - self.origin) / self.resolution).astype(np.int64)
        ix, iy = ij[..., 0], ij[..., 1]
        ok = (ix >= 0) & (ix < self.shape[1]) & (iy >= 0) & (iy < self.shape[0])
        return np.where(ok, iy * self.shape[1] + ix, 0), ok

    def centres(self) -> tuple[F64, F64]:
        """Cell-centre coordinates (x of columns, y of rows)."""
        xs = self.origin[0] + (np.arange(self.shape[1]) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(self.shape[0]) + 0.5) * self.resolution
        return xs, ys


def make_grid_spec(centre: npt.ArrayLike, half_widths: npt.ArrayLike, resolution: float) -> GridSpec:
    """A grid covering ``centre +- half_widths``."""
    c = np.asarray(centre, dtype=np.float64)
    L = np.asarray(half_widths, dtype=np.float64)
    n = np.ceil(2 * L / resolution).astype(int)
    return GridSpec(c - L, float(resolution), (int(n[1]), int(n[0])))


@dataclass(frozen=True)
class GridModel:
    """Inverse sensor model and likelihood-field parameters."""

    l_occ: float = 0.85
    l_free: float = -0.4
    l_min: float = -4.0
    l_max: float = 4.0
    #: a cell counts as occupied in the likelihood field above this log-odds
    occupied_threshold: float = 0.0
    sigma_hit: float = 0.2
    max_dist: float = 0.5
    z_hit: float = 0.9
    z_rand: float = 0.1


def beam_cells(
    spec: GridSpec, origins: F64, endpoints: F64
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """Free and endpoint cells of beams for a batch of particles.

    ``origins (Np, 2)``, ``endpoints (Np, B, 2)`` world frame. Free cells are traversed by sampling
    each beam every half cell (excluding the endpoint cell). Returns flat indices into the stacked
    grids ``(Np * n_cells)``: unique free cells (endpoint cells removed), endpoint cells, and a
    validity mask of the endpoint cells.
    """
    Np, B = endpoints.shape[:2]
    if B == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros((Np, 0), bool)
    d = endpoints - origins[:, None, :]
    length = np.linalg.norm(d, axis=-1)
    step = 0.5 * spec.resolution
    n_max = int(np.ceil(length.max() / step)) if length.size else 0
    t = np.arange(n_max) * step  # (S,)
    frac = t[None, None, :] / np.maximum(length[..., None], 1e-12)
    inside_beam = frac < 1.0
    pts = origins[:, None, None, :] + frac[..., None] * d[:, :, None, :]  # (Np, B, S, 2)
    free_idx, free_ok = spec.cell_index(pts)
    end_idx, end_ok = spec.cell_index(endpoints)
    offset = (np.arange(Np) * spec.n_cells)[:, None]
    free_flat = (free_idx + offset[:, :, None])[inside_beam & free_ok]
    end_flat = (end_idx + offset)[end_ok]
    free_flat = np.setdiff1d(np.unique(free_flat), end_flat, assume_unique=False)
    return free_flat, end_flat, end_ok


def update_grids(grids: npt.NDArray[np.float32], spec: GridSpec, origins: F64, endpoints: F64,
                 model: GridModel) -> None:
    """Log-odds update of every particle's grid in place (inverse sensor model, clamped)."""
    free_flat, end_flat, _ = beam_cells(spec, origins, endpoints)
    flat = grids.reshape(-1)
    flat[free_flat] += np.float32(model.l_free)
    end_u = np.unique(end_flat)
    flat[end_u] += np.float32(model.l_occ)
    touched = np.concatenate([free_flat, end_u])
    flat[touched] = np.clip(flat[touched], model.l_min, model.l_max)


def window_offsets(spec: GridSpec, max_dist: float) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F64]:
    """Cell offsets (dy, dx) within ``max_dist`` and their distances, nearest first."""
    w = int(np.ceil(max_dist / spec.resolution))
    dy, dx = np.meshgrid(np.arange(-w, w + 1), np.arange(-w, w + 1), indexing="ij")
    dist = spec.resolution * np.hypot(dy, dx).ravel()
    keep = dist <= max_dist
    order = np.argsort(dist[keep], kind="stable")
    return dy.ravel()[keep][order], dx.ravel()[keep][order], dist[keep][order]


def nearest_occupied_distance(grids: npt.NDArray[np.float32], spec: GridSpec, points: F64,
                              model: GridModel) -> F64:
    """Distance from each point ``(Np, B, 2)`` to the nearest occupied cell of its particle's grid.

    Capped at ``max_dist`` (no occupied cell in the window, or outside the grid).
    """
    Np = points.shape[0]
    dy, dx, dist = window_offsets(spec, model.max_dist)
    ij = np.floor((points - spec.origin) / spec.resolution).astype(np.int64)
    iy = ij[..., 1][..., None] + dy  # (Np, B, W)
    ix = ij[..., 0][..., None] + dx
    ny, nx = spec.shape
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    flat = np.where(ok, iy * nx + ix, 0) + (np.arange(Np) * spec.n_cells)[:, None, None]
    occ = (grids.reshape(-1)[flat] > model.occupied_threshold) & ok
    d = np.where(occ, dist, np.inf).min(axis=-1)
    return np.minimum(d, model.max_dist)


def likelihood_field_log_likelihood(grids: npt.NDArray[np.float32], spec: GridSpec, endpoints: F64,
                                    model: GridModel) -> F64:
    """Per-particle ``sum_b log(z_hit exp(-d_b^2 / 2 sigma^2) + z_rand)`` over endpoints ``(Np, B, 2)``."""
    if endpoints.shape[1] == 0:
        return np.zeros(endpoints.shape[0])
    d = nearest_occupied_distance(grids, spec, endpoints, model)
    return np.sum(np.log(model.z_hit * np.exp(-0.5 * (d / model.sigma_hit) ** 2) + model.z_rand), axis=1)


def occupancy_probability(grid: npt.ArrayLike) -> F64:
    """``1 / (1 + exp(-l))`` per cell."""
    return 1.0 / (1.0 + np.exp(-np.asarray(grid, dtype=np.float64)))


class GridParticleMaps:
    """One log-odds grid per particle, stacked ``(Np, ny, nx)`` float32."""

    def __init__(self, spec: GridSpec, n_particles: int, model: GridModel) -> None:
        self.spec = spec
        self.model = model
        self.grids = np.zeros((n_particles, *spec.shape), dtype=np.float32)

    def log_likelihood(self, poses: F64, samples: BeamSamples) -> F64:
        ends = to_world(poses, samples.endpoints)
        return likelihood_field_log_likelihood(self.grids, self.spec, ends, self.model)

    def update(self, poses: F64, samples: BeamSamples) -> None:
        if len(samples.endpoints) == 0:
            return
        origins = to_world(poses, samples.origin[None, :])[:, 0, :]
        update_grids(self.grids, self.spec, origins, to_world(poses, samples.endpoints), self.model)

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        self.grids = self.grids[indices]
