"""Modelled radar point uncertainty: range / azimuth / elevation noise propagated to a Cartesian covariance.

For p = r (cos e cos a, cos e sin a, sin e) the Jacobian J = dp/d(r, a, e) gives
``Sigma = J diag(s_r^2, s_a^2, s_e^2) J^T`` (Xu et al.'s point-uncertainty model used by RICH-SLAM's
front end). The gate uses the largest standard deviation of the horizontal block of Sigma expressed in
the base frame (the map is 2D), or of the whole Sigma.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


def spherical(xyz: F64) -> tuple[F64, F64, F64]:
    """Range, azimuth and elevation of points in the sensor frame."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    r = np.sqrt(x * x + y * y + z * z)
    az = np.arctan2(y, x)
    el = np.arcsin(np.clip(z / np.where(r > 0, r, 1.0), -1.0, 1.0))
    return r, az, el


def point_covariances(xyz: F64, sigma_range: float, sigma_azimuth: float, sigma_elevation: float) -> F64:
    """(N, 3, 3) Cartesian covariances in the sensor frame (angles in radians)."""
    r, a, e = spherical(np.asarray(xyz, dtype=np.float64))
    ca, sa, ce, se = np.cos(a), np.sin(a), np.cos(e), np.sin(e)
    J = np.empty((len(r), 3, 3))
    J[:, 0] = np.stack([ce * ca, -r * ce * sa, -r * se * ca], axis=1)
    J[:, 1] = np.stack([ce * sa, r * ce * ca, -r * se * sa], axis=1)
    J[:, 2] = np.stack([se, np.zeros_like(r), r * ce], axis=1)
    D = np.array([sigma_range, sigma_azimuth, sigma_elevation]) ** 2
    return np.einsum("nij,j,nkj->nik", J, D, J)


def max_sigma(cov: F64, rotation: F64 | None = None, horizontal: bool = True) -> F64:
    """Largest standard deviation per point; ``rotation`` (base <- sensor) first, then the xy block."""
    if rotation is not None:
        cov = np.einsum("ij,njk,lk->nil", rotation, cov, rotation)
    if horizontal:
        a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
        lam = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)
    else:
        lam = np.asarray(np.linalg.eigvalsh(cov)[:, -1], dtype=np.float64)
    return np.asarray(np.sqrt(np.maximum(lam, 0.0)))
