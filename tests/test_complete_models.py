"""Both completion models side by side: ``complete.models`` writes every model's map, the
evaluate stage scores each as its own method, and those rows equal the single-model runs' ``completed_map``
rows; the report's per-model Tables III, IV and VI carry them. A toy map on the 0.15 m lattice, a tiny
UpPoinTr checkpoint and the shipped voxel checkpoint (``auto``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from core.stage import StageContext
from pipeline.sequences import SequenceInfo
from schemas import read_artifact, write_artifact
from stages.complete.synthetic import make_patches, patches_table

torch = pytest.importorskip("torch")

SEQ = SequenceInfo(name="rmap_toy", kind="rmap", source=Path("/nonexistent"))
SIM = SequenceInfo(name="sim_toy", kind="simulated", source=Path("/nonexistent"))
RES = 0.15


def _inputs(root: Path) -> Path:
    """voxel/ (radar and lidar maps on one lattice, the trajectory) and patches/ under ``root``; the tiny
    UpPoinTr checkpoint's path."""
    from stages.complete.checkpoint import CheckpointMeta, save_checkpoint
    from stages.complete.model import ModelConfig, UpPoinTr

    rng = np.random.default_rng(0)
    vox = root / "voxel"
    vox.mkdir(parents=True)
    t = np.linspace(0, 1, 60)
    traj = np.stack([t * 5, t * 2, np.full_like(t, 1.0)], 1)
    near = traj[rng.integers(60, size=600)] + rng.normal(0, 1.5, (600, 3))
    far = traj[rng.integers(60, size=100)] + np.array([20.0, 0.0, 0.0])  # outside the band: pre-filtered away
    radar = (np.unique(np.floor(np.concatenate([near, far]) / RES), axis=0) + 0.5) * RES
    lidar_pts = traj[rng.integers(60, size=1500)] + rng.normal(0, 1.2, (1500, 3))
    lidar = (np.unique(np.floor(lidar_pts / RES), axis=0) + 0.5) * RES
    for name, pts in (("radar_map", radar), ("lidar_map", lidar)):
        write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2],
                        "log_odds": np.full(len(pts), np.nan, np.float32)}, vox / f"{name}.parquet", name)
    write_artifact({"x": traj[:, 0], "y": traj[:, 1], "z": traj[:, 2]}, vox / "map_trajectory.parquet",
                   "map_trajectory")
    (vox / "manifest.json").write_text(json.dumps({"params": {"resolution": RES},
                                                   "stats": {"map_set": {"lidar_filtered_source": "map"}}}))
    (root / "patches").mkdir()
    write_artifact(patches_table(make_patches(3, seed=5, n_radar=300, n_lidar=512, seq=SEQ.name)),
                   root / "patches" / "patches.parquet", "patches")
    (root / "patches" / "manifest.json").write_text(json.dumps({"params": {"a": 4}}))
    torch.manual_seed(0)
    cfg = ModelConfig(n_input=256, n_query=64, up_factors=(1, 2, 2), centers=(128, 64), grouper_k=8, embed_dim=32,
                      encoder_depth=1, decoder_depth=1, num_heads=4, graph_k=4, global_dim=64, hidden_dim=64,
                      up_dim=16, up_k=4)
    return save_checkpoint(root / "tiny.safetensors", UpPoinTr(cfg), CheckpointMeta(cfg, 3.0, {"config": {}}))


def _complete(root: Path, name: str, seq: SequenceInfo = SEQ, **params: Any) -> tuple[Path, dict[str, Any]]:
    """Run the complete stage into ``root/name`` and write its manifest as the runner does."""
    from stages.complete.stage import STAGE, CompleteParams

    out = root / name
    out.mkdir()
    p = CompleteParams(runtime={"batch_size": 2, "threads": 1}, **params)
    ctx = StageContext(stage="complete", seq=seq, params=p, out_dir=out,
                       input_dirs={n: root / n for n in STAGE.input_stages(p)}, console=Console(quiet=True))
    STAGE.run(ctx)
    ctx.close()
    (out / "manifest.json").write_text(json.dumps({"params": p.model_dump(mode="json"), "stats": ctx.stats}))
    return out, ctx.stats


def _evaluate(root: Path, complete_dir: Path) -> list[dict[str, Any]]:
    """The evaluate stage's rmap section on one complete output; its records."""
    from stages.evaluate.stage import STAGE, EvaluateParams

    out = complete_dir.with_name(complete_dir.name + "_eval")
    out.mkdir()
    ctx = StageContext(stage="evaluate", seq=SEQ, params=EvaluateParams(sections=["rmap"]), out_dir=out,
                       input_dirs={"voxel": root / "voxel", "complete": complete_dir, "patches": root / "patches"},
                       console=Console(quiet=True))
    STAGE.run(ctx)
    ctx.close()
    t = read_artifact(out / "metrics.parquet", "metrics")
    return [{"seq": s, "method": m, "metric": k, "value": v, "section": sec} for s, m, k, v, sec in
            zip(*(t[c].to_pylist() for c in ("seq", "method", "metric", "value", "section")), strict=True)]


def _rows(records: list[dict[str, Any]], method: str) -> dict[str, float]:
    return {r["metric"]: r["value"] for r in records if r["method"] == method}


def _xyz(path: Path) -> np.ndarray:
    t = read_artifact(path, "completed_map")
    return np.stack([t[c].to_numpy() for c in "xyz"], 1)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("models")
    ckpt = str(_inputs(root))
    both, both_stats = _complete(root, "both", checkpoint=ckpt, models=["uppointr", "voxel"])
    up, _ = _complete(root, "single_uppointr", checkpoint=ckpt, models=["uppointr"])
    vox, _ = _complete(root, "single_voxel", model="voxel", models=["voxel"])
    return {"root": root, "both": both, "both_stats": both_stats, "uppointr": up, "voxel": vox,
            "rec_both": _evaluate(root, both), "rec_up": _evaluate(root, up), "rec_vox": _evaluate(root, vox)}


def test_models_write_every_map_and_the_configured_one_as_completed_map(runs: dict[str, Any]) -> None:
    both = runs["both"]
    assert sorted(p.name for p in both.glob("*.parquet")) == ["completed_map.parquet", "completed_map_voxel.parquet",
                                                             "radar_map_band.parquet"]
    np.testing.assert_array_equal(_xyz(both / "completed_map.parquet"),
                                  _xyz(runs["uppointr"] / "completed_map.parquet"))
    np.testing.assert_array_equal(_xyz(both / "completed_map_voxel.parquet"),
                                  _xyz(runs["voxel"] / "completed_map.parquet"))
    stats = runs["both_stats"]
    assert stats["model"] == "uppointr" and set(stats["models"]) == {"uppointr", "voxel"}
    assert stats["models"]["voxel"]["file"] == "completed_map_voxel.parquet"
    assert stats["models"]["voxel"]["n_parameters"] == 531_905 and stats["models"]["uppointr"]["n_parameters"] > 0
    band = _xyz(both / "radar_map_band.parquet")
    assert 0 < len(band) == stats["n_radar_band"] and band[:, 0].max() < 15  # the far cluster is cut


def test_per_model_rows_equal_the_single_model_runs(runs: dict[str, Any]) -> None:
    both, up, vox = runs["rec_both"], runs["rec_up"], runs["rec_vox"]
    single_up, single_vox = _rows(up, "completed_map"), _rows(vox, "completed_map")
    map_keys = ("cd_l1", "cd_l2", "fscore_0.15", "fscore_0.15_robust", "ddist_p95", "cd_z", "lr_ratio", "n_pred")
    for k in map_keys:
        assert _rows(both, "completed_map_uppointr")[k] == single_up[k]
        assert _rows(both, "completed_map_voxel")[k] == single_vox[k]
        assert _rows(both, "completed_map")[k] == single_up[k]  # the configured model
    assert _rows(both, "radar_map_band")["cd_l2"] < _rows(both, "radar_map")["cd_l2"]  # the far cluster was cut
    assert _rows(both, "completed_map_voxel")["n_parameters"] == 531_905
    assert _rows(both, "completed_map_uppointr")["n_parameters"] == single_up["n_parameters"] > 0
    assert _rows(both, "completed_map_uppointr")["n_patches"] == 3
    assert not _rows(up, "completed_map_voxel") and not _rows(vox, "completed_map_uppointr")


def test_report_tables_have_one_row_per_model(runs: dict[str, Any]) -> None:
    from stages.evaluate import rmap_tables as rt
    from stages.evaluate.report import map_set_results, map_set_tables

    seqs = {SEQ.name: {"kind": "rmap", "scene": "arpg_lab_run0"}}
    results = map_set_results(runs["rec_both"], seqs)
    titles = [t.title for t in map_set_tables(runs["rec_both"], seqs)]
    assert any("Table III, one row per map" in t for t in titles) and any("Table IV, one row" in t for t in titles)
    t3 = rt.table_iii_models(results)
    maps = [r[1] for r in t3.rows if r[0] == "arpg_lab_run0"]
    assert maps == ["paper input", "input", "pre-filtered input", "UpPoinTr", "voxel U-Net", "paper RMap"]
    vox = next(r for r in t3.rows if r[0] == "arpg_lab_run0" and r[1] == "voxel U-Net")
    single = _rows(runs["rec_vox"], "completed_map")
    assert vox[2:6] == [rt.fmt(single[k]) for k in ("cd_l1", "cd_l2", "fscore_0.15", "fscore_0.15_robust")]
    overall_vox = next(r for r in t3.rows if r[0] == "**Overall**" and r[1] == "voxel U-Net")
    assert overall_vox[2:6] == vox[2:6]  # one scene: Overall = its row
    t4 = rt.table_iv_models(results)
    assert [r[0] for r in t4.rows] == ["paper input", "input", "pre-filtered input", "UpPoinTr", "voxel U-Net",
                                       "paper RMap"]
    t6 = rt.table_vi(results)
    ours = {r[1]: r for r in t6.rows if r[0] == "4" and r[1].startswith("ours")}
    assert set(ours) == {"ours UpPoinTr", "ours voxel U-Net"}
    assert ours["ours voxel U-Net"][-1] == "531,905" and ours["ours UpPoinTr"][7] == "3"


def test_simulated_sequences_run_only_the_configured_model(tmp_path: Path) -> None:
    from stages.complete.stage import STAGE, CompleteParams

    p = CompleteParams()
    assert STAGE.models_to_run("simulated", p) == ["uppointr"]
    assert STAGE.models_to_run("rmap", p) == ["uppointr", "voxel"]
    assert STAGE.models_to_run("rmap", CompleteParams(model="voxel")) == ["voxel", "uppointr"]
    assert STAGE.models_to_run("simulated", CompleteParams(models=["voxel"])) == ["uppointr", "voxel"]
    assert "model_checkpoints_sha256" not in STAGE.key_material(SIM, p)  # the demo's cache key is as before
    assert set(STAGE.key_material(SEQ, p)["model_checkpoints_sha256"]) == {"voxel"}


def test_top_views_show_both_models(runs: dict[str, Any], tmp_path: Path) -> None:
    from stages.evaluate.rmap_results import MODEL_COLUMNS, load_scene_maps, plot_run_top_views

    seq = tmp_path / "runs" / "rmap_arpg_lab_run0"
    seq.mkdir(parents=True)
    (seq / "voxel").symlink_to(runs["root"] / "voxel")
    (seq / "complete").symlink_to(runs["both"])
    maps = load_scene_maps(seq)
    assert all(m in maps for m, _ in MODEL_COLUMNS)
    np.testing.assert_array_equal(maps["completed_map_voxel"], _xyz(runs["voxel"] / "completed_map.parquet"))
    fig = plot_run_top_views(tmp_path / "runs", tmp_path / "top.png", ("rmap_arpg_lab_run0",))
    assert fig is not None and fig.stat().st_size > 10_000


@pytest.mark.parametrize(("kind", "model"), [("rmap", "voxel"), ("coloradar", "voxel"), ("source", "voxel"),
                                             ("simulated", "voxel")])
def test_every_sequence_kind_completes_with_the_voxel_model_by_default(tmp_path: Path, kind: str, model: str
                                                                      ) -> None:
    """The sequence kind's defaults (``data/kinds.toml``) pick the completion model, the voxel U-Net, over the
    stage's own default (the paper's UpPoinTr); ``--set`` still overrides them."""
    from pipeline.config import Workflow
    from pipeline.registry import load_stages
    from pipeline.runner import Runner

    seq = SequenceInfo(name=f"{kind}_toy", kind=kind, source=Path("/nonexistent"),
                       scene="arpg_lab_run0" if kind == "rmap" else None)
    reg = load_stages()
    wf = Workflow("t", ["complete"])
    assert Runner(seq, tmp_path, reg, wf).params("complete").model == model  # type: ignore[attr-defined]
    override = Runner(seq, tmp_path, reg, wf, {"complete": {"model": "uppointr"}})
    assert override.params("complete").model == "uppointr"  # type: ignore[attr-defined]
