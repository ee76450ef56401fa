"""Dataset profiles (``data/datasets/<name>.toml``): topics, field names, frames, default extrinsics."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import tomllib
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from core.errors import UserError
from core.geometry import F64, pose_matrix
from core.paths import data_dir

STREAMS = ("radar", "lidar", "imu", "groundtruth", "odometry")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Topics(_Model):
    radar: str = Field("", description="sensor_msgs/PointCloud2 radar detections ('' = detect)")
    lidar: str = Field("", description="sensor_msgs/PointCloud2 lidar ('' = detect)")
    imu: str = Field("", description="sensor_msgs/Imu ('' = detect)")
    groundtruth: str = Field("", description="nav_msgs/Odometry or geometry_msgs/PoseStamped, world<-base")
    odometry: str = Field("", description="optional nav_msgs/Odometry used as an odometry source")
    tf: list[str] = Field(default_factory=lambda: ["/tf_static", "/tf"], description="tf2_msgs/TFMessage topics")


class Frames(_Model):
    base: str = Field("", description="base (body) frame id; '' = the IMU frame")
    radar: str = Field("", description="radar frame id; '' = from the messages")
    lidar: str = Field("", description="lidar frame id; '' = from the messages")
    imu: str = Field("", description="IMU frame id; '' = from the messages")


class Extrinsic(_Model):
    translation: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0], description="metres")
    quaternion: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0, 1.0], description="x y z w")

    def matrix(self) -> F64:
        return pose_matrix(self.translation, self.quaternion)


class Extrinsics(_Model):
    fallback: bool = Field(False, description="values are dataset defaults for logs missing their tf "
                                              "(warned when used)")
    radar: Extrinsic = Field(default_factory=Extrinsic, description="base <- radar")
    lidar: Extrinsic = Field(default_factory=Extrinsic, description="base <- lidar")
    imu: Extrinsic = Field(default_factory=Extrinsic, description="base <- imu")


class RadarSettings(_Model):
    doppler_sign: float = Field(1.0, description="factor giving the convention doppler = -r.v")


class FolderLayout(_Model):
    """Extracted-folder form: paths relative to the run folder; ``{i}`` is the line index in the timestamps file."""

    radar_timestamps: str = "single_chip/pointclouds/timestamps.txt"
    radar_files: str = "single_chip/pointclouds/data/radar_pointcloud_{i}.bin"
    radar_columns: list[str] = Field(default_factory=lambda: ["x", "y", "z", "intensity", "doppler"])
    lidar_timestamps: str = "lidar/timestamps.txt"
    lidar_files: str = "lidar/pointclouds/lidar_pointcloud_{i}.bin"
    lidar_columns: list[str] = Field(default_factory=lambda: ["x", "y", "z", "intensity"])
    imu_timestamps: str = "imu/timestamps.txt"
    imu_data: str = "imu/imu_data.txt"
    groundtruth_timestamps: str = "groundtruth/timestamps.txt"
    groundtruth_data: str = "groundtruth/groundtruth_poses.txt"
    calib_radar: str = "calib/transforms/base_to_single_chip.txt"
    calib_lidar: str = "calib/transforms/base_to_lidar.txt"
    calib_imu: str = "calib/transforms/base_to_imu.txt"


def _xyz_fields() -> dict[str, list[str]]:
    return {"x": ["x"], "y": ["y"], "z": ["z"], "intensity": ["intensity"]}


class DatasetProfile(_Model):
    name: str
    description: str = ""
    required: list[str] = Field(default_factory=lambda: ["radar"])
    topics: Topics = Field(default_factory=Topics)
    frames: Frames = Field(default_factory=Frames)
    radar_fields: dict[str, list[str]] = Field(default_factory=_xyz_fields)
    lidar_fields: dict[str, list[str]] = Field(default_factory=_xyz_fields)
    radar: RadarSettings = Field(default_factory=RadarSettings)
    extrinsics: Extrinsics = Field(default_factory=Extrinsics)
    rates: dict[str, float] = Field(default_factory=dict)
    folder: FolderLayout = Field(default_factory=FolderLayout)
    #: where the profile was loaded from (for messages and the cache key)
    path: str = ""
    digest: str = ""


def profiles_dir() -> Path:
    return data_dir() / "datasets"


def available_profiles() -> list[str]:
    return sorted(p.stem for p in profiles_dir().glob("*.toml"))


def load_profile(name: str) -> DatasetProfile:
    """Load ``data/datasets/<name>.toml`` (or a path to a ``.toml``)."""
    path = Path(name) if name.endswith(".toml") else profiles_dir() / f"{name}.toml"
    if not path.exists():
        raise UserError(f"dataset profile '{name}' not found ({path}); known: {', '.join(available_profiles())}")
    raw = path.read_bytes()
    try:
        doc: dict[str, Any] = tomllib.loads(raw.decode())
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: invalid TOML ({exc})") from exc
    doc.setdefault("name", path.stem)
    try:
        return DatasetProfile(**doc, path=str(path), digest=hashlib.sha256(raw).hexdigest()[:16])
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        raise UserError(f"{path}: '{loc}': {err['msg']}") from exc
