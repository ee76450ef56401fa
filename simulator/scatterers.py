"""Persistent radar scatterers of a world: where a single-chip radar's detections come from.

A world's scatterers are drawn once from its geometry and the run's seed (``build_scatterers``), so the
same physical feature returns from the same place scan after scan:

- **line scatterers** (strong, view-dependent point): a straight edge returns from its stationary-phase
  point, the point of the line closest to the radar (a vertical edge at the radar's height); seen beyond
  an end the return comes from the tip, ``tip_loss_db`` weaker. Lines are the vertical edges at wall
  polyline vertices (a dihedral, ``dihedral_rcs_db``, from the concave side; an edge, ``edge_rcs_db``, from
  the convex side or at a free wall end), the vertical edges of boxes (convex), the junctions of walls and
  box faces with the floor and of walls with the ceiling (dihedrals) and pillars (a cylinder returns from
  the surface point facing the radar, ``pillar_rcs_db`` at 0.1 m radius, proportional to the radius);
- **corner scatterers**: trihedral room corners where a concave wall vertex meets the floor or ceiling
  (``trihedral_rcs_db``, only from the concave side);
- **surface scatterers** (weak): points drawn uniformly on walls, box faces, pillar caps, the floor and
  the ceiling at ``scatterer_density`` per m^2, each a patch of ``1 / density`` m^2 with backscatter
  ``surface_sigma0_db + material`` at normal incidence, falling as ``cos(incidence)**incidence_exponent``,
  and a Rayleigh (exponential power) factor drawn once, so some patches are bright.

Strong scatterers get their material's ``radar_db`` and a once-drawn log-normal spread
(``strong_rcs_spread_db``). The per-scan Swerling fluctuation, occlusion and detection are
:mod:`simulator.radar`'s.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from simulator.params import RadarParams
from simulator.world import DEFAULT_MATERIALS, WorldSpec

KIND_SURFACE, KIND_LINE, KIND_CORNER, KIND_PILLAR = 0, 1, 2, 3
EPS = 1e-6


@dataclass(frozen=True)
class Returns:
    """The scatterers' return points for one radar position (world frame)."""

    pos: np.ndarray  # (K, 3)
    rcs_db: np.ndarray  # (K,) RCS towards the radar, dBsm (incidence, wedge side and tip included)
    kind: np.ndarray  # (K,) int8 KIND_*
    specular: np.ndarray  # (K,) mirror reflectivity of the surface (surface scatterers; 0 otherwise)


@dataclass(frozen=True)
class Scatterers:
    """All persistent scatterers of a world (fixed points, lines, wedges), world frame, metres."""

    pt_pos: np.ndarray  # (N, 3) surface and corner points
    pt_normal: np.ndarray  # (N, 3) unit normal (surface points), zero for corners
    pt_rcs_db: np.ndarray  # (N,) dBsm at normal incidence (surfaces) or from the concave side (corners)
    pt_kind: np.ndarray  # (N,) int8
    pt_wedge: np.ndarray  # (N,) index of the wedge a corner needs to be seen from (-1: none)
    pt_specular: np.ndarray  # (N,) mirror reflectivity of a surface point's material (0 for corners)
    line_a: np.ndarray  # (L, 3) end points
    line_b: np.ndarray  # (L, 3)
    line_radius: np.ndarray  # (L,) pillars: the return comes from the surface facing the radar
    line_rcs_db: np.ndarray  # (L,) broadside RCS (concave side of its wedge, if any)
    line_convex_rcs_db: np.ndarray  # (L,) broadside RCS from the convex side of its wedge
    line_wedge: np.ndarray  # (L,) wedge index (-1: none)
    line_kind: np.ndarray  # (L,) int8
    wedge_v: np.ndarray  # (W, 2) apex of a wall vertex
    wedge_e1: np.ndarray  # (W, 2) unit directions along the two walls from the apex
    wedge_e2: np.ndarray  # (W, 2)
    incidence_exponent: float  # surface backscatter ~ cos(incidence)**exponent
    tip_loss_db: float  # a line seen beyond its end

    def __len__(self) -> int:
        return len(self.pt_pos) + len(self.line_a)

    def inside_wedge(self, origin: np.ndarray) -> np.ndarray:
        """(W,) whether ``origin`` lies inside each wedge's concave (< 180 degree) side."""
        q = origin[:2] - self.wedge_v
        e1, e2 = self.wedge_e1, self.wedge_e2
        c12 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        c1q = e1[:, 0] * q[:, 1] - e1[:, 1] * q[:, 0]
        cq2 = q[:, 0] * e2[:, 1] - q[:, 1] * e2[:, 0]
        return (c1q * c12 > 0) & (cq2 * c12 > 0)

    def returns(self, origin: np.ndarray, max_range: float) -> Returns:
        """Return points and their RCS towards a radar at ``origin`` within ``max_range`` (no occlusion test)."""
        inside = self.inside_wedge(origin) if len(self.wedge_v) else np.zeros(0, bool)
        # fixed points: surfaces (incidence) and corners (only from the concave side)
        d = self.pt_pos - origin
        r = np.linalg.norm(d, axis=1)
        near = np.nonzero((r < max_range) & (r > EPS))[0]
        d, r = d[near], r[near]
        kind = self.pt_kind[near]
        rcs = self.pt_rcs_db[near].copy()
        surf = kind == KIND_SURFACE
        cos_inc = np.abs((d[surf] * self.pt_normal[near][surf]).sum(1)) / r[surf]
        rcs[surf] += 10 * self.incidence_exponent * np.log10(np.maximum(cos_inc, 1e-6))
        wedge = self.pt_wedge[near]
        ok = (wedge < 0) | inside[np.maximum(wedge, 0)] if len(inside) else wedge < 0
        pos_p, rcs_p, kind_p, spec_p = self.pt_pos[near][ok], rcs[ok], kind[ok], self.pt_specular[near][ok]

        # lines: the stationary-phase point (closest point of the segment), tips weaker
        ab = self.line_b - self.line_a
        L2 = np.maximum((ab * ab).sum(1), EPS)
        t = ((origin - self.line_a) * ab).sum(1) / L2
        tip = (t < 0) | (t > 1)
        p = self.line_a + np.clip(t, 0, 1)[:, None] * ab
        pil = self.line_radius > 0
        if pil.any():
            h = origin[:2] - p[pil, :2]
            h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), EPS)
            p[pil, :2] += self.line_radius[pil, None] * h
        lw = self.line_wedge
        concave = (lw < 0) | (inside[np.maximum(lw, 0)] if len(inside) else False)
        lrcs = np.where(concave, self.line_rcs_db, self.line_convex_rcs_db) - self.tip_loss_db * tip
        rl = np.linalg.norm(p - origin, axis=1)
        keep = (rl < max_range) & (rl > EPS)
        return Returns(
            pos=np.concatenate([pos_p, p[keep]]),
            rcs_db=np.concatenate([rcs_p, lrcs[keep]]),
            kind=np.concatenate([kind_p, self.line_kind[keep]]).astype(np.int8),
            specular=np.concatenate([spec_p, np.zeros(int(keep.sum()))]),
        )


class _Builder:
    def __init__(self, spec: WorldSpec, p: RadarParams, rng: np.random.Generator) -> None:
        self.spec, self.p, self.rng = spec, p, rng
        mats = {**DEFAULT_MATERIALS, **spec.materials}
        self.db = {k: m.radar_db for k, m in mats.items()}
        self.spec_of = {k: m.specular for k, m in mats.items()}
        self.top = spec.ceiling if spec.ceiling is not None else spec.floor + 3.0
        self.pts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.lines: list[tuple[Any, ...]] = []
        self.wedges: list[tuple[tuple[float, float], np.ndarray, np.ndarray]] = []

    # -- helpers -----------------------------------------------------------------------------------------
    def strong(self, base_db: float, n: int = 1) -> np.ndarray:
        return base_db + self.rng.normal(0.0, self.p.strong_rcs_spread_db, n)

    def surface(self, pos: np.ndarray, normal: np.ndarray, material: str) -> None:
        """Surface scatterers at ``pos`` (n, 3) with ``normal`` (3,) or (n, 3)."""
        n = len(pos)
        if n == 0:
            return
        p = self.p
        area_db = -10 * math.log10(p.scatterer_density)
        rcs = (p.surface_sigma0_db + self.db[material] + area_db
               + 10 * np.log10(np.maximum(self.rng.exponential(1.0, n), 1e-12)))
        nrm = np.broadcast_to(np.asarray(normal, float), (n, 3))
        self.pts.append((pos, nrm, rcs, np.full(n, KIND_SURFACE, np.int8), np.full(n, -1, np.int64),
                         np.full(n, self.spec_of[material])))

    def count(self, area: float) -> int:
        return int(self.rng.poisson(self.p.scatterer_density * max(area, 0.0)))

    def rect_vertical(self, a: tuple[float, float], b: tuple[float, float], z: tuple[float, float],
                      material: str) -> None:
        a_, b_ = np.asarray(a, float), np.asarray(b, float)
        length = float(np.linalg.norm(b_ - a_))
        n = self.count(length * (z[1] - z[0]))
        u = self.rng.random(n)
        xy = a_ + u[:, None] * (b_ - a_)
        zz = self.rng.uniform(z[0], z[1], n)
        e = (b_ - a_) / max(length, EPS)
        self.surface(np.column_stack([xy, zz]), np.array([-e[1], e[0], 0.0]), material)

    def line(self, a: tuple[float, float, float], b: tuple[float, float, float], rcs_db: float, kind: int,
             convex_db: float | None = None, wedge: int = -1, radius: float = 0.0) -> None:
        r = float(self.strong(0.0)[0])
        self.lines.append((np.asarray(a, float), np.asarray(b, float), np.float64(radius), np.float64(rcs_db + r),
                           np.float64((rcs_db if convex_db is None else convex_db) + r), np.int64(wedge),
                           np.int8(kind)))

    def corner(self, pos: tuple[float, float, float], rcs_db: float, wedge: int) -> None:
        self.pts.append((np.asarray([pos], float), np.zeros((1, 3)), self.strong(rcs_db),
                         np.array([KIND_CORNER], np.int8), np.array([wedge], np.int64), np.zeros(1)))

    # -- world features ----------------------------------------------------------------------------------
    def walls(self) -> None:
        s, p = self.spec, self.p
        for w in s.walls:
            z = w.z if w.z is not None else (s.floor, self.top)
            on_floor = z[0] <= s.floor + 1e-6
            on_ceiling = s.ceiling is not None and z[1] >= s.ceiling - 1e-6
            mdb = self.db[w.material]
            pts: list[tuple[float, float]] = [(float(q[0]), float(q[1])) for q in w.points]
            if w.closed and math.dist(pts[0], pts[-1]) < 1e-9:
                pts = pts[:-1]
            segs = list(itertools.pairwise(pts + ([pts[0]] if w.closed else [])))
            for a, b in segs:
                if math.dist(a, b) < 1e-9:
                    continue
                self.rect_vertical(a, b, z, w.material)
                if on_floor:
                    self.line((a[0], a[1], z[0]), (b[0], b[1], z[0]), p.dihedral_rcs_db + mdb, KIND_LINE)
                if on_ceiling:
                    self.line((a[0], a[1], z[1]), (b[0], b[1], z[1]), p.dihedral_rcs_db + mdb, KIND_LINE)
            n = len(pts)
            for i in range(n):
                v = pts[i]
                prev = pts[i - 1] if (w.closed or i > 0) else None
                nxt = pts[(i + 1) % n] if (w.closed or i < n - 1) else None
                if prev is None or nxt is None:  # a free wall end: an edge
                    self.line((v[0], v[1], z[0]), (v[0], v[1], z[1]), p.edge_rcs_db + mdb, KIND_LINE)
                    continue
                e1 = np.subtract(prev, v, dtype=float)
                e2 = np.subtract(nxt, v, dtype=float)
                n1, n2 = np.linalg.norm(e1), np.linalg.norm(e2)
                if n1 < 1e-9 or n2 < 1e-9:
                    continue
                e1, e2 = e1 / n1, e2 / n2
                if abs(e1[0] * e2[1] - e1[1] * e2[0]) < 1e-3:  # straight continuation: no edge
                    continue
                k = len(self.wedges)
                self.wedges.append((v, e1, e2))
                self.line((v[0], v[1], z[0]), (v[0], v[1], z[1]), p.dihedral_rcs_db + mdb, KIND_LINE,
                          convex_db=p.edge_rcs_db + mdb, wedge=k)
                if on_floor:
                    self.corner((v[0], v[1], z[0]), p.trihedral_rcs_db + mdb, k)
                if on_ceiling:
                    self.corner((v[0], v[1], z[1]), p.trihedral_rcs_db + mdb, k)

    def boxes(self) -> None:
        s, p = self.spec, self.p
        for box in s.boxes:
            c, sn = math.cos(math.radians(box.yaw)), math.sin(math.radians(box.yaw))
            hx, hy = box.size[0] / 2, box.size[1] / 2
            corners = [(box.center[0] + c * u - sn * v, box.center[1] + sn * u + c * v)
                       for u, v in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]
            mdb = self.db[box.material]
            z0, z1 = box.z
            on_floor = z0 <= s.floor + 1e-6
            for i in range(4):
                a, b = corners[i], corners[(i + 1) % 4]
                self.rect_vertical(a, b, (z0, z1), box.material)
                self.line((a[0], a[1], z0), (a[0], a[1], z1), p.edge_rcs_db + mdb, KIND_LINE)
                if on_floor:
                    self.line((a[0], a[1], z0), (b[0], b[1], z0), p.dihedral_rcs_db + mdb, KIND_LINE)
            for zf, nz in ((z1, 1.0), (z0, -1.0)):
                if s.floor + 1e-6 < zf and (s.ceiling is None or zf < s.ceiling - 1e-6):
                    n = self.count(box.size[0] * box.size[1])
                    u = self.rng.uniform(-hx, hx, n)
                    v = self.rng.uniform(-hy, hy, n)
                    xy = np.column_stack([box.center[0] + c * u - sn * v, box.center[1] + sn * u + c * v])
                    self.surface(np.column_stack([xy, np.full(n, zf)]), np.array([0.0, 0.0, nz]), box.material)

    def pillars(self) -> None:
        s, p = self.spec, self.p
        for pil in s.pillars:
            z = pil.z if pil.z is not None else (s.floor, self.top)
            rcs = p.pillar_rcs_db + 10 * math.log10(pil.radius / 0.1) + self.db[pil.material]
            self.line((pil.center[0], pil.center[1], z[0]), (pil.center[0], pil.center[1], z[1]), rcs, KIND_PILLAR,
                      radius=pil.radius)
            if s.ceiling is None or z[1] < s.ceiling - 1e-6:
                n = self.count(math.pi * pil.radius**2)
                rr = pil.radius * np.sqrt(self.rng.random(n))
                th = self.rng.uniform(0, 2 * math.pi, n)
                xy = np.column_stack([pil.center[0] + rr * np.cos(th), pil.center[1] + rr * np.sin(th)])
                self.surface(np.column_stack([xy, np.full(n, z[1])]), np.array([0.0, 0.0, 1.0]), pil.material)

    def floor_ceiling(self) -> None:
        s = self.spec
        xy = [q for w in s.walls for q in w.points]
        if s.ceiling is None or not xy:  # open world: the ground around the path, to the radar's reach
            wp = np.asarray(s.trajectory.waypoints, float)
            lo, hi = wp.min(0) - self.p.max_range, wp.max(0) + self.p.max_range
        else:
            arr = np.asarray(xy, float)
            lo, hi = arr.min(0), arr.max(0)
        area = float(np.prod(hi - lo))
        planes = [(s.floor, 1.0, s.floor_material)]
        if s.ceiling is not None:
            planes.append((s.ceiling, -1.0, s.ceiling_material))
        for z, nz, mat in planes:
            n = self.count(area)
            pos = np.column_stack([self.rng.uniform(lo[0], hi[0], n), self.rng.uniform(lo[1], hi[1], n),
                                   np.full(n, z)])
            self.surface(pos, np.array([0.0, 0.0, nz]), mat)

    def build(self) -> Scatterers:
        self.walls()
        self.boxes()
        self.pillars()
        self.floor_ceiling()
        if self.pts:
            pos, nrm, rcs, kind, wedge, spec = (np.concatenate([np.asarray(x[i]) for x in self.pts]) for i in range(6))
        else:
            pos, nrm, rcs, kind, wedge, spec = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int8),
                                                np.zeros(0, np.int64), np.zeros(0))
        cols: list[Any] = list(zip(*self.lines, strict=True)) if self.lines else [[] for _ in range(7)]
        out = Scatterers(
            pt_pos=pos, pt_normal=np.ascontiguousarray(nrm), pt_rcs_db=rcs, pt_kind=kind.astype(np.int8),
            pt_wedge=wedge.astype(np.int64), pt_specular=spec.astype(float),
            line_a=np.asarray(cols[0], float).reshape(-1, 3), line_b=np.asarray(cols[1], float).reshape(-1, 3),
            line_radius=np.asarray(cols[2], float), line_rcs_db=np.asarray(cols[3], float),
            line_convex_rcs_db=np.asarray(cols[4], float), line_wedge=np.asarray(cols[5], np.int64),
            line_kind=np.asarray(cols[6], np.int8),
            wedge_v=np.asarray([w[0] for w in self.wedges], float).reshape(-1, 2),
            wedge_e1=np.asarray([w[1] for w in self.wedges], float).reshape(-1, 2),
            wedge_e2=np.asarray([w[2] for w in self.wedges], float).reshape(-1, 2),
            incidence_exponent=self.p.incidence_exponent, tip_loss_db=self.p.tip_loss_db,
        )
        return out


def build_scatterers(spec: WorldSpec, p: RadarParams, rng: np.random.Generator) -> Scatterers:
    """The world's persistent scatterers (deterministic for a given ``rng`` state)."""
    return _Builder(spec, p, rng).build()
