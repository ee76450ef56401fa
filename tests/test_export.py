"""`pipeline export`: TUM trajectories, PLY maps and MCAP with Foxglove schemas, read back independently."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import UserError
from pipeline.export import export
from pipeline.store import RunStore
from schemas import write_artifact


@pytest.fixture
def store(tmp_path: Path) -> RunStore:
    st = RunStore(tmp_path, "s")
    rng = np.random.default_rng(0)
    n = 20
    t = np.arange(n, dtype=np.int64) * 100_000_000 + 1_600_000_000_000_000_000
    yaw = np.linspace(0, 1, n)
    for stage in ("ingest", "odometry", "voxel"):
        st.stage_dir(stage).mkdir(parents=True)
    write_artifact({"t_ns": t, "x": np.arange(n) * 1.0, "y": np.zeros(n), "z": np.zeros(n), "qx": np.zeros(n),
                    "qy": np.zeros(n), "qz": np.sin(yaw / 2), "qw": np.cos(yaw / 2)},
                   st.stage_dir("ingest") / "groundtruth.parquet", "groundtruth")
    write_artifact({"scan": np.arange(n, dtype=np.int32), "t_ns": t, "x": np.arange(n) * 1.0, "y": np.ones(n),
                    "yaw": yaw}, st.stage_dir("odometry") / "odometry.parquet", "odometry")
    pts = rng.normal(size=(50, 3)).astype(np.float32)
    write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "log_odds": np.ones(50)},
                   st.stage_dir("voxel") / "radar_map.parquet", "radar_map")
    return st


def test_tum(store: RunStore, tmp_path: Path) -> None:
    files = export(store, "tum", tmp_path / "out")
    assert sorted(f.name for f in files) == ["groundtruth.tum", "odometry.tum"]
    odo = np.loadtxt(tmp_path / "out" / "odometry.tum")
    assert odo.shape == (20, 8)
    np.testing.assert_allclose(odo[:, 0], 1_600_000_000 + np.arange(20) * 0.1, atol=1e-6)
    # yaw survives the quaternion: 2 atan2(qz, qw)
    np.testing.assert_allclose(2 * np.arctan2(odo[:, 6], odo[:, 7]), np.linspace(0, 1, 20), atol=1e-6)
    from evo.tools import file_interface

    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "out" / "groundtruth.tum"))
    assert traj.num_poses == 20


def test_ply(store: RunStore, tmp_path: Path) -> None:
    (path,) = export(store, "ply", tmp_path / "out")
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    assert b"element vertex 50" in header and b"property float log_odds" in header
    data = np.frombuffer(body, dtype=np.dtype([(n, "<f4") for n in ("x", "y", "z", "log_odds")]))
    assert len(data) == 50 and np.all(data["log_odds"] == 1)


def test_mcap_reads_back_with_protobuf_decoder(store: RunStore, tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    (path,) = export(store, "mcap", tmp_path / "out")
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics: dict[str, int] = {}
        schemas = set()
        for schema, channel, _msg, decoded in reader.iter_decoded_messages():
            topics[channel.topic] = topics.get(channel.topic, 0) + 1
            schemas.add(schema.name)
            if channel.topic == "/map/radar_map":
                assert decoded.point_stride == 12 and len(decoded.data) == 50 * 12
    assert topics == {"/trajectory/groundtruth": 20, "/trajectory/odometry": 20, "/map/radar_map": 1}
    assert schemas == {"foxglove.PoseInFrame", "foxglove.PointCloud"}


def test_nothing_to_export(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="no runs for sequence 'x'"):
        export(RunStore(tmp_path, "x"), "tum", tmp_path / "o")
    (tmp_path / "y").mkdir()
    with pytest.raises(UserError, match="nothing to export for 'y'"):
        export(RunStore(tmp_path, "y"), "ply", tmp_path / "o")
    with pytest.raises(UserError, match="--format obj: expected one of tum, ply, mcap"):
        export(RunStore(tmp_path, "y"), "obj", tmp_path / "o")
