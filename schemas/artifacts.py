"""The artifact schemas of the pipeline, each with a version.

A schema lists the *required* columns and their types; artifacts may carry more columns. Bump
``version`` when a required column changes meaning or type; readers refuse files written under another
version with a message that says how to rebuild them.
"""

from __future__ import annotations

from dataclasses import dataclass

import pyarrow as pa

F32 = pa.float32()
F64 = pa.float64()
I32 = pa.int32()
I64 = pa.int64()


@dataclass(frozen=True)
class ArtifactSchema:
    """One artifact: its file name, owning stage, version and required columns."""

    name: str
    stage: str
    filename: str
    version: int
    schema: pa.Schema
    description: str = ""

    @property
    def columns(self) -> list[str]:
        return list(self.schema.names)


def _s(*fields: tuple[str, pa.DataType]) -> pa.Schema:
    return pa.schema([pa.field(n, t, nullable=False) for n, t in fields])


_POINT_COLS = (("x", F32), ("y", F32), ("z", F32))
#: odometry.parquet's increment covariance columns and the (row, column) of the 3 x 3 (dx, dy, dyaw) they hold
ODOMETRY_COV_COLS = ("cov_xx", "cov_xy", "cov_xyaw", "cov_yy", "cov_yyaw", "cov_yawyaw")
ODOMETRY_COV_IDX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: map coordinates (voxel maps, patches, completed maps) are float64: published maps are compared on their
#: stored float64 values (the F-score at d = one voxel decides lattice-neighbour ties on them)
_MAP_COLS = (("x", F64), ("y", F64), ("z", F64))

ARTIFACTS: dict[str, ArtifactSchema] = {
    a.name: a
    for a in [
        ArtifactSchema(
            "radar", "ingest", "radar.parquet", 1,
            _s(("scan", I32), ("t_ns", I64), *_POINT_COLS, ("intensity", F32), ("doppler", F32)),
            "radar detections in the radar frame, one row per point, sorted by scan",
        ),
        ArtifactSchema(
            "imu", "ingest", "imu.parquet", 1,
            _s(("t_ns", I64), ("ax", F64), ("ay", F64), ("az", F64), ("gx", F64), ("gy", F64), ("gz", F64)),
            "IMU samples in the IMU frame (m/s^2, rad/s)",
        ),
        ArtifactSchema(
            "lidar", "ingest", "lidar.parquet", 1,
            _s(("scan", I32), ("t_ns", I64), *_POINT_COLS, ("intensity", F32)),
            "lidar points in the lidar frame, one row per point, sorted by scan",
        ),
        ArtifactSchema(
            "groundtruth", "ingest", "groundtruth.parquet", 1,
            _s(("t_ns", I64), ("x", F64), ("y", F64), ("z", F64),
               ("qx", F64), ("qy", F64), ("qz", F64), ("qw", F64)),
            "ground-truth poses world<-base",
        ),
        ArtifactSchema(
            "radar_filtered", "filter", "radar_filtered.parquet", 1,
            _s(("scan", I32), ("t_ns", I64), *_POINT_COLS, ("intensity", F32), ("doppler", F32)),
            "radar points kept by the multi-frame filter (radar frame)",
        ),
        ArtifactSchema(
            "ego_velocity", "filter", "ego_velocity.parquet", 1,
            _s(("scan", I32), ("t_ns", I64), ("vx", F64), ("vy", F64), ("vz", F64), ("n_inliers", I32)),
            "radar ego-velocity per scan in the radar frame",
        ),
        ArtifactSchema(
            "odometry", "odometry", "odometry.parquet", 3,
            _s(("scan", I32), ("t_ns", I64), ("x", F64), ("y", F64), ("z", F64), ("roll", F64), ("pitch", F64),
               ("yaw", F64), ("cov_xx", F64), ("cov_xy", F64), ("cov_xyaw", F64), ("cov_yy", F64),
               ("cov_yyaw", F64), ("cov_yawyaw", F64)),
            "odometry world<-base at radar scan times: x, y, yaw anchored in the plane; z, roll, pitch (Z-Y-X) "
            "as estimated (z shifted with the anchor); cov_*: covariance of the body-frame increment (dx, dy, "
            "dyaw) from the previous scan (0 on the first)",
        ),
        ArtifactSchema(
            "trajectory", "slam", "trajectory.parquet", 1,
            _s(("scan", I32), ("t_ns", I64), ("x", F64), ("y", F64), ("yaw", F64), ("n_eff", F64)),
            "best-particle trajectory world<-base (one file per method: trajectory[_<method>].parquet)",
        ),
        ArtifactSchema(
            "map_posterior", "slam", "map_posterior.parquet", 1,
            _s(("theta", pa.list_(F64)), ("cov", pa.list_(F64)),
               ("L1", F64), ("L2", F64), ("cx", F64), ("cy", F64), ("M", I32),
               ("lengthscale", F64), ("signal_variance", F64), ("noise_variance", F64)),
            "Hilbert-GP weight posterior of the best particle with its basis metadata",
        ),
        ArtifactSchema(
            "map_grid", "slam", "map_grid.parquet", 1,
            _s(("x", F64), ("y", F64), ("occupancy", F64), ("variance", F64)),
            "the map posterior queried on a regular grid",
        ),
        ArtifactSchema(
            "radar_map", "voxel", "radar_map.parquet", 2,
            _s(*_MAP_COLS, ("log_odds", F32)),
            "occupied voxel centres of the radar OctoMap-style map (world frame)",
        ),
        ArtifactSchema(
            "lidar_map", "voxel", "lidar_map.parquet", 2,
            _s(*_MAP_COLS, ("log_odds", F32)),
            "occupied voxel centres of the lidar map (world frame; for a map set: lidar_filtered)",
        ),
        ArtifactSchema(
            "map_poses", "voxel", "map_poses.parquet", 1,
            _s(*_MAP_COLS),
            "a map set's thinned poses (the authors' patch seeds come from them), world frame",
        ),
        ArtifactSchema(
            "map_trajectory", "voxel", "map_trajectory.parquet", 1,
            _s(*_MAP_COLS),
            "the trajectory a map was built along (positions): a map set's recorded one, or the radar's at the "
            "scans the radar map was built from, world frame",
        ),
        ArtifactSchema(
            "patches", "patches", "patches.parquet", 2,
            _s(("patch", I32), ("kind", pa.string()), *_MAP_COLS,
               ("seed_x", F64), ("seed_y", F64), ("seed_z", F64)),
            "FPS patches of the radar and lidar maps, world coordinates",
        ),
        ArtifactSchema(
            "completed_map", "complete", "completed_map.parquet", 2,
            _s(*_MAP_COLS),
            "the completed (lidar-like) map, world frame",
        ),
        ArtifactSchema(
            "metrics", "evaluate", "metrics.parquet", 1,
            _s(("seq", pa.string()), ("method", pa.string()), ("metric", pa.string()), ("value", F64)),
            "long table of evaluation metrics",
        ),
        ArtifactSchema(
            "paths", "plan", "paths.parquet", 1,
            _s(("strategy", pa.string()), ("k", I32), ("x", F64), ("y", F64)),
            "planned paths per strategy",
        ),
    ]
}


def artifact_for_file(filename: str) -> ArtifactSchema | None:
    """The schema whose file name matches (``trajectory_<method>.parquet`` maps to ``trajectory``)."""
    exact = [a for a in ARTIFACTS.values() if a.filename == filename]
    if exact:
        return exact[0]
    for art in ARTIFACTS.values():
        stem = art.filename.removesuffix(".parquet")
        if filename.startswith(stem + "_") and filename.endswith(".parquet"):
            return art
    return None
