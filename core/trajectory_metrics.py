"""SE(2) trajectory helpers for the odometry stage: anchoring and drift against ground truth."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from core.geometry import wrap_angle

F64 = npt.NDArray[np.float64]


def se2_compose_anchor(x: F64, y: F64, yaw: F64, at: int, x_ref: float, y_ref: float, yaw_ref: float
                       ) -> tuple[F64, F64, F64]:
    """Move a planar trajectory rigidly so that its pose ``at`` equals (x_ref, y_ref, yaw_ref)."""
    dyaw = yaw_ref - yaw[at]
    c, s = np.cos(dyaw), np.sin(dyaw)
    dx, dy = x - x[at], y - y[at]
    return x_ref + c * dx - s * dy, y_ref + s * dx + c * dy, wrap_angle(yaw + dyaw)


def drift(t_ns: npt.NDArray[np.int64], est: F64, ref: F64) -> dict[str, Any]:
    """Drift of an anchored trajectory ``est`` against ``ref`` (both (N, 3): x, y, yaw) at the same times.

    End-point translation error as a percentage of the ground-truth path length, the largest and RMS
    position error, the final yaw error, and the yaw drift rate in degrees per minute (least-squares slope
    of the unwrapped yaw error against time, and end-point error over duration).
    """
    if len(t_ns) < 2:
        return {"frames": len(t_ns)}
    pos_err = np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])
    length = float(np.hypot(np.diff(ref[:, 0]), np.diff(ref[:, 1])).sum())
    minutes = float(t_ns[-1] - t_ns[0]) * 1e-9 / 60.0
    yaw_err = np.unwrap(wrap_angle(est[:, 2] - ref[:, 2]))
    tt = (t_ns - t_ns[0]) * 1e-9 / 60.0
    slope = float(np.polyfit(tt, np.degrees(yaw_err), 1)[0]) if minutes > 0 else float("nan")
    return {
        "frames": len(t_ns),
        "path_length_m": round(length, 3),
        "duration_s": round(minutes * 60.0, 3),
        "final_position_error_m": round(float(pos_err[-1]), 4),
        "drift_pct_of_distance": round(100.0 * float(pos_err[-1]) / length, 3) if length > 0 else None,
        "max_position_error_m": round(float(pos_err.max()), 4),
        "rmse_position_m": round(float(np.sqrt((pos_err ** 2).mean())), 4),
        "final_yaw_error_deg": round(float(np.degrees(yaw_err[-1])), 3),
        "yaw_drift_deg_per_min": round(abs(float(np.degrees(yaw_err[-1]))) / minutes, 3) if minutes > 0 else None,
        "yaw_drift_slope_deg_per_min": round(slope, 3),
        "rmse_yaw_deg": round(float(np.degrees(np.sqrt((yaw_err ** 2).mean()))), 3),
    }


def se2_increments(poses: F64) -> F64:
    """Body-frame increments ``x[i-1]^-1 (+) x[i]`` of a planar trajectory ``(N, 3)``; row 0 is zero."""
    x = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    u = np.zeros_like(x)
    if len(x) > 1:
        dp = x[1:, :2] - x[:-1, :2]
        c, s = np.cos(x[:-1, 2]), np.sin(x[:-1, 2])
        u[1:, 0] = c * dp[:, 0] + s * dp[:, 1]
        u[1:, 1] = -s * dp[:, 0] + c * dp[:, 1]
        u[1:, 2] = wrap_angle(x[1:, 2] - x[:-1, 2])
    return u


#: the NEES check's tolerance: the mean NEES of a sequence within this factor of its expectation (3)
NEES_TOLERANCE = 2.0


def increment_nees(est: F64, ref: F64, cov: F64, ok: npt.NDArray[np.bool_]) -> dict[str, Any]:
    """Normalised estimation error squared of the body-frame increments ``e^T Sigma^-1 e`` (e = estimated
    minus true increment from scan i-1 to i), over the increments whose two scans are ``ok`` and whose
    covariance is positive definite. Consistent covariances give chi-square(3): mean 3, 95 % of the values
    below 7.81. Also the per-axis normalised error variance (``e_j^2 / Sigma_jj``, expectation 1)."""
    e = se2_increments(est) - se2_increments(ref)
    e[:, 2] = wrap_angle(e[:, 2])
    use = np.zeros(len(e), bool)
    use[1:] = ok[1:] & ok[:-1]
    c = np.asarray(cov, dtype=np.float64)
    use &= np.all(np.isfinite(c.reshape(len(c), -1)), axis=1)
    use &= np.linalg.eigvalsh(np.where(np.isfinite(c), c, 0.0))[:, 0] > 0
    if use.sum() < 2:
        return {"increments": int(use.sum())}
    e, c = e[use], c[use]
    nees = np.einsum("si,si->s", e, np.linalg.solve(c, e[:, :, None])[:, :, 0])
    axis = e ** 2 / np.diagonal(c, axis1=1, axis2=2)
    mean = float(nees.mean())
    return {"increments": int(use.sum()), "mean": round(mean, 4), "median": round(float(np.median(nees)), 4),
            "share_below_chi2_95": round(float(np.mean(nees < 7.8147)), 4),
            "axis_mean": [round(float(v), 4) for v in axis.mean(axis=0)],
            "within_tolerance": bool(3.0 / NEES_TOLERANCE <= mean <= 3.0 * NEES_TOLERANCE)}


#: windows (increments) of :func:`heading_window_nees`: one scan, 1 s, 10 s and 30 s at the radar's 10 Hz
NEES_WINDOWS = (1, 10, 100, 300)


def heading_window_nees(est_yaw: F64, ref_yaw: F64, var_yaw: F64, ok: npt.NDArray[np.bool_],
                        windows: tuple[int, ...] = NEES_WINDOWS) -> dict[int, float]:
    """The heading change over windows of W consecutive increments, normalised by the sum of the W increments'
    own yaw variances: mean of ``(d_est - d_true)^2 / sum var`` over non-overlapping windows whose scans are all
    ``ok`` (NaN where none). Independent increments with honest variances give 1 at every W (chi-square(1));
    errors correlated from one increment to the next (a gyro bias, a scale error) make it grow with W: the
    summed per-increment variance then understates the heading error over a window, which is what a proposal
    that draws each increment's noise independently spreads its particles by."""
    est_yaw, ref_yaw = np.asarray(est_yaw, np.float64), np.asarray(ref_yaw, np.float64)
    var = np.asarray(var_yaw, np.float64)
    pose_ok = np.asarray(ok, bool)
    inc_ok = np.zeros(len(var), bool)  # increment i: from pose i-1 to pose i
    inc_ok[1:] = pose_ok[1:] & pose_ok[:-1] & np.isfinite(var[1:]) & (var[1:] > 0)
    n_ok = np.r_[0, np.cumsum(inc_ok)]
    total = np.r_[0.0, np.cumsum(np.where(inc_ok, var, 0.0))]
    out: dict[int, float] = {}
    for w in windows:
        k = np.arange(0, len(est_yaw) - w, w)  # window k: poses k..k+w, increments k+1..k+w
        good = n_ok[k + w + 1] - n_ok[k + 1] == w
        v = total[k + w + 1] - total[k + 1]
        e = wrap_angle((est_yaw[k + w] - est_yaw[k]) - (ref_yaw[k + w] - ref_yaw[k]))
        out[w] = float(np.mean(e[good] ** 2 / v[good])) if good.any() else float("nan")
    return out


def distance_ratio(t_s: F64, est_xy: F64, ref_xy: F64, ok: npt.NDArray[np.bool_], window_s: float = 10.0,
                   min_m: float = 3.0) -> dict[str, Any]:
    """The odometry's speed scale against the truth: from every scan, the straight-line distance the estimate
    moves in the next ``window_s`` seconds over the distance the truth moves, where the truth moves at least
    ``min_m`` (a short window bends too little for a heading error to matter; straight-line, so position
    noise at a standstill does not add length as a summed path would). Both ends ``ok``. Returns the count,
    median and 10th / 90th percentiles of the ratio (1: no scale error; NaN where no window qualifies). A
    persistent scale error shows as a median off 1; noise as the spread."""
    t = np.asarray(t_s, np.float64)
    est, ref = np.asarray(est_xy, np.float64), np.asarray(ref_xy, np.float64)
    good = np.asarray(ok, bool)
    j = np.searchsorted(t, t + window_s)
    i = np.flatnonzero(j < len(t))
    j = j[i]
    d_ref = np.hypot(*(ref[j] - ref[i]).T)
    use = good[i] & good[j] & (d_ref >= min_m)
    r = np.hypot(*(est[j[use]] - est[i[use]]).T) / d_ref[use]
    if not len(r):
        return {"windows": 0, "median": float("nan"), "p10": float("nan"), "p90": float("nan")}
    p10, med, p90 = np.percentile(r, [10, 50, 90])
    return {"windows": len(r), "median": round(float(med), 5), "p10": round(float(p10), 5),
            "p90": round(float(p90), 5)}
