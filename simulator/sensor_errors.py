"""Sensor errors beyond white noise and bias random walk: the ``[errors]`` table of a world file.

IMU (applied by :mod:`simulator.imu` to the true signal, before bias and noise):

- scale factors and axis misalignment: ``m = (I + S + M) m_true`` with ``S = diag(scale)`` and ``M`` a
  small-angle misalignment with zero diagonal (each axis tilted towards the others);
- fixed zero-rate offset (``gyro_bias``): the unit's own offset, the same in every run, added to the random
  turn-on offset (``[imu] gyro_bias_sigma``, drawn per run) at the start of the bias random walk;
- bias instability: a first-order Gauss-Markov bias ``b[k+1] = phi b[k] + sigma sqrt(1 - phi^2) w[k]``,
  ``phi = exp(-dt / tau)``, stationary with std ``sigma`` (the usual MEMS model of the flicker floor that
  datasheets quote as "bias instability"; the twins set ``sigma`` to the datasheet value), added to
  the random-walk bias of :class:`simulator.params.ImuParams` (``gyro_bias_walk``, the rate random walk).

Radar (applied by :mod:`simulator.simulate`):

- time offset: each scan measures the scene ``radar_time_offset_s`` before the time it is stamped with
  (positive: the stamp is late, as when a driver stamps a frame after processing and transfer);
- mounting error: the true mount is the stated one (what ``/tf``, ``calib/`` or the profile says) moved by
  ``radar_mount_offset_m`` (base frame) and rotated by ``R_e`` (roll, pitch, yaw about the stated radar
  frame's x, y, z axes, scipy's extrinsic ``xyz`` angles); the radar reports its points in the true
  frame, ``p_true = R_e^T p_stated``. Detection (field of view, antenna gain, azimuth bins) is computed in
  the stated frame, which is exact for the geometry of the reported points and off by the (sub-degree) tilt
  for which points are seen. Doppler is a scalar per point and does not change with the frame.

All zero (the default) leaves every measurement untouched, bit for bit. ``*_sigma`` fields draw a per-run
value from the seeded generator on top of the fixed one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from simulator.params import _Params

Vec3 = tuple[float, float, float]


class SensorErrors(_Params):
    """The ``[errors]`` table of a world file."""

    gyro_bias: Vec3 = Field((0.0, 0.0, 0.0), description="fixed gyro zero-rate offset of the unit per axis, rad/s, "
                            "added to the random turn-on offset of [imu] gyro_bias_sigma")
    gyro_scale: Vec3 = Field((0.0, 0.0, 0.0), description="gyro scale-factor error per axis")
    accel_scale: Vec3 = Field((0.0, 0.0, 0.0), description="accel scale-factor error per axis")
    gyro_scale_sigma: float = Field(0.0, ge=0, description="std of a per-run random gyro scale error per axis")
    accel_scale_sigma: float = Field(0.0, ge=0, description="std of a per-run random accel scale error per axis")
    misalignment_sigma_rad: float = Field(0.0, ge=0, description="std of the per-run axis misalignment angles, rad")
    gyro_bias_instability: float = Field(0.0, ge=0, description="std of the Gauss-Markov gyro bias, rad/s")
    gyro_bias_tau_s: float = Field(100.0, gt=0, description="correlation time of the Gauss-Markov gyro bias, s")
    accel_bias_instability: float = Field(0.0, ge=0, description="std of the Gauss-Markov accel bias, m/s^2")
    accel_bias_tau_s: float = Field(100.0, gt=0, description="correlation time of the Gauss-Markov accel bias, s")
    radar_time_offset_s: float = Field(0.0, ge=-0.2, le=0.2, description="radar stamp minus true measurement "
                                                                        "time, s (positive: stamped late)")
    radar_mount_rpy_deg: Vec3 = Field((0.0, 0.0, 0.0), description="rotation of the true radar mount against "
                                                                   "the stated one: roll, pitch, yaw, deg")
    radar_mount_sigma_deg: float = Field(0.0, ge=0, description="std of a per-run random mount rotation per axis, "
                                                                "deg")
    radar_mount_offset_m: Vec3 = Field((0.0, 0.0, 0.0), description="true minus stated radar position, base "
                                                                    "frame, m")
    radar_mount_offset_sigma_m: float = Field(0.0, ge=0, description="std of a per-run random mount offset per "
                                                                     "axis, m")

    @property
    def active(self) -> bool:
        """Scale factors or misalignment are set (the IMU matrices of :func:`error_matrices` are needed)."""
        return any(v != 0.0 for v in (*self.gyro_scale, *self.accel_scale, self.gyro_scale_sigma,
                                      self.accel_scale_sigma, self.misalignment_sigma_rad))

    @property
    def bias_instability_active(self) -> bool:
        return self.gyro_bias_instability > 0.0 or self.accel_bias_instability > 0.0

    @property
    def mount_active(self) -> bool:
        return any(v != 0.0 for v in (*self.radar_mount_rpy_deg, *self.radar_mount_offset_m,
                                      self.radar_mount_sigma_deg, self.radar_mount_offset_sigma_m))


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


def gauss_markov(n: int, dt: float, sigma: float, tau: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) stationary first-order Gauss-Markov process of std ``sigma`` and correlation time ``tau``."""
    phi = float(np.exp(-dt / tau))
    w = rng.normal(0.0, 1.0, (n, 3))
    w[0] *= sigma  # stationary start: b[0] ~ N(0, sigma^2)
    w[1:] *= sigma * np.sqrt(1.0 - phi * phi)
    return np.asarray(lfilter([1.0], [1.0, -phi], w, axis=0))


def bias_instability(e: SensorErrors, n: int, rate: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 6) gyro (3) then accelerometer (3) Gauss-Markov biases at ``rate`` Hz for a whole run."""
    dt = 1.0 / rate
    g = gauss_markov(n, dt, e.gyro_bias_instability, e.gyro_bias_tau_s, rng)
    a = gauss_markov(n, dt, e.accel_bias_instability, e.accel_bias_tau_s, rng)
    return np.hstack([g, a])


@dataclass(frozen=True)
class MountError:
    """The true radar mount against the stated one, drawn once per run."""

    rotation: Rotation  # R_e: stated radar frame <- true radar frame
    offset: np.ndarray  # (3,) true minus stated position, base frame

    def to_true_frame(self, xyz: np.ndarray) -> np.ndarray:
        """(n, 3) points from the stated radar frame into the true one (``R_e^T p``), same dtype."""
        return self.rotation.inv().apply(np.asarray(xyz, dtype=np.float64)).astype(xyz.dtype, copy=False)


def mount_error(e: SensorErrors, rng: np.random.Generator) -> MountError:
    rpy = np.asarray(e.radar_mount_rpy_deg, dtype=np.float64) + rng.normal(0.0, 1.0, 3) * e.radar_mount_sigma_deg
    off = np.asarray(e.radar_mount_offset_m, dtype=np.float64) + rng.normal(0.0, 1.0, 3) * e.radar_mount_offset_sigma_m
    return MountError(rotation=Rotation.from_euler("xyz", rpy, degrees=True), offset=off)


def rotate_points(points: np.ndarray, xyz_true: np.ndarray, m: MountError) -> tuple[np.ndarray, np.ndarray]:
    """A scan's structured points (fields x, y, z) and noise-free (n, 3) positions in the true radar frame."""
    pts = np.zeros(len(points), points.dtype)  # not points.copy(): that leaves the dtype's padding bytes
    pts[:] = points                             # uninitialised (the bag's bytes would differ run to run)
    if len(pts):
        xyz = np.column_stack([pts["x"], pts["y"], pts["z"]])
        r = m.to_true_frame(xyz)
        pts["x"], pts["y"], pts["z"] = r[:, 0], r[:, 1], r[:, 2]
    return pts, m.to_true_frame(xyz_true)
