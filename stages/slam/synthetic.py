"""Small synthetic 2D worlds (wall segments, a trajectory, ray-cast sparse beams) for tests and benchmarks.

Pure numpy; deterministic given the generator. Not a radar simulator (that is ``simulator/``): just
enough geometry to exercise the filter with known ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.slam.rbpf import compose, odometry_increments
from stages.slam.se2 import wrap_angle

F64 = npt.NDArray[np.floating[Any]]


def box_walls(xmin: float, ymin: float, xmax: float, ymax: float) -> F64:
    """The four walls of an axis-aligned box as segments ``(4, 2, 2)``."""
    c = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    return np.stack([c, np.roll(c, -1, axis=0)], axis=1)


def corridor_world() -> F64:
    """A 20 m x 12 m loop corridor: an outer box, an inner block, and a few pillars."""
    walls = [box_walls(-10, -6, 10, 6), box_walls(-6, -2, 6, 2)]
    for cx, cy in ((-8.0, 4.5), (8.0, -4.5), (0.0, 4.6)):
        walls.append(box_walls(cx - 0.3, cy - 0.3, cx + 0.3, cy + 0.3))
    return np.concatenate(walls, axis=0)


def loop_trajectory(n: int, speed: float = 1.0, dt: float = 0.1) -> F64:
    """Poses ``(n, 3)`` around the corridor loop (rounded rectangle at |x| <= 8, |y| <= 4)."""
    s = np.arange(n) * speed * dt
    a, b, r = 8.0, 4.0, 2.0
    straight_x, straight_y = 2 * (a - r), 2 * (b - r)
    quarter = np.pi * r / 2
    per = 2 * straight_x + 2 * straight_y + 4 * quarter
    s = s % per
    out = np.zeros((n, 3))
    segs = [("line", (-a + r, -b), 0.0, straight_x), ("arc", (a - r, -b + r), -np.pi / 2, quarter),
            ("line", (a, -b + r), np.pi / 2, straight_y), ("arc", (a - r, b - r), 0.0, quarter),
            ("line", (a - r, b), np.pi, straight_x), ("arc", (-a + r, b - r), np.pi / 2, quarter),
            ("line", (-a, b - r), -np.pi / 2, straight_y), ("arc", (-a + r, -b + r), np.pi, quarter)]
    start = 0.0
    for kind, p0, ang, length in segs:
        m = (s >= start) & (s < start + length)
        t = s[m] - start
        if kind == "line":
            out[m, 0] = p0[0] + t * np.cos(ang)
            out[m, 1] = p0[1] + t * np.sin(ang)
            out[m, 2] = ang
        else:
            phi = ang + t / r
            out[m, 0] = p0[0] + r * np.cos(phi)
            out[m, 1] = p0[1] + r * np.sin(phi)
            out[m, 2] = phi + np.pi / 2
        start += length
    out[:, 2] = wrap_angle(out[:, 2])
    return out


def ray_cast(origins: F64, directions: F64, walls: F64) -> F64:
    """Distance along each ray ``(R, 2)`` to the nearest wall segment; inf when none is hit."""
    p = origins[:, None, :]
    r = directions[:, None, :]
    a = walls[None, :, 0, :]
    s = walls[None, :, 1, :] - a
    denom = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    qp = a - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]) / denom
        u = (qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 1e-9) & (u >= 0) & (u <= 1)
    return np.where(hit, t, np.inf).min(axis=1)


@dataclass
class SyntheticRun:
    groundtruth: F64  # (T, 3)
    odometry: F64  # (T, 3)
    scans: list[F64]  # body-frame 2D endpoints per scan
    walls: F64


def make_run(
    n_scans: int,
    rng: np.random.Generator,
    beams_per_scan: int = 25,
    fov_deg: float = 120.0,
    max_range: float = 5.0,
    range_noise: float = 0.05,
    angle_noise_deg: float = 1.0,
    outlier_fraction: float = 0.1,
    odo_trans_noise: float = 0.01,
    odo_yaw_noise: float = 0.004,
    odo_yaw_bias: float = 0.002,
    walls: F64 | None = None,
) -> SyntheticRun:
    """Ground truth on the corridor loop, drifting odometry, sparse noisy beams (radar at the body origin)."""
    walls = corridor_world() if walls is None else walls
    gt = loop_trajectory(n_scans)
    u = odometry_increments(gt)
    noisy = u + rng.standard_normal(u.shape) * [odo_trans_noise, odo_trans_noise, odo_yaw_noise]
    noisy[:, 2] += odo_yaw_bias
    noisy[0] = 0.0
    odo = np.zeros_like(gt)
    odo[0] = gt[0]
    for i in range(1, n_scans):
        odo[i] = compose(odo[i - 1], noisy[i])
    scans = []
    half = np.radians(fov_deg) / 2
    for i in range(n_scans):
        ang = rng.uniform(-half, half, beams_per_scan)
        world_ang = ang + gt[i, 2]
        dirs = np.stack([np.cos(world_ang), np.sin(world_ang)], axis=1)
        d = ray_cast(np.repeat(gt[i : i + 1, :2], beams_per_scan, 0), dirs, walls)
        ok = d <= max_range
        d = d[ok] + rng.standard_normal(ok.sum()) * range_noise
        a = ang[ok] + np.radians(angle_noise_deg) * rng.standard_normal(ok.sum())
        pts = np.stack([d * np.cos(a), d * np.sin(a)], axis=1)
        n_out = rng.binomial(len(pts), outlier_fraction)
        if n_out:
            idx = rng.choice(len(pts), n_out, replace=False)
            rr = rng.uniform(0.5, max_range, n_out)
            aa = rng.uniform(-half, half, n_out)
            pts[idx] = np.stack([rr * np.cos(aa), rr * np.sin(aa)], axis=1)
        scans.append(pts)
    return SyntheticRun(gt, odo, scans, walls)
