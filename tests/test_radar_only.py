"""Radar-only maps: the workflow on a short simulated log, its recording, and the sweep's table."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from core.recording import entity_paths_in, recording_id
from schemas import read_artifact
from stages.evaluate.radar_only import radar_only_rows, radar_only_table, source_of
from tests.test_cli_run import SEQ, SLAM, cli, run  # noqa: F401  (the module-scoped run fixture)


def test_radar_only_workflow_builds_completes_and_scores_the_map_along_the_slam_trajectory(
        run: tuple[Path, Path], tmp_path: Path) -> None:  # noqa: F811
    pytest.importorskip("torch")
    runs = tmp_path / "runs"
    shutil.copytree(run[0], runs)
    r = cli("run", "all", "--source", str(run[1]), "--seq", SEQ, "--runs-dir", str(runs), "--workflow",
            "radar_only", *SLAM)
    assert r.returncode == 0, r.stderr
    seq = runs / SEQ
    assert "ingest    done" not in r.stderr and "filter    done" not in r.stderr  # cached: the default workflow's
    # the odometry estimates the radar's mount under the level prior (the map's height; stages/odometry/README.md)
    odo = json.loads((seq / "odometry" / "manifest.json").read_text())
    assert odo["params"]["height"]["level_velocity_sigma"] > 0 and odo["params"]["height"]["mount_sigma0_deg"] > 0
    assert len(odo["stats"]["mount_error_deg"]) == 3
    voxel = json.loads((seq / "voxel" / "manifest.json").read_text())
    assert voxel["params"]["trajectory"]["source"] == "slam" and voxel["params"]["trajectory"]["attitude"] == "odometry"
    assert voxel["stats"]["attitude"] == "odometry" and voxel["stats"]["trajectory_coverage"] >= 0.9
    meta = read_artifact(seq / "voxel" / "radar_map.parquet", "radar_map").schema.metadata
    assert meta[b"trajectory"] == b"slam"
    m = read_artifact(seq / "evaluate" / "metrics.parquet", "metrics").to_pylist()
    got = {(x["method"], x["metric"]): x["value"] for x in m}
    for name in ("radar_map", "completed_map"):
        assert np.isfinite(got[(name, "cd_l2")]) and 0 <= got[(name, "fscore_0.15")] <= 1
    # the trajectories' errors without alignment (the maps' frame) beside the Table III protocol
    assert got[("rich_slam", "ate_yaw_rmse_anchored_deg")] >= 0
    assert got[("odometry", "ate_pos_rmse_anchored_m")] >= 0
    # one recording: the radar-only map as built and completed, the lidar map and the trajectories
    paths = set().union(*(entity_paths_in(f) for f in seq.glob("*/*.rrd")))
    for p in ("/world/voxel/radar", "/world/voxel/trajectory/pose", "/world/complete", "/world/voxel/lidar",
              "/world/slam/trajectory", "/world/odometry", "/world/groundtruth"):
        assert any(q == p or q.startswith(p + "/") for q in paths), (p, sorted(paths))
    from rerun.chunk import RrdReader

    ids = {r.recording_id for f in seq.glob("*/*.rrd") for r in RrdReader(str(f)).recordings()}
    assert ids == {recording_id(SEQ)}
    traj = {str(c.entity_path): c for c in RrdReader(str(seq / "slam" / "slam.rrd")).stream().to_chunks()}
    assert "scan" in traj["/world/slam/trajectory/pose"].timeline_names  # on the scan timeline


def _records() -> list[dict]:
    pts = {"groundtruth": {"voxel.trajectory.source": "groundtruth"},
           "odometry": {"voxel.trajectory.source": "odometry"},
           "rich_slam": {"voxel.trajectory.source": "slam", "voxel.trajectory.slam_method": "rich_slam"}}
    cd = {"groundtruth": 0.2, "odometry": 0.5, "rich_slam": 0.3}
    yaw = {"odometry": 4.0, "rich_slam": 2.0}
    out = []
    for src, params in pts.items():
        pj = json.dumps(params)
        out.append({"seq": "s", "method": "completed_map", "metric": "cd_l2", "value": cd[src], "params": pj})
        out.append({"seq": "s", "method": "radar_map", "metric": "cd_l2", "value": 2 * cd[src], "params": pj})
        for m, v in yaw.items():  # every point scores every trajectory of its run; only its own source counts
            out.append({"seq": "s", "method": m, "metric": "ate_yaw_rmse_anchored_deg", "value": v, "params": pj})
    return out


def test_radar_only_rows_pair_each_map_with_the_trajectory_it_was_built_along() -> None:
    assert source_of('{"voxel.trajectory.source": "slam", "voxel.trajectory.slam_method": ""}') == "slam"
    assert source_of('{"evaluate.gp.lengthscale_m": 2}') is None
    level = {"voxel.trajectory.source": "slam", "voxel.trajectory.slam_method": "g",
             "voxel.trajectory.attitude": "level"}
    assert source_of(level) == "g (level)"
    rows = {r["source"]: r for r in radar_only_rows(_records())}
    assert list(rows) == ["groundtruth", "odometry", "rich_slam"]
    assert rows["odometry"]["traj.ate_yaw_rmse_anchored_deg"] == 4.0
    assert rows["rich_slam"]["traj.ate_yaw_rmse_anchored_deg"] == 2.0
    assert rows["groundtruth"]["traj.ate_yaw_rmse_anchored_deg"] == 0.0
    assert rows["odometry"]["ratio_cd_l2"] == pytest.approx(2.5)
    assert rows["rich_slam"]["radar_map.cd_l2"] == pytest.approx(0.6)
    title, headers, body = radar_only_table(_records())  # type: ignore[misc]
    assert title.startswith("Radar-only maps") and len(body) == 3 and body[1][-1] == "2.50"
    assert headers[1] == "built along" and body[2][1] == "rich_slam"
    assert radar_only_table([{"seq": "s", "method": "x", "metric": "auc", "value": 1.0, "params": "{}"}]) is None
    # a sequence without lidar (trajectory metrics only): a stated skip, not a row of dashes
    no_lidar = [{**r, "seq": "radar_imu"} for r in _records() if not r["method"].endswith("_map")]
    title, _, body = radar_only_table(_records() + no_lidar)  # type: ignore[misc]
    assert len(body) == 3 and title.endswith("skipped, no lidar map to score against: radar_imu")


def test_map_vs_trajectory_figure(tmp_path: Path) -> None:
    from stages.evaluate.radar_only import plot_map_vs_trajectory

    path = plot_map_vs_trajectory(tmp_path / "f.png", _records())
    assert path.stat().st_size > 5000


def test_map_vs_trajectory_axis_turns_logarithmic_when_one_map_is_far_off() -> None:
    from stages.evaluate.radar_only import wide_span

    assert not wide_span([0.3, 0.5, 1.7, 5.9])  # the twins along odometry: a linear axis reads fine
    assert wide_span([0.3, 0.5, 1.7, 33.5])  # one diverged trajectory (coloradar_6_twin)
    assert not wide_span([]) and not wide_span([0.0, 2.0])


def test_radar_only_workflow_on_a_radar_imu_log_completes_the_map_and_says_what_it_cannot_score(
        tmp_path: Path) -> None:
    """No lidar and no ground truth: the map is built along the SLAM trajectory and completed from radar
    patches alone; evaluate is skipped with its reason; exit 0."""
    pytest.importorskip("torch")
    import simulator

    bag = simulator.simulate_to(world="handheld_loop", out=tmp_path / "walk.bag", duration=15.0, seed=5, fmt="bag")
    r = cli("run", "all", "--source", str(bag), "--seq", "walk", "--dataset", "generic", "--runs-dir",
            str(tmp_path / "runs"), "--workflow", "radar_only", "--set", "slam.n_particles=5",
            "--set", "slam.map.n_basis=64", "--set", 'slam.methods=["odometry","rich_slam"]')
    assert r.returncode == 0, r.stderr
    seq = tmp_path / "runs" / "walk"
    assert "radar patches only" in r.stderr
    patches = read_artifact(seq / "patches" / "patches.parquet", "patches")
    assert set(patches.column("kind").to_pylist()) == {"radar"}
    done = read_artifact(seq / "complete" / "completed_map.parquet", "completed_map")
    assert done.num_rows > 0
    assert not (seq / "evaluate").exists()
    assert re.search(r"evaluate\s+skipped: the log has no ground-truth poses", r.stderr)
