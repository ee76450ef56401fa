"""Has a filter left its odometry further than the odometry's own uncertainty allows? (a stage warning).

Pure numpy. The odometry's heading error after scan k has, by its own increment covariance, a variance of at
most the sum of the increments' yaw variances (``cov[1:k+1, 2, 2]``; correlated errors such as a gyro bias
make the true spread of a *drift* larger, which is why this is a warning, not a test). A filter whose
heading differs from the odometry's by many of those sigmas has either corrected a drift the odometry did
not know it had, or diverged; the stage says which scan and by how much, and the user compares
``trajectory_<method>.parquet`` with ``trajectory_odometry.parquet``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.floating[Any]]


@dataclass(frozen=True)
class HeadingDeviation:
    """The largest heading deviation from the odometry, in odometry sigmas, and where it is."""

    sigmas: float  # max_k |yaw_k - odo_yaw_k| / sigma_k
    index: int  # the scan index k of the maximum
    degrees: float  # |yaw_k - odo_yaw_k| at that scan
    sigma_degrees: float  # sigma_k there


def heading_deviation(odometry: npt.ArrayLike, poses: npt.ArrayLike, increment_cov: npt.ArrayLike,
                      floor_rad: float = np.radians(0.5)) -> HeadingDeviation:
    """``odometry``, ``poses`` ``(T, 3)`` at the same scans; ``increment_cov (T, 3, 3)`` the odometry's per-scan
    increment covariance (row 0 unused). ``floor_rad``: the smallest sigma used (a filter may move a little
    even where the odometry's accumulated uncertainty is still near zero)."""
    odo = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    est = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    cov = np.asarray(increment_cov, dtype=np.float64).reshape(-1, 3, 3)
    if len(odo) == 0:
        return HeadingDeviation(0.0, 0, 0.0, 0.0)
    var = np.cumsum(np.r_[0.0, np.maximum(cov[1:, 2, 2], 0.0)])
    sigma = np.maximum(np.sqrt(var), floor_rad)
    dev = np.abs(np.angle(np.exp(1j * (est[:, 2] - odo[:, 2]))))
    ratio = dev / sigma
    k = int(np.argmax(ratio))
    return HeadingDeviation(float(ratio[k]), k, float(np.degrees(dev[k])), float(np.degrees(sigma[k])))
