"""Simulated worlds as data: ``data/worlds/<name>.toml`` (walls, boxes, pillars, floor, ceiling, trajectory).

A world file is parsed into pydantic models (every field described) and flattened into a :class:`Scene`
of numpy arrays that the vectorised ray caster (:mod:`simulator.raycast`) consumes. Geometry:

- ``walls``: polylines in the xy plane extruded between two heights (two-sided, zero thickness);
- ``boxes``: yawed boxes (four vertical faces plus the top and bottom faces);
- ``pillars``: vertical cylinders with a top cap;
- ``floor`` (always) and ``ceiling`` (optional: outdoors has none) as horizontal planes.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomllib
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from core.errors import UserError
from core.paths import data_dir
from simulator.trajectory import LoopPath, TrajectorySpec


class Material(BaseModel):
    """How a surface returns radar and lidar energy."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    radar_db: float = Field(0.0, description="radar reflectivity offset in dB added to the SNR of a return")
    specular: float = Field(0.5, ge=0.0, le=1.0, description="amplitude reflection coefficient of the surface as a "
                                                              "mirror for multipath (radar ghosts), 0..1")
    lidar_reflectivity: float = Field(0.5, gt=0.0, le=1.0, description="lidar diffuse reflectivity, 0..1")


DEFAULT_MATERIALS: dict[str, Material] = {
    "concrete": Material(radar_db=0.0, specular=0.6, lidar_reflectivity=0.45),
    "drywall": Material(radar_db=-3.0, specular=0.4, lidar_reflectivity=0.75),
    "metal": Material(radar_db=8.0, specular=1.0, lidar_reflectivity=0.35),
    "wood": Material(radar_db=-4.0, specular=0.3, lidar_reflectivity=0.55),
    "glass": Material(radar_db=-1.0, specular=0.9, lidar_reflectivity=0.15),
    "foliage": Material(radar_db=-8.0, specular=0.05, lidar_reflectivity=0.35),
    "brick": Material(radar_db=1.0, specular=0.5, lidar_reflectivity=0.4),
    "floor": Material(radar_db=-6.0, specular=0.2, lidar_reflectivity=0.3),
    "ceiling": Material(radar_db=-5.0, specular=0.2, lidar_reflectivity=0.8),
    "ground": Material(radar_db=-8.0, specular=0.1, lidar_reflectivity=0.25),
}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Wall(_Strict):
    points: list[tuple[float, float]] = Field(description="polyline vertices [[x, y], ...] in metres")
    closed: bool = Field(False, description="connect the last vertex back to the first")
    z: tuple[float, float] | None = Field(None, description="bottom and top height (default: floor to ceiling)")
    material: str = Field("drywall", description="a material name")

    @field_validator("points")
    @classmethod
    def _two_points(cls, v: list[tuple[float, float]]) -> list[tuple[float, float]]:
        if len(v) < 2:
            raise ValueError("a wall needs at least two points")
        return v


class Box(_Strict):
    center: tuple[float, float] = Field(description="centre [x, y] in metres")
    size: tuple[float, float] = Field(description="extent [sx, sy] along its own axes, metres")
    z: tuple[float, float] = Field((0.0, 1.0), description="bottom and top height, metres")
    yaw: float = Field(0.0, description="rotation about z in degrees")
    material: str = Field("wood", description="a material name")


class Pillar(_Strict):
    center: tuple[float, float] = Field(description="axis position [x, y] in metres")
    radius: float = Field(gt=0.0, description="radius in metres")
    z: tuple[float, float] | None = Field(None, description="bottom and top height (default: floor to ceiling)")
    material: str = Field("concrete", description="a material name")


class WorldSpec(_Strict):
    name: str = Field(description="world name")
    description: str = Field("", description="one line about the world")
    floor: float = Field(0.0, description="floor height, metres")
    ceiling: float | None = Field(None, description="ceiling height, metres (omit for outdoor worlds)")
    floor_material: str = Field("floor", description="material of the floor")
    ceiling_material: str = Field("ceiling", description="material of the ceiling")
    min_clearance: float = Field(0.35, ge=0.0, description="minimum distance from the path to any obstacle, metres")
    materials: dict[str, Material] = Field(default_factory=dict, description="extra or overriding materials")
    walls: list[Wall] = Field(default_factory=list, description="extruded polylines")
    boxes: list[Box] = Field(default_factory=list, description="yawed boxes")
    pillars: list[Pillar] = Field(default_factory=list, description="vertical cylinders")
    trajectory: TrajectorySpec = Field(description="the loop the rig follows")
    radar: dict[str, Any] = Field(default_factory=dict, description="overrides of simulator.params.RadarParams")
    lidar: dict[str, Any] = Field(default_factory=dict, description="overrides of simulator.params.LidarParams")
    imu: dict[str, Any] = Field(default_factory=dict, description="overrides of simulator.params.ImuParams")
    rig: dict[str, Any] = Field(default_factory=dict, description="a non-default rig: simulator.handheld.HandheldRig "
                                                                  "(empty: the ColoRadar rig of simulator.rig)")
    errors: dict[str, Any] = Field(default_factory=dict, description="simulator.sensor_errors.SensorErrors")

    @model_validator(mode="after")
    def _check(self) -> WorldSpec:
        known = set(DEFAULT_MATERIALS) | set(self.materials)
        used = [self.floor_material, self.ceiling_material] + [w.material for w in self.walls]
        used += [b.material for b in self.boxes] + [p.material for p in self.pillars]
        unknown = sorted(set(used) - known)
        if unknown:
            raise ValueError(f"unknown material(s) {unknown}; known: {sorted(known)}")
        if self.ceiling is not None and self.ceiling <= self.floor + 0.5:
            raise ValueError("ceiling must be at least 0.5 m above the floor")
        return self


# Primitive kinds, as stored in Hit.kind
KIND_NONE, KIND_SEGMENT, KIND_CYLINDER, KIND_RECT, KIND_DISC, KIND_FLOOR, KIND_CEILING = range(7)
VERTICAL_KINDS = (KIND_SEGMENT, KIND_CYLINDER)


@dataclass(frozen=True)
class Scene:
    """A world flattened into arrays for vectorised ray casting (all float64, metres)."""

    name: str
    seg_a: np.ndarray  # (S, 2) segment start
    seg_b: np.ndarray  # (S, 2) segment end
    seg_z: np.ndarray  # (S, 2) bottom, top
    seg_mat: np.ndarray  # (S,) material index
    cyl_c: np.ndarray  # (C, 2) axis
    cyl_r: np.ndarray  # (C,)
    cyl_z: np.ndarray  # (C, 2)
    cyl_mat: np.ndarray  # (C,)
    rect_c: np.ndarray  # (H, 2) centre of a horizontal rectangle (box top/bottom)
    rect_half: np.ndarray  # (H, 2) half extents along its axes
    rect_cs: np.ndarray  # (H, 2) cos(yaw), sin(yaw)
    rect_z: np.ndarray  # (H,) height
    rect_mat: np.ndarray  # (H,)
    disc_c: np.ndarray  # (D, 2) pillar caps
    disc_r: np.ndarray  # (D,)
    disc_z: np.ndarray  # (D,)
    disc_mat: np.ndarray  # (D,)
    floor: float
    ceiling: float | None
    floor_mat: int
    ceiling_mat: int
    material_names: tuple[str, ...]
    radar_db: np.ndarray  # (M,) per material
    specular: np.ndarray  # (M,)
    lidar_reflectivity: np.ndarray  # (M,)


@dataclass(frozen=True)
class World:
    spec: WorldSpec
    scene: Scene
    path: Path
    text: str  # the world file as read (copied into the simulation sidecar)


def worlds_dir() -> Path:
    return data_dir() / "worlds"


def available_worlds() -> list[str]:
    return sorted(p.stem for p in worlds_dir().glob("*.toml"))


def resolve_world_path(name_or_path: str | Path) -> Path:
    """``demo`` -> ``data/worlds/demo.toml``; a path to a ``.toml`` file is used as is."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise UserError(f"world file {p} does not exist")
        return p
    cand = worlds_dir() / f"{name_or_path}.toml"
    if not cand.is_file():
        import difflib  # not pipeline.config's did_you_mean: the simulator imports no orchestration module

        names = available_worlds()
        close = difflib.get_close_matches(str(name_or_path), names, n=1, cutoff=0.5)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        raise UserError(
            f"unknown world '{name_or_path}'{hint} "
            f"(available in {worlds_dir()}: {', '.join(names) or 'none'})"
        )
    return cand


def load_world(name_or_path: str | Path) -> World:
    """Parse and validate a world file; errors name the file and the offending field."""
    path = resolve_world_path(name_or_path)
    text = path.read_text()
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: invalid TOML ({exc}); fix the file") from exc
    try:
        spec = WorldSpec(**doc)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(x) for x in first["loc"]) or "(top level)"
        raise UserError(f"{path}: {loc}: {first['msg']} ({len(exc.errors())} problem(s) in all)") from None
    scene = build_scene(spec)
    clearance = path_clearance(spec, scene)
    if clearance < spec.min_clearance:
        raise UserError(
            f"{path}: the trajectory comes within {max(clearance, 0.0):.2f} m of an obstacle (min_clearance "
            f"{spec.min_clearance} m); move the waypoints or the obstacle"
        )
    return World(spec=spec, scene=scene, path=path, text=text)


def build_scene(spec: WorldSpec) -> Scene:
    """Flatten walls, boxes and pillars into primitive arrays."""
    mats = {**DEFAULT_MATERIALS, **spec.materials}
    names = tuple(sorted(mats))
    mid = {n: i for i, n in enumerate(names)}
    top = spec.ceiling if spec.ceiling is not None else spec.floor + 3.0

    seg_a: list[tuple[float, float]] = []
    seg_b: list[tuple[float, float]] = []
    seg_z: list[tuple[float, float]] = []
    seg_m: list[int] = []
    for w in spec.walls:
        pts = list(w.points) + ([w.points[0]] if w.closed else [])
        z = w.z if w.z is not None else (spec.floor, top)
        for a, b in itertools.pairwise(pts):
            if math.dist(a, b) > 1e-9:
                seg_a.append(a)
                seg_b.append(b)
                seg_z.append(z)
                seg_m.append(mid[w.material])

    rect_c, rect_half, rect_cs, rect_z, rect_m = [], [], [], [], []
    for box in spec.boxes:
        c, s = math.cos(math.radians(box.yaw)), math.sin(math.radians(box.yaw))
        hx, hy = box.size[0] / 2, box.size[1] / 2
        corners = [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)]
        world = [(box.center[0] + c * u - s * v, box.center[1] + s * u + c * v) for u, v in corners]
        for i in range(4):
            seg_a.append(world[i])
            seg_b.append(world[(i + 1) % 4])
            seg_z.append(box.z)
            seg_m.append(mid[box.material])
        for zf in box.z:
            if spec.floor + 1e-6 < zf and (spec.ceiling is None or zf < spec.ceiling - 1e-6):
                rect_c.append(box.center)
                rect_half.append((hx, hy))
                rect_cs.append((c, s))
                rect_z.append(zf)
                rect_m.append(mid[box.material])

    cyl_c, cyl_r, cyl_z, cyl_m = [], [], [], []
    disc_c, disc_r, disc_z, disc_m = [], [], [], []
    for pil in spec.pillars:
        z = pil.z if pil.z is not None else (spec.floor, top)
        cyl_c.append(pil.center)
        cyl_r.append(pil.radius)
        cyl_z.append(z)
        cyl_m.append(mid[pil.material])
        if spec.ceiling is None or z[1] < spec.ceiling - 1e-6:
            disc_c.append(pil.center)
            disc_r.append(pil.radius)
            disc_z.append(z[1])
            disc_m.append(mid[pil.material])

    def arr(x: list[Any], shape: tuple[int, ...]) -> np.ndarray:
        return np.asarray(x, dtype=np.float64).reshape(shape)

    def iarr(x: list[int]) -> np.ndarray:
        return np.asarray(x, dtype=np.int64).reshape(-1)

    return Scene(
        name=spec.name,
        seg_a=arr(seg_a, (-1, 2)), seg_b=arr(seg_b, (-1, 2)), seg_z=arr(seg_z, (-1, 2)), seg_mat=iarr(seg_m),
        cyl_c=arr(cyl_c, (-1, 2)), cyl_r=arr(cyl_r, (-1,)), cyl_z=arr(cyl_z, (-1, 2)), cyl_mat=iarr(cyl_m),
        rect_c=arr(rect_c, (-1, 2)), rect_half=arr(rect_half, (-1, 2)), rect_cs=arr(rect_cs, (-1, 2)),
        rect_z=arr(rect_z, (-1,)), rect_mat=iarr(rect_m),
        disc_c=arr(disc_c, (-1, 2)), disc_r=arr(disc_r, (-1,)), disc_z=arr(disc_z, (-1,)), disc_mat=iarr(disc_m),
        floor=spec.floor, ceiling=spec.ceiling,
        floor_mat=mid[spec.floor_material], ceiling_mat=mid[spec.ceiling_material],
        material_names=names,
        radar_db=np.array([mats[n].radar_db for n in names]),
        specular=np.array([mats[n].specular for n in names]),
        lidar_reflectivity=np.array([mats[n].lidar_reflectivity for n in names]),
    )


def distance_to_obstacles_2d(scene: Scene, pts: np.ndarray) -> np.ndarray:
    """Horizontal distance from points (N, 2) to the nearest wall segment or pillar surface."""
    out = np.full(len(pts), np.inf)
    if len(scene.seg_a):
        e = scene.seg_b - scene.seg_a  # (S, 2)
        w = pts[:, None, :] - scene.seg_a[None]  # (N, S, 2)
        u = np.clip((w * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-12), 0.0, 1.0)
        d = np.linalg.norm(w - u[..., None] * e, axis=-1)
        out = np.minimum(out, d.min(axis=1))
    if len(scene.cyl_c):
        d = np.linalg.norm(pts[:, None, :] - scene.cyl_c[None], axis=-1) - scene.cyl_r[None]
        out = np.minimum(out, d.min(axis=1))
    return out


def path_clearance(spec: WorldSpec, scene: Scene) -> float:
    """Smallest horizontal distance between the trajectory loop and any obstacle."""
    path = LoopPath(spec.trajectory)
    s = np.linspace(0.0, path.length, max(200, int(path.length / 0.05)), endpoint=False)
    return float(distance_to_obstacles_2d(scene, path.position(s)).min())
