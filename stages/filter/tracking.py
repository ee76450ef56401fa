"""Multi-frame tracking of radar points (RICH-SLAM Sec. IV-B, following Xu et al.'s RIO front end).

Motion of the radar between consecutive scans comes from the gyro (rotation: the integrated angular
rate over the interval, moved into the radar frame) and the Doppler ego-velocity (translation:
trapezoid of the velocities at both scans). A point of scan i is kept when, for each of the k previous
scans, some candidate point of that scan predicted into scan i's frame lies within the gate.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

F64 = npt.NDArray[np.float64]


def interval_rotations(imu_t: npt.NDArray[np.int64], gyro: F64, scan_t: npt.NDArray[np.int64]) -> F64:
    """(S, 3, 3) rotations R_{i-1 <- i} of the gyro's frame between consecutive scan times (R_0 = I).

    The angular rate is integrated with the trapezoid rule into a cumulative rotation vector, sampled at
    the scan times by linear interpolation; per 0.1 s interval the first-order composition is exact to
    well below the gyro noise.
    """
    S = len(scan_t)
    out = np.tile(np.eye(3), (S, 1, 1))
    if S < 2 or len(imu_t) < 2:
        return out
    t = (imu_t - imu_t[0]).astype(np.float64) * 1e-9
    cum = np.zeros((len(t), 3))
    cum[1:] = np.cumsum(0.5 * (gyro[1:] + gyro[:-1]) * np.diff(t)[:, None], axis=0)
    ts = (scan_t - imu_t[0]).astype(np.float64) * 1e-9
    theta = np.stack([np.interp(ts, t, cum[:, k]) for k in range(3)], axis=1)
    out[1:] = Rotation.from_rotvec(np.diff(theta, axis=0)).as_matrix()
    return out


def frame_motions(R_rel: F64, velocity: F64, scan_t: npt.NDArray[np.int64]) -> F64:
    """(S, 4, 4) transforms T_{i-1 <- i} of the radar frame from rotations and ego-velocities (radar frame)."""
    S = len(scan_t)
    T = np.tile(np.eye(4), (S, 1, 1))
    if S < 2:
        return T
    dt = np.diff(scan_t).astype(np.float64) * 1e-9
    v_prev = velocity[:-1]
    v_cur = np.einsum("nij,nj->ni", R_rel[1:], velocity[1:])
    T[1:, :3, :3] = R_rel[1:]
    T[1:, :3, 3] = 0.5 * (v_prev + v_cur) * dt[:, None]
    return T


def _nearest(query: F64, ref: F64) -> F64:
    if len(ref) == 0:
        return np.full(len(query), np.inf)
    if len(query) * len(ref) <= 50_000:
        d2 = ((query[:, None, :] - ref[None, :, :]) ** 2).sum(axis=2)
        return np.asarray(np.sqrt(d2.min(axis=1)))
    return np.asarray(cKDTree(ref).query(query, k=1)[0])


def track_masks(points: Sequence[F64], motions: F64, k: int, gates: Sequence[F64], use_z: bool = False,
                usable: npt.NDArray[np.bool_] | None = None) -> list[npt.NDArray[np.bool_]]:
    """For each scan, which of its candidate points are matched in every one of the ``k`` previous scans.

    ``points[i]`` are scan i's candidates (radar frame), ``motions[i]`` = T_{i-1 <- i}, ``gates[i]`` the
    per-point match radius. ``usable[i]`` false (no motion estimate, or a gap in time) breaks every
    track through scan i. Distances are horizontal (x, y of the radar frame) unless ``use_z``.
    """
    S = len(points)
    usable = np.ones(S, bool) if usable is None else usable
    dims = 3 if use_z else 2
    out: list[npt.NDArray[np.bool_]] = []
    for i in range(S):
        cur = points[i]
        keep = np.ones(len(cur), bool)
        if i < k or len(cur) == 0:
            out.append(np.zeros(len(cur), bool) if i < k else keep)
            continue
        acc = np.eye(4)  # T_{i-j <- i}
        for j in range(1, k + 1):
            if not usable[i - j + 1]:
                keep[:] = False
                break
            acc = motions[i - j + 1] @ acc
            prev = points[i - j]
            inv = np.linalg.inv(acc)
            pred = prev @ inv[:3, :3].T + inv[:3, 3]
            dist = _nearest(cur[:, :dims], pred[:, :dims])
            keep &= dist <= gates[i]
            if not keep.any():
                break
        out.append(keep)
    return out
