"""Trajectory accuracy (RICH-SLAM Table III): position and yaw RMSE after an SE(2) alignment, two ways.

Pure functions on numpy arrays. Estimates are matched to ground truth by timestamp (ground truth
interpolated linearly in position and in unwrapped yaw), a rigid SE(2) transform (Kabsch/Umeyama on
xy, no scale) is estimated on the matched frames and applied to the whole estimate:

- the paper's protocol (Table III): the transform is fitted on the first ``n_align`` (100) matched frames
  (:func:`evaluate_trajectory` with ``n_align=100``); ill-posed when the rig barely moves during them;
- the whole trajectory: fitted on every matched frame (:func:`evaluate_trajectory_whole`, ``n_align=None``),
  the transform that minimises the position RMSE itself; it equals evo's ``evo_ape --align`` on the
  trajectories projected to the plane (``tests/test_cli_run.py`` checks it on a TUM export).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


def wrap_angle(a: npt.ArrayLike) -> F64:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi


def quat_to_yaw(qx: F64, qy: F64, qz: F64, qw: F64) -> F64:
    """Yaw (rotation about world z) of quaternions (x, y, z, w), ZYX convention."""
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def interpolate_pose2d(
    t_ref: npt.NDArray[np.int64], xy_ref: F64, yaw_ref: F64, t: npt.NDArray[np.int64], max_gap_ns: int
) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Ground truth (x, y, yaw) at times ``t``: linear in xy and in unwrapped yaw.

    Returns (xy (N,2), yaw (N,), valid (N,)); a time is valid when it lies inside the reference's span
    and the bracketing reference samples are at most ``max_gap_ns`` apart.
    """
    t_ref = np.asarray(t_ref, dtype=np.int64)
    t = np.asarray(t, dtype=np.int64)
    order = np.argsort(t_ref, kind="stable")
    t_ref, xy_ref, yaw_ref = t_ref[order], np.asarray(xy_ref, np.float64)[order], np.asarray(yaw_ref, np.float64)[order]
    if len(t_ref) < 2:
        return np.zeros((len(t), 2)), np.zeros(len(t)), np.zeros(len(t), bool)
    hi = np.clip(np.searchsorted(t_ref, t, side="left"), 1, len(t_ref) - 1)
    lo = hi - 1
    exact = t_ref[hi] == t
    lo = np.where(exact, hi, lo)
    gap = t_ref[hi] - t_ref[lo]
    valid = (t >= t_ref[0]) & (t <= t_ref[-1]) & (gap <= max_gap_ns)
    span = np.where(gap > 0, gap, 1).astype(np.float64)
    w = np.where(gap > 0, (t - t_ref[lo]) / span, 0.0)[:, None]
    xy = xy_ref[lo] * (1.0 - w) + xy_ref[hi] * w
    yaw_u = np.unwrap(yaw_ref)
    yaw = wrap_angle(yaw_u[lo] * (1.0 - w[:, 0]) + yaw_u[hi] * w[:, 0])
    return xy, yaw, valid


def umeyama_se2(src: F64, dst: F64) -> tuple[F64, F64]:
    """Rotation R (2x2) and translation t minimising sum ||R src_i + t - dst_i||^2 (Umeyama 1991, no scale)."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if len(src) < 2:
        raise ValueError("SE(2) alignment needs at least 2 matched poses")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    u, _, vt = np.linalg.svd(cov)
    s = np.diag([1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    r = u @ s @ vt
    return r, mu_d - r @ mu_s


@dataclass(frozen=True)
class TrajectoryErrors:
    """Errors of one aligned estimate against ground truth."""

    pos_rmse_m: float
    yaw_rmse_deg: float
    n_matched: int
    n_aligned: int
    rotation_deg: float
    translation: tuple[float, float]
    #: the aligned estimate and the matched ground truth (for plots)
    xy_aligned: F64
    yaw_aligned: F64
    xy_gt: F64
    yaw_gt: F64
    t_ns: npt.NDArray[np.int64]


def evaluate_trajectory(
    t_est: npt.NDArray[np.int64], xy_est: F64, yaw_est: F64,
    t_gt: npt.NDArray[np.int64], xy_gt: F64, yaw_gt: F64,
    n_align: int | None = 100, max_gap_ns: int = 250_000_000,
) -> TrajectoryErrors:
    """Position RMSE [m] and yaw RMSE [deg] after the SE(2) alignment on the first ``n_align`` matched frames
    (``None``: on all of them, the whole-trajectory alignment).

    The alignment (R, t) minimises sum_i ||R p_i + t - q_i||^2 over the aligned pairs (Umeyama 1991, no
    scale); the estimate's yaw is rotated by the angle of R. RMSE over all matched frames:
    sqrt(mean ||R p_i + t - q_i||^2) and sqrt(mean wrap(yaw_i + angle(R) - yaw_gt_i)^2)."""
    if n_align is not None and n_align < 2:
        raise ValueError(f"n_align = {n_align}: the SE(2) alignment needs at least 2 frames")
    gxy, gyaw, ok = interpolate_pose2d(t_gt, xy_gt, yaw_gt, t_est, max_gap_ns)
    n = int(ok.sum())
    if n < 2:
        raise ValueError(f"only {n} estimated poses fall inside the ground truth's time span")
    exy, eyaw, gxy, gyaw, t = (np.asarray(xy_est, np.float64)[ok], np.asarray(yaw_est, np.float64)[ok],
                               gxy[ok], gyaw[ok], np.asarray(t_est)[ok])
    k = n if n_align is None else min(n_align, n)
    r, tr = umeyama_se2(exy[:k], gxy[:k])
    dtheta = float(np.arctan2(r[1, 0], r[0, 0]))
    axy = exy @ r.T + tr
    ayaw = wrap_angle(eyaw + dtheta)
    pos = float(np.sqrt(np.mean(np.sum((axy - gxy) ** 2, axis=1))))
    dyaw = wrap_angle(ayaw - gyaw)
    yaw = float(np.degrees(np.sqrt(np.mean(dyaw**2))))
    return TrajectoryErrors(pos, yaw, n, k, float(np.degrees(dtheta)), (float(tr[0]), float(tr[1])),
                            axy, ayaw, gxy, gyaw, t)


def evaluate_trajectory_whole(
    t_est: npt.NDArray[np.int64], xy_est: F64, yaw_est: F64,
    t_gt: npt.NDArray[np.int64], xy_gt: F64, yaw_gt: F64, max_gap_ns: int = 250_000_000,
) -> TrajectoryErrors:
    """Position RMSE [m] and yaw RMSE [deg] after the SE(2) alignment on every matched frame: the rigid
    transform that minimises the position RMSE (evo's ``--align`` in the plane)."""
    return evaluate_trajectory(t_est, xy_est, yaw_est, t_gt, xy_gt, yaw_gt, None, max_gap_ns)


def anchored_errors(
    t_est: npt.NDArray[np.int64], xy_est: F64, yaw_est: F64,
    t_gt: npt.NDArray[np.int64], xy_gt: F64, yaw_gt: F64, max_gap_ns: int = 250_000_000,
) -> tuple[float, float]:
    """Position RMSE [m] and yaw RMSE [deg] with no alignment, for an estimate already in the ground truth's
    frame (the odometry stage's ``anchor = groundtruth``): well posed where the Table III alignment is not,
    e.g. when the rig barely moves during the first ``n_align`` frames."""
    gxy, gyaw, ok = interpolate_pose2d(t_gt, xy_gt, yaw_gt, t_est, max_gap_ns)
    if int(ok.sum()) < 1:
        raise ValueError("no estimated pose falls inside the ground truth's time span")
    d = np.asarray(xy_est, np.float64)[ok] - gxy[ok]
    dyaw = wrap_angle(np.asarray(yaw_est, np.float64)[ok] - gyaw[ok])
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1)))), float(np.degrees(np.sqrt(np.mean(dyaw**2))))


def path_length(xy: F64) -> float:
    """Length of a polyline [m]."""
    xy = np.asarray(xy, np.float64)
    return float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))) if len(xy) > 1 else 0.0
