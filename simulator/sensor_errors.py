"""Deterministic IMU errors beyond white noise and bias random walk: scale factors and axis misalignment.

The measured vector is ``m = (I + S + M) m_true`` with ``S = diag(scale)`` (per-axis scale-factor errors)
and ``M`` a skew-free small-angle misalignment (each axis tilted towards the others by the given
angles), applied before the noise and bias of :mod:`simulator.imu`. A world sets them in its ``[errors]``
table; all zero (the default) leaves the measurements untouched, bit for bit. Errors are drawn once per
run from the seeded generator (``*_sigma`` fields) on top of the fixed values.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from simulator.params import _Params


class SensorErrors(_Params):
    """The ``[errors]`` table of a world file."""

    gyro_scale: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="gyro scale-factor error per axis")
    accel_scale: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="accel scale-factor error per axis")
    gyro_scale_sigma: float = Field(0.0, ge=0, description="std of a per-run random gyro scale error per axis")
    accel_scale_sigma: float = Field(0.0, ge=0, description="std of a per-run random accel scale error per axis")
    misalignment_sigma_rad: float = Field(0.0, ge=0, description="std of the per-run axis misalignment angles, rad")

    @property
    def active(self) -> bool:
        return any(v != 0.0 for v in (*self.gyro_scale, *self.accel_scale, self.gyro_scale_sigma,
                                      self.accel_scale_sigma, self.misalignment_sigma_rad))


def error_matrices(e: SensorErrors, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The (3, 3) matrices ``I + S + M`` of the gyro and the accelerometer for one run."""
    out = []
    for scale, sigma in ((e.gyro_scale, e.gyro_scale_sigma), (e.accel_scale, e.accel_scale_sigma)):
        s = np.asarray(scale, dtype=np.float64) + rng.normal(0.0, 1.0, 3) * sigma
        m = rng.normal(0.0, 1.0, (3, 3)) * e.misalignment_sigma_rad
        np.fill_diagonal(m, 0.0)
        out.append(np.eye(3) + np.diag(s) + m)
    return out[0], out[1]


def apply(gyro: np.ndarray, accel: np.ndarray, g_mat: np.ndarray, a_mat: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Measured (n, 3) gyro and accelerometer vectors from the true ones."""
    return gyro @ g_mat.T, accel @ a_mat.T
