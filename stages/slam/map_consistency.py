"""How well a trajectory makes the radar's scans agree with each other, and the fused correction it prefers.

A trajectory with the heading right puts a wall seen now where the same wall was seen a while ago; a heading
error smears it. :func:`map_consistency` scores that without ground truth: every scan's endpoints are put in
the world along the trajectory (one point per ``cell`` and ``block`` seconds), and each point's distance to the
nearest point of a scan at least ``separation`` seconds away (the scans around it agree whatever the heading),
truncated at ``truncation``, is squared and averaged: lower is more consistent. It is the likelihood field that
fastslam_grid's weight uses (a distance to the nearest endpoint, capped), taken over the whole run at once
instead of one scan against the map before it.

:func:`consistent_scale` uses it on the fused estimate (stages/slam/README.md, stop 51): the fusion's heading
correction ``c`` (:func:`heading_fusion.fuse_heading`) is applied scaled by the ``alpha`` in
``{0, step, ..., alpha_max}`` whose trajectory (:func:`heading_fusion.recompose`) scores lowest (or, with
``MapConsistency.criterion = 'matched'``, whose matched points agree best; with ``'common'``, whose one fixed set
of points matched at every scale agrees best, :func:`common_support_scores`). ``alpha = 0``
is the odometry and ``alpha = 1`` the fused estimate, so the scan's own geometry decides how much of the
filter's heading the result keeps.

The score has a measured bias (stages/slam/README.md, stop 52): it falls when the trajectory contracts, because
more points then find a counterpart within the cap whether or not they agree (:func:`consistency_parts` splits
the two). :func:`scaled_positions` and :func:`heading_ramp` are the perturbations that show it, against the truth
(:mod:`consistency_sweep`).

Pure numpy/scipy on arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.spatial import cKDTree

from stages.slam.heading_fusion import recompose

F64 = npt.NDArray[np.floating[Any]]
I64 = npt.NDArray[np.int64]


class MapConsistency(BaseModel):
    """The score of :func:`map_consistency` and the search of :func:`consistent_scale` (SI units). The score's
    settings were set once before any calibration run was scored and not tuned; ``alpha_max`` was chosen between
    1 and 1.5 on the twelve calibration runs by a rule written first (stages/slam/README.md, stop 51)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    cell: float = Field(0.15, ge=0, description="one point per cell of this size (m) and time block (0: every "
                        "endpoint)")
    block: float = Field(1.0, gt=0, description="time block of the thinning, s")
    separation: float = Field(5.0, gt=0, description="a point is compared with scans at least this far in time, s")
    neighbours: int = Field(64, ge=1, description="nearest points searched for one that far in time")
    truncation: float = Field(0.5, gt=0, description="distances are capped here (m): a point with no counterpart "
                              "(clutter, a wall seen once) scores the cap whatever the trajectory")
    alpha_max: float = Field(1.5, ge=0, description="largest scale of the fused correction searched (0: off, the "
                             "fused estimate as the fusion gives it; 1.5 chosen on the calibration runs, stop 51)")
    alpha_step: float = Field(0.125, gt=0, description="step of the scale's grid")
    criterion: Literal["capped", "matched", "common"] = Field(
        "capped", description="what the scale minimises: 'capped', the whole score (stop 51; it also falls when "
        "more points merely overlap), 'matched', the mean square distance of the points that have a counterpart "
        "within the cap (how well the overlap agrees; better on the calibration runs, worse on the evaluated ones: "
        "stages/slam/README.md, stop 52), or 'common', the same for the one set of points matched at every scale "
        "searched (:func:`common_support_scores`, stop 53)")

    guard: float = Field(0.0, ge=0, description="keep the odometry (scale 0) unless the chosen scale's criterion "
                         "is below the odometry's by more than this many standard errors of the difference, taken "
                         "over time blocks of guard_block s (:func:`difference_evidence`; 0: off)")
    guard_block: float = Field(10.0, gt=0, description="time block of the guard's standard error, s")

    @model_validator(mode="after")
    def _guard_criterion(self) -> MapConsistency:
        if self.guard > 0 and self.criterion == "common":
            raise ValueError("the guard compares the odometry's points with the chosen scale's, and criterion "
                             "'common' scores one shared set: use criterion 'capped' or 'matched', or guard 0")
        return self

    def scales(self) -> F64:
        """The scales searched, ``{0, alpha_step, ..., alpha_max}`` (empty when ``alpha_max`` is 0: off)."""
        if self.alpha_max <= 0:
            return np.zeros(0)
        return np.arange(int(np.floor(self.alpha_max / self.alpha_step + 1e-9)) + 1) * self.alpha_step


class ScaleChoice(NamedTuple):
    """:func:`consistent_scale`'s result."""

    alpha: float  # the chosen scale of the correction
    alphas: F64  # the grid searched
    scores: F64  # the criterion at each (nan: no point matched)
    evidence: float = float("nan")  # the best scale's gain over the odometry in standard errors (guard on only)


def stacked_endpoints(scans: Sequence[Any]) -> tuple[F64, I64]:
    """Every scan's kept endpoints (body frame, ``BeamSamples.endpoints``) stacked ``(N, 2)``, and their scan
    index ``(N,)``: the inputs of :func:`map_consistency`."""
    points = np.concatenate([np.zeros((0, 2)), *(np.asarray(s.endpoints, np.float64).reshape(-1, 2) for s in scans)])
    return points, np.repeat(np.arange(len(scans)), [len(s.endpoints) for s in scans]).astype(np.int64)


def world_points(poses: npt.ArrayLike, points: npt.ArrayLike, scan: npt.ArrayLike) -> F64:
    """Body-frame points ``(N, 2)`` of scans ``scan (N,)`` put in the world along ``poses (T, 3)``."""
    p = np.asarray(poses, np.float64)[np.asarray(scan, np.int64)]
    b = np.asarray(points, np.float64).reshape(-1, 2)
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    return np.c_[c * b[:, 0] - s * b[:, 1] + p[:, 0], s * b[:, 0] + c * b[:, 1] + p[:, 1]]


class ConsistencyParts(NamedTuple):
    """:func:`consistency_parts`'s result: the score and what it is made of."""

    score: float  # map_consistency: mean squared capped distance (m^2)
    matched: float  # share of the (thinned) points with a point of a scan ``separation`` away within the cap
    matched_ms: float  # mean squared distance of those points (m^2; nan where none)


def thinned(world: F64, t_points: F64, params: MapConsistency | None = None) -> I64:
    """Indices of the points :func:`consistency_parts` scores: the finite ones, one per ``cell`` and ``block``
    (a wall seen by many scans in a row counts once a block; ``cell = 0``: every finite point), in order."""
    p = params or MapConsistency()
    idx = np.flatnonzero(np.all(np.isfinite(world), axis=1))
    if p.cell > 0 and len(idx):
        key = np.c_[np.floor(world[idx] / p.cell).astype(np.int64), np.floor(t_points[idx] / p.block).astype(np.int64)]
        _, first = np.unique(key, axis=0, return_index=True)
        idx = idx[np.sort(first)]
    return idx.astype(np.int64)


def nearest_far(world: F64, t_points: F64, params: MapConsistency | None = None) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Each point's distance to the nearest point at least ``separation`` s away in time, capped at
    ``truncation`` (``(N,)``), and whether one lies within the cap (``(N,)``)."""
    p = params or MapConsistency()
    if len(world) == 0:
        return np.zeros(0), np.zeros(0, bool)
    k = min(p.neighbours, len(world))
    d, j = cKDTree(world).query(world, k=k, distance_upper_bound=p.truncation)
    d, j = d.reshape(len(world), k), j.reshape(len(world), k)
    found = np.isfinite(d)
    far = found & (np.abs(t_points[np.where(found, j, 0)] - t_points[:, None]) >= p.separation)
    return np.where(far, d, p.truncation).min(axis=1), far.any(axis=1)


class PointDistances(NamedTuple):
    """The scored points of one trajectory (:func:`point_distances`)."""

    t: F64  # (N,) the thinned points' scan times, s
    nearest: F64  # (N,) each one's capped distance to the nearest point ``separation`` away in time
    matched: npt.NDArray[np.bool_]  # (N,) whether one lies within the cap


def point_distances(poses: npt.ArrayLike, points: npt.ArrayLike, scan: npt.ArrayLike, t_s: npt.ArrayLike,
                    params: MapConsistency | None = None) -> PointDistances:
    """The points :func:`consistency_parts` scores along ``poses`` (:func:`thinned`) and their capped distances
    (:func:`nearest_far`): what the score and its block sums are made of."""
    p = params or MapConsistency()
    t = np.asarray(t_s, np.float64)
    scan = np.asarray(scan, np.int64)
    _check_stamps(poses, t)
    w = world_points(poses, points, scan)
    tp = t[scan]
    keep = thinned(w, tp, p)
    nearest, matched = nearest_far(w[keep], tp[keep], p)
    return PointDistances(tp[keep], nearest, matched)


def _parts(d: PointDistances) -> ConsistencyParts:
    if len(d.nearest) == 0:
        return ConsistencyParts(0.0, 0.0, float("nan"))
    ms = float(np.mean(d.nearest[d.matched] ** 2)) if d.matched.any() else float("nan")
    return ConsistencyParts(float(np.mean(d.nearest ** 2)), float(np.mean(d.matched)), ms)


def _block_sums(d: PointDistances, t0: float, n_blocks: int, block_s: float,
                matched_only: bool) -> tuple[F64, F64]:
    use = d.matched if matched_only else np.ones(len(d.nearest), bool)
    block = np.floor((d.t[use] - t0) / block_s).astype(np.int64)
    return (np.bincount(block, d.nearest[use] ** 2, n_blocks).astype(np.float64),
            np.bincount(block, None, n_blocks).astype(np.float64))


def _n_blocks(t: F64, block_s: float) -> int:
    return int(np.floor((t[-1] - t[0]) / block_s)) + 1 if len(t) else 0


def block_sums(poses: npt.ArrayLike, points: npt.ArrayLike, scan: npt.ArrayLike, t_s: npt.ArrayLike,
               params: MapConsistency | None = None, matched_only: bool = False) -> tuple[F64, F64]:
    """Per time block of ``params.guard_block`` s from the first stamp: the sum of the thinned points' squared
    capped distances and their count (``matched_only``: of the points with a counterpart within the cap), so that
    ``S.sum() / N.sum()`` is :func:`consistency_parts`' ``score`` (``matched_ms``)."""
    p = params or MapConsistency()
    t = np.asarray(t_s, np.float64)
    d = point_distances(poses, points, scan, t, p)
    return _block_sums(d, float(t[0]) if len(t) else 0.0, _n_blocks(t, p.guard_block), p.guard_block, matched_only)


def difference_evidence(base: tuple[F64, F64], other: tuple[F64, F64]) -> float:
    """How many standard errors ``other``'s ratio score ``S.sum() / N.sum()`` is below ``base``'s, from per-block
    sums ``(S, N)`` (:func:`block_sums`): the difference over the square root of its linearised variance across
    blocks, ``B / (B - 1) * sum_b r_b^2`` with ``r_b`` each block's residual ``(S_b - score N_b) / N`` of ``base``
    minus that of ``other`` (a ratio estimator's delta method, blocks as the independent units). ``inf`` for a
    gain without spread, 0 for none, nan when either side has no point."""
    (s0, n0), (s1, n1) = base, other
    if n0.sum() == 0 or n1.sum() == 0:
        return float("nan")
    q0, q1 = s0.sum() / n0.sum(), s1.sum() / n1.sum()
    r = (s0 - q0 * n0) / n0.sum() - (s1 - q1 * n1) / n1.sum()
    used = int(np.count_nonzero((n0 + n1) > 0))
    gain = q0 - q1
    if gain <= 0:
        return 0.0
    var = used / (used - 1) * float(np.sum(r ** 2)) if used > 1 else 0.0
    return float(gain / np.sqrt(var)) if var > 0 else float("inf")


def consistency_parts(poses: npt.ArrayLike, points: npt.ArrayLike, scan: npt.ArrayLike, t_s: npt.ArrayLike,
                      params: MapConsistency | None = None) -> ConsistencyParts:
    """:func:`map_consistency` with its two parts: ``score = matched * matched_ms + (1 - matched) *
    truncation^2``. A trajectory can lower the score by bringing points closer to their counterparts or by giving
    more points a counterpart at all (stages/slam/README.md, stop 52: the second rewards overlap, not agreement)."""
    return _parts(point_distances(poses, points, scan, t_s, params))


def _check_stamps(poses: npt.ArrayLike, t: F64) -> None:
    n_poses = len(np.asarray(poses).reshape(-1, 3))
    if len(t) != n_poses:
        raise ValueError(f"map_consistency: {n_poses} poses for {len(t)} stamps")


def common_support_scores(trajectories: Sequence[npt.ArrayLike], points: npt.ArrayLike, scan: npt.ArrayLike,
                          t_s: npt.ArrayLike, params: MapConsistency | None = None) -> tuple[F64, float]:
    """The ``common`` criterion (stages/slam/README.md, stop 53): the points are thinned once, on the first
    trajectory; the ones that have a counterpart within the cap on *every* trajectory form one fixed set, and each
    trajectory scores their mean square distance. The same points for every candidate, so a trajectory cannot
    score better by making more points overlap. Returns the scores (nan where the set is empty) and the set's
    share of the thinned points."""
    p = params or MapConsistency()
    t = np.asarray(t_s, np.float64)
    scan = np.asarray(scan, np.int64)
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if not trajectories:
        return np.zeros(0), 0.0
    for traj in trajectories:
        _check_stamps(traj, t)
    tp = t[scan]
    keep = thinned(world_points(trajectories[0], pts, scan), tp, p)
    nearest, matched = zip(*(nearest_far(world_points(traj, pts[keep], scan[keep]), tp[keep], p)
                             for traj in trajectories), strict=True)
    common = np.logical_and.reduce(matched)
    if not common.any():
        return np.full(len(trajectories), np.nan), 0.0
    return np.array([float(np.mean(n[common] ** 2)) for n in nearest]), float(np.mean(common))


def map_consistency(poses: npt.ArrayLike, points: npt.ArrayLike, scan: npt.ArrayLike, t_s: npt.ArrayLike,
                    params: MapConsistency | None = None) -> float:
    """Mean squared truncated distance from each (thinned) endpoint to the nearest endpoint of a scan at least
    ``params.separation`` s away (module docstring); ``params.truncation ** 2`` where no point is that close. Lower
    is more consistent. ``points (N, 2)`` body frame, ``scan (N,)`` their scan index into ``poses (T, 3)`` and
    ``t_s (T,)``. A run without points scores 0."""
    return consistency_parts(poses, points, scan, t_s, params).score


def scaled_positions(poses: npt.ArrayLike, scale: float) -> F64:
    """``poses (T, 3)`` with the positions scaled by ``scale`` about the first one (headings kept): a trajectory
    that contracts (``scale < 1``) or stretches the path."""
    out = np.array(poses, np.float64).reshape(-1, 3)
    out[:, :2] = out[0, :2] + scale * (out[:, :2] - out[0, :2])
    return out


def heading_ramp(odometry: npt.ArrayLike, t_s: npt.ArrayLike, total: float) -> F64:
    """The odometry recomposed along its heading plus a ramp that grows linearly in time from 0 to ``total``
    (rad) over the run: the error a constant gyro bias makes, or undoes."""
    t = np.asarray(t_s, np.float64)
    span = t[-1] - t[0] if len(t) > 1 else 0.0
    ramp = total * (t - t[0]) / span if span > 0 else np.zeros_like(t)
    return recompose(odometry, ramp)


def consistent_scale(odometry: npt.ArrayLike, correction: npt.ArrayLike, points: npt.ArrayLike,
                     scan: npt.ArrayLike, t_s: npt.ArrayLike, params: MapConsistency | None = None) -> ScaleChoice:
    """The scale ``alpha`` of the heading ``correction (T,)`` on ``odometry (T, 3)`` whose recomposed trajectory is
    the most consistent over ``{0, alpha_step, ..., alpha_max}`` (:func:`consistency_parts`: the whole capped
    score, or the matched points' mean square distance; :func:`common_support_scores`: that of the points matched
    at every scale; as ``params.criterion`` says); of equal scores the one
    nearest 1 (the correction as the fusion gives it: scans without endpoints, or without any point matched, say
    nothing). With ``params.guard > 0`` the chosen scale stands only if its criterion is below the odometry's
    (scale 0) by more than ``guard`` standard errors over time blocks (:func:`difference_evidence`), else the
    odometry stays; ``evidence`` records that many. ``alpha_max = 0``: 1, nothing scored."""
    p = params or MapConsistency()
    if p.alpha_max <= 0:
        return ScaleChoice(1.0, np.ones(1), np.zeros(1))
    alphas = p.scales()
    c = np.asarray(correction, np.float64)
    trajectories = [recompose(odometry, a * c) for a in alphas]
    dists: list[PointDistances] = []
    if p.criterion == "common":
        scores = common_support_scores(trajectories, points, scan, t_s, p)[0]
    else:
        dists = [point_distances(traj, points, scan, t_s, p) for traj in trajectories]
        parts = [_parts(d) for d in dists]
        scores = np.array([q.score if p.criterion == "capped" else q.matched_ms for q in parts])
    key = np.where(np.isnan(scores), np.inf, scores)  # nothing matched (nan): no evidence at that scale
    best = int(np.lexsort((np.abs(alphas - 1.0), key))[0])  # the lowest score; of equal ones, nearest 1
    if p.guard <= 0:
        return ScaleChoice(float(alphas[best]), alphas, scores)
    evidence = 0.0
    if best != 0 and np.isfinite(key[best]) and np.isfinite(key[0]):  # the points scored above, summed by block
        t = np.asarray(t_s, np.float64)
        blocks = (float(t[0]), _n_blocks(t, p.guard_block), p.guard_block, p.criterion == "matched")
        evidence = difference_evidence(_block_sums(dists[0], *blocks), _block_sums(dists[best], *blocks))
    if not evidence > p.guard:  # too little evidence (or none): the odometry stays
        best = 0
    return ScaleChoice(float(alphas[best]), alphas, scores, evidence)
