"""Independent references for the simulator tests (no tests here): world geometry from the TOML file, readers.

Nothing here imports the simulator: distances to surfaces are computed from the world file with plain
numpy (closest points on rectangles and cylinders), the bag is read with rosbags' AnyReader and the
PointCloud2 layout is decoded from the message's own field list.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import numpy as np
import tomllib
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation

DT = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}


def cloud_array(msg: Any) -> np.ndarray:
    """PointCloud2 -> structured array built from the message's fields, offsets and point_step."""
    dt = np.dtype({"names": [f.name for f in msg.fields], "formats": [DT[f.datatype] for f in msg.fields],
                   "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_step})
    return np.frombuffer(bytes(msg.data), dtype=dt, count=msg.width * msg.height)


def stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def read_bag(path: Path) -> dict[str, list[tuple[int, Any, str]]]:
    """topic -> [(record time ns, message, msgtype)] for every message in the bag."""
    out: dict[str, list[tuple[int, Any, str]]] = {}
    with AnyReader([path]) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype), conn.msgtype))
    return out


def transforms(bag: dict[str, list[tuple[int, Any, str]]]) -> dict[tuple[str, str], np.ndarray]:
    """(parent, child) -> 4x4 from every /tf and /tf_static message."""
    out = {}
    for topic in ("/tf", "/tf_static"):
        for _, msg, _ in bag.get(topic, []):
            for tr in msg.transforms:
                T = np.eye(4)
                r = tr.transform.rotation
                T[:3, :3] = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
                T[:3, 3] = [tr.transform.translation.x, tr.transform.translation.y, tr.transform.translation.z]
                out[(tr.header.frame_id, tr.child_frame_id)] = T
    return out


class WorldGeometry:
    """Surfaces of a world file as vertical rectangles, horizontal rectangles, cylinders and discs."""

    def __init__(self, toml_text: str) -> None:
        w = tomllib.loads(toml_text)
        self.floor = float(w.get("floor", 0.0))
        self.ceiling = w.get("ceiling")
        top = self.ceiling if self.ceiling is not None else self.floor + 3.0
        vr: list[tuple[float, float, float, float, float, float]] = []  # x0 y0 x1 y1 z0 z1
        hr: list[tuple[float, float, float, float, float, float]] = []  # cx cy hx hy yaw z
        cyl: list[tuple[float, float, float, float, float]] = []  # cx cy r z0 z1
        for wall in w.get("walls", []):
            pts = [tuple(p) for p in wall["points"]]
            if wall.get("closed", False):
                pts.append(pts[0])
            z0, z1 = wall.get("z", (self.floor, top))
            for a, b in itertools.pairwise(pts):
                vr.append((a[0], a[1], b[0], b[1], z0, z1))
        for box in w.get("boxes", []):
            (cx, cy), (sx, sy) = box["center"], box["size"]
            z0, z1 = box.get("z", (0.0, 1.0))
            yaw = math.radians(box.get("yaw", 0.0))
            c, s = math.cos(yaw), math.sin(yaw)
            corners = [(cx + c * u - s * v, cy + s * u + c * v)
                       for u, v in ((-sx / 2, -sy / 2), (sx / 2, -sy / 2), (sx / 2, sy / 2), (-sx / 2, sy / 2))]
            for i in range(4):
                a, b = corners[i], corners[(i + 1) % 4]
                vr.append((a[0], a[1], b[0], b[1], z0, z1))
            for z in (z0, z1):
                hr.append((cx, cy, sx / 2, sy / 2, yaw, z))
        for p in w.get("pillars", []):
            z0, z1 = p.get("z", (self.floor, top))
            cyl.append((p["center"][0], p["center"][1], p["radius"], z0, z1))
        self.vr = np.array(vr, dtype=float).reshape(-1, 6)
        self.hr = np.array(hr, dtype=float).reshape(-1, 6)
        self.cyl = np.array(cyl, dtype=float).reshape(-1, 5)

    def distance(self, pts: np.ndarray) -> np.ndarray:
        """Distance from points (N, 3) to the nearest surface."""
        p = np.asarray(pts, dtype=float)
        d = np.abs(p[:, 2] - self.floor)
        if self.ceiling is not None:
            d = np.minimum(d, np.abs(p[:, 2] - self.ceiling))
        if len(self.vr):
            a, b = self.vr[:, 0:2], self.vr[:, 2:4]
            e = b - a
            w = p[:, None, :2] - a[None]
            u = np.clip((w * e).sum(-1) / (e * e).sum(-1), 0, 1)
            dxy = np.linalg.norm(w - u[..., None] * e, axis=-1)
            dz = np.maximum(0, np.maximum(self.vr[:, 4] - p[:, None, 2], p[:, None, 2] - self.vr[:, 5]))
            d = np.minimum(d, np.hypot(dxy, dz).min(1))
        if len(self.hr):
            c, s = np.cos(self.hr[:, 4]), np.sin(self.hr[:, 4])
            dx = p[:, None, 0] - self.hr[:, 0]
            dy = p[:, None, 1] - self.hr[:, 1]
            lx, ly = dx * c + dy * s, -dx * s + dy * c
            ox = np.maximum(0, np.abs(lx) - self.hr[:, 2])
            oy = np.maximum(0, np.abs(ly) - self.hr[:, 3])
            d = np.minimum(d, np.sqrt(ox**2 + oy**2 + (p[:, None, 2] - self.hr[:, 5]) ** 2).min(1))
        if len(self.cyl):
            rho = np.hypot(p[:, None, 0] - self.cyl[:, 0], p[:, None, 1] - self.cyl[:, 1])
            dz = np.maximum(0, np.maximum(self.cyl[:, 3] - p[:, None, 2], p[:, None, 2] - self.cyl[:, 4]))
            side = np.hypot(np.abs(rho - self.cyl[:, 2]), dz)
            cap = np.hypot(np.maximum(0, rho - self.cyl[:, 2]), p[:, None, 2] - self.cyl[:, 4])
            d = np.minimum(d, np.minimum(side, cap).min(1))
        return d

    def first_vertical_crossing(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Fraction along each segment a->b (N, 3) where it first crosses a vertical face or pillar (inf: none)."""
        out = np.full(len(a), np.inf)
        for x0, y0, x1, y1, z0, z1 in self.vr:
            e = np.array([x1 - x0, y1 - y0])
            d = b[:, :2] - a[:, :2]
            den = d[:, 0] * e[1] - d[:, 1] * e[0]
            w = np.array([x0, y0]) - a[:, :2]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (w[:, 0] * e[1] - w[:, 1] * e[0]) / den
                u = (w[:, 0] * d[:, 1] - w[:, 1] * d[:, 0]) / den
            z = a[:, 2] + t * (b[:, 2] - a[:, 2])
            ok = (np.abs(den) > 1e-12) & (t > 0) & (t < 1) & (u >= 0) & (u <= 1) & (z >= z0) & (z <= z1)
            out = np.where(ok, np.minimum(out, t), out)
        for cx, cy, r, z0, z1 in self.cyl:
            d = b[:, :2] - a[:, :2]
            f = a[:, :2] - np.array([cx, cy])
            qa, qb, qc = (d * d).sum(1), 2 * (f * d).sum(1), (f * f).sum(1) - r * r
            disc = qb * qb - 4 * qa * qc
            with np.errstate(invalid="ignore"):
                t = (-qb - np.sqrt(disc)) / (2 * qa)
            z = a[:, 2] + t * (b[:, 2] - a[:, 2])
            ok = (disc >= 0) & (t > 0) & (t < 1) & (z >= z0) & (z <= z1)
            out = np.where(ok, np.minimum(out, t), out)
        return out


_CACHE: dict[tuple[str, float, int, str], Path] = {}


def simulated(factory: Any, world: str = "hallway_loop", duration: float = 4.0, seed: int = 7,
              fmt: str = "bag") -> Path:
    """A simulated log made once per test run (shared by the simulator test modules)."""
    from simulator import simulate_to

    key = (world, duration, seed, fmt)
    if key not in _CACHE:
        name = Path(world).stem
        out = factory.mktemp(f"sim-{name}-{fmt}") / name
        _CACHE[key] = simulate_to(world, out, duration=duration, seed=seed, fmt=fmt)
    return _CACHE[key]
