"""2D correlative scan matching on a likelihood field (Olson, "Real-time correlative scan matching", ICRA 2009).

Pure numpy and scipy. A reference point set (a local map) is rasterised into a likelihood field: each cell holds
the log-likelihood of a point there, ``log(z_hit exp(-d^2 / 2 sigma^2) + z_rand)`` with ``d`` the distance to the
nearest reference point. A query point set is scored at every candidate pose of an exhaustive search over yaw and
translation, coarse to fine; the best pose is the estimate and the candidates' scores, read as a likelihood
tempered by ``temperature`` (the points are not independent), give its covariance (Olson, Sec. III-D).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import ndimage

F64 = npt.NDArray[np.floating[Any]]


@dataclass(frozen=True)
class MatcherModel:
    """The likelihood field and the search of :func:`match`."""

    resolution: float = 0.1  # m, cell size of the fine field and translation step
    sigma: float = 0.15  # m, std of a point's distance to the reference
    z_rand: float = 0.05  # weight of the uniform term (a point the map does not explain)
    coarse_factor: int = 4  # the coarse field's cells are this many fine cells
    yaw_step_deg: float = 0.5  # the fine yaw step
    temperature: float = 30.0  # divides the summed log-likelihood when read as a pose likelihood
    inlier_distance: float = 0.3  # m: a query point within this of the reference counts as matched
    candidates: int = 4  # coarse candidates refined at the fine level


@dataclass(frozen=True)
class LikelihoodField:
    """Log-likelihood per cell on a grid whose cell ``(i, j)`` is centred at ``origin + (i, j) * resolution``."""

    log_p: F64  # (nx, ny)
    distance: F64  # (nx, ny) metres to the nearest reference point
    origin: F64  # (2,)
    resolution: float
    floor: float  # log-likelihood outside the grid


def likelihood_field(reference: F64, model: MatcherModel, margin: float, resolution: float | None = None
                     ) -> LikelihoodField:
    """The field of ``reference (N, 2)`` over its bounding box grown by ``margin`` (m)."""
    res = model.resolution if resolution is None else resolution
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    lo = ref.min(axis=0) - margin
    hi = ref.max(axis=0) + margin
    shape = np.ceil((hi - lo) / res).astype(int) + 1
    occ = np.ones(tuple(shape), dtype=bool)
    idx = np.round((ref - lo) / res).astype(int)
    occ[idx[:, 0], idx[:, 1]] = False
    d = ndimage.distance_transform_edt(occ) * res
    floor = float(np.log(model.z_rand))
    log_p = np.log(np.exp(-0.5 * (d / model.sigma) ** 2) * (1.0 - model.z_rand) + model.z_rand)
    return LikelihoodField(log_p, d, lo, res, floor)


def coarse_field(fine: LikelihoodField, factor: int) -> LikelihoodField:
    """A field at ``factor`` times the cell size whose cells hold the best fine value within reach (an upper bound
    of the fine score at any translation inside the coarse cell, as in Olson's multi-resolution search)."""
    best = ndimage.maximum_filter(fine.log_p, size=2 * factor + 1, mode="nearest")
    near = ndimage.minimum_filter(fine.distance, size=2 * factor + 1, mode="nearest")
    return LikelihoodField(best[::factor, ::factor], near[::factor, ::factor], fine.origin, fine.resolution * factor,
                           fine.floor)


def _rotate(points: F64, yaws: F64) -> F64:
    """``points (N, 2)`` rotated by each of ``yaws (K,)``: ``(K, N, 2)``."""
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    x, y = points[None, :, 0], points[None, :, 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=-1)


def _scores(field: LikelihoodField, points: F64, yaws: F64, centre_xy: F64, half_cells: int
            ) -> tuple[F64, F64]:
    """Summed log-likelihood of ``points`` (query frame) at every yaw of ``yaws`` and translation
    ``centre_xy + (i, j) * field.resolution``, ``|i|, |j| <= half_cells``: ``(K, 2h+1, 2h+1)`` scores and the
    translations' offsets ``(2h+1,)`` in metres."""
    res = field.resolution
    offs = np.arange(-half_cells, half_cells + 1)
    nx, ny = field.log_p.shape
    out = np.empty((len(yaws), len(offs), len(offs)))
    for k, placed in enumerate(_rotate(points, yaws) + centre_xy):  # one yaw at a time: memory N * S^2
        base = np.round((placed - field.origin) / res).astype(np.int64)
        ix = base[:, 0, None] + offs[None, :]  # (N, S)
        iy = base[:, 1, None] + offs[None, :]
        inside = ((ix >= 0) & (ix < nx))[:, :, None] & ((iy >= 0) & (iy < ny))[:, None, :]
        vals = field.log_p[np.clip(ix, 0, nx - 1)[:, :, None], np.clip(iy, 0, ny - 1)[:, None, :]]
        out[k] = np.where(inside, vals, field.floor).sum(axis=0)
    return out, offs * res


@dataclass(frozen=True)
class Match:
    """A registration result: the pose of the query frame in the reference frame and its quality."""

    pose: F64  # (3,) x, y, yaw
    cov: F64  # (3, 3)
    score: float  # mean log-likelihood per point at the best pose
    inliers: float  # share of the query points within ``inlier_distance`` of the reference at the best pose
    n_points: int


def log_prior(offsets: F64, info: F64 | None) -> F64:
    """``-1/2 d^T S^-1 d`` of pose offsets ``(..., 3)`` from the guess, ``info = S^-1`` the prior's information
    matrix; 0 without a prior."""
    if info is None:
        return np.zeros(offsets.shape[:-1])
    return -0.5 * np.einsum("...i,ij,...j->...", offsets, info, offsets)


def _grid_offsets(yaws: F64, xy_offs: F64, guess: F64) -> F64:
    """Pose offsets from ``guess`` of a (yaw, x, y) candidate grid, ``(n_yaw, n_x, n_y, 3)``."""
    dyaw = yaws - guess[2]
    dx, dy = np.meshgrid(xy_offs[0], xy_offs[1], indexing="ij")
    out = np.empty((len(yaws), *dx.shape, 3))
    out[..., 0], out[..., 1], out[..., 2] = dx[None], dy[None], dyaw[:, None, None]
    return out


def match(reference: F64, query: F64, guess: npt.ArrayLike, model: MatcherModel, search_xy: float,
          search_yaw_deg: float, field: LikelihoodField | None = None, prior_cov: F64 | None = None) -> Match:
    """Register ``query (N, 2)`` (its own frame) against ``reference (M, 2)``: the pose of the query frame in the
    reference frame that maximises the summed field log-likelihood within ``search_xy`` (m) and ``search_yaw_deg``
    of ``guess (3,)``. Coarse level: the field pooled by ``coarse_factor``, yaw steps of ``coarse_factor`` fine
    steps, over the whole window; fine level: the best ``candidates`` coarse poses refined over one coarse cell
    and step. With ``prior_cov`` (the covariance of the pose around ``guess``, in the reference frame) the
    candidates are ranked by their posterior, ``score / temperature`` plus the Gaussian log prior (Olson, Sec.
    III-B), so that an aliased match far from what the odometry allows loses to a nearby one; without it, by the
    score alone. The covariance is that of the fine candidates weighted by ``exp(score / temperature)``, the
    likelihood alone (Olson, Sec. III-D; the prior is the odometry's, which the graph holds already), at least
    the search resolution's own (cell^2 / 12)."""
    guess = np.asarray(guess, dtype=np.float64).reshape(3)
    q = np.asarray(query, dtype=np.float64).reshape(-1, 2)
    if field is None:
        field = likelihood_field(reference, model, margin=search_xy + float(np.max(np.abs(q))) if len(q) else 1.0)
    if len(q) == 0:
        raise ValueError("match: the query holds no points")
    f = model.coarse_factor
    coarse = coarse_field(field, f)
    fine_step = np.radians(model.yaw_step_deg)
    coarse_step = fine_step * f
    n_yaw = int(np.ceil(np.radians(search_yaw_deg) / coarse_step))
    yaws = guess[2] + coarse_step * np.arange(-n_yaw, n_yaw + 1)
    half = int(np.ceil(search_xy / coarse.resolution))
    sc, offs = _scores(coarse, q, yaws, guess[:2], half)
    info = None if prior_cov is None else np.linalg.inv(prior_cov)
    rank = sc / model.temperature + log_prior(_grid_offsets(yaws, np.stack([offs, offs]), guess), info)
    flat = np.argsort(rank.ravel())[::-1][: model.candidates]
    best_score = -np.inf
    best: tuple[F64, F64, F64, F64] | None = None
    for k in flat:
        a, i, j = np.unravel_index(k, sc.shape)
        centre = guess[:2] + np.array([offs[i], offs[j]])
        fy = yaws[a] + fine_step * np.arange(-f, f + 1)
        fs, foffs = _scores(field, q, fy, centre, f)
        fr = fs / model.temperature + log_prior(
            _grid_offsets(fy, np.stack([centre[0] - guess[0] + foffs, centre[1] - guess[1] + foffs]), guess),
            info)
        m = float(fr.max())
        if m > best_score:
            best_score, best = m, (fr, fs, fy, centre + np.stack(np.meshgrid(foffs, foffs, indexing="ij"), -1))
    assert best is not None
    post, fs, fy, xy = best  # posterior, likelihood, yaws, translations of the fine window
    a, i, j = np.unravel_index(int(np.argmax(post)), post.shape)
    pose = np.array([xy[i, j, 0], xy[i, j, 1], fy[a]])
    w = np.exp((fs - fs.max()) / model.temperature)
    w /= w.sum()
    cand = np.concatenate([np.broadcast_to(xy[None], (len(fy), *xy.shape)),
                           np.broadcast_to(fy[:, None, None, None], (len(fy), *xy.shape[:2], 1))], axis=-1)
    d = cand.reshape(-1, 3) - pose
    cov = (d * w.reshape(-1, 1)).T @ d
    cov += np.diag([field.resolution**2 / 12, field.resolution**2 / 12, fine_step**2 / 12])
    placed = _rotate(q, np.array([pose[2]]))[0] + pose[:2]
    idx = np.round((placed - field.origin) / field.resolution).astype(np.int64)
    nx, ny = field.distance.shape
    ok = (idx[:, 0] >= 0) & (idx[:, 0] < nx) & (idx[:, 1] >= 0) & (idx[:, 1] < ny)
    dist = np.full(len(q), np.inf)
    dist[ok] = field.distance[idx[ok, 0], idx[ok, 1]]
    return Match(pose, cov, float(fs[a, i, j]) / len(q), float(np.mean(dist <= model.inlier_distance)), len(q))
