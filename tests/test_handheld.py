"""The handheld rig (simulator/handheld.py) end to end: a log like a real handheld radar + IMU recording
(zero radar stamps, IMU on another clock, empty frame_id, rotated radar, MEMS IMU, walking, a dropout)
through ingest, filter and odometry on the defaults, with the mounting given only in a profile file.

References are the simulator's own truth (``X.sim/trajectory.parquet``, the rig model), not the pipeline.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from core.errors import UserError
from core.geometry import pose_matrix
from pipeline.config import Workflow
from pipeline.registry import load_stages
from pipeline.runner import Runner
from pipeline.sequences import SequenceInfo, load_registry
from schemas.io import read_artifact
from tests.test_ingest import run_unwrapped

simulator = pytest.importorskip("simulator")
DURATION, SEED = 40.0, 5
NS = 1_000_000_000


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out: Path = simulator.simulate_to(world="handheld_loop", out=tmp_path_factory.mktemp("hh") / "walk.bag",
                                      duration=DURATION, seed=SEED, fmt="bag")
    return out


@pytest.fixture(scope="module")
def rig() -> Any:
    from simulator.handheld import HandheldRig
    from simulator.world import load_world

    return HandheldRig(**load_world("handheld_loop").spec.rig)


def _truth(bag: Path) -> Any:
    return pq.read_table(bag.with_suffix(".sim") / "trajectory.parquet").to_pandas()


def _profile(path: Path, rig: Any) -> Path:
    """`pipeline profile new PATH --from generic`, then the radar mounting filled in as a user would."""
    from pipeline.cli import app

    res = CliRunner().invoke(app, ["profile", "new", str(path), "--from", "generic"])
    assert res.exit_code == 0, res.output
    m = rig.radar_mount()
    text = path.read_text()
    commented = "# [extrinsics.radar]\n# translation = [0.0, 0.0, 0.0]\n# quaternion = [0.0, 0.0, 0.0, 1.0]\n"
    assert commented in text
    path.write_text(text.replace(commented, f"[extrinsics.radar]\ntranslation = {list(m.translation)}\n"
                                            f"quaternion = {list(m.quaternion)}\n"))
    return path


def _run(bag: Path, runs: Path, targets: list[str], **ingest: Any) -> Path:
    seq = SequenceInfo(name="walk", kind="source", dataset=str(ingest.pop("dataset", "generic")), source=bag)
    wf = Workflow("t", ["ingest", "filter", "odometry"])
    run_unwrapped(Runner(seq, runs, load_stages(), wf, {"ingest": ingest} if ingest else {}), targets)
    return runs / "walk"


def _stats(folder: Path) -> dict[str, Any]:
    out: dict[str, Any] = json.loads((folder / "manifest.json").read_text())["stats"]
    return out


# -- the log -----------------------------------------------------------------------------------------------------
def test_handheld_bag_looks_like_the_real_recording(bag: Path, rig: Any) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS1_NOETIC)) as r:
        topics = {c.topic: c for c in r.connections}
        assert set(topics) == {"/ti_mmwave/radar_scan_pcl", "/imu/data"}  # no tf, lidar or ground truth
        conn = topics["/ti_mmwave/radar_scan_pcl"]
        radar = [(rec, r.deserialize(raw, c.msgtype)) for c, rec, raw in r.messages([conn])]
        imu = [(rec, r.deserialize(raw, c.msgtype)) for c, rec, raw in r.messages([topics["/imu/data"]])]
    assert len(radar) == pytest.approx(10 * DURATION, abs=2)
    assert all(m.header.stamp.sec == 0 and m.header.stamp.nanosec == 0 and m.header.frame_id == "" for _, m in radar)
    assert [f.name for f in radar[0][1].fields] == ["x", "y", "z", "intensity", "velocity"]
    assert sum(m.width == 0 for _, m in radar) >= 10  # the dropout: published, empty
    rec = np.array([t for t, _ in imu])
    head = np.array([m.header.stamp.sec * NS + m.header.stamp.nanosec for _, m in imu])
    assert len(imu) / DURATION == pytest.approx(400, rel=0.01)
    assert np.median(head - rec) / NS == pytest.approx(rig.imu_clock_offset_s, abs=0.01)  # days away


def test_walk_is_a_closed_loop_with_standstills_and_steps(bag: Path, rig: Any) -> None:
    tr = _truth(bag)
    t = (tr["t_ns"].to_numpy() - tr["t_ns"].iloc[0]) / NS
    xy = tr[["x", "y"]].to_numpy()
    speed = np.hypot(tr["vx"], tr["vy"]).to_numpy()
    assert np.hypot(*(xy[-1] - xy[0])) < 0.01  # ends where it started
    assert speed[t < rig.standstill_start_s].max() < 1e-6 and speed[t > DURATION - rig.standstill_end_s].max() < 1e-6
    walking = (t > 8) & (t < 30)
    az = tr["az"].to_numpy()[walking] - tr["az"].to_numpy()[walking].mean()
    freq = np.fft.rfftfreq(len(az), d=float(np.median(np.diff(t))))
    peak = freq[np.argmax(np.abs(np.fft.rfft(az)))]
    assert peak == pytest.approx(rig.step_frequency_hz, abs=0.1)  # the vertical bob at the step frequency


def test_heel_strikes_add_no_net_velocity(rig: Any) -> None:
    from simulator.handheld import heel_strike

    t = np.arange(0, 2.0, 1 / 400)
    acc, gyr = heel_strike(t, np.array([0.5, 1.05]), rig, np.random.default_rng(0))
    assert np.abs(acc).max() > 0.5 * rig.vibration_accel
    dv = np.abs(acc.sum(axis=0) / 400)
    assert dv.max() < 0.02 * np.abs(acc).max() / 400 * len(t)  # integrates to ~0 (a ring's derivative)
    assert np.abs(gyr.sum(axis=0) / 400).max() < 1e-3


# -- ingest on the real log's problems ----------------------------------------------------------------------------
def test_clocks_are_lined_up_and_gaps_reported(bag: Path, tmp_path: Path, rig: Any) -> None:
    out = _run(bag, tmp_path / "runs", ["ingest"]) / "ingest"
    st = _stats(out)
    clock = st["clock"]["streams"]
    assert clock["radar"]["use"] == "record" and clock["radar"]["problem"] == "header stamps are all zero"
    assert clock["imu"]["use"] == "shifted"
    assert clock["imu"]["shift_s"] == pytest.approx(-rig.imu_clock_offset_s, abs=0.01)
    warnings = st["warnings"]
    assert any("lined up" in w and "337000.2" in w for w in warnings)
    radar = read_artifact(out / "radar.parquet", "radar", columns=["t_ns"])["t_ns"].to_numpy()
    imu = read_artifact(out / "imu.parquet", "imu", columns=["t_ns"])["t_ns"].to_numpy()
    assert imu[0] < radar[0] and radar[-1] < imu[-1]  # one clock now
    # the dropout: empty scans counted, one gap reported with its length and time
    n_empty = round(rig.dropout_s * 10)
    assert abs(st["radar_empty_scans"] - n_empty) <= 1
    (gap,) = st["radar_gaps"]
    assert gap["length_s"] == pytest.approx(rig.dropout_s + 0.1, abs=0.11)
    assert gap["start_s"] == pytest.approx(rig.dropout_start_s - 0.1, abs=0.2)
    assert any("no points for 1." in w and "into the radar stream" in w for w in warnings)
    # generic profile, no tf, empty frame_id: the warning says so instead of naming a frame 'radar'
    tf_warn = [w for w in warnings if "no tf" in w]
    assert tf_warn and all("empty frame_id" in w and "'radar'" not in w for w in tf_warn)


def test_header_time_source_refuses_clocks_that_never_overlap(bag: Path, tmp_path: Path) -> None:
    pattern = (r"radar and IMU clocks never overlap \(radar 337000\.\d-3370\d\d\.\d s, IMU 0\.0-4\d\.\d s"
               r".*time_source=auto")
    with pytest.raises(UserError, match=pattern):
        _run(bag, tmp_path / "runs", ["ingest"], clock={"time_source": "header"})


def test_record_time_source_uses_the_record_time_everywhere(bag: Path, tmp_path: Path) -> None:
    st = _stats(_run(bag, tmp_path / "runs", ["ingest"], clock={"time_source": "record"}) / "ingest")
    assert {c["use"] for c in st["clock"]["streams"].values()} == {"record"}
    assert any("record time" in w for w in st["warnings"])


# -- the defaults close the loop ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def walked(bag: Path, rig: Any, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """ingest, filter and odometry on the defaults, the mounting in a profile file: (runs dir, profile)."""
    root = tmp_path_factory.mktemp("walked")
    profile = _profile(root / "my_rig.toml", rig)
    _run(bag, root / "runs", ["odometry"], dataset=str(profile))
    return root / "runs", profile


def test_defaults_close_the_handheld_loop_with_the_mounting_from_a_profile_file(bag: Path, walked: tuple[Path, Path],
                                                                                 rig: Any) -> None:
    out = walked[0] / "walk"
    ingest = _stats(out / "ingest")
    assert not any("no tf" in w for w in ingest["warnings"])
    calib = json.loads((out / "ingest" / "calibration.json").read_text())
    m = rig.radar_mount()
    np.testing.assert_allclose(calib["base_from_radar"], pose_matrix(m.translation, m.quaternion), atol=1e-9)
    assert "my_rig.toml" in calib["sources"]["radar"]
    odo = read_artifact(out / "odometry" / "odometry.parquet", "odometry").to_pandas()
    odo = odo[odo["valid"]]
    tr = _truth(bag)
    length = float(np.hypot(np.diff(tr["x"]), np.diff(tr["y"])).sum())
    closure = float(np.hypot(odo["x"].iloc[-1] - odo["x"].iloc[0], odo["y"].iloc[-1] - odo["y"].iloc[0]))
    assert closure < 0.02 * length, f"loop closed within {closure:.3f} m of {length:.1f} m"
    odo_stats = _stats(out / "odometry")
    assert odo_stats.get("warnings", []) == []  # no rejections to speak of, no recovery, no ground truth missed
    ekf = odo_stats["ekf"]
    assert ekf["standstill"] is not None and ekf["standstill"]["seconds"] >= 2.0
    # the estimated gyro bias at the standstill is the simulator's true bias there
    true_bg = tr[["bgx", "bgy", "bgz"]].to_numpy()[:400].mean(axis=0)
    np.testing.assert_allclose(ekf["standstill"]["gyro_bias"], true_bg, atol=1e-3)


def test_an_imu_noise_set_too_low_is_warned_about(bag: Path, walked: tuple[Path, Path], tmp_path: Path) -> None:
    import shutil

    runs = tmp_path / "runs"
    shutil.copytree(walked[0], runs)  # ingest and filter are cached there
    seq = SequenceInfo(name="walk", kind="source", dataset=str(walked[1]), source=bag)
    over = {"odometry": {"imu": {"accel_noise_density": 0.002}, "velocity": {"gate_probability": 0.99}}}
    run_unwrapped(Runner(seq, runs, load_stages(), Workflow("t", ["ingest", "filter", "odometry"]), over),
                  ["odometry"])
    st = _stats(runs / "walk" / "odometry")
    ekf = st["ekf"]
    share = ekf["velocity_rejected"] / (ekf["velocity_rejected"] + ekf["velocity_updates"])
    assert share > 0.1
    assert any(f"rejected {ekf['velocity_rejected']} of" in w and "accel_noise_density=0.002" in w
               for w in st["warnings"])
    # the rejection streaks are either recovered from (and warned) or, their innovations scattered (the stiff
    # filter's vertical error swings with the steps), kept rejected and counted
    assert ekf["recoveries"] + ekf["recoveries_declined"] >= 1
    assert (ekf["recoveries"] == 0) == (not any("recovered" in w for w in st["warnings"]))


def test_the_registered_handheld_sequence_uses_a_profile_file() -> None:
    seq = load_registry()["sim_handheld_loop"]
    assert seq.world == "handheld_loop" and seq.dataset == "sim_handheld"
    from stages.ingest.profile import load_profile

    prof = load_profile(seq.dataset)
    assert "radar" in prof.extrinsics.model_fields_set and not prof.extrinsics.fallback
