"""Radar ego-velocity from one scan's Doppler measurements (REVE: Doer & Trommer, MFI 2020).

Model for a static point seen from a sensor moving with velocity v (radar frame), r the unit direction:
``d = -r . v`` (negative when approaching). Steps as in REVE: a zero-velocity test on the Doppler
quantile, 3-point RANSAC with ``ln(1-p_success)/ln(1-(1-p_outlier)^3)`` iterations (all hypotheses
solved as one batch of 3x3 systems), then least squares on the inliers with the covariance
``sigma^2 (A^T A)^-1 + sigma_offset^2 I``. Scans whose geometry leaves v_z unobservable (all points in
one plane: condition number above a bound) are solved for (v_x, v_y) with v_z = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class EgoVelocityConfig:
    """REVE's parameters (defaults from its public configuration)."""

    inlier_threshold: float = 0.15
    outlier_probability: float = 0.4
    success_probability: float = 0.9999
    max_iterations: int = 200
    min_points: int = 5
    zero_velocity_threshold: float = 0.05
    allowed_outlier_fraction: float = 0.3
    sigma_offset: float = 0.05
    max_condition: float = 1000.0
    refine: bool = True


@dataclass
class EgoVelocity:
    """Estimate for one scan (radar frame)."""

    v: F64
    cov: F64
    inliers: npt.NDArray[np.bool_]
    valid: bool
    #: 3 for a full 3D estimate, 2 when v_z was fixed to 0, 0 for the zero-velocity test
    dims: int = 3


def ransac_iterations(cfg: EgoVelocityConfig, sample_size: int = 3) -> int:
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


def _lsq(dirs: F64, doppler: F64, dims: int, cfg: EgoVelocityConfig) -> tuple[F64, F64] | None:
    A = -dirs[:, :dims]
    n = len(doppler)
    if n <= dims:
        return None
    AtA = A.T @ A
    if np.linalg.cond(AtA) > cfg.max_condition ** 2:
        return None
    v = np.linalg.solve(AtA, A.T @ doppler)
    e = A @ v - doppler
    sigma2 = float(e @ e) / (n - dims)
    cov = sigma2 * np.linalg.inv(AtA) + cfg.sigma_offset ** 2 * np.eye(dims)
    v3 = np.zeros(3)
    v3[:dims] = v
    cov3 = np.zeros((3, 3))
    cov3[:dims, :dims] = cov
    if dims < 3:
        cov3[2, 2] = np.inf
    return v3, cov3


def _ransac(dirs: F64, doppler: F64, dims: int, cfg: EgoVelocityConfig, rng: np.random.Generator
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
    best = int(np.argmax(inl.sum(axis=1)))
    return np.asarray(inl[best])


def estimate(dirs: F64, doppler: F64, cfg: EgoVelocityConfig, rng: np.random.Generator) -> EgoVelocity:
    """Ego-velocity of the sensor from unit directions (N, 3) and Doppler velocities (N,)."""
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
    for dims in (3, 2):
        sub = dirs[:, :dims]
        if np.linalg.cond(sub.T @ sub) > cfg.max_condition ** 2 and dims == 3:
            continue  # planar geometry: v_z unobservable
        inl = _ransac(dirs, doppler, dims, cfg, rng)
        if inl.sum() < max(cfg.min_points, dims + 1):
            continue
        sol = _lsq(dirs[inl], doppler[inl], dims, cfg)
        if sol is None:
            continue
        v, cov = sol
        if cfg.refine:  # re-select inliers with the least-squares solution, solve once more
            inl2 = np.abs(doppler + dirs @ v) < cfg.inlier_threshold
            if inl2.sum() >= max(cfg.min_points, dims + 1):
                sol2 = _lsq(dirs[inl2], doppler[inl2], dims, cfg)
                if sol2 is not None:
                    (v, cov), inl = sol2, inl2
        return EgoVelocity(v, cov, inl, True, dims)
    return invalid


def doppler_residual(dirs: F64, doppler: F64, v: F64) -> F64:
    """|d + r . v| for every point: zero for a static point under the estimated motion."""
    return np.asarray(np.abs(doppler + dirs @ v))
