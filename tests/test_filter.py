"""The filter stage through the runner on an analytic radar-inertial run with labelled clutter and ghosts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from core.recording import entity_paths_in
from pipeline.config import Workflow
from pipeline.registry import load_stages
from pipeline.runner import Runner
from pipeline.sequences import SequenceInfo
from schemas.io import read_artifact
from tests.test_filter_scene import circle_run, write_circle_log
from tests.test_ingest import run_unwrapped


def run_stages(path: Path, runs: Path, targets: list[str], overrides: dict | None = None) -> Path:
    seq = SequenceInfo(name="circle", kind="source", source=path)
    run_unwrapped(Runner(seq, runs, load_stages(), Workflow("test", ["ingest", "filter", "odometry"]), overrides or {}),
                  targets)
    return runs / "circle"


@pytest.fixture(scope="module")
def circle(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    root = tmp_path_factory.mktemp("circle")
    run = circle_run(duration=12.0, seed=1)
    return write_circle_log(root / "circle", run), run


def test_filter_stage_outputs_and_measurements(circle, tmp_path: Path) -> None:
    bag, run = circle
    out = run_stages(bag, tmp_path / "runs", ["filter"])
    ego = read_artifact(out / "filter" / "ego_velocity.parquet", "ego_velocity")
    assert ego.schema.field("n_inliers").type == pa.int32()
    assert ego.num_rows == len(run.scene.radar)
    v = np.stack([ego[c].to_numpy() for c in ("vx", "vy", "vz")], axis=1)
    assert ego["valid"].to_numpy().all()
    # against the analytic radar velocity (independent of the ground-truth differencing in the stage)
    err_xy = np.linalg.norm(v[:, :2] - run.v_radar[:, :2], axis=1)
    assert np.sqrt((err_xy ** 2).mean()) < 0.05
    stats = json.loads((out / "filter" / "manifest.json").read_text())["stats"]
    # the stage's own ground-truth comparison agrees with the analytic one
    assert abs(stats["ego_velocity_error"]["rmse_xy_mps"] - np.sqrt((err_xy ** 2).mean())) < 0.02
    lab = stats["labels"]
    assert lab["true_kept"] > 0.8 and lab["clutter_rejected"] > 0.85
    assert lab["n_ghost"] > 0 and lab["ghost_rejected"] is not None
    kept = read_artifact(out / "filter" / "radar_filtered.parquet", "radar_filtered")
    assert kept.num_rows == stats["kept"] and "label" in kept.column_names
    assert np.all(np.diff(kept["scan"].to_numpy()) >= 0)
    # the first track_frames scans have no history: nothing kept there
    assert kept["scan"].to_numpy().min() >= 2
    paths = entity_paths_in(out / "filter" / "filter.rrd")
    assert {"/world/radar/filtered", "/world/radar/filtered/rejected", "/metrics/ego_velocity/vx"} <= paths


def test_filter_parameters_change_the_result(circle, tmp_path: Path) -> None:
    bag, _ = circle
    loose = {"filter": {"tracking": {"frames": 0}, "points": {"min_intensity": -100.0}}}
    out = run_stages(bag, tmp_path / "runs", ["filter"], loose)
    no_track = json.loads((out / "filter" / "manifest.json").read_text())["stats"]
    out2 = run_stages(bag, tmp_path / "runs2", ["filter"], {"filter": {"tracking": {"frames": 3}}})
    strict = json.loads((out2 / "filter" / "manifest.json").read_text())["stats"]
    assert no_track["kept"] > strict["kept"]
    assert no_track["labels"]["ghost_rejected"] < strict["labels"]["ghost_rejected"]
