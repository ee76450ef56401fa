"""Rigid-transform helpers shared by ingest, filter and odometry (pure numpy/scipy).

Conventions: quaternions are (x, y, z, w); ``a_from_b`` (or ``a<-b``) is the 4x4 transform taking
coordinates in frame b to frame a.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

F64 = npt.NDArray[np.float64]


def quat_to_matrix(q: npt.ArrayLike) -> F64:
    """Rotation matrix of a quaternion (x, y, z, w); normalised first."""
    return np.asarray(Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix())


def pose_matrix(t: npt.ArrayLike, q: npt.ArrayLike) -> F64:
    """4x4 transform from a translation and a quaternion (x, y, z, w)."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def invert(T: F64) -> F64:
    """Inverse of a rigid 4x4 transform."""
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def lookup(edges: Mapping[tuple[str, str], F64], target: str, source: str) -> F64 | None:
    """``target <- source`` through a graph of ``(parent, child) -> parent <- child`` edges (BFS), or None."""
    target, source = target.lstrip("/"), source.lstrip("/")
    if target == source:
        return np.eye(4)
    adj: dict[str, list[tuple[str, F64]]] = {}
    for (parent, child), T in edges.items():
        adj.setdefault(parent, []).append((child, T))
        adj.setdefault(child, []).append((parent, invert(T)))
    seen = {target: np.eye(4)}
    todo = deque([target])
    while todo:
        frame = todo.popleft()
        for nxt, T in adj.get(frame, []):
            if nxt not in seen:
                seen[nxt] = seen[frame] @ T
                if nxt == source:
                    return seen[nxt]
                todo.append(nxt)
    return None


def poses_to_matrices(values: F64) -> F64:
    """(N, 7) rows ``x y z qx qy qz qw`` to (N, 4, 4)."""
    values = np.asarray(values, dtype=np.float64).reshape(-1, 7)
    out = np.tile(np.eye(4), (len(values), 1, 1))
    if len(values):
        out[:, :3, :3] = Rotation.from_quat(values[:, 3:7]).as_matrix()
        out[:, :3, 3] = values[:, :3]
    return out


def matrices_to_poses(T: F64) -> F64:
    """(N, 4, 4) to (N, 7) rows ``x y z qx qy qz qw``."""
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    out = np.zeros((len(T), 7))
    if len(T):
        out[:, :3] = T[:, :3, 3]
        out[:, 3:] = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    return out


def interpolate_poses(t_ref: npt.NDArray[np.int64], poses: F64, t_query: npt.ArrayLike
                      ) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Poses (N, 7) at times ``t_ref`` interpolated at ``t_query``: linear position, slerp rotation.

    Returns (M, 4, 4) transforms and a mask of queries inside ``[t_ref[0], t_ref[-1]]`` (others clamp).
    """
    tq = np.asarray(t_query, dtype=np.int64)
    out = np.tile(np.eye(4), (tq.size, 1, 1))
    if len(t_ref) == 0:
        return out, np.zeros(tq.size, bool)
    inside = (tq >= t_ref[0]) & (tq <= t_ref[-1])
    if len(t_ref) == 1:
        out[:] = poses_to_matrices(poses)[0]
        return out, inside
    t0 = t_ref[0]
    x = (t_ref - t0).astype(np.float64)
    xq = np.clip((tq - t0).astype(np.float64), x[0], x[-1])
    for k in range(3):
        out[:, k, 3] = np.interp(xq, x, poses[:, k])
    out[:, :3, :3] = Slerp(x, Rotation.from_quat(poses[:, 3:7]))(xq).as_matrix()
    return out, inside


def yaw_of(R: F64) -> F64:
    """Heading of rotation matrices (..., 3, 3): the angle of the rotated x axis in the xy plane."""
    R = np.asarray(R)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def roll_pitch_of(R: F64) -> tuple[F64, F64]:
    """Roll and pitch of rotation matrices (..., 3, 3) in the yaw-pitch-roll (Z-Y-X) convention,
    R = Rz(yaw) Ry(pitch) Rx(roll): both unchanged by a rotation about the world z axis."""
    R = np.asarray(R, dtype=np.float64)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return roll, pitch


def wrap_angle(a: npt.ArrayLike) -> F64:
    """Angles wrapped to (-pi, pi]."""
    return np.asarray((np.asarray(a) + np.pi) % (2 * np.pi) - np.pi, dtype=np.float64)
