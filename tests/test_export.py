"""`pipeline export`: TUM trajectories, PLY maps and MCAP with Foxglove schemas, read back independently."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.errors import UserError
from pipeline.export import export
from pipeline.store import RunStore
from schemas import write_artifact
from stages.odometry.stage import cov_columns

T0 = 1_600_000_000_000_000_000
N = 20
#: ground truth at 50 Hz starting 7 ms after the first scan: no scan stamp is a ground-truth stamp
GT_T = T0 + 7_000_000 + np.arange(110, dtype=np.int64) * 20_000_000
SCAN_T = T0 + np.arange(N, dtype=np.int64) * 100_000_000 + 10_000_000


def gt_pose(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z, yaw of an analytic ground truth: linear in time, so linear interpolation is exact."""
    s = (t_ns - T0) / 1e9
    return 2.0 * s, -s, 1.1 + 0.1 * s, 0.5 * s


def write_run(root: Path, gt: bool = True, odo_z: bool = False, slam: bool = False) -> RunStore:
    st = RunStore(root, "s")
    for stage in ("ingest", "odometry", "voxel", "slam"):
        st.stage_dir(stage).mkdir(parents=True)
    x, y, z, yaw = gt_pose(GT_T)
    half = yaw / 2
    rows = {"t_ns": GT_T, "x": x, "y": y, "z": z, "qx": 0 * x, "qy": 0 * x, "qz": np.sin(half), "qw": np.cos(half)}
    if not gt:
        rows = {k: v[:0] for k, v in rows.items()}
    write_artifact(rows, st.stage_dir("ingest") / "groundtruth.parquet", "groundtruth")
    odo = {"scan": np.arange(N, dtype=np.int32), "t_ns": SCAN_T, "x": np.arange(N) * 1.0, "y": np.ones(N),
           "yaw": np.linspace(0, 1, N), "z": np.zeros(N), "roll": np.zeros(N), "pitch": np.zeros(N),
           **cov_columns(N)}
    if odo_z:  # an odometry that estimated height and attitude
        odo["z"] = 1.0 + 0.01 * np.arange(N)
        odo["roll"], odo["pitch"] = np.full(N, 0.05), np.full(N, -0.03)
    write_artifact(odo, st.stage_dir("odometry") / "odometry.parquet", "odometry")
    if slam:  # as the slam stage writes them: every method, the odometry replayed, trajectory.parquet = main's
        for name, dx in (("odometry", 0.0), ("rich_slam", 0.5), ("fastslam_grid", 0.25)):
            rows = {**odo, "x": odo["x"] + dx, "n_eff": np.ones(N)}
            rows.pop("z", None)
            write_artifact(rows, st.stage_dir("slam") / f"trajectory_{name}.parquet", "trajectory")
            if name == "rich_slam":
                write_artifact(rows, st.stage_dir("slam") / "trajectory.parquet", "trajectory")
    pts = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "log_odds": np.ones(50)},
                   st.stage_dir("voxel") / "radar_map.parquet", "radar_map")
    return st


def run_export(store: RunStore, fmt: str, out: Path, **kw: str) -> tuple[list[Path], list[str]]:
    notes: list[str] = []
    return export(store, fmt, out, notes.append, **kw), notes


def test_tum_groundtruth_at_the_estimate_stamps(tmp_path: Path) -> None:
    files, notes = run_export(write_run(tmp_path), "tum", tmp_path / "out")
    assert sorted(f.name for f in files) == ["groundtruth.tum", "odometry.tum"]
    odo = np.loadtxt(tmp_path / "out" / "odometry.tum")
    gt = np.loadtxt(tmp_path / "out" / "groundtruth.tum")
    assert odo.shape == (N, 8) and gt.shape == (N, 8)
    np.testing.assert_allclose(odo[:, 0], (SCAN_T - T0) / 1e9 + T0 / 1e9, atol=1e-6)
    # the stamps are written from the integers: identical text, so evo pairs them exactly
    lines = [ln.split()[0] for ln in (tmp_path / "out" / "odometry.tum").read_text().splitlines()]
    assert lines == [ln.split()[0] for ln in (tmp_path / "out" / "groundtruth.tum").read_text().splitlines()]
    assert lines[1] == "1600000000.110000000"
    x, y, z, yaw = gt_pose(SCAN_T)
    np.testing.assert_allclose(gt[:, 1:4], np.column_stack([x, y, z]), atol=1e-9)
    np.testing.assert_allclose(2 * np.arctan2(gt[:, 6], gt[:, 7]), yaw, atol=1e-9)
    # yaw survives the quaternion: 2 atan2(qz, qw)
    np.testing.assert_allclose(2 * np.arctan2(odo[:, 6], odo[:, 7]), np.linspace(0, 1, N), atol=1e-6)
    assert any("interpolated at the 20 estimate stamps" in n for n in notes)
    # evo's own reader and association with its default 10 ms limit: every estimate finds its reference
    from evo.core import sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "out" / "groundtruth.tum"))
    est = file_interface.read_tum_trajectory_file(str(tmp_path / "out" / "odometry.tum"))
    ref, est = sync.associate_trajectories(ref, est)
    assert est.num_poses == N and np.array_equal(ref.timestamps, est.timestamps)


def test_tum_groundtruth_at_its_own_stamps_on_request(tmp_path: Path) -> None:
    files, _ = run_export(write_run(tmp_path), "tum", tmp_path / "out", groundtruth_stamps="own")
    gt = np.loadtxt(tmp_path / "out" / "groundtruth.tum")
    assert len(gt) == len(GT_T) and files[0].name == "groundtruth.tum"
    with pytest.raises(UserError, match="--groundtruth-stamps nearest: expected estimates or own"):
        export(write_run(tmp_path / "b"), "tum", tmp_path / "o", groundtruth_stamps="nearest")


def test_each_trajectory_written_once(tmp_path: Path) -> None:
    store = write_run(tmp_path, slam=True)
    files, _ = run_export(store, "tum", tmp_path / "out")
    # trajectory_odometry.parquet replays the odometry; trajectory.parquet copies trajectory_rich_slam.parquet
    assert [f.name for f in files] == ["groundtruth.tum", "odometry.tum", "fastslam_grid.tum", "rich_slam.tum"]
    np.testing.assert_allclose(np.loadtxt(tmp_path / "out" / "rich_slam.tum")[:, 1], np.arange(N) + 0.5)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "out" / "odometry.tum")[:, 1], np.arange(N) * 1.0)
    (tmp_path / "out" / "slam.tum").write_text("")  # as an older export wrote it
    _, notes = run_export(store, "tum", tmp_path / "out")
    assert any("also holds slam.tum from an earlier export" in n for n in notes)


def test_slam_poses_take_the_odometrys_z_roll_and_pitch(tmp_path: Path) -> None:
    """A slam method estimates x, y, yaw; the exported 3D pose takes z, roll, pitch of its odometry."""
    from scipy.spatial.transform import Rotation

    _, notes = run_export(write_run(tmp_path / "a", odo_z=True, slam=True), "tum", tmp_path / "a" / "out")
    z = 1.0 + 0.01 * np.arange(N)
    odo = np.loadtxt(tmp_path / "a" / "out" / "odometry.tum")
    slam = np.loadtxt(tmp_path / "a" / "out" / "rich_slam.tum")
    np.testing.assert_allclose(odo[:, 3], z)
    np.testing.assert_allclose(slam[:, 3], z)  # the odometry's z
    ypr = Rotation.from_quat(slam[:, 4:8]).as_euler("ZYX")
    np.testing.assert_allclose(ypr[:, 0], np.linspace(0, 1, N), atol=1e-7)  # the slam method's own yaw
    np.testing.assert_allclose(ypr[:, 1], -0.03, atol=1e-7)  # the odometry's pitch
    np.testing.assert_allclose(ypr[:, 2], 0.05, atol=1e-7)  # and roll
    assert not any("without z" in n for n in notes)


def test_an_estimate_without_odometry_is_planar_and_said(tmp_path: Path) -> None:
    store = write_run(tmp_path / "b", slam=True)
    (store.stage_dir("odometry") / "odometry.parquet").unlink()
    _, notes = run_export(store, "tum", tmp_path / "b" / "out")
    assert np.all(np.loadtxt(tmp_path / "b" / "out" / "rich_slam.tum")[:, 3] == 0)
    (planar,) = [n for n in notes if "without z" in n]
    assert planar.startswith("fastslam_grid, odometry, rich_slam: planar estimates")  # odometry: the slam replay
    assert "ground truth averages z = 1.21 m" in planar
    assert "--project_to_plane xy" in planar


def test_no_ground_truth_writes_no_groundtruth_file(tmp_path: Path) -> None:
    files, notes = run_export(write_run(tmp_path, gt=False), "tum", tmp_path / "out")
    assert [f.name for f in files] == ["odometry.tum"]
    assert not (tmp_path / "out" / "groundtruth.tum").exists()
    assert any(n.startswith("no ground truth in ") and "groundtruth.tum not written" in n for n in notes)
    assert not any("without z" in n for n in notes)  # the odometry is a 3D estimate


def test_invalid_poses_and_uncovered_stamps_are_left_out_and_said(tmp_path: Path) -> None:
    store = write_run(tmp_path)
    odo = {"scan": np.arange(N + 1, dtype=np.int32), "t_ns": np.r_[SCAN_T, GT_T[-1] + 3_000_000_000],
           "x": np.r_[np.arange(N) * 1.0, 0.0], "y": np.ones(N + 1), "yaw": np.zeros(N + 1),
           "z": np.zeros(N + 1), "roll": np.zeros(N + 1), "pitch": np.zeros(N + 1), **cov_columns(N + 1),
           "valid": np.r_[np.ones(N, bool), True]}
    odo["valid"][3] = False
    odo["x"][4] = np.nan
    write_artifact(odo, store.stage_dir("odometry") / "odometry.parquet", "odometry")
    _, notes = run_export(store, "tum", tmp_path / "out")
    assert len(np.loadtxt(tmp_path / "out" / "odometry.tum")) == N - 1
    assert len(np.loadtxt(tmp_path / "out" / "groundtruth.tum")) == N - 2  # the last stamp is after the end
    assert any("2 of 21 poses are not valid estimates" in n for n in notes)
    assert any("1 of 19 poses have no ground truth around them" in n for n in notes)


def test_ply(tmp_path: Path) -> None:
    (path,) = export(write_run(tmp_path), "ply", tmp_path / "out")
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    assert b"element vertex 50" in header and b"property float log_odds" in header
    data = np.frombuffer(body, dtype=np.dtype([(n, "<f4") for n in ("x", "y", "z", "log_odds")]))
    assert len(data) == 50 and np.all(data["log_odds"] == 1)
    assert not list((tmp_path / "out").glob(".*.tmp"))


def test_mcap_reads_back_once_per_stamp_in_time_order(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    (path,) = export(write_run(tmp_path, slam=True), "mcap", tmp_path / "out")
    stamps: dict[str, list[int]] = {}
    log_times = []
    schemas = set()
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, msg, decoded in reader.iter_decoded_messages(log_time_order=False):
            stamps.setdefault(channel.topic, []).append(msg.log_time)
            log_times.append(msg.log_time)
            schemas.add(schema.name)
            if channel.topic == "/map/radar_map":
                assert decoded.point_stride == 12 and len(decoded.data) == 50 * 12
            if channel.topic == "/trajectory/rich_slam" and msg.log_time == SCAN_T[2]:
                assert decoded.pose.position.x == pytest.approx(2.5)
    assert {k: len(v) for k, v in stamps.items()} == {
        "/trajectory/groundtruth": len(GT_T), "/trajectory/odometry": N, "/trajectory/rich_slam": N,
        "/trajectory/fastslam_grid": N, "/map/radar_map": 1}
    assert stamps["/trajectory/odometry"] == SCAN_T.tolist()  # once each, in order
    assert log_times == sorted(log_times)  # the file itself is in log-time order
    assert schemas == {"foxglove.PoseInFrame", "foxglove.PointCloud"}


def test_nothing_to_export(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="no runs for sequence 'x'"):
        export(RunStore(tmp_path, "x"), "tum", tmp_path / "o")
    (tmp_path / "y").mkdir()
    with pytest.raises(UserError, match="nothing to export for 'y'"):
        export(RunStore(tmp_path, "y"), "ply", tmp_path / "o")
    with pytest.raises(UserError, match="--format obj: expected one of tum, ply, mcap"):
        export(RunStore(tmp_path, "y"), "obj", tmp_path / "o")
    (tmp_path / "afile").write_text("")
    with pytest.raises(UserError, match=r"--out .*afile/sub: cannot create the folder"):
        export(write_run(tmp_path / "z"), "tum", tmp_path / "afile" / "sub")


def test_a_tum_export_before_the_slam_stage_says_that_no_filter_trajectory_is_there(tmp_path: Path) -> None:
    written, notes = run_export(write_run(tmp_path / "runs"), "tum", tmp_path / "out")
    assert sorted(p.name for p in written) == ["groundtruth.tum", "odometry.tum"]
    said = [n for n in notes if n.startswith("no SLAM trajectory")]
    assert len(said) == 1 and "pipeline run slam --seq s" in said[0]
    _, notes = run_export(write_run(tmp_path / "runs2", slam=True), "tum", tmp_path / "out2")
    assert not any(n.startswith("no SLAM trajectory") for n in notes)
