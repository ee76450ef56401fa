"""Radar detections placed in the world with ground-truth poses (the AUC protocol's input). Pure numpy/scipy.

Ground truth (world <- base) is interpolated at each scan time: linearly in position and by slerp in
orientation; a scan is used only when the ground-truth samples around it are at most ``max_gap_ns``
apart. Points go radar -> base with the calibration, are gated by base-frame height and range, then
go to the world; the 2D beam runs from the radar origin to the detection, both projected on the plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

F64 = npt.NDArray[np.float64]


@dataclass
class GTInterpolator:
    """World <- base poses at arbitrary times."""

    t_ns: npt.NDArray[np.int64]
    pos: F64
    slerp: Slerp
    max_gap_ns: int

    def valid(self, t: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        t = np.asarray(t, np.int64)
        hi = np.clip(np.searchsorted(self.t_ns, t, side="left"), 1, len(self.t_ns) - 1)
        lo = np.where(self.t_ns[hi] == t, hi, hi - 1)
        return (t >= self.t_ns[0]) & (t <= self.t_ns[-1]) & (self.t_ns[hi] - self.t_ns[lo] <= self.max_gap_ns)

    def span_mask(self, t: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        t = np.asarray(t, np.int64)
        return (t >= self.t_ns[0]) & (t <= self.t_ns[-1])

    def at(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        """Positions (K, 3) and rotation matrices (K, 3, 3) at times inside the span."""
        t = np.asarray(t, np.int64)
        rel = (t - self.t_ns[0]).astype(np.float64)
        ref = (self.t_ns - self.t_ns[0]).astype(np.float64)
        pos = np.stack([np.interp(rel, ref, self.pos[:, i]) for i in range(3)], 1)
        return pos, self.slerp(rel).as_matrix()


def gt_interpolator(gt: dict[str, Any], max_gap_ns: int) -> GTInterpolator:
    """From ground-truth columns t_ns, x, y, z, qx, qy, qz, qw (sorted by time; duplicates dropped)."""
    t = np.asarray(gt["t_ns"], np.int64)
    keep = np.r_[True, np.diff(t) > 0]
    t = t[keep]
    pos = np.stack([np.asarray(gt[k], np.float64)[keep] for k in ("x", "y", "z")], 1)
    q = np.stack([np.asarray(gt[k], np.float64)[keep] for k in ("qx", "qy", "qz", "qw")], 1)
    rel = (t - t[0]).astype(np.float64)
    return GTInterpolator(t, pos, Slerp(rel, Rotation.from_quat(q)), max_gap_ns)


@dataclass
class WorldBeams:
    """One 2D beam per kept radar point."""

    scan: npt.NDArray[np.int64]
    t_ns: npt.NDArray[np.int64]
    origin: F64  # (B, 2)
    end: F64  # (B, 2)
    stats: dict[str, int] = field(default_factory=dict)


def radar_beams_world(
    radar: Any, base_from_radar: F64, gt: GTInterpolator, max_range: float,
    z_min: float | None = None, z_max: float | None = None,
) -> WorldBeams:
    """Radar points (table with scan, t_ns, x, y, z in the radar frame) as world beams."""
    scan = radar["scan"].to_numpy().astype(np.int64)
    t = radar["t_ns"].to_numpy().astype(np.int64)
    p = np.stack([radar[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], 1)
    T = np.asarray(base_from_radar, np.float64)
    q = p @ T[:3, :3].T + T[:3, 3]
    keep_range = np.linalg.norm(p, axis=1) <= max_range
    keep_z = np.ones(len(q), bool)
    if z_min is not None:
        keep_z &= q[:, 2] >= z_min
    if z_max is not None:
        keep_z &= q[:, 2] <= z_max
    keep_gt = gt.valid(t)
    keep = keep_range & keep_z & keep_gt
    stats = {"points": len(p), "beyond_max_range": int((~keep_range).sum()), "height_gated": int((~keep_z).sum()),
             "no_groundtruth": int((~keep_gt).sum()), "kept": int(keep.sum())}
    scan, t, q = scan[keep], t[keep], q[keep]
    # one interpolation per scan time, not per point
    ut, inv = np.unique(t, return_inverse=True)
    pos, rot = gt.at(ut)
    Rw = rot[inv]
    end = np.einsum("kij,kj->ki", Rw, q) + pos[inv]
    origin = np.einsum("kij,j->ki", Rw, T[:3, 3]) + pos[inv]
    return WorldBeams(scan, t, origin[:, :2], end[:, :2], stats)
