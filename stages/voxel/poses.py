"""Sensor poses at scan times: interpolation of SE(3) ground truth and SE(2) trajectories, FoV filters."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def interpolate_se3(
    t_query: npt.ArrayLike, t: npt.ArrayLike, xyz: npt.ArrayLike, quat_xyzw: npt.ArrayLike
) -> tuple[FloatArray, BoolArray]:
    """Poses (N, 4, 4) at ``t_query``: linear in position, slerp in rotation; ``valid`` marks query times
    inside the pose time span (others get the identity and must be dropped)."""
    tq = np.asarray(t_query, dtype=np.int64)
    tt = np.asarray(t, dtype=np.int64)
    order = np.argsort(tt, kind="stable")
    tt = tt[order]
    keep = np.r_[True, np.diff(tt) > 0]  # duplicate stamps: keep the first
    idx = order[keep]
    tt = tt[keep]
    p = np.asarray(xyz, dtype=np.float64)[idx]
    q = np.asarray(quat_xyzw, dtype=np.float64)[idx]
    out = np.tile(np.eye(4), (len(tq), 1, 1))
    valid = (tq >= tt[0]) & (tq <= tt[-1]) if len(tt) else np.zeros(len(tq), bool)
    if not np.any(valid):
        return out, valid
    ref = tt[0]
    ts = (tt - ref).astype(np.float64) * 1e-9
    tv = (tq[valid] - ref).astype(np.float64) * 1e-9
    if len(tt) == 1:
        out[valid, :3, :3] = Rotation.from_quat(q[0]).as_matrix()
        out[valid, :3, 3] = p[0]
        return out, valid
    out[valid, :3, :3] = Slerp(ts, Rotation.from_quat(q))(tv).as_matrix()
    out[valid, :3, 3] = np.stack([np.interp(tv, ts, p[:, i]) for i in range(3)], axis=1)
    return out, valid


def sorted_unique_stamps(t: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Stamps sorted (stable) with repeats dropped (the first kept), and the indices of the kept rows."""
    tt = np.asarray(t, dtype=np.int64)
    order = np.argsort(tt, kind="stable")
    keep = np.r_[True, np.diff(tt[order]) > 0] if len(tt) else np.zeros(0, bool)
    return tt[order][keep], order[keep]


def interpolate_se2(
    t_query: npt.ArrayLike, t: npt.ArrayLike, x: npt.ArrayLike, y: npt.ArrayLike, yaw: npt.ArrayLike, z: float
) -> tuple[FloatArray, BoolArray]:
    """SE(2) poses lifted to SE(3) at ``t_query`` (linear x, y and unwrapped yaw; constant height ``z``,
    zero roll and pitch); ``valid`` marks query times inside the trajectory's time span."""
    tq = np.asarray(t_query, dtype=np.int64)
    tt, idx = sorted_unique_stamps(t)
    out = np.tile(np.eye(4), (len(tq), 1, 1))
    valid = (tq >= tt[0]) & (tq <= tt[-1]) if len(tt) else np.zeros(len(tq), bool)
    if not np.any(valid):
        return out, valid
    ref = tt[0]
    ts = (tt - ref).astype(np.float64)
    tv = (tq[valid] - ref).astype(np.float64)
    xi = np.interp(tv, ts, np.asarray(x, dtype=np.float64)[idx])
    yi = np.interp(tv, ts, np.asarray(y, dtype=np.float64)[idx])
    th = np.interp(tv, ts, np.unwrap(np.asarray(yaw, dtype=np.float64)[idx]))
    c, s = np.cos(th), np.sin(th)
    out[valid, 0, 0], out[valid, 0, 1], out[valid, 1, 0], out[valid, 1, 1] = c, -s, s, c
    out[valid, 0, 3], out[valid, 1, 3], out[valid, 2, 3] = xi, yi, z
    return out, valid


def interpolate_planar_attitude(
    t_query: npt.ArrayLike, t: npt.ArrayLike, x: npt.ArrayLike, y: npt.ArrayLike, yaw: npt.ArrayLike,
    t_att: npt.ArrayLike, z: npt.ArrayLike, roll: npt.ArrayLike, pitch: npt.ArrayLike,
) -> tuple[FloatArray, BoolArray]:
    """3D poses at ``t_query`` from a planar estimate (x, y, yaw at ``t``: a SLAM method's) and the height and
    attitude of another (z, roll, pitch at ``t_att``: the odometry's), R = Rz(yaw) Ry(pitch) Rx(roll).

    Each part is interpolated on its own stamps (linear x, y, z, unwrapped yaw, roll and pitch); ``valid`` marks
    query times inside both time spans. A planar SLAM method corrects the odometry's x, y and yaw and leaves the
    rest untouched, so its 3D pose is the odometry's with those three replaced.
    """
    tq = np.asarray(t_query, dtype=np.int64)
    planar, valid = interpolate_se2(tq, t, x, y, yaw, 0.0)
    ta, idx = sorted_unique_stamps(t_att)
    valid = valid & ((tq >= ta[0]) & (tq <= ta[-1]) if len(ta) else np.zeros(len(tq), bool))
    out = np.tile(np.eye(4), (len(tq), 1, 1))
    if not np.any(valid):
        return out, valid
    ref = ta[0]
    ts = (ta - ref).astype(np.float64)
    tv = (tq[valid] - ref).astype(np.float64)
    zi = np.interp(tv, ts, np.asarray(z, dtype=np.float64)[idx])
    ri, pi = (np.interp(tv, ts, np.unwrap(np.asarray(v, dtype=np.float64)[idx])) for v in (roll, pitch))
    th = np.arctan2(planar[valid, 1, 0], planar[valid, 0, 0])
    out[valid, :3, :3] = Rotation.from_euler("ZYX", np.stack([th, pi, ri], axis=1)).as_matrix()
    out[valid, 0, 3], out[valid, 1, 3], out[valid, 2, 3] = planar[valid, 0, 3], planar[valid, 1, 3], zi
    return out, valid


def horizontal_fov_mask(points: npt.ArrayLike, axis: npt.ArrayLike, fov: float) -> BoolArray:
    """Points (sensor frame) whose horizontal bearing lies within ``fov / 2`` of the bearing of ``axis``.

    Used to restrict the lidar to the radar's field of view (RMap Sec. III-A: 180 degrees): ``axis`` is
    the radar boresight expressed in the lidar frame; ``fov`` in radians (>= 2 pi keeps everything).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if fov >= 2 * np.pi:
        return np.ones(len(pts), bool)
    ax = np.asarray(axis, dtype=np.float64)
    bearing = np.arctan2(pts[:, 1], pts[:, 0]) - np.arctan2(ax[1], ax[0])
    bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
    return np.abs(bearing) <= fov / 2
