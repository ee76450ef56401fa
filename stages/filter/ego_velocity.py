"""Radar ego-velocity from one scan's Doppler measurements (REVE: Doer & Trommer, MFI 2020).

Model for a static point seen from a sensor moving with velocity v (radar frame), r the unit direction:
``d = -r . v`` (negative when approaching). Steps as in REVE: a zero-velocity test on the Doppler
quantile, 3-point RANSAC with ``ln(1-p_success)/ln(1-(1-p_outlier)^3)`` iterations (all hypotheses
solved as one batch of 3x3 systems; ties in the inlier count go to the smaller truncated squared
residual), then least squares on the inliers with the covariance
``sigma^2 (A^T A)^-1 + sigma_offset^2 I``, rejected when a standard deviation exceeds REVE's
``max_sigma``. Both the 3D model and the planar one (v_z = 0) are fitted; the 3D hypothesis is kept only
when it explains strictly more points (a wrong 3D hypothesis can fit a few points in a narrow elevation
band as well as the true motion), else the planar consensus set is refitted in 3D when that is well
determined, else the planar solution stands. 3D solutions with an implausible vertical speed (|v_z| above
``max_vz``, radar z being up for a level mount) are discarded the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from stages.filter.params import EgoVelocityParams

F64 = npt.NDArray[np.float64]


@dataclass
class EgoVelocity:
    """Estimate for one scan (radar frame)."""

    v: F64
    cov: F64
    inliers: npt.NDArray[np.bool_]
    valid: bool
    #: 3 for a full 3D estimate, 2 when v_z was fixed to 0, 0 for the zero-velocity test
    dims: int = 3


def ransac_iterations(cfg: EgoVelocityParams, sample_size: int = 3) -> int:
    """Number of RANSAC hypotheses for the configured outlier and success probabilities."""
    good = (1.0 - cfg.outlier_probability) ** sample_size
    if good >= 1.0:
        return 1
    n = math.log(1.0 - cfg.success_probability) / math.log(1.0 - good)
    return int(min(max(math.ceil(n), 1), cfg.max_iterations))


def unit_directions(xyz: F64) -> tuple[F64, F64]:
    """Unit directions and ranges of points (zero-range points get a zero direction)."""
    rng = np.linalg.norm(xyz, axis=1)
    return xyz / np.where(rng > 0, rng, 1.0)[:, None], rng


def _lsq(dirs: F64, doppler: F64, dims: int, cfg: EgoVelocityParams) -> tuple[F64, F64] | None:
    """Least squares on the inliers; None when ill-conditioned or less precise than ``max_sigma_*``."""
    A = -dirs[:, :dims]
    n = len(doppler)
    if n <= dims:
        return None
    AtA = A.T @ A
    if np.linalg.cond(AtA) > cfg.max_condition ** 2:
        return None
    v = np.linalg.solve(AtA, A.T @ doppler)
    e = A @ v - doppler
    # the residual variance of a handful of quantised Doppler values is unreliable: floor it at the sensor's
    # Doppler precision, so the covariance (and the max_sigma test) reflects the geometry of the inliers
    sigma2 = max(float(e @ e) / (n - dims), cfg.doppler_sigma_floor ** 2)
    cov = sigma2 * np.linalg.inv(AtA)
    sd = np.sqrt(np.diag(cov))
    if np.any(sd[:2] > cfg.max_sigma_xy) or (dims == 3 and sd[2] > cfg.max_sigma_z):
        return None
    cov = cov + cfg.sigma_offset ** 2 * np.eye(dims)
    v3 = np.zeros(3)
    v3[:dims] = v
    cov3 = np.zeros((3, 3))
    cov3[:dims, :dims] = cov
    if dims < 3:
        cov3[2, 2] = np.inf
    return v3, cov3


def _ransac(dirs: F64, doppler: F64, dims: int, cfg: EgoVelocityParams, rng: np.random.Generator
            ) -> npt.NDArray[np.bool_]:
    """Inlier mask of the best hypothesis from minimal ``dims``-point samples (batched solves)."""
    n = len(doppler)
    k = ransac_iterations(cfg, dims)
    # dims distinct indices per hypothesis: argsort of random keys, vectorised
    idx = np.argsort(rng.random((k, n)), axis=1)[:, :dims]
    A = -dirs[idx][:, :, :dims]  # (k, dims, dims)
    b = doppler[idx]  # (k, dims)
    det = np.linalg.det(A)
    ok = np.abs(det) > 1e-6
    if not ok.any():
        return np.zeros(n, bool)
    v = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]  # (k', dims)
    resid = np.abs(doppler[None, :] + v @ dirs[:, :dims].T)  # (k', n)
    inl = resid < cfg.inlier_threshold
    # most inliers (REVE); among equally many, the smallest truncated squared residual (MSAC)
    cost = (np.minimum(resid, cfg.inlier_threshold) ** 2).sum(axis=1)
    best = int(np.lexsort((cost, -inl.sum(axis=1)))[0])
    return np.asarray(inl[best])


def estimate(dirs: F64, doppler: F64, cfg: EgoVelocityParams, rng: np.random.Generator,
             prior: F64 | None = None) -> EgoVelocity:
    """Ego-velocity of the sensor from unit directions (N, 3) and Doppler velocities (N,).

    ``prior`` (e.g. the previous scan's estimate moved into this frame) adds one hypothesis: its consensus
    set, refitted, wins when it explains at least as many points as the RANSAC result (temporal
    consistency breaks ties that sparse scans leave open).
    """
    est = _estimate(dirs, doppler, cfg, rng)
    if prior is None or not np.all(np.isfinite(prior)) or est.dims == 0:
        return est
    inl = np.abs(doppler + dirs @ prior) < cfg.inlier_threshold
    if inl.sum() < max(cfg.min_points, 3) or (est.valid and inl.sum() < est.inliers.sum()):
        return est
    for dims in (3, 2):
        if dims == 3 and est.valid and est.dims == 2:
            continue  # the data did not support a 3D fit
        sol = _lsq(dirs[inl], doppler[inl], dims, cfg)
        if sol is not None and abs(sol[0][2]) <= cfg.max_vz:
            inl2 = np.abs(doppler + dirs @ sol[0]) < cfg.inlier_threshold
            if not est.valid or inl2.sum() >= est.inliers.sum():
                return EgoVelocity(sol[0], sol[1], inl2, True, dims)
    return est


def _estimate(dirs: F64, doppler: F64, cfg: EgoVelocityParams, rng: np.random.Generator) -> EgoVelocity:
    n = len(doppler)
    invalid = EgoVelocity(np.full(3, np.nan), np.full((3, 3), np.nan), np.zeros(n, bool), False)
    if n < max(cfg.min_points, 3):
        return invalid
    # zero-velocity test: the (1 - allowed outliers) quantile of |d| is small
    q = np.quantile(np.abs(doppler), 1.0 - cfg.allowed_outlier_fraction)
    if q < cfg.zero_velocity_threshold:
        inl = np.abs(doppler) < cfg.zero_velocity_threshold
        cov = np.eye(3) * cfg.zero_velocity_threshold ** 2
        return EgoVelocity(np.zeros(3), cov, inl, True, 0)
    sols: dict[int, EgoVelocity] = {}
    for dims in (3, 2):
        sub = dirs[:, :dims]
        if dims == 3 and np.linalg.cond(sub.T @ sub) > cfg.max_condition ** 2:
            continue  # planar geometry: v_z unobservable
        est = _solve(dirs, doppler, dims, cfg, rng)
        if est is not None and abs(est.v[2]) <= cfg.max_vz:
            sols[dims] = est
    # model selection: the 3D hypothesis must explain strictly more points than the planar one (v_z = 0);
    # with few points in a narrow elevation band a wrong 3D hypothesis can otherwise fit as many. When it
    # does not, the planar consensus set is refitted in 3D and kept if that fit is well determined.
    if 3 in sols and (2 not in sols or sols[3].inliers.sum() > sols[2].inliers.sum()):
        return sols[3]
    if 2 not in sols:
        return invalid
    planar = sols[2]
    if 3 in sols or np.linalg.cond(dirs.T @ dirs) <= cfg.max_condition ** 2:
        refit = _lsq(dirs[planar.inliers], doppler[planar.inliers], 3, cfg)
        if refit is not None and abs(refit[0][2]) <= cfg.max_vz:
            inl = np.abs(doppler + dirs @ refit[0]) < cfg.inlier_threshold
            if inl.sum() >= planar.inliers.sum():
                return EgoVelocity(refit[0], refit[1], planar.inliers, True, 3)
    return planar


def _solve(dirs: F64, doppler: F64, dims: int, cfg: EgoVelocityParams, rng: np.random.Generator
           ) -> EgoVelocity | None:
    inl = _ransac(dirs, doppler, dims, cfg, rng)
    if inl.sum() < max(cfg.min_points, dims + 1):
        return None
    sol = _lsq(dirs[inl], doppler[inl], dims, cfg)
    if sol is None:
        return None
    v, cov = sol
    inl2 = np.abs(doppler + dirs @ v) < cfg.inlier_threshold  # re-select inliers with the LSQ solution, solve again
    if inl2.sum() >= max(cfg.min_points, dims + 1):
        sol2 = _lsq(dirs[inl2], doppler[inl2], dims, cfg)
        if sol2 is not None:
            (v, cov), inl = sol2, inl2
    return EgoVelocity(v, cov, inl, True, dims)


def doppler_residual(dirs: F64, doppler: F64, v: F64) -> F64:
    """|d + r . v| for every point: zero for a static point under the estimated motion."""
    return np.asarray(np.abs(doppler + dirs @ v))
