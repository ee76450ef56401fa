"""Spinning lidar (Ouster OS1 point layout) ray-cast against the same world.

Each column fires at its own time during the 100 ms sweep from the lidar pose at that time, and the
points stay in the lidar frame at their column's time (no de-skewing, as the driver publishes them).
The cloud is organised (height = beams, width = columns, row-major by ring); missing returns are all-zero
points with only ``t``, ``ring`` and ``noise`` set, like the driver's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulator.params import LidarParams
from simulator.raycast import cast
from simulator.world import Scene

LIDAR_DTYPE = np.dtype(
    {"names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "noise", "range"],
     "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "u1", "<u2", "<u4"],
     "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32], "itemsize": 48}
)


@dataclass(frozen=True)
class LidarScan:
    index: int
    t: float  # start of the sweep, seconds from the start of the run
    cloud: np.ndarray  # LIDAR_DTYPE (beams * columns,), row-major (ring, column)
    height: int
    width: int


def beam_elevations(p: LidarParams) -> np.ndarray:
    """Elevation of each ring (ring 0 is the top beam), radians."""
    half = np.deg2rad(p.vertical_fov_deg) / 2
    return np.linspace(half, -half, p.beams) if p.beams > 1 else np.zeros(1)


def column_azimuths(p: LidarParams) -> np.ndarray:
    """Azimuth of each column in the lidar frame (clockwise sweep from +x), radians."""
    return -2 * np.pi * np.arange(p.columns) / p.columns


def simulate_scan(scene: Scene, p: LidarParams, index: int, t: float, origins: np.ndarray, yaws: np.ndarray,
                  sweep: float, rng: np.random.Generator) -> LidarScan:
    """One sweep; ``origins`` (W, 3) and ``yaws`` (W,) are the lidar frame's pose at each column time."""
    el = beam_elevations(p)
    az = column_azimuths(p)
    heading = yaws + az
    hits = cast(scene, origins, np.stack([np.cos(heading), np.sin(heading)], axis=1), np.tan(el)[None, :],
                p.max_range)  # (W, B)
    r = hits.range.T  # (B, W)
    valid = np.isfinite(r) & (r >= p.min_range) & (rng.random(r.shape) >= p.dropout)
    r_m = np.where(valid, r + rng.normal(0.0, p.range_noise, r.shape), 0.0)
    valid &= r_m > 0
    refl = scene.lidar_reflectivity[np.maximum(hits.material.T, 0)]
    cos_inc = hits.cos_incidence.T
    ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
    cloud = np.zeros(p.beams * p.columns, dtype=LIDAR_DTYPE)
    x = np.where(valid, r_m * ce * np.cos(az)[None, :], 0.0)
    y = np.where(valid, r_m * ce * np.sin(az)[None, :], 0.0)
    z = np.where(valid, r_m * se, 0.0)
    intensity = np.where(valid, p.intensity_scale * refl * cos_inc / np.maximum(r_m, 0.5) ** 2, 0.0)
    intensity = intensity * rng.gamma(20.0, 1 / 20.0, r.shape)
    cloud["x"], cloud["y"], cloud["z"] = x.ravel(), y.ravel(), z.ravel()
    cloud["intensity"] = intensity.ravel()
    t_off = np.round(np.arange(p.columns) * sweep / p.columns * 1e9).astype(np.uint32)
    cloud["t"] = np.broadcast_to(t_off[None, :], r.shape).ravel()
    cloud["reflectivity"] = np.where(valid, np.round(refl * 255), 0).astype(np.uint16).ravel()
    cloud["ring"] = np.repeat(np.arange(p.beams, dtype=np.uint8), p.columns)
    cloud["noise"] = rng.poisson(30.0, r.shape).astype(np.uint16).ravel()
    cloud["range"] = np.where(valid, np.round(r_m * 1000.0), 0).astype(np.uint32).ravel()
    return LidarScan(index=index, t=t, cloud=cloud, height=p.beams, width=p.columns)
