"""End to end on short simulated sequences: ingest -> filter -> odometry on the simulator's bag and folder forms.

References are the simulator's own ground truth (``X.sim/trajectory.parquet``: exact world velocity and
yaw rate at every IMU sample) and its rig extrinsics, independent of the pipeline's code.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from core.geometry import pose_matrix, poses_to_matrices
from core.trajectory_metrics import NEES_TOLERANCE
from pipeline.config import Workflow
from pipeline.registry import load_stages
from pipeline.runner import Runner
from pipeline.sequences import SequenceInfo
from schemas.io import read_artifact
from tests.test_ingest import run_unwrapped

simulator = pytest.importorskip("simulator")
DURATION = 12.0


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("sim")
    out = {}
    for fmt in ("bag", "folder"):
        path = root / ("demo.bag" if fmt == "bag" else "demo")
        out[fmt] = simulator.simulate_to(world="demo", out=path, duration=DURATION, seed=5, fmt=fmt)
    return out


def _run(path: Path, runs: Path) -> Path:
    seq = SequenceInfo(name="simdemo", kind="source", source=path)
    run_unwrapped(Runner(seq, runs, load_stages(), Workflow("t", ["ingest", "filter", "odometry"])), ["odometry"])
    return runs / "simdemo"


def _sidecar(path: Path) -> Path:
    return path.with_suffix(".sim") if path.suffix == ".bag" else path / "sim"


def _true_radar_velocity(path: Path, t_ns: np.ndarray) -> np.ndarray:
    """Radar velocity in the radar frame from the simulator's exact kinematics (nearest IMU-rate sample)."""
    from simulator import rig

    tr = pq.read_table(_sidecar(path) / "trajectory.parquet").to_pandas()
    k = np.abs(tr["t_ns"].to_numpy()[None, :] - t_ns[:, None]).argmin(axis=1)
    T_br = pose_matrix(rig.BASE_TO_RADAR.translation, rig.BASE_TO_RADAR.quaternion)
    T_wb = poses_to_matrices(tr[["x", "y", "z", "qx", "qy", "qz", "qw"]].to_numpy()[k])
    w = np.zeros((len(k), 3))
    w[:, 2] = tr["wz"].to_numpy()[k]
    lever = T_wb[:, :3, :3] @ T_br[:3, 3]
    v_w = tr[["vx", "vy", "vz"]].to_numpy()[k] + np.cross(w, lever)
    return np.einsum("nji,nj->ni", T_wb[:, :3, :3] @ T_br[:3, :3], v_w)


@pytest.mark.parametrize("fmt", ["bag", "folder"])
def test_simulated_sequence_end_to_end(simulated: dict[str, Path], tmp_path: Path, fmt: str) -> None:
    from simulator import rig

    path = simulated[fmt]
    out = _run(path, tmp_path / "runs")
    calib = json.loads((out / "ingest" / "calibration.json").read_text())
    np.testing.assert_allclose(calib["base_from_radar"],
                               pose_matrix(rig.BASE_TO_RADAR.translation, rig.BASE_TO_RADAR.quaternion), atol=1e-6)
    radar = read_artifact(out / "ingest" / "radar.parquet", "radar")
    assert (radar["label"].to_numpy() >= 0).all()  # every point found its simulator label
    # ego-velocity against the simulator's exact kinematics
    ego = read_artifact(out / "filter" / "ego_velocity.parquet", "ego_velocity")
    v = np.stack([ego[c].to_numpy() for c in ("vx", "vy", "vz")], axis=1)
    ok = ego["valid"].to_numpy()
    assert ok.mean() > 0.9
    truth = _true_radar_velocity(path, ego["t_ns"].to_numpy())
    err = np.linalg.norm(v[ok, :2] - truth[ok, :2], axis=1)
    assert np.sqrt((err ** 2).mean()) < 0.1
    # the Doppler sign: forward motion of the radar (boresight x) gives positive v_x
    moving = truth[:, 0] > 0.5
    assert np.all(np.sign(v[ok & moving, 0]) > 0)
    fstats = json.loads((out / "filter" / "manifest.json").read_text())["stats"]
    # the tracking gate keeps a point only if it matches points of each of the 2 previous scans: the simulator's
    # persistent scatterers are detected intermittently (CFAR, Swerling), so not every true point is tracked
    assert fstats["labels"]["true_kept"] > 0.8 and fstats["labels"]["clutter_rejected"] > 0.9
    ostats = json.loads((out / "odometry" / "manifest.json").read_text())["stats"]
    assert ostats["anchor"] == "groundtruth" and ostats["drift"]["drift_pct_of_distance"] < 3.0
    # the increment covariance: not overconfident on the simulator's errors (the NEES check;
    # stages/odometry/README.md): 95 % of the normalised increment errors below chi-square(3)'s 95 % point
    nees = ostats["increment_nees"]
    assert nees["increments"] >= 100 and nees["share_below_chi2_95"] >= 0.95 and nees["mean"] <= 3.0 * NEES_TOLERANCE
    if fmt == "folder":  # the check's command on the same run: its speed scale (drift under 3 %) is near 1
        from experiments import odometry_nees as nees_cli

        rows = tmp_path / "nees.jsonl"
        assert nees_cli.main([str(out.parent), out.name, "--speed", "--json", str(rows)]) == 0
        ratio = json.loads(rows.read_text().splitlines()[0])["distance_ratio_10s"]
        assert ratio["windows"] > 0 and 0.95 < ratio["p10"] <= ratio["median"] <= ratio["p90"] < 1.05


def test_bag_and_folder_forms_ingest_the_same_points(simulated: dict[str, Path], tmp_path: Path) -> None:
    a = read_artifact(_run(simulated["bag"], tmp_path / "a") / "ingest" / "radar.parquet", "radar")
    b = read_artifact(_run(simulated["folder"], tmp_path / "b") / "ingest" / "radar.parquet", "radar")
    assert a.num_rows == b.num_rows
    for c in ("scan", "x", "y", "z", "intensity", "doppler", "label"):
        np.testing.assert_array_equal(a[c].to_numpy(), b[c].to_numpy())
    # the folder form keeps microseconds
    assert np.abs(a["t_ns"].to_numpy() - b["t_ns"].to_numpy()).max() <= 1000
