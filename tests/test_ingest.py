"""The ingest stage on every source form, its artifacts, calibration, Rerun output and bad-input errors."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from core.errors import UserError
from core.geometry import pose_matrix
from core.recording import entity_paths_in
from pipeline.config import Workflow
from pipeline.registry import load_stages
from pipeline.runner import Runner
from pipeline.sequences import SequenceInfo
from schemas.io import ArtifactWriter, read_artifact
from tests.test_ingest_logs import (
    BASE_FROM_IMU,
    BASE_FROM_OS1,
    BASE_FROM_RADAR,
    GT_TOPIC,
    IMU_TOPIC,
    LIDAR_TOPIC,
    OS1_FROM_LIDAR,
    RADAR_TOPIC,
    make_scene,
    write_log,
)

FORMS = ["ros1", "ros2", "mcap", "bare_mcap", "folder"]


def run_unwrapped(runner: Runner, targets: list[str]) -> None:
    """``runner.run``, re-raising a failed stage's own error when the runner wraps it."""
    try:
        runner.run(targets)
    except Exception as exc:
        first = getattr(exc, "first", None)
        if isinstance(first, BaseException):
            raise first from exc
        raise


def ingest(path: Path, runs: Path, dataset: str = "coloradar", **params: Any) -> Path:
    seq = SequenceInfo(name=path.name.replace(".", "_"), kind="source", dataset=dataset, source=path)
    run_unwrapped(Runner(seq, runs, load_stages(), Workflow("test", ["ingest"]), {"ingest": params} if params else {}),
                  ["ingest"])
    return runs / seq.name / "ingest"


def manifest(out: Path) -> dict[str, Any]:
    return json.loads((out / "manifest.json").read_text())


@pytest.mark.parametrize("form", FORMS)
def test_round_trip_every_source_form(tmp_path: Path, form: str) -> None:
    sc = make_scene()
    out = ingest(write_log(tmp_path / "log", sc, form), tmp_path / "runs")
    radar = read_artifact(out / "radar.parquet", "radar")
    assert radar.schema.field("scan").type == pa.int32() and radar.schema.field("doppler").type == pa.float32()
    for i, (t, cols) in enumerate(sc.radar):
        rows = radar.filter(pa.compute.equal(radar["scan"], i))
        assert rows.num_rows == len(cols["x"])
        assert set(rows["t_ns"].to_pylist()) == {t}
        for c in ("x", "y", "z", "intensity", "doppler"):
            np.testing.assert_array_equal(rows[c].to_numpy(), cols[c])
    assert radar["label"].to_pylist() == [-1] * radar.num_rows
    lidar = read_artifact(out / "lidar.parquet", "lidar")
    np.testing.assert_array_equal(lidar["intensity"].to_numpy(), np.concatenate([c["intensity"] for _, c in sc.lidar]))
    assert lidar["scan"].to_numpy()[-1] == len(sc.lidar) - 1
    imu = read_artifact(out / "imu.parquet", "imu")
    np.testing.assert_array_equal(imu["t_ns"].to_numpy(), sc.imu_t)
    got = np.stack([imu[c].to_numpy() for c in ("ax", "ay", "az", "gx", "gy", "gz")], axis=1)
    np.testing.assert_allclose(got, sc.imu, rtol=1e-15)
    gt = read_artifact(out / "groundtruth.parquet", "groundtruth")
    np.testing.assert_array_equal(gt["t_ns"].to_numpy(), sc.gt_t)
    np.testing.assert_allclose(np.stack([gt[c].to_numpy() for c in ("x", "y", "z", "qx", "qy", "qz", "qw")], 1), sc.gt,
                               rtol=1e-12, atol=1e-15)
    calib = json.loads((out / "calibration.json").read_text())
    np.testing.assert_allclose(calib["base_from_radar"], pose_matrix(*BASE_FROM_RADAR), atol=1e-9)
    np.testing.assert_allclose(calib["base_from_imu"], pose_matrix(*BASE_FROM_IMU), atol=1e-9)
    np.testing.assert_allclose(calib["base_from_lidar"], pose_matrix(*BASE_FROM_OS1) @ pose_matrix(*OS1_FROM_LIDAR),
                               atol=1e-9)
    # the radar frame of ColoRadar looks along the base +y axis
    np.testing.assert_allclose(np.asarray(calib["base_from_radar"])[:3, 0], [0, 1, 0], atol=2e-3)
    assert calib["base_frame"] == "imu_viz_link"
    stats = manifest(out)["stats"]
    assert stats["streams"]["radar"]["messages"] == len(sc.radar)
    assert stats["nonfinite_dropped"]["radar"] == 0
    assert not stats.get("warnings")
    paths = entity_paths_in(out / "ingest.rrd")
    assert {"/world/radar/raw", "/world/lidar", "/world/groundtruth/path"} <= paths
    from rerun.chunk import RrdReader

    timelines: dict[str, set[str]] = {}
    for ch in RrdReader(str(out / "ingest.rrd")).stream().to_chunks():
        timelines.setdefault(str(ch.entity_path), set()).update(ch.timeline_names)
    assert timelines["/world/radar/raw"] == {"scan", "sensor_time"}
    assert timelines["/world/lidar"] == {"sensor_time"}  # lidar sweeps are not radar scans


def test_missing_topic_lists_what_the_log_has(tmp_path: Path) -> None:
    bag = write_log(tmp_path / "log", make_scene(), "ros1", radar_topic="/radar/points")
    with pytest.raises(UserError) as err:
        ingest(bag, tmp_path / "runs")
    msg = str(err.value)
    assert str(bag) in msg and RADAR_TOPIC in msg and "not found" in msg
    for topic in ("/radar/points", LIDAR_TOPIC, IMU_TOPIC, GT_TOPIC):
        assert topic in msg
    # mapping the topic fixes it
    out = ingest(bag, tmp_path / "runs2", topics={"radar": "/radar/points"})
    assert read_artifact(out / "radar.parquet", "radar").num_rows == sum(len(c["x"]) for _, c in make_scene().radar)


def test_optional_ground_truth_missing_is_a_warning(tmp_path: Path) -> None:
    bag = write_log(tmp_path / "log", make_scene(), "ros1", skip=(GT_TOPIC,))
    out = ingest(bag, tmp_path / "runs")
    assert read_artifact(out / "groundtruth.parquet", "groundtruth").num_rows == 0
    assert any(GT_TOPIC in w for w in manifest(out)["stats"]["warnings"])


def test_generic_profile_detects_topics_and_velocity_field(tmp_path: Path) -> None:
    sc = make_scene()
    bag = write_log(tmp_path / "log", sc, "mcap", radar_topic="/some/radar")
    out = ingest(bag, tmp_path / "runs", dataset="generic")
    src = manifest(out)["stats"]["source"]
    assert src["profile"] == "generic"
    assert src["streams"]["radar"] == "/some/radar" and src["streams"]["lidar"] == LIDAR_TOPIC
    assert src["streams"]["imu"] == IMU_TOPIC and src["streams"]["groundtruth"] == GT_TOPIC
    radar = read_artifact(out / "radar.parquet", "radar")
    np.testing.assert_array_equal(radar["doppler"].to_numpy(), np.concatenate([c["doppler"] for _, c in sc.radar]))


@pytest.mark.parametrize("form", ["ros1", "mcap", "bare_mcap", "ros2"])
def test_truncated_or_corrupt_log_names_the_file(tmp_path: Path, form: str) -> None:
    path = write_log(tmp_path / "log", make_scene(n_lidar=20), form)
    target = path if path.is_file() else next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    raw = target.read_bytes()
    target.write_bytes(raw[: len(raw) * 2 // 3])
    with pytest.raises(UserError) as err:
        ingest(path, tmp_path / "runs")
    assert str(path) in str(err.value) or str(target) in str(err.value)
    assert "corrupt or truncated" in str(err.value) or "malformed" in str(err.value)


def test_truncated_folder_file_names_the_file(tmp_path: Path) -> None:
    path = write_log(tmp_path / "run", make_scene(), "folder")
    f = path / "single_chip/pointclouds/data/radar_pointcloud_2.bin"
    f.write_bytes(f.read_bytes()[:-3])
    with pytest.raises(UserError, match=r"radar_pointcloud_2\.bin.*truncated"):
        ingest(path, tmp_path / "runs")


def test_nan_points_are_dropped_and_counted(tmp_path: Path) -> None:
    sc = make_scene()
    sc.radar[1][1]["x"][0] = np.nan
    sc.radar[3][1]["doppler"][1] = np.inf
    sc.lidar[0][1]["z"][:5] = np.nan
    sc.imu[4, 2] = np.nan
    out = ingest(write_log(tmp_path / "log", sc, "ros1"), tmp_path / "runs")
    stats = manifest(out)["stats"]
    assert stats["nonfinite_dropped"] == {"radar": 2, "lidar": 5, "imu": 1, "groundtruth": 0, "odometry": 0}
    radar = read_artifact(out / "radar.parquet", "radar")
    assert radar.num_rows == sum(len(c["x"]) for _, c in sc.radar) - 2
    assert np.isfinite(radar["doppler"].to_numpy()).all()
    assert read_artifact(out / "imu.parquet", "imu").num_rows == len(sc.imu) - 1
    assert any("NaN" in w for w in stats["warnings"])


def test_time_going_backwards_is_reported_and_sorted(tmp_path: Path) -> None:
    sc = make_scene(n_radar=8)
    # swap the stamps of radar scans 2 and 3 (jitter) and send scan 6 far into the past (clock jump)
    (t2, c2), (t3, c3) = sc.radar[2], sc.radar[3]
    sc.radar[2], sc.radar[3] = (t3, c2), (t2, c3)
    sc.radar[6] = (sc.radar[0][0] - 10, sc.radar[6][1])
    sc.imu_t[10], sc.imu_t[11] = sc.imu_t[11], sc.imu_t[10]
    out = ingest(write_log(tmp_path / "log", sc, "folder"), tmp_path / "runs", clock={"reorder_window": 2})
    stats = manifest(out)["stats"]
    assert stats["streams"]["radar"]["backwards"] == 2
    assert stats["streams"]["radar"]["out_of_order_dropped"] == 1
    assert stats["streams"]["imu"]["backwards"] == 1 and stats["streams"]["imu"]["out_of_order_dropped"] == 0
    assert any("backwards" in w and "radar" in w for w in stats["warnings"])
    radar = read_artifact(out / "radar.parquet", "radar")
    t = radar["t_ns"].to_numpy()
    assert np.all(np.diff(t) >= 0) and np.all(np.diff(radar["scan"].to_numpy()) >= 0)
    assert len(np.unique(radar["scan"].to_numpy())) == 7
    assert np.all(np.diff(read_artifact(out / "imu.parquet", "imu")["t_ns"].to_numpy()) > 0)


def test_radar_latency_moves_only_the_radar_stamps(tmp_path: Path) -> None:
    """``radar_latency_s``: a radar stamped on arrival is late; every radar stamp moves back by it, nothing else."""
    sc = make_scene()
    log = write_log(tmp_path / "log", sc, "mcap")
    plain = ingest(log, tmp_path / "runs_a")
    late = ingest(log, tmp_path / "runs_b", clock={"radar_latency_s": 0.03})
    for name in ("radar", "lidar", "imu", "groundtruth"):
        t0 = read_artifact(plain / f"{name}.parquet", name)["t_ns"].to_numpy()
        t1 = read_artifact(late / f"{name}.parquet", name)["t_ns"].to_numpy()
        np.testing.assert_array_equal(t1, t0 - 30_000_000 if name == "radar" else t0)
    stamps = set(read_artifact(late / "radar.parquet", "radar")["t_ns"].to_numpy())
    assert stamps == {t - 30_000_000 for t, _ in sc.radar}
    with pytest.raises(UserError, match=r"ingest\.clock\.radar_latency_s=2\.0"):
        ingest(log, tmp_path / "runs_c", clock={"radar_latency_s": 2.0})


@pytest.mark.parametrize("form", ["ros1", "folder"])
def test_label_sidecar_is_joined_by_scan_and_point_index(tmp_path: Path, form: str) -> None:
    sc = make_scene()
    sc.radar[2][1]["y"][1] = np.nan  # dropped: its label must go with it
    log = write_log(tmp_path / "log", sc, form)
    if form == "folder":  # the extracted form keeps microseconds ('%6f' % stamp.to_sec())
        ts = np.array([t for t, _ in sc.radar])
        (log / "single_chip/pointclouds/timestamps.txt").write_text("".join("%6f\n" % (t * 1e-9) for t in ts))
    rows = []
    for i, (t, cols) in enumerate(sc.radar):
        rows += [(i, t, j, (i + j) % 3) for j in range(len(cols["x"]))]
    side = log / "sim" if form == "folder" else tmp_path / "log.sim"
    side.mkdir()
    arr = np.array(rows, dtype=np.int64)
    pq.write_table(pa.table({"scan": arr[:, 0].astype(np.int32), "t_ns": arr[:, 1], "point": arr[:, 2].astype(np.int32),
                             "label": arr[:, 3].astype(np.int8)}), side / "radar_labels.parquet")
    out = ingest(log, tmp_path / "runs")
    radar = read_artifact(out / "radar.parquet", "radar")
    assert radar.schema.field("label").type == pa.int8()
    expect = np.array([(i + j) % 3 for i, (_, c) in enumerate(sc.radar) for j in range(len(c["x"]))
                       if not (i == 2 and j == 1)])
    np.testing.assert_array_equal(radar["label"].to_numpy(), expect)
    assert not any("labels" in w for w in manifest(out)["stats"].get("warnings", []))


def test_odometry_topic_is_kept_when_named(tmp_path: Path) -> None:
    sc = make_scene()
    bag = write_log(tmp_path / "log", sc, "ros1")
    out = ingest(bag, tmp_path / "runs", topics={"odometry": GT_TOPIC})
    odo = read_artifact(out / "bag_odometry.parquet", "groundtruth")
    np.testing.assert_array_equal(odo["t_ns"].to_numpy(), sc.gt_t)


def test_streaming_writer_writes_row_groups_and_schema_metadata(tmp_path: Path) -> None:
    path = tmp_path / "imu.parquet"
    with ArtifactWriter(path, "imu", batch_rows=1000) as w:
        for k in range(5):
            t = np.arange(k * 700, (k + 1) * 700, dtype=np.int64)
            w.write({"t_ns": t, **{c: t * 1.0 for c in ("ax", "ay", "az", "gx", "gy", "gz")}})
    assert pq.ParquetFile(path).num_row_groups == 3  # 1400 + 1400 + 700 rows
    table = read_artifact(path, "imu")
    np.testing.assert_array_equal(table["t_ns"].to_numpy(), np.arange(3500))
    empty = tmp_path / "empty.parquet"
    ArtifactWriter(empty, "imu").close()
    assert read_artifact(empty, "imu").num_rows == 0


def test_cache_key_follows_the_source_file(tmp_path: Path) -> None:
    bag = write_log(tmp_path / "log", make_scene(), "ros1")
    seq = SequenceInfo(name="k", kind="source", source=bag)
    runner = Runner(seq, tmp_path / "runs", load_stages(), Workflow("test", ["ingest"]))
    runner.run(["ingest"])
    assert Runner(seq, tmp_path / "runs", load_stages(), Workflow("test", ["ingest"])).stage_status("ingest").state \
        == "done"
    bag.unlink()
    write_log(tmp_path / "log", make_scene(n_radar=7), "ros1")
    status = Runner(seq, tmp_path / "runs", load_stages(), Workflow("test", ["ingest"])).stage_status("ingest")
    assert status.state == "stale" and "source data changed" in status.reason


def _peak_ingest_memory(tmp_path: Path, n_lidar: int) -> float:
    import tracemalloc

    from rich.console import Console

    from core.stage import StageContext
    from stages.ingest.stage import STAGE, IngestParams

    sc = make_scene(n_radar=4, n_lidar=1, n_imu=10, n_gt=3)
    rng = np.random.default_rng(0)
    t0 = sc.lidar[0][0]
    keys = ("x", "y", "z", "intensity")
    sc.lidar = [(t0 + i * 10_000_000, {k: rng.normal(size=5000).astype(np.float32) for k in keys})
                for i in range(n_lidar)]
    bag = write_log(tmp_path / f"long{n_lidar}", sc, "ros1")
    out = tmp_path / f"out{n_lidar}"
    out.mkdir()
    ctx = StageContext("ingest", SequenceInfo(name="m", kind="source", source=bag), IngestParams(batch_rows=20_000),
                       out, {}, Console(quiet=True))
    tracemalloc.start()
    try:
        STAGE.run(ctx)
        ctx.close()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert read_artifact(out / "lidar.parquet", "lidar").num_rows == 5000 * n_lidar
    return peak


def test_memory_stays_bounded_on_long_bags(tmp_path: Path) -> None:
    # 3x the lidar data must not mean 3x the peak memory (Python-side allocations, numpy included)
    _peak_ingest_memory(tmp_path, 2)  # imports and caches out of the way
    short = _peak_ingest_memory(tmp_path, 40)
    long = _peak_ingest_memory(tmp_path, 120)
    assert long < 1.3 * short
    assert long < 0.5 * 120 * 5000 * 48  # well under the bag's lidar payload


def test_no_return_points_are_dropped_and_counted(tmp_path: Path) -> None:
    sc = make_scene()
    for k in ("x", "y", "z"):
        sc.lidar[1][1][k][:7] = 0.0  # the Ouster driver's organised cloud: missing returns at the origin
    out = ingest(write_log(tmp_path / "log", sc, "ros1"), tmp_path / "runs")
    stats = manifest(out)["stats"]
    assert stats["zero_points_dropped"] == {"radar": 0, "lidar": 7}
    lidar = read_artifact(out / "lidar.parquet", "lidar")
    assert lidar.num_rows == sum(len(c["x"]) for _, c in sc.lidar) - 7


def test_shared_dataset_calib_folder_beside_the_run(tmp_path: Path) -> None:
    run = write_log(tmp_path / "dataset" / "run0", make_scene(), "folder")
    (run / "calib").rename(tmp_path / "dataset" / "calib")  # the real dataset keeps one calib/ for all runs
    out = ingest(run, tmp_path / "runs")
    calib = json.loads((out / "calibration.json").read_text())
    np.testing.assert_allclose(calib["base_from_radar"], pose_matrix(*BASE_FROM_RADAR), atol=1e-9)
    assert calib["sources"]["radar"] == "file calib/transforms/base_to_single_chip.txt"


def test_log_without_tf_uses_the_profile_extrinsics_with_a_warning(tmp_path: Path) -> None:
    from stages.ingest.profile import load_profile

    bag = write_log(tmp_path / "log", make_scene(), "ros1", skip=("/tf_static",))
    out = ingest(bag, tmp_path / "runs")
    calib = json.loads((out / "calibration.json").read_text())
    prof = load_profile("coloradar")
    np.testing.assert_allclose(calib["base_from_lidar"], prof.extrinsics.lidar.matrix(), atol=1e-12)
    assert calib["sources"]["lidar"] == "profile 'coloradar' default"
    assert any("no tf" in w for w in manifest(out)["stats"]["warnings"])
