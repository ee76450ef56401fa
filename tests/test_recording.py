"""Rerun recordings: one recording id per sequence, expected entity paths and timelines."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rerun.chunk import RrdReader

from core.recording import StageRecording, entity_paths_in, recording_id, scan_lengths
from pipeline.runner import Runner
from pipeline.sequences import SequenceInfo
from tests import toy_stages


def test_scan_lengths() -> None:
    scans, lengths = scan_lengths(np.array([0, 0, 1, 3, 3, 3]))
    assert scans.tolist() == [0, 1, 3] and lengths.tolist() == [2, 1, 3]


def test_stage_rrd_reads_back_with_entity_paths_and_timelines(tmp_path: Path) -> None:
    seq = SequenceInfo(name="toyseq", kind="source", source=tmp_path)
    Runner(seq, tmp_path, toy_stages.registry(), toy_stages.workflow()).run(["make_numbers"])
    rrd = tmp_path / "toyseq" / "make_numbers" / "make_numbers.rrd"
    assert rrd.exists()
    reader = RrdReader(str(rrd))
    assert [r.recording_id for r in reader.recordings()] == [recording_id("toyseq")]
    chunks = {str(c.entity_path): c for c in reader.stream().to_chunks()}
    assert {"/world/radar/raw", "/metrics/value"} <= set(chunks)
    raw = chunks["/world/radar/raw"]
    assert raw.num_rows == 5 and set(raw.timeline_names) == {"scan", "sensor_time"}
    assert "/metrics/value" in entity_paths_in(rrd)


def test_ragged_points_and_trajectory(tmp_path: Path) -> None:
    rec = StageRecording("s", tmp_path / "x.rrd")
    pts = np.random.default_rng(0).normal(size=(10, 3))
    rec.points_by_scan("world/radar/filtered", np.array([0, 0, 0, 1, 1, 2, 2, 2, 2, 2]), np.arange(10) * 10, pts)
    rec.trajectory("world/odometry", np.arange(4), None, np.zeros((4, 3)))
    rec.close()
    chunks = {str(c.entity_path): c.num_rows for c in RrdReader(str(tmp_path / "x.rrd")).stream().to_chunks()}
    assert chunks["/world/radar/filtered"] == 3  # one row per scan
    assert "/world/odometry/path" in chunks and chunks["/world/odometry/pose"] == 4
