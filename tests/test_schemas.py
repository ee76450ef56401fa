"""Artifact schemas: validation errors are clear, round trips keep types and metadata."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from schemas import ARTIFACTS, SchemaError, artifact_for_file, read_artifact, write_artifact


def radar_columns(n: int = 4) -> dict[str, np.ndarray]:
    return {
        "scan": np.zeros(n, np.int32), "t_ns": np.arange(n, dtype=np.int64),
        "x": np.ones(n), "y": np.ones(n), "z": np.ones(n), "intensity": np.ones(n), "doppler": np.ones(n),
    }


def test_round_trip_casts_and_keeps_extra_columns(tmp_path: Path) -> None:
    cols = radar_columns()
    cols["label"] = np.array([0, 1, 2, -1], np.int8)
    path = write_artifact(cols, tmp_path / "radar.parquet", "radar")
    t = read_artifact(path, "radar")
    assert t.schema.field("x").type == pa.float32()  # cast from float64 on write
    assert t.column_names[:7] == ["scan", "t_ns", "x", "y", "z", "intensity", "doppler"]
    assert t["label"].to_pylist() == [0, 1, 2, -1]
    assert not list(tmp_path.glob(".*tmp"))


def test_missing_column_is_named(tmp_path: Path) -> None:
    cols = radar_columns()
    del cols["doppler"]
    with pytest.raises(SchemaError, match=r"missing column 'doppler' required by schema 'radar' v1"):
        write_artifact(cols, tmp_path / "radar.parquet", "radar")


def test_wrong_type_version_and_name_are_refused(tmp_path: Path) -> None:
    # a file written by someone else with float64 doppler
    art = ARTIFACTS["radar"]
    table = pa.table({k: v for k, v in radar_columns().items()})
    table = table.cast(pa.schema([pa.field(n, art.schema.field(n).type if n != "doppler" else pa.float64())
                                  for n in table.column_names]))
    meta = {b"radar_pipeline.schema": b"radar", b"radar_pipeline.schema_version": b"1"}
    pq.write_table(table.replace_schema_metadata(meta), tmp_path / "a.parquet")
    with pytest.raises(SchemaError, match=r"a.parquet: column 'doppler' has type double, .* expects float"):
        read_artifact(tmp_path / "a.parquet", "radar")

    pq.write_table(pa.table(radar_columns()).replace_schema_metadata(
        {b"radar_pipeline.schema": b"radar", b"radar_pipeline.schema_version": b"0"}), tmp_path / "b.parquet")
    with pytest.raises(SchemaError, match=r"written with schema 'radar' v0, this version reads v1; rebuild it"):
        read_artifact(tmp_path / "b.parquet", "radar")

    write_artifact(radar_columns(), tmp_path / "c.parquet", "radar")
    with pytest.raises(SchemaError, match=r"holds schema 'radar', expected 'lidar'"):
        read_artifact(tmp_path / "c.parquet", "lidar")

    (tmp_path / "d.parquet").write_bytes(b"not parquet")
    with pytest.raises(SchemaError, match=r"d.parquet: not a readable Parquet file"):
        read_artifact(tmp_path / "d.parquet", "radar")
    with pytest.raises(SchemaError, match=r"artifact 'radar' not found; run `pipeline run ingest"):
        read_artifact(tmp_path / "missing.parquet", "radar")


def test_column_subset_read(tmp_path: Path) -> None:
    write_artifact(radar_columns(), tmp_path / "r.parquet", "radar")
    t = read_artifact(tmp_path / "r.parquet", "radar", columns=["scan", "x"])
    assert t.column_names == ["scan", "x"]


def test_every_design_artifact_has_a_schema() -> None:
    files = {a.filename for a in ARTIFACTS.values()}
    for name in ["radar.parquet", "imu.parquet", "lidar.parquet", "groundtruth.parquet", "radar_filtered.parquet",
                 "ego_velocity.parquet", "odometry.parquet", "trajectory.parquet", "map_posterior.parquet",
                 "map_grid.parquet", "radar_map.parquet", "lidar_map.parquet", "patches.parquet",
                 "completed_map.parquet", "metrics.parquet", "paths.parquet"]:
        assert name in files
    traj = artifact_for_file("trajectory_rich_slam.parquet")
    assert traj is not None and traj.name == "trajectory"
