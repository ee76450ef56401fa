"""Occupancy samples along filtered radar beams (RICH-SLAM Sec. IV-B, Fig. 3a). Pure numpy.

A beam runs from the radar origin to a detection, both in the 2D base (body) frame. Free samples
(label -1) sit at ``step, 2 step, ...`` along the beam, stopping ``clearance`` short of the endpoint;
the endpoint itself is the positive sample (+1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class BeamSamples:
    """Samples of one scan in the body frame."""

    points: npt.NDArray[np.float64]  # (N, 2) body-frame positions (Delta p^b of eq. 13)
    labels: npt.NDArray[np.float64]  # (N,) -1 free, +1 endpoint
    beam: npt.NDArray[np.int64]  # (N,) beam index of each sample
    endpoints: npt.NDArray[np.float64]  # (B, 2) kept endpoints
    origin: npt.NDArray[np.float64]  # (2,) beam origin (radar position in the body frame)

    @property
    def n(self) -> int:
        return int(self.labels.size)

    @property
    def is_endpoint(self) -> npt.NDArray[np.bool_]:
        return self.labels > 0


def radar_to_body_2d(
    points_radar: npt.ArrayLike,
    base_from_radar: npt.ArrayLike,
    z_min: float | None = None,
    z_max: float | None = None,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Transform radar-frame points (N, 3) to the base frame and project to the plane.

    Returns the 2D points kept by the optional height gate (base-frame z in [z_min, z_max]) and the
    2D radar origin in the base frame.
    """
    T = np.asarray(base_from_radar, dtype=np.float64).reshape(4, 4)
    p = np.asarray(points_radar, dtype=np.float64).reshape(-1, 3)
    q = p @ T[:3, :3].T + T[:3, 3]
    keep = np.ones(len(q), dtype=bool)
    if z_min is not None:
        keep &= q[:, 2] >= z_min
    if z_max is not None:
        keep &= q[:, 2] <= z_max
    return q[keep, :2], T[:2, 3].copy()


def sample_beams(
    endpoints: npt.ArrayLike,
    origin: npt.ArrayLike,
    step: float,
    max_range: float,
    min_range: float = 0.0,
    clearance: float = 0.0,
) -> BeamSamples:
    """Free samples every ``step`` metres and a +1 endpoint per beam (Fig. 3a).

    Beams longer than ``max_range`` or shorter than ``min_range`` are dropped. A free sample at
    distance ``t`` is kept when ``step <= t < d - clearance`` (``d`` the beam length).
    """
    if step <= 0:
        raise ValueError(f"ray step must be positive, got {step}")
    e = np.asarray(endpoints, dtype=np.float64).reshape(-1, 2)
    o = np.asarray(origin, dtype=np.float64).reshape(2)
    d_vec = e - o
    d = np.linalg.norm(d_vec, axis=1)
    keep = (d <= max_range) & (d >= max(min_range, 1e-9))
    e, d_vec, d = e[keep], d_vec[keep], d[keep]
    B = len(e)
    n_free = np.maximum(np.ceil((d - clearance) / step).astype(np.int64) - 1, 0)
    # t = step * j for j = 1..n_free; guard the strict inequality against rounding
    beam_free = np.repeat(np.arange(B), n_free)
    j = np.arange(n_free.sum()) - np.repeat(np.cumsum(n_free) - n_free, n_free) + 1
    t = step * j
    ok = t < d[beam_free] - clearance
    beam_free, t = beam_free[ok], t[ok]
    unit = d_vec / np.where(d > 0, d, 1.0)[:, None]
    free_pts = o + unit[beam_free] * t[:, None]
    points = np.concatenate([free_pts, e], axis=0)
    labels = np.concatenate([-np.ones(len(free_pts)), np.ones(B)])
    beam = np.concatenate([beam_free, np.arange(B)]).astype(np.int64)
    return BeamSamples(points, labels, beam, e, o)


def to_world(poses: npt.ArrayLike, points_body: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """``T(x, Delta p^b)`` of eq. 13 for poses ``(..., 3)`` (x, y, yaw) and body points ``(N, 2)``.

    Returns ``(..., N, 2)``.
    """
    x = np.asarray(poses, dtype=np.float64)
    p = np.asarray(points_body, dtype=np.float64)
    c = np.cos(x[..., 2])[..., None]
    s = np.sin(x[..., 2])[..., None]
    wx = c * p[:, 0] - s * p[:, 1] + x[..., 0:1]
    wy = s * p[:, 0] + c * p[:, 1] + x[..., 1:2]
    return np.stack([wx, wy], axis=-1)


def stencil_offsets(radius: float, ring_points: int, rings: int = 1) -> npt.NDArray[np.float64]:
    """Offsets of the endpoint-tolerance neighbourhood (Fig. 3b): the centre plus ``rings`` rings.

    Ring r (1..rings) has radius ``radius * r / rings`` and ``ring_points`` points. Returns (K, 2)
    with the centre first.
    """
    out = [np.zeros((1, 2))]
    if radius > 0 and ring_points > 0:
        for r in range(1, rings + 1):
            ang = 2 * np.pi * (np.arange(ring_points) + 0.5 * (r % 2 == 0)) / ring_points
            out.append(radius * r / rings * np.stack([np.cos(ang), np.sin(ang)], axis=1))
    return np.concatenate(out, axis=0)
