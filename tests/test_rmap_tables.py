"""RMap side-by-side tables, the result collector and the top-view figure on small synthetic inputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core import map_metrics as mm
from core import rmap_paper as paper
from schemas import write_artifact
from sources.mapset import rebuilt_scenes
from stages.evaluate import rmap_tables as rt
from stages.evaluate.rmap_figures import plot_top_views
from stages.evaluate.rmap_results import (
    collect_scene_results,
    load_scene_maps,
    plot_run_top_views,
    score_maps,
)

SCENES = ("arpg_lab_run0", "aspen_run1", "outdoors_run4")


def _metrics(base: float) -> dict[str, float]:
    return {"cd_l1": base, "cd_l2": 2 * base, "fscore_0.15": 1 - base, "fscore_0.15_robust": 0.5 - base / 2,
            "ddist_p50": base / 4, "ddist_p75": base / 2, "ddist_p90": base, "ddist_p95": 2 * base,
            "cd_x": base / 2, "cd_y": base / 2, "cd_z": base, "lr_ratio": 10 * base}


def _results(**kw: object) -> list[rt.SceneResult]:
    return [rt.SceneResult(scene=s, seq=f"rmap_{s}", rebuilt=(i == 1),
                           metrics={rt.INPUT: _metrics(0.1 * (i + 1)), rt.COMPLETED: _metrics(0.05 * (i + 1))},
                           **kw)  # type: ignore[arg-type]
            for i, s in enumerate(SCENES)]


def _row(table: rt.Table, first: str) -> list[str]:
    return next(r for r in table.rows if r[0] == first)


def test_table_iii_rows_overall_and_marks() -> None:
    t = rt.table_iii(_results())
    assert len(t.headers) == 17 and t.headers[5] == "ours input CD-l1" and t.headers[13] == "ours completed CD-l1"
    assert [r[0] for r in t.rows[:21]][:2] == ["arpg_lab_run0", "arpg_lab_run1"]  # the paper's 21 rows, in order
    assert _row(t, "arpg_lab_run0")[1:4] == ["0.329", "0.651", "0.297"]  # paper input
    assert _row(t, "arpg_lab_run0")[5:8] == ["0.100", "0.200", "0.900"]  # ours input
    assert _row(t, "aspen_run1 †")[13] == "0.100"  # rebuilt scene marked; ours completed CD-l1 = 0.05 * 2
    assert _row(t, "aspen_run3")[5] == "–"  # a scene without results
    overall = _row(t, "**Overall**")
    assert overall[1:4] == ["0.477", "1.065", "0.193"]
    assert overall[5] == rt.fmt(np.mean([0.1, 0.2, 0.3]))  # ours Overall = the mean of our rows
    assert overall[13] == rt.fmt(np.mean([0.05, 0.10, 0.15]))
    assert overall[8] == rt.ddist_cell([np.mean([0.1 * k * f for k in (1, 2, 3)]) for f in (0.25, 0.5, 1, 2)])
    same = _row(t, "paper, same scenes")
    assert same[1] == rt.fmt(np.mean([paper.TABLE_III[s].input.cd_l1 for s in SCENES]))
    text = t.markdown()
    assert "18 of the paper's" not in text and "3 of the paper's 21 test scenes" in text
    assert "† ground truth rebuilt" in text and "aspen_run1" in text and "mean of the rows' percentiles" in text
    part = _results()
    part[0] = rt.SceneResult(part[0].scene, {rt.INPUT: part[0].metrics[rt.INPUT]})
    t2 = rt.table_iii(part)
    assert _row(t2, "**Overall**")[13] == rt.fmt(np.mean([0.10, 0.15]))  # over the scenes that have one
    assert "the 2 scenes with a completed map (input: 3)" in t2.markdown()


def test_overall_ddist_pools_distances_when_every_row_has_them() -> None:
    rng = np.random.default_rng(3)
    d = {s: rng.exponential(0.3, size=50 + 40 * i) for i, s in enumerate(SCENES)}
    res = [rt.SceneResult(r.scene, r.metrics, rebuilt=r.rebuilt, distances={rt.INPUT: d[r.scene]})
           for r in _results()]
    o, pooled = rt.overall(res, rt.INPUT)
    assert pooled
    assert [o[k] for k in rt.DDIST_KEYS] == pytest.approx(np.percentile(np.concatenate(list(d.values())),
                                                                        [50, 75, 90, 95]))
    assert o["cd_l1"] == pytest.approx(0.2)
    _, pooled_c = rt.overall(res, rt.COMPLETED)  # no distances for the completed maps: mean of rows
    assert not pooled_c
    assert "pooled over the scenes" not in rt.table_iii(res).markdown()


def test_table_iv_means_beside_the_paper() -> None:
    t = rt.table_iv(_results())
    inp = _row(t, "Input map")
    assert inp[1:3] == ["1.065", rt.fmt(np.mean([0.2, 0.4, 0.6]))]  # CD-l2 paper | ours
    assert inp[3:5] == ["0.267", rt.fmt(np.mean([0.05, 0.1, 0.15]))]  # CD^x
    assert "same scenes" not in t.markdown() and "3 of the paper's 21" in t.markdown()
    assert _row(t, "RMap / ours completed")[7:9] == ["0.080", rt.fmt(np.mean([0.05, 0.1, 0.15]))]  # CD^z


def test_table_vi_groups_runs_by_a_test() -> None:
    runs = []
    for a, n, secs in ((4.0, 10, 1.5), (2.0, 5, 0.5)):
        runs += [rt.SceneResult(r.scene, r.metrics, rebuilt=r.rebuilt, a_test=a, n_patches=n + i,
                                inference_s=secs, device="cpu") for i, r in enumerate(_results())]
    t = rt.table_vi(runs)
    assert [r[0] for r in t.rows if r[1] == "paper"] == ["1", "2", "4", "8"]
    ours4 = next(r for r in t.rows if r[:2] == ["4", "ours"])
    assert ours4[2] == "3" and ours4[7] == str(10 + 11 + 12) and ours4[8] == "4.5" and ours4[9] == "cpu"
    assert ours4[3] == rt.fmt(np.mean([0.05, 0.1, 0.15]))  # completed maps' mean CD-l1
    paper4 = next(r for r in t.rows if r[:2] == ["4", "paper"])
    assert paper4[7] == "1262" and paper4[8] == "56"
    assert next(r for r in t.rows if r[:2] == ["1", "ours"])[2] == "0"  # a paper row without our run


def test_table_i_mean_of_ratios_per_environment() -> None:
    res = _results()
    extra = rt.SceneResult("arpg_lab_run2", {rt.INPUT: _metrics(0.5)})
    t = rt.table_i([*res, extra])
    arpg = _row(t, "arpg_lab")
    assert arpg[1:5] == ["5", "2", "4.28", rt.fmt(np.mean([1.0, 5.0]), 2)]
    assert _row(t, "**Overall**")[2] == "4"


def test_collect_from_run_folders(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    # values exact in float32, so the comparison holds whether the map schemas store float32 or float64
    gt = rng.uniform(0, 4, size=(300, 3)).astype(np.float32).astype(np.float64)
    radar = (gt[::3] + 0.05).astype(np.float32).astype(np.float64)
    completed = (gt[::2] + 0.01).astype(np.float32).astype(np.float64)
    seq = tmp_path / "rmap_arpg_lab_run0"
    for stage in ("voxel", "patches", "complete", "evaluate"):
        (seq / stage).mkdir(parents=True)
    for name, pts in (("radar_map", radar), ("lidar_map", gt)):
        write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "log_odds": np.ones(len(pts))},
                       seq / "voxel" / f"{name}.parquet", name)
    write_artifact({"x": completed[:, 0], "y": completed[:, 1], "z": completed[:, 2]},
                   seq / "complete" / "completed_map.parquet", "completed_map")
    recs = [("radar_map", k, v) for k, v in mm.map_metrics(radar, gt).items()]
    recs += [("completed_map", k, v) for k, v in mm.map_metrics(completed, gt).items()]
    recs += [("lidar_map", "n_points", float(len(gt))), ("rich_slam", "ate_pos_rmse_m", 0.3)]
    write_artifact({"seq": [seq.name] * len(recs), "method": [r[0] for r in recs], "metric": [r[1] for r in recs],
                    "value": np.array([r[2] for r in recs])}, seq / "evaluate" / "metrics.parquet", "metrics")
    (seq / "patches" / "manifest.json").write_text(json.dumps({"params": {"a": 4.0}, "stats": {"n_seeds": 7}}))
    (seq / "complete" / "manifest.json").write_text(json.dumps(
        {"stats": {"n_patches": 7, "model_seconds": 2.5, "device": "cpu"}}))
    (tmp_path / "rmap_aspen_run0").mkdir()  # not evaluated yet: skipped with a warning
    with pytest.warns(UserWarning, match="rmap_aspen_run0"):
        res = collect_scene_results(tmp_path, rebuilt={"arpg_lab_run0"}, with_distances=True)
    assert len(res) == 1
    r = res[0]
    assert (r.scene, r.seq, r.rebuilt, r.a_test, r.n_patches, r.inference_s, r.device) == (
        "arpg_lab_run0", "rmap_arpg_lab_run0", True, 4.0, 7, 2.5, "cpu")
    assert "rich_slam" not in r.metrics and r.get(rt.COMPLETED, "cd_l1") == pytest.approx(
        mm.chamfer_l1(completed, gt))
    assert r.distances[rt.INPUT] == pytest.approx(mm.nearest(gt, radar)[0])
    direct = score_maps("rmap_arpg_lab_run0", load_scene_maps(seq), rebuilt=True)
    assert direct.get(rt.INPUT, "fscore_0.15") == r.get(rt.INPUT, "fscore_0.15")
    assert direct.get(rt.INPUT, "lr_ratio") == pytest.approx(len(gt) / len(radar))
    with pytest.warns(UserWarning, match="rmap_aspen_run0 left out of the top-view figure"):
        fig = plot_run_top_views(tmp_path, tmp_path / "top.png", ("rmap_arpg_lab_run0", "rmap_aspen_run0"))
    assert fig is not None and fig.stat().st_size > 0
    text = rt.report(res, sweep=res, figure="top.png")
    for title in ("Table I:", "Table III:", "Table IV:", "Table VI:", "](top.png)"):
        assert title in text
    assert "| arpg_lab_run0 † |" in text
    assert rebuilt_scenes({"a": {"lidar_filtered": {"source": "map"}},
                           "b": {"lidar_filtered": {"source": "union of 3 published gt patches"}}}) == {"b"}


def test_top_view_figure(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    maps = {s: {rt.INPUT: rng.normal(size=(200, 3)), rt.LIDAR: rng.normal(size=(900, 3))} for s in SCENES}
    maps[SCENES[0]][rt.COMPLETED] = rng.normal(size=(500, 3))
    out = plot_top_views(tmp_path / "top.png", maps, "three scenes", z_max=0.8)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and list(tmp_path.iterdir()) == [out]
    with pytest.raises(ValueError, match="at least one scene"):
        plot_top_views(tmp_path / "none.png", {})
