"""ColoRadar twins: a real scene's voxel map and recorded path as a simulator world.

:func:`twin_world` takes a scene's occupied voxel centres (the lidar map, ``lidar`` where the scene has it,
else ``lidar_filtered``) and its recorded trajectory (positions only) and returns a :class:`TwinWorld`:
the radar, lidar and ground truth of :class:`simulator.simulate.Simulation` then run in the voxel map
(:mod:`simulator.voxel_world`, :mod:`simulator.voxel_scatterers`) along the recorded path
(:mod:`simulator.path_trajectory`) with the ColoRadar rig and sensor models.

Before the grid is built, every map voxel within ``carve_radius`` of the recorded path is removed: the
real lidar maps hold a trail of voxels along the path itself (the person carrying the rig, seen by the
lidar; e.g. 63 of 83 316 voxels of aspen_run0 and 6 130 of 325 968 of edgar_classroom_run3 within
0.45 m), where the rig demonstrably passed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomllib
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from core.errors import UserError
from core.paths import data_dir
from simulator.params import ImuParams, RadarParams, make_params
from simulator.path_trajectory import PathParams, PathTrajectory
from simulator.sensor_errors import SensorErrors
from simulator.trajectory import TrajectorySpec
from simulator.voxel_scatterers import VoxelScatterers, VoxelScatterParams, build_voxel_scatterers
from simulator.voxel_world import VoxelGrid, grid_from_points, voxel_scene
from simulator.world import World, WorldSpec

#: run lengths of RICH-SLAM Table III's ColoRadar sequences 1-6 (seconds, the paper's durations); a twin's
#: recorded samples are spread uniformly over them
PAPER_DURATIONS_S: dict[str, float] = {
    "aspen_run0": 86.0,
    "outdoors_run0": 109.0,
    "edgar_classroom_run0": 187.0,
    "ec_hallways_run0": 100.0,
    "arpg_lab_run0": 119.0,
    "edgar_classroom_run3": 275.0,
}
#: The ColoRadar rig's sensor errors beyond white noise and bias random walk (simulator.sensor_errors), the
#: same datasheet-class values as the drifting twins' ``[errors]`` tables (data/worlds/*_drift.toml): the
#: ColoRadar IMU is a 3DM-GX5 class MEMS unit (simulator.params.ImuParams' defaults), its in-run bias
#: stability 8 deg/h; the TI radar's frames are stamped on arrival (~30 ms late) and its extrinsic is known
#: to about 1 deg and 2 cm per axis. Chosen from the datasheets before any twin ran; not tuned on results.
COLORADAR_ERRORS: dict[str, float] = {
    "gyro_scale_sigma": 2.0e-3,
    "accel_scale_sigma": 3.0e-3,
    "misalignment_sigma_rad": 1.0e-3,
    "gyro_bias_instability": 3.9e-5,
    "gyro_bias_tau_s": 100.0,
    "accel_bias_instability": 4.0e-4,
    "accel_bias_tau_s": 100.0,
    "radar_time_offset_s": 0.03,
    "radar_mount_sigma_deg": 1.0,
    "radar_mount_offset_sigma_m": 0.02,
}

#: RadarParams overrides of the twins (the AWR1843 defaults of simulator.params otherwise), picked by
#: experiments/twins_tune_radar.py on three of RMap's *train* scenes (aspen_run9, arpg_lab_run2,
#: ec_hallways_run4; never on the twins' own scenes): the trial of 13 with the smallest mean
#: |log L/R ratio| + |log CD-l2 ratio| against the real radar maps (README "ColoRadar twins",
#: docs/twins_radar_trials.csv)
TWIN_RADAR: dict[str, float] = {"clutter_rate": 50.0, "max_points": 100}

#: sample rate assumed for a scene without a known duration (the ground truth's ~15 Hz)
DEFAULT_RATE_HZ = 15.0


class TwinParams(BaseModel):
    """How a scene's maps become a twin world."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    resolution: float = Field(0.15, gt=0, description="voxel edge of the map, metres (RMap's maps: 0.15)")
    carve_radius: float = Field(0.45, ge=0, description="map voxels this close to the recorded path are removed, m")
    path: PathParams = Field(default_factory=PathParams, description="trajectory smoothing")
    scatter: VoxelScatterParams = Field(default_factory=VoxelScatterParams, description="radar scatterers")
    radar: dict[str, float] = Field(default_factory=lambda: dict(TWIN_RADAR),
                                    description="simulator.params.RadarParams overrides of the twin's radar")
    errors: dict[str, Any] = Field(default_factory=lambda: dict(COLORADAR_ERRORS),
                                   description="simulator.sensor_errors.SensorErrors of the rig ({} for none)")
    imu: dict[str, float] = Field(default_factory=dict, description="simulator.params.ImuParams overrides of the "
                                                                    "rig's IMU ({}: the 3DM-GX5 defaults)")


def twins_dir() -> Path:
    """``data/twins/``: twin variants (``drift.toml``: the drifting twins' sensor model)."""
    return data_dir() / "twins"


def variant_file(variant: str) -> Path:
    """The file of a twin variant; a one-line error naming it and the known ones when it does not exist."""
    f = twins_dir() / f"{variant}.toml"
    if not f.is_file():
        known = ", ".join(sorted(p.stem for p in twins_dir().glob("*.toml"))) or "none"
        raise UserError(f"twin variant '{variant}': {f} does not exist (known: {known})")
    return f


def variant_params(variant: str | None) -> TwinParams:
    """The :class:`TwinParams` of a twin variant (``data/twins/<variant>.toml``), the defaults for None.

    The file's ``[imu]`` and ``[errors]`` replace the twin defaults (3DM-GX5, :data:`COLORADAR_ERRORS`);
    its ``[radar]`` is laid over :data:`TWIN_RADAR`. Other tables or keys are a one-line error."""
    if variant is None:
        return TwinParams()
    f = variant_file(variant)
    try:
        doc = tomllib.loads(f.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{f}: invalid TOML ({exc})") from None
    unknown = sorted(set(doc) - {"imu", "errors", "radar"})
    if unknown:
        raise UserError(f"{f}: unknown table(s) {unknown}; a twin variant has [imu], [errors] and [radar]")
    make_params(ImuParams, doc.get("imu", {}), f"{f} [imu]")  # checked here: names the file and the key
    make_params(SensorErrors, doc.get("errors", {}), f"{f} [errors]")
    radar = dict(TWIN_RADAR) | doc.get("radar", {})
    make_params(RadarParams, radar, f"{f} [radar]")
    return TwinParams(radar=radar, errors=dict(doc.get("errors", {})), imu=dict(doc.get("imu", {})))


@dataclass(frozen=True)
class TwinWorld(World):
    """A :class:`~simulator.world.World` whose geometry is a voxel grid and whose motion is a recorded path."""

    grid: VoxelGrid
    trajectory: PathTrajectory
    params: TwinParams
    duration: float  # the log's full length (the path's time scale), seconds

    def scatterers(self, p: RadarParams, rng: np.random.Generator) -> VoxelScatterers:
        return build_voxel_scatterers(self.grid, p, self.params.scatter, rng)


def scene_duration(scene: str, n_samples: int) -> float:
    """The paper's duration of ``scene``, or the samples at :data:`DEFAULT_RATE_HZ`."""
    return PAPER_DURATIONS_S.get(scene, (n_samples - 1) / DEFAULT_RATE_HZ)


def carve_path(points: np.ndarray, path: np.ndarray, radius: float) -> np.ndarray:
    """``points`` without those within ``radius`` of any ``path`` sample (boolean mask of the kept ones)."""
    if radius <= 0 or not len(points):
        return np.ones(len(points), bool)
    d, _ = cKDTree(path).query(points, distance_upper_bound=radius)
    return np.asarray(~np.isfinite(d) | (d >= radius))


def twin_world(scene: str, map_points: np.ndarray, path: np.ndarray, map_file: Path | str = "",
               duration: float | None = None, params: TwinParams | None = None) -> TwinWorld:
    """The twin world of ``scene`` from its occupied voxel centres (N, 3) and recorded path (M, 3)."""
    p = params or TwinParams()
    path = np.asarray(path, np.float64)
    pts = np.asarray(map_points, np.float64)
    keep = carve_path(pts, path, p.carve_radius)
    grid = grid_from_points(pts[keep], p.resolution)
    d = float(duration) if duration is not None else scene_duration(scene, len(path))
    traj = PathTrajectory(path, d, p.path)
    sc = voxel_scene(f"{scene}_twin", grid)
    wp = [(float(x), float(y)) for x, y in path[[0, len(path) // 3, 2 * len(path) // 3], :2]]
    spec = WorldSpec(name=f"{scene}_twin", description=f"ColoRadar twin of {scene} (voxel map, recorded path)",
                     floor=sc.floor, ceiling=None, min_clearance=0.0,
                     # the loop is not used: the twin follows `traj`
                     trajectory=TrajectorySpec(waypoints=wp), radar=dict(p.radar), errors=dict(p.errors),
                     imu=dict(p.imu))
    # the world text of a twin without IMU overrides stays as it was before ``imu`` existed (byte-identical logs)
    dumped = p.model_dump_json(exclude={"imu"} if not p.imu else None)
    text = "# ColoRadar twin (simulator.twin): not a world file; what it was made from\n" + "".join(
        f"{k} = {json.dumps(v)}\n" for k, v in {
            "scene": scene, "map_file": str(map_file), "map_voxels": len(pts), "carved_voxels": int((~keep).sum()),
            "path_samples": len(path), "duration_s": d, "params": dumped,
        }.items())
    return TwinWorld(spec=spec, scene=sc, path=Path(str(map_file) or scene), text=text, grid=grid, trajectory=traj,
                     params=p, duration=d)
