"""Measurements of the filter against references: ground-truth radar velocity and simulator point labels."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from core.geometry import interpolate_poses

F64 = npt.NDArray[np.float64]
LABELS = {0: "true", 1: "clutter", 2: "ghost"}


def radar_velocity_from_groundtruth(gt_t: npt.NDArray[np.int64], gt_poses: F64, base_from_radar: F64,
                                    t_query: npt.NDArray[np.int64], half_window_s: float
                                    ) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Velocity of the radar in its own frame at ``t_query``, by central differences of ground truth.

    The radar origin in the world is ``p_wb + R_wb t_br``; its derivative over ``t +- half_window`` is
    rotated into the radar frame at ``t``. Returns (M, 3) and a mask of queries whose window lies inside
    the ground-truth time span.
    """
    h = round(half_window_s * 1e9)
    Tm, in_m = interpolate_poses(gt_t, gt_poses, t_query - h)
    Tp, in_p = interpolate_poses(gt_t, gt_poses, t_query + h)
    T0, _ = interpolate_poses(gt_t, gt_poses, t_query)
    p_m = (Tm @ base_from_radar)[:, :3, 3]
    p_p = (Tp @ base_from_radar)[:, :3, 3]
    v_world = (p_p - p_m) / (2 * h * 1e-9)
    R_wr = (T0 @ base_from_radar)[:, :3, :3]
    v = np.einsum("nji,nj->ni", R_wr, v_world)
    return v, in_m & in_p


def velocity_errors(v_est: F64, v_ref: F64, mask: npt.NDArray[np.bool_]) -> dict[str, Any]:
    """RMSE of the velocity error (3D norm, horizontal x-y of the radar frame, per axis) over ``mask``."""
    if not mask.any():
        return {"scans": 0}
    e = v_est[mask] - v_ref[mask]
    return {
        "scans": int(mask.sum()),
        "rmse_mps": round(float(np.sqrt((e ** 2).sum(axis=1).mean())), 4),
        "rmse_xy_mps": round(float(np.sqrt((e[:, :2] ** 2).sum(axis=1).mean())), 4),
        "rmse_axes_mps": [round(float(x), 4) for x in np.sqrt((e ** 2).mean(axis=0))],
        "median_abs_mps": round(float(np.median(np.linalg.norm(e, axis=1))), 4),
        "mean_speed_mps": round(float(np.linalg.norm(v_ref[mask], axis=1).mean()), 4),
    }


def label_fractions(labels: npt.NDArray[np.integer[Any]], masks: dict[str, npt.NDArray[np.bool_]]) -> dict[str, Any]:
    """Fractions of true points kept and of clutter / ghost points rejected, overall and per gate."""
    kept = masks["kept"]
    out: dict[str, Any] = {}
    for value, name in LABELS.items():
        sel = labels == value
        out[f"n_{name}"] = int(sel.sum())
        if not sel.any():
            out[f"{name}_kept" if value == 0 else f"{name}_rejected"] = None
            continue
        frac_kept = float(kept[sel].mean())
        if value == 0:
            out["true_kept"] = round(frac_kept, 4)
        else:
            out[f"{name}_rejected"] = round(1.0 - frac_kept, 4)
        out[f"{name}_passed"] = {g: round(float(masks[g][sel].mean()), 4)
                                 for g in ("in_range", "static", "bright", "certain", "candidate", "kept")}
    return out
