"""Vectorised ray casting against a :class:`~simulator.world.Scene`.

Rays are given as *fans*: ``G`` groups, each with an origin and a horizontal heading, and ``E`` slopes
(``tan`` of the elevation) per group, so a ray is ``o + s * (h, m)`` with ``s`` the horizontal distance.
Intersections with vertical primitives (extruded wall segments, cylinders) depend only on the group's
origin and heading, so they are solved once per group in 2D and then checked against each slope's
height; horizontal primitives (box tops, pillar caps, floor, ceiling) are solved per ray. A spinning
lidar column is one group with one slope per beam; radar rays are groups of one slope each.
All work is numpy broadcasting over (groups, slopes, primitives); there is no Python loop over rays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulator.world import (
    KIND_CEILING,
    KIND_CYLINDER,
    KIND_DISC,
    KIND_FLOOR,
    KIND_NONE,
    KIND_RECT,
    KIND_SEGMENT,
    Scene,
)

S_MIN = 1e-6


@dataclass(frozen=True)
class Hits:
    """First intersections of a fan of rays, each array shaped (G, E)."""

    range: np.ndarray  # 3D distance along the ray (inf: no hit within max_range)
    kind: np.ndarray  # int8 primitive kind (KIND_NONE when no hit)
    material: np.ndarray  # int64 material index (-1 when no hit)
    cos_incidence: np.ndarray  # |cos| of the angle between the ray and the surface normal
    normal_xy: np.ndarray  # (G, E, 2) horizontal unit normal facing the ray origin (vertical surfaces; else 0)

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.range)


def _argmin(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum along the last axis and its index (inf and 0 when the axis is empty)."""
    if values.shape[-1] == 0:
        return np.full(values.shape[:-1], np.inf), np.zeros(values.shape[:-1], dtype=np.int64)
    idx = np.argmin(values, axis=-1)
    return np.take_along_axis(values, idx[..., None], axis=-1)[..., 0], idx


def cast(scene: Scene, origins: np.ndarray, headings: np.ndarray, slopes: np.ndarray,
         max_range: float = np.inf) -> Hits:
    """Cast fans of rays. ``origins`` (G, 3), ``headings`` (G, 2) unit, ``slopes`` (G, E) or (E,)."""
    own = getattr(scene, "cast_fan", None)
    if own is not None:  # a scene with its own geometry (simulator.voxel_world.VoxelScene)
        return own(origins, headings, slopes, max_range)
    o = np.asarray(origins, dtype=np.float64)
    h = np.asarray(headings, dtype=np.float64)
    G = len(o)
    m = np.broadcast_to(np.asarray(slopes, dtype=np.float64), (G, np.shape(slopes)[-1]))
    E = m.shape[1]
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    hx, hy = h[:, 0], h[:, 1]

    best = np.full((G, E), np.inf)
    kind = np.full((G, E), KIND_NONE, dtype=np.int8)
    prim = np.zeros((G, E), dtype=np.int64)

    def take(s: np.ndarray, idx: np.ndarray, k: int) -> None:
        better = s < best
        best[better] = s[better]
        kind[better] = k
        prim[better] = idx[better]

    # vertical: wall segments (2D intersection per group, height check per slope)
    sc = scene
    if len(sc.seg_a):
        ex = sc.seg_b[:, 0] - sc.seg_a[:, 0]
        ey = sc.seg_b[:, 1] - sc.seg_a[:, 1]
        wx = sc.seg_a[None, :, 0] - ox[:, None]
        wy = sc.seg_a[None, :, 1] - oy[:, None]
        den = hx[:, None] * ey[None] - hy[:, None] * ex[None]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(np.abs(den) > 1e-12, 1.0 / den, np.nan)
            s2 = (wx * ey[None] - wy * ex[None]) * inv
            u = (wx * hy[:, None] - wy * hx[:, None]) * inv
        s2 = np.where((s2 > S_MIN) & (u >= 0.0) & (u <= 1.0), s2, np.inf)
        z = oz[:, None, None] + s2[:, None, :] * m[:, :, None]
        ok = (z >= sc.seg_z[None, None, :, 0]) & (z <= sc.seg_z[None, None, :, 1])
        s, idx = _argmin(np.where(ok, s2[:, None, :], np.inf))
        take(s, idx, KIND_SEGMENT)

    # vertical: cylinders
    if len(sc.cyl_c):
        cx = ox[:, None] - sc.cyl_c[None, :, 0]
        cy = oy[:, None] - sc.cyl_c[None, :, 1]
        b = hx[:, None] * cx + hy[:, None] * cy
        disc = b * b - (cx * cx + cy * cy - sc.cyl_r[None] ** 2)
        with np.errstate(invalid="ignore"):
            s2 = -b - np.sqrt(disc)
        s2 = np.where((disc >= 0) & (s2 > S_MIN), s2, np.inf)
        z = oz[:, None, None] + s2[:, None, :] * m[:, :, None]
        ok = (z >= sc.cyl_z[None, None, :, 0]) & (z <= sc.cyl_z[None, None, :, 1])
        s, idx = _argmin(np.where(ok, s2[:, None, :], np.inf))
        take(s, idx, KIND_CYLINDER)

    # horizontal primitives: per ray, s = (z - oz) / m
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_m = np.where(m != 0.0, 1.0 / m, np.inf)

    def plane_s(zp: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            s = (zp[None, None, :] - oz[:, None, None]) * inv_m[:, :, None]
        return np.where(np.isfinite(s) & (s > S_MIN), s, np.inf)

    if len(sc.rect_z):
        s3 = plane_s(sc.rect_z)
        with np.errstate(invalid="ignore"):
            dx = ox[:, None, None] + s3 * hx[:, None, None] - sc.rect_c[None, None, :, 0]
            dy = oy[:, None, None] + s3 * hy[:, None, None] - sc.rect_c[None, None, :, 1]
        c, sn = sc.rect_cs[:, 0], sc.rect_cs[:, 1]
        with np.errstate(invalid="ignore"):
            lx = dx * c + dy * sn
            ly = -dx * sn + dy * c
            ok = (np.abs(lx) <= sc.rect_half[:, 0]) & (np.abs(ly) <= sc.rect_half[:, 1])
        s, idx = _argmin(np.where(ok, s3, np.inf))
        take(s, idx, KIND_RECT)
    if len(sc.disc_z):
        s3 = plane_s(sc.disc_z)
        with np.errstate(invalid="ignore"):
            dx = ox[:, None, None] + s3 * hx[:, None, None] - sc.disc_c[None, None, :, 0]
            dy = oy[:, None, None] + s3 * hy[:, None, None] - sc.disc_c[None, None, :, 1]
        with np.errstate(invalid="ignore"):
            ok = dx * dx + dy * dy <= sc.disc_r**2
        s, idx = _argmin(np.where(ok, s3, np.inf))
        take(s, idx, KIND_DISC)
    zero = np.zeros((G, E), dtype=np.int64)
    with np.errstate(invalid="ignore"):
        s_floor = np.where(m < 0, (sc.floor - oz[:, None]) * inv_m, np.inf)
    take(np.where(s_floor > S_MIN, s_floor, np.inf), zero, KIND_FLOOR)
    if sc.ceiling is not None:
        with np.errstate(invalid="ignore"):
            s_ceil = np.where(m > 0, (sc.ceiling - oz[:, None]) * inv_m, np.inf)
        take(np.where(s_ceil > S_MIN, s_ceil, np.inf), zero, KIND_CEILING)

    # range, material, normals
    norm = np.sqrt(1.0 + m * m)
    rng = best * norm
    miss = ~(rng <= max_range)
    rng[miss] = np.inf
    kind[miss] = KIND_NONE
    material = np.full((G, E), -1, dtype=np.int64)
    nxy = np.zeros((G, E, 2))
    cos_inc = np.zeros((G, E))
    hh = np.broadcast_to(h[:, None, :], (G, E, 2))

    sel = kind == KIND_SEGMENT
    if sel.any():
        i = prim[sel]
        e = sc.seg_b[i] - sc.seg_a[i]
        n = np.stack([-e[:, 1], e[:, 0]], axis=1) / np.linalg.norm(e, axis=1, keepdims=True)
        n *= np.where((n * hh[sel]).sum(1) > 0, -1.0, 1.0)[:, None]
        nxy[sel] = n
        material[sel] = sc.seg_mat[i]
    sel = kind == KIND_CYLINDER
    if sel.any():
        i = prim[sel]
        gi = np.nonzero(sel)[0]
        p = o[gi, :2] + best[sel][:, None] * h[gi]
        n = (p - sc.cyl_c[i]) / sc.cyl_r[i][:, None]
        nxy[sel] = n
        material[sel] = sc.cyl_mat[i]
    vert = (kind == KIND_SEGMENT) | (kind == KIND_CYLINDER)
    cos_inc[vert] = np.abs((nxy[vert] * hh[vert]).sum(1)) / norm[vert]
    horiz = (kind == KIND_RECT) | (kind == KIND_DISC) | (kind == KIND_FLOOR) | (kind == KIND_CEILING)
    cos_inc[horiz] = np.abs(m[horiz]) / norm[horiz]
    sel = kind == KIND_RECT
    material[sel] = sc.rect_mat[prim[sel]]
    sel = kind == KIND_DISC
    material[sel] = sc.disc_mat[prim[sel]]
    material[kind == KIND_FLOOR] = sc.floor_mat
    material[kind == KIND_CEILING] = sc.ceiling_mat
    return Hits(range=rng, kind=kind, material=material, cos_incidence=cos_inc, normal_xy=nxy)


def directions(headings: np.ndarray, slopes: np.ndarray) -> np.ndarray:
    """Unit 3D directions (G, E, 3) of a fan."""
    h = np.asarray(headings, dtype=np.float64)
    m = np.broadcast_to(np.asarray(slopes, dtype=np.float64), (len(h), np.shape(slopes)[-1]))
    d = np.concatenate([np.broadcast_to(h[:, None, :], (*m.shape, 2)), m[..., None]], axis=-1)
    return d / np.sqrt(1.0 + m * m)[..., None]
