"""The radar occupancy sensor model of RMap Sec. III-A (the ColoRadar authors' OctoMap fork, ref. [3]).

Decided from the public fork (``RadarPointOctomapServer``, ``getCellsInFov`` and
``insertRadarScanToMap``):

- The field of view is a fan of rays in the sensor frame, ``az = i * delta - az_fov`` and
  ``el = j * delta - el_fov`` for ``i < floor(2 az_fov / delta)``, ``j < floor(2 el_fov / delta)``, with
  ``delta = 2 atan(res / 2 / max_range)`` (adjacent rays one voxel apart at the maximum range), direction
  ``(cos az cos el, sin az cos el, sin el)``; ``az_fov``/``el_fov`` are half-angles (the fork's defaults
  are 45 and 22.5 degrees; the ColoRadar tools and RMap use +-45 / +-45 degrees to 10 m).
- Every voxel a ray passes between ``min_range`` and ``max_range`` (OctoMap ``computeRayKeys``: the
  ray's end voxel excluded) is a *miss*, however many returns the scan has; there is no ray casting
  through the returns, so the radar's penetration past a first return is kept.
- A voxel holding a radar return is a *hit* if and only if it lies in that fan set (returns outside
  the fan or beyond ``max_range`` are ignored); hit voxels are removed from the miss set.
- Each voxel is updated once per scan with OctoMap's clamped log-odds update; RMap's values are
  hit 0.7, miss 0.4, clamping [0.12, 0.97], resolution 0.15 m.

Not reproduced: the fork's optional ``filterReflections`` (Euclidean clustering of multipath
reflections) and its sliding-window local mapping mode; RMap does not mention either.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from stages.voxel.raycast import ray_keys
from stages.voxel.voxel_map import coord_to_key

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.integer[Any]]


def fan_directions(
    azimuth_fov: float, elevation_fov: float, resolution: float, max_range: float
) -> FloatArray:
    """Unit ray directions (R, 3) of the fan in the radar frame (x boresight, y left, z up); angles in rad."""
    if max_range <= 0:
        raise ValueError(f"radar max_range must be positive, got {max_range}")
    delta = 2.0 * np.arctan(0.5 * resolution / max_range)
    n_az = int(2.0 * azimuth_fov / delta)
    n_el = int(2.0 * elevation_fov / delta)
    az = np.arange(n_az) * delta - azimuth_fov
    el = np.arange(n_el) * delta - elevation_fov
    a, e = np.meshgrid(az, el, indexing="ij")
    dirs = np.stack([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)], axis=-1)
    return dirs.reshape(-1, 3)


def radar_scan_keys(
    points_sensor: npt.ArrayLike,
    world_from_sensor: npt.ArrayLike,
    directions: npt.ArrayLike,
    resolution: float,
    min_range: float,
    max_range: float,
) -> tuple[IntArray, IntArray]:
    """Fan (miss candidates) and return keys of one radar scan in world voxel keys.

    Pass both to ``VoxelMap.integrate(fan, hits, hits_need_free=True)``, which keeps only the returns
    inside the fan and removes them from the miss set.
    """
    T = np.asarray(world_from_sensor, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    dirs_w = np.asarray(directions, dtype=np.float64) @ R.T
    starts = t + dirs_w * min_range
    ends = t + dirs_w * max_range
    fan = ray_keys(starts if min_range > 0 else t, ends, resolution)
    pts = np.asarray(points_sensor, dtype=np.float64).reshape(-1, 3)
    hits = coord_to_key(pts @ R.T + t, resolution)
    return fan, hits
