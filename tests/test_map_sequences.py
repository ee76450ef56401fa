"""Map sequences (``rmap_<scene>``): the registry, the map-set reader in both layouts, bad input, and the DAG.

The real maps are read from ``../shared/data/coloradar_maps`` (beside the clone, as in CI); tests that need
them skip with a message when it is absent. Broken inputs are made in ``tmp_path`` from tiny synthetic
scenes, never in the shared folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from core.errors import UserError
from pipeline.config import load_workflow
from pipeline.registry import load_stages
from pipeline.runner import Runner, StagesFailed
from pipeline.sequences import SequenceInfo, load_registry, source_sequence
from sources import mapset

ROOT = Path(__file__).resolve().parents[1]
SHARED_MAPS = ROOT.parent / "shared" / "data" / "coloradar_maps"
needs_shared = pytest.mark.skipif(not (SHARED_MAPS / "index.json").is_file(),
                                  reason=f"the shared ColoRadar maps are not at {SHARED_MAPS} (CI puts shared/ "
                                         "beside the clone)")

#: RMap Table III's scenes (the paper's test split)
TABLE_III = (
    "arpg_lab_run0 arpg_lab_run1 aspen_run0 aspen_run1 aspen_run2 aspen_run3 aspen_run4 aspen_run5 "
    "ec_hallways_run0 ec_hallways_run1 edgar_army_run0 edgar_army_run1 edgar_army_run2 edgar_classroom_run0 "
    "edgar_classroom_run1 edgar_classroom_run2 outdoors_run0 outdoors_run1 outdoors_run2 outdoors_run3 "
    "outdoors_run4"
).split()


# -- registry ------------------------------------------------------------------------------------------------
def test_registry_has_the_papers_44_scenes_with_table_iii_as_test() -> None:
    maps = {s.scene: s for s in load_registry().values() if s.kind == "rmap"}
    assert len(maps) == 44
    assert sorted(s for s, info in maps.items() if info.split == "test") == sorted(TABLE_III)
    assert all(info.split == "train" for s, info in maps.items() if s not in TABLE_III)
    counts: dict[str, int] = {}
    for info in maps.values():
        assert info.name == f"rmap_{info.scene}" and info.scene.startswith(info.environment + "_run")
        counts[info.environment] = counts.get(info.environment, 0) + 1
    # Table I's environments (outdoors has 10 scenes, not the 9 Table I prints)
    assert counts == {"arpg_lab": 5, "aspen": 12, "ec_hallways": 5, "edgar_army": 6, "edgar_classroom": 6,
                      "outdoors": 10}


@needs_shared
def test_registry_split_agrees_with_the_shared_index() -> None:
    index = json.loads((SHARED_MAPS / "index.json").read_text())
    reg = {s.scene: s for s in load_registry().values() if s.kind == "rmap"}
    assert set(index) <= set(reg) and len(set(reg) - set(index)) == 3
    for scene, entry in index.items():
        assert (reg[scene].split, reg[scene].environment) == (entry["split"], entry["environment"]), scene


def _cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "COLUMNS": "250", **(env or {})}, timeout=300)


@needs_shared
def test_sequences_command_shows_map_sequences_present_or_not() -> None:
    r = _cli("sequences", env={"RMAP_ROOT": str(SHARED_MAPS)})
    assert r.returncode == 0, r.stderr
    rows = {ln.split("│")[1].strip(): ln for ln in r.stdout.splitlines() if ln.count("│") > 3}
    assert "yes" in rows["rmap_arpg_lab_run0"] and str(SHARED_MAPS / "arpg_lab_run0") in rows["rmap_arpg_lab_run0"]
    assert "no" in rows["rmap_aspen_run3"].split("│")[4]  # one of the 3 scenes not in the shared copy


# -- reading both layouts --------------------------------------------------------------------------------------
@needs_shared
def test_authors_layout_and_shared_layout_give_the_same_float64_values() -> None:
    authors = mapset.read_map_set(SHARED_MAPS / "original", "aspen_run0")
    folders = mapset.read_map_set(SHARED_MAPS, "aspen_run0")
    assert (authors.layout, folders.layout) == ("authors", "folders")
    for name in ("radar", "lidar_filtered", "lidar", "poses", "trajectory"):
        a, b = getattr(authors, name), getattr(folders, name)
        assert a.dtype == np.float64 and a.shape[1] == 3 and len(a) > 10
        assert np.array_equal(a, b), name  # bit for bit: the F-score depends on the stored values
    assert folders.split == "test" and folders.environment == "aspen" and folders.lidar_filtered_source == "map"


@needs_shared
def test_rebuilt_ground_truth_is_recorded_and_lidar_may_be_absent() -> None:
    ms = mapset.read_map_set(SHARED_MAPS, "ec_hallways_run1")
    assert ms.lidar is None and ms.lidar_filtered_source == "rebuilt" and "patches" in ms.source_detail


@needs_shared
def test_source_accepts_either_layout_for_one_scene() -> None:
    a = source_sequence(SHARED_MAPS / "original", None, "coloradar")
    b = source_sequence(SHARED_MAPS / "aspen_run0", None, "coloradar")
    assert (a.kind, a.name, a.scene) == ("rmap", "rmap_aspen_run0", "aspen_run0")
    assert (b.kind, b.scene) == ("rmap", "aspen_run0") and b.map_root() == (SHARED_MAPS / "aspen_run0").resolve()
    c = source_sequence(SHARED_MAPS, "rmap_outdoors_run0", "coloradar")
    assert c.scene == "outdoors_run0"
    with pytest.raises(UserError, match="name one with --seq rmap_<scene>"):
        source_sequence(SHARED_MAPS, None, "coloradar")


# -- bad input ------------------------------------------------------------------------------------------------
SCENE = "toy_run0"


def _write_ply(path: Path, pts: np.ndarray) -> None:
    """An ASCII, vertex-only, double-precision PLY like the authors' (Open3D) files."""
    from sources.ply import write_ply

    write_ply(path, np.asarray(pts, np.float64), binary=False)


def toy_scene(root: Path, n: int = 300) -> Path:
    """A tiny scene in the authors' layout (lattice voxel centres, poses as comma-separated x,y,z)."""
    rng = np.random.default_rng(0)
    (root / "data" / "ply").mkdir(parents=True)
    (root / "data" / "poses").mkdir(parents=True)
    for kind, m in (("radar", n), ("lidar_filtered", 4 * n), ("lidar", 5 * n)):
        _write_ply(root / "data" / "ply" / f"{SCENE}_{kind}.ply", rng.integers(-20, 20, (m, 3)) * 0.15 + 0.075)
    for name, m in ((SCENE, 10), (f"{SCENE}_all", 50)):
        np.savetxt(root / "data" / "poses" / f"{name}.txt", rng.normal(size=(m, 3)), delimiter=",")
    return root


def _run_voxel(root: Path, runs: Path) -> str:
    seq = SequenceInfo(name=f"rmap_{SCENE}", kind="rmap", scene=SCENE, source=root)
    runner = Runner(seq, runs, load_stages(), load_workflow("default"))
    with pytest.raises(StagesFailed) as info:
        runner.run(["voxel"])
    assert info.value.user_error
    store = runs / seq.name
    assert not (store / "voxel").exists() and not list(store.glob(".tmp-*"))  # nothing half-written
    message = str(info.value.first)
    assert "\n" not in message
    return message


def test_toy_scene_imports(tmp_path: Path) -> None:
    root = toy_scene(tmp_path / "scene")
    seq = SequenceInfo(name=f"rmap_{SCENE}", kind="rmap", scene=SCENE, source=root)
    outcomes = Runner(seq, tmp_path / "runs", load_stages(), load_workflow("default")).run(["voxel"])
    assert [o.action for o in outcomes] == ["ran"]
    t = pq.read_table(tmp_path / "runs" / seq.name / "voxel" / "lidar_map.parquet")
    assert t.schema.field("x").type == pa.float64() and t.num_rows == 1200


@pytest.mark.parametrize("case", ["missing", "truncated", "not_ply", "empty", "poses_columns"])
def test_bad_scene_files_give_one_line_errors(tmp_path: Path, case: str) -> None:
    root = toy_scene(tmp_path / "scene")
    ply = root / "data" / "ply"
    if case == "missing":
        target = ply / f"{SCENE}_lidar_filtered.ply"
        target.unlink()
        expect = "missing from scene"
    elif case == "truncated":
        target = ply / f"{SCENE}_radar.ply"
        raw = target.read_bytes()
        target.write_bytes(raw[: len(raw) * 2 // 3])
        expect = "unreadable PLY radar map"
    elif case == "not_ply":
        target = ply / f"{SCENE}_lidar_filtered.ply"
        target.write_text("this is not a ply file\n")
        expect = "unreadable PLY lidar_filtered map"
    elif case == "empty":
        target = ply / f"{SCENE}_radar.ply"
        _write_ply(target, np.zeros((0, 3)))
        expect = "is empty"
    else:
        target = root / "data" / "poses" / f"{SCENE}.txt"
        lines = target.read_text().splitlines()
        lines[3] = ",".join(lines[3].split(",")[:2])
        target.write_text("\n".join(lines) + "\n")
        expect = "line 4 has 2 comma-separated columns, expected 3"
    message = _run_voxel(root, tmp_path / "runs")
    assert str(target) in message and expect in message, message


def test_bad_shared_layout_files(tmp_path: Path) -> None:
    scene = tmp_path / "maps" / SCENE
    scene.mkdir(parents=True)
    rng = np.random.default_rng(1)
    for name in ("radar", "lidar_filtered", "poses", "trajectory"):
        pts = rng.normal(size=(20, 3))
        pq.write_table(pa.table({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}), scene / f"{name}.parquet")
    assert len(mapset.read_map_set(tmp_path / "maps", SCENE).radar) == 20
    pq.write_table(pa.table({"x": pa.array(np.zeros(3), pa.float32()), "y": np.zeros(3), "z": np.zeros(3)}),
                   scene / "radar.parquet")
    with pytest.raises(UserError, match="must be float64 as published"):
        mapset.read_map_set(tmp_path / "maps", SCENE)
    raw = (scene / "poses.parquet").read_bytes()
    (scene / "radar.parquet").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(UserError, match=r"radar.parquet: unreadable Parquet radar map"):
        mapset.read_map_set(tmp_path / "maps", SCENE)


def _folder_scene(maps: Path, name: str = SCENE) -> None:
    scene = maps / name
    scene.mkdir(parents=True)
    rng = np.random.default_rng(2)
    for f in ("radar", "lidar_filtered", "poses", "trajectory"):
        pts = rng.normal(size=(20, 3))
        pq.write_table(pa.table({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}), scene / f"{f}.parquet")


def test_index_json_has_one_reader_for_scenes_and_sets(tmp_path: Path) -> None:
    """``sources.mapset`` reads index.json for one scene (read_map_set), for a map set (read_index) and for the
    rebuilt-ground-truth marks (rebuilt_scenes); the callers in stages/ import it instead of parsing it."""
    maps = tmp_path / "maps"
    _folder_scene(maps)
    _folder_scene(maps, "other_run1")
    entry = {"split": "test", "environment": "toy", "lidar_filtered": {"source": "union of 3 published gt patches"}}
    (maps / "index.json").write_text(json.dumps({SCENE: entry, "other_run1": {"split": "train", "environment": "o"}}))
    ms = mapset.read_map_set(maps, SCENE)
    assert (ms.split, ms.environment, ms.lidar_filtered_source) == ("test", "toy", "rebuilt")
    info = mapset.read_index(maps)
    assert list(info) == ["other_run1", SCENE] and info[SCENE].gt_source == entry["lidar_filtered"]["source"]
    assert info["other_run1"].gt_source == "map"
    assert mapset.rebuilt_scenes(mapset.read_index_file(maps / "index.json")) == {SCENE}
    from stages.complete import maps as complete_maps
    from stages.evaluate import rmap_results

    assert not hasattr(rmap_results, "read_index") and not hasattr(complete_maps, "read_index")  # the old readers


@pytest.mark.parametrize("case, expect", [
    ("not_json", "unreadable map-set index"),
    ("list", "not a map-set index"),
    ("entry", "scene 'toy_run0' is not an object"),
])
def test_bad_index_json_is_one_line_error_for_every_reader(tmp_path: Path, case: str, expect: str) -> None:
    maps = tmp_path / "maps"
    _folder_scene(maps)
    index = maps / "index.json"
    index.write_text({"not_json": '{"toy_run0": {"split": "te', "list": "[1, 2]",
                      "entry": json.dumps({SCENE: "test"})}[case])
    for read in (lambda: mapset.read_map_set(maps, SCENE), lambda: mapset.read_index(maps),
                 lambda: mapset.read_index_file(index)):
        with pytest.raises(UserError) as info:
            read()
        message = str(info.value)
        assert message.startswith(str(index)) and expect in message and "\n" not in message, message


def test_rmap_root_unset_wrong_or_without_the_scene(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seq = SequenceInfo(name=f"rmap_{SCENE}", kind="rmap", scene=SCENE)
    monkeypatch.delenv("RMAP_ROOT", raising=False)
    assert seq.locate() is None
    with pytest.raises(UserError, match="RMAP_ROOT is not set"):
        seq.resolve_source()
    monkeypatch.setenv("RMAP_ROOT", str(tmp_path / "nowhere"))
    with pytest.raises(UserError, match=r"RMAP_ROOT=.*nowhere: no such folder"):
        seq.resolve_source()
    monkeypatch.setenv("RMAP_ROOT", str(tmp_path))
    with pytest.raises(UserError, match=r"no maps of scene 'toy_run0' \(looked for .*toy_run0_radar.ply"):
        seq.resolve_source()
    toy_scene(tmp_path)
    assert seq.locate() == tmp_path and seq.resolve_source() == tmp_path


def test_cli_map_errors_exit_2_with_one_line(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "RMAP_ROOT"}
    r = subprocess.run([sys.executable, "-m", "pipeline", "run", "all", "--seq", "rmap_arpg_lab_run0", "--runs-dir",
                        str(tmp_path / "runs")], capture_output=True, text=True, cwd=ROOT,
                       env={**env, "COLUMNS": "250"}, timeout=300)
    assert r.returncode == 2, r.stderr
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "RMAP_ROOT is not set" in err[0] and "Traceback" not in r.stderr
    assert not (tmp_path / "runs" / "rmap_arpg_lab_run0" / "voxel").exists()


def test_without_the_learn_extra_completion_is_named_not_dropped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """Without torch, `run evaluate` on a map sequence names the missing completion instead of leaving it out
    and exiting 0. Simulated by the import check saying torch is missing (torch stays)."""
    from pipeline import cli
    from stages.complete.stage import CompleteStage

    monkeypatch.setattr(CompleteStage, "missing_requirements", lambda self: ["torch", "safetensors"])
    monkeypatch.setenv("COLUMNS", "250")
    root = toy_scene(tmp_path / "scene")
    runs = tmp_path / "runs"
    install = "needs torch, safetensors, not installed (the 'learn' extra: pip install -e '.[learn]', or make demo)"

    def main(*args: str) -> int:
        monkeypatch.setattr(sys, "argv", ["pipeline", *args, "--source", str(root), "--runs-dir", str(runs)])
        try:
            cli.main()
        except SystemExit as exc:
            return int(exc.code or 0)
        return 0

    # the request needs the completion: exit 2, one line, nothing run
    assert main("run", "evaluate") == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines == [f"error: stage 'evaluate' needs 'complete' for sequence 'rmap_{SCENE}', and 'complete' cannot "
                     f"run: {install}; `pipeline run all` goes on without it"], err
    assert not (runs / f"rmap_{SCENE}").exists()
    # `run complete` names it the same way
    assert main("run", "complete") == 2
    assert f"stage 'complete' cannot run: {install}" in capsys.readouterr().err
    # run all: the workflow goes on without it, says so in the table and on stderr, exit 0
    assert main("run", "all") == 0
    err = capsys.readouterr().err
    rows = {ln.split("│")[1].strip(): ln for ln in err.splitlines() if ln.count("│") > 3}
    assert "skipped" in rows["complete"] and install in rows["complete"]
    assert "ran" in rows["evaluate"] and "without 'complete' (not installed)" in rows["evaluate"]
    assert f"warning: 'evaluate' of rmap_{SCENE} went without 'complete', which cannot run: {install}" in err
    assert (runs / f"rmap_{SCENE}" / "evaluate" / "metrics.parquet").is_file()
    assert not (runs / f"rmap_{SCENE}" / "complete").exists()


# -- the DAG on a real scene ----------------------------------------------------------------------------------
@needs_shared
def test_run_all_on_a_map_sequence_skips_the_log_stages(tmp_path: Path) -> None:
    """voxel(import), patches, complete and evaluate (map metrics only) run; the log stages are skipped."""
    pytest.importorskip("torch")
    runs = tmp_path / "runs"
    r = _cli("run", "all", "--seq", "rmap_aspen_run2", "--runs-dir", str(runs), "--set", "patches.a=0.2",
             env={"RMAP_ROOT": str(SHARED_MAPS)})
    assert r.returncode == 0, r.stderr
    for stage in ("ingest", "filter", "odometry", "slam", "plan"):
        line = next(ln for ln in r.stderr.splitlines() if ln.startswith(f"{stage} ") and "skipped" in ln)
        assert "published map set, it has no log" in line, line
    seq_dir = runs / "rmap_aspen_run2"
    assert sorted(p.name for p in seq_dir.iterdir() if p.is_dir() and not p.name.startswith(".")) == \
        ["complete", "evaluate", "patches", "voxel"]
    ours = pq.read_table(seq_dir / "voxel" / "lidar_map.parquet")
    shared = pq.read_table(SHARED_MAPS / "aspen_run2" / "lidar_filtered.parquet")
    assert all(np.array_equal(ours[c].to_numpy(), shared[c].to_numpy()) for c in "xyz")
    assert pq.read_schema(seq_dir / "complete" / "completed_map.parquet").field("x").type == pa.float64()
    m = pq.read_table(seq_dir / "evaluate" / "metrics.parquet").to_pylist()
    assert {r["section"] for r in m} == {"rmap"}
    val = {(r["method"], r["metric"]): r["value"] for r in m}
    # Table III, aspen_run2 input: CD-l1 0.641, CD-l2 1.931, D-Dist 0.300 / 0.474 / 0.779 / 1.061
    assert val[("radar_map", "cd_l1")] == pytest.approx(0.641, abs=1e-3)
    assert val[("radar_map", "cd_l2")] == pytest.approx(1.931, abs=1e-3)
    assert val[("radar_map", "ddist_p95")] == pytest.approx(1.061, abs=1e-3)
    assert val[("lidar_map", "gt_rebuilt")] == 0.0 and val[("completed_map", "patches_a")] == 0.2
    # real data completes with the voxel U-Net (data/kinds.toml); UpPoinTr runs beside it (models = auto)
    manifest = json.loads((seq_dir / "complete" / "manifest.json").read_text())
    assert manifest["params"]["model"] == "voxel" and manifest["stats"]["model"] == "voxel"
    assert val[("completed_map", "cd_l2")] == val[("completed_map_voxel", "cd_l2")] != \
        val[("completed_map_uppointr", "cd_l2")]
    assert val[("completed_map_uppointr", "n_patches")] >= 1


# -- the report hook --------------------------------------------------------------------------------------------
def test_report_builds_the_rmap_tables_from_map_sequence_records() -> None:
    """``pipeline report`` reaches the evaluate stage's report through the registry; for map sequences it
    builds RMap Tables III/IV/VI/I (``rmap_tables``) from the gathered records, rebuilt scenes marked."""
    pytest.importorskip("stages.evaluate.rmap_tables", reason="stages/evaluate/rmap_tables.py (the table builders) "
                        "is not in this tree")
    from pipeline import report as rep

    def rows(seq: str, method: str, values: dict[str, float]) -> list[dict[str, Any]]:
        return [{"seq": seq, "section": "rmap", "method": method, "metric": k, "value": v, "features": 0}
                for k, v in values.items()]

    inp = {"cd_l1": 0.329, "cd_l2": 0.651, "fscore_0.15": 0.297, "ddist_p50": 0.212, "ddist_p75": 0.367,
           "ddist_p90": 0.618, "ddist_p95": 0.808, "cd_x": 0.1, "cd_y": 0.2, "cd_z": 0.351, "lr_ratio": 4.2}
    recs = (rows("rmap_arpg_lab_run0", "radar_map", inp)
            + rows("rmap_arpg_lab_run0", "completed_map", {**inp, "cd_l2": 0.5, "patches_a": 4.0, "n_patches": 79,
                                                           "model_seconds": 30.0})
            + rows("rmap_arpg_lab_run0", "lidar_map", {"n_points": 171357, "gt_rebuilt": 0.0})
            + rows("rmap_ec_hallways_run1", "radar_map", {**inp, "cd_l2": 0.992})
            + rows("rmap_ec_hallways_run1", "lidar_map", {"n_points": 1000, "gt_rebuilt": 1.0})
            + rows("demo", "radar_map", {**inp, "cd_l2": 9.0}))
    tables = {t[0]: t for t in rep.build_tables(recs)}
    t3 = next(t for title, t in tables.items() if title.startswith("RMap Table III"))
    by_scene = {r[0]: r for r in t3[2]}
    assert "0.651" in by_scene["arpg_lab_run0"] and "0.500" in by_scene["arpg_lab_run0"]
    assert any(k.startswith("ec_hallways_run1") and "†" in k for k in by_scene)  # rebuilt ground truth marked
    assert not any("9.000" in c for r in t3[2] for c in r)  # the simulated sequence stays out
    assert any(title.startswith("RMap Table VI") for title in tables)
    md = rep.to_markdown(recs)
    assert "## RMap Table III" in md and "- Ground truth: lidar_filtered" in md
    assert not [t for t in rep.build_tables(rows("demo", "radar_map", inp)) if t[0].startswith("RMap")]
