"""SE(2) trajectory helpers for the odometry stage: anchoring and drift against ground truth."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from stages.ingest.geometry import wrap_angle

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
