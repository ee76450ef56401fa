"""The `complete` stage with ``model = voxel``: output on the lattice inside the band, checkpoint
choice by model, and the bad inputs (wrong model kind, resolution, no voxels, maps off one lattice,
no trajectory) as one-line errors with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from core.errors import UserError
from core.stage import StageContext
from pipeline.sequences import SequenceInfo
from schemas import read_artifact, write_artifact

torch = pytest.importorskip("torch")

SEQ = SequenceInfo(name="rmap_toy", kind="rmap", source=Path("/nonexistent"))
RES = 0.15


def _maps(tmp_path: Path, radar: np.ndarray | None = None, lidar_shift: float = 0.0, trajectory: bool = True,
          resolution: float = RES) -> Path:
    rng = np.random.default_rng(0)
    vox = tmp_path / "voxel"
    vox.mkdir(exist_ok=True)
    t = np.linspace(0, 1, 50)
    traj = np.stack([t * 4, t * 2, np.full_like(t, 1.0)], 1)
    if radar is None:
        keys = np.unique(np.floor((traj[rng.integers(50, size=300)] + rng.normal(0, 1.0, (300, 3))) / RES), axis=0)
        radar = np.round((keys + 0.5) * RES, 6)
    lidar = np.round((np.unique(np.floor(radar / RES), axis=0) + 0.5) * RES, 6) + lidar_shift
    for name, pts in (("radar_map", radar), ("lidar_map", lidar)):
        write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "log_odds": np.full(len(pts), np.nan,
                                                                                               np.float32)},
                       vox / f"{name}.parquet", name)
    if trajectory:
        write_artifact({"x": traj[:, 0], "y": traj[:, 1], "z": traj[:, 2]}, vox / "map_trajectory.parquet",
                       "map_trajectory")
    (vox / "manifest.json").write_text(json.dumps({"params": {"resolution": resolution}}))
    return vox


def _ckpt(tmp_path: Path, resolution: float = RES) -> Path:
    from stages.complete.voxel_checkpoint import VoxelMeta, save_voxel_checkpoint
    from stages.complete.voxel_grid import Band
    from stages.complete.voxel_net import VoxelNetConfig, VoxelUNet

    torch.manual_seed(0)
    model = VoxelUNet(VoxelNetConfig(widths=(3, 4)))
    with torch.no_grad():
        model.head.weight.mul_(4.0)
    return save_voxel_checkpoint(tmp_path / "voxel.safetensors", model,
                                 VoxelMeta(model.config, resolution, 0.3, Band(2.0, -1.0, 1.5)), half=False)


def _context(tmp_path: Path, params: object) -> StageContext:
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    return StageContext(stage="complete", seq=SEQ, params=params, out_dir=out,
                        input_dirs={"voxel": tmp_path / "voxel"}, console=Console(quiet=True))


def test_voxel_model_writes_lattice_voxels_inside_the_band(tmp_path: Path) -> None:
    from stages.complete.stage import STAGE, CompleteParams
    from stages.complete.voxel_grid import Band, in_band, lattice_keys

    _maps(tmp_path)
    params = CompleteParams(model="voxel", checkpoint=str(_ckpt(tmp_path)), runtime={"tile": 16})
    assert STAGE.input_stages(params) == ("patches", "voxel")  # models = auto may add UpPoinTr
    params = CompleteParams(model="voxel", models=["voxel"], checkpoint=str(_ckpt(tmp_path)), runtime={"tile": 16})
    assert STAGE.input_stages(params) == ("voxel",)
    ctx = _context(tmp_path, params)
    STAGE.run(ctx)
    ctx.close()
    t = read_artifact(ctx.output("completed_map.parquet"), "completed_map")
    pts = np.stack([t.column(c).to_numpy() for c in "xyz"], axis=1)
    assert len(pts) == ctx.stats["n_points"] > 0
    lattice_keys(pts, RES)  # on the lattice
    traj = np.stack([np.linspace(0, 4, 50), np.linspace(0, 2, 50), np.ones(50)], 1)
    assert in_band(pts, traj, Band(2.0, -1.0, 1.5)).all()
    assert ctx.stats["model"] == "voxel" and ctx.stats["prefilter"] == "band" and ctx.stats["n_tiles"] > 1


def test_voxel_bf16_option_reaches_the_network(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``complete.runtime.bf16`` runs the network under bfloat16 autocast: passed to ``predict_tiles``, recorded in the
    stats, and the map it writes is the float32 map to within a few voxels (probabilities near the threshold
    may cross it)."""
    from stages.complete import voxel_net
    from stages.complete.stage import STAGE, CompleteParams

    seen: list[bool] = []
    real = voxel_net.predict_tiles

    def spy(*args: object, **kwargs: object) -> object:
        seen.append(bool(kwargs.get("bf16")))
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(voxel_net, "predict_tiles", spy)
    _maps(tmp_path)
    maps = {}
    for bf16 in (False, True):
        params = CompleteParams(model="voxel", models=["voxel"], checkpoint=str(_ckpt(tmp_path)),
                                runtime={"tile": 16, "bf16": bf16})
        ctx = _context(tmp_path, params)
        STAGE.run(ctx)
        ctx.close()
        assert ctx.stats["bf16"] is bf16
        t = read_artifact(ctx.output("completed_map.parquet"), "completed_map")
        maps[bf16] = {tuple(p) for p in np.round(np.stack([t.column(c).to_numpy() for c in "xyz"], 1), 4)}
    assert seen == [False, True]
    assert len(maps[True] ^ maps[False]) <= 0.02 * len(maps[False])


@pytest.mark.parametrize("case", ["uppointr_ckpt", "resolution", "empty", "off_lattice", "no_trajectory"])
def test_voxel_bad_inputs_are_one_line_errors_and_write_nothing(tmp_path: Path, case: str) -> None:
    from stages.complete.checkpoint import CheckpointMeta, save_checkpoint
    from stages.complete.model import ModelConfig, UpPoinTr
    from stages.complete.stage import STAGE, CompleteParams

    ckpt = _ckpt(tmp_path)
    match = {"uppointr_ckpt": "uppointr checkpoint, not a voxel model", "resolution": "trained for 0.15 m voxels",
             "empty": "has no voxels", "off_lattice": "one lattice", "no_trajectory": "no recorded trajectory"}[case]
    if case == "uppointr_ckpt":
        cfg = ModelConfig(n_input=256, n_query=64, up_factors=(1, 2, 2), centers=(128, 64), grouper_k=8,
                          embed_dim=32, encoder_depth=1, decoder_depth=1, num_heads=4, graph_k=4, global_dim=64,
                          hidden_dim=64, up_dim=16, up_k=4)
        ckpt = save_checkpoint(tmp_path / "up.safetensors", UpPoinTr(cfg), CheckpointMeta(cfg, 3.0, {}))
    _maps(tmp_path, radar=np.zeros((0, 3)) if case == "empty" else None,
          lidar_shift=0.05 if case == "off_lattice" else 0.0, trajectory=case != "no_trajectory",
          resolution=0.2 if case == "resolution" else RES)
    ctx = _context(tmp_path, CompleteParams(model="voxel", checkpoint=str(ckpt), runtime={"tile": 16}))
    with pytest.raises(UserError, match=match) as err:
        STAGE.run(ctx)
    ctx.close()
    assert "\n" not in str(err.value)
    assert not (tmp_path / "out" / "completed_map.parquet").exists()


def test_uppointr_model_refuses_a_voxel_checkpoint(tmp_path: Path) -> None:
    from stages.complete.stage import STAGE, CompleteParams

    _maps(tmp_path)
    (tmp_path / "patches").mkdir()
    ctx = StageContext(stage="complete", seq=SEQ, params=CompleteParams(checkpoint=str(_ckpt(tmp_path))),
                       out_dir=tmp_path / "out", input_dirs={"voxel": tmp_path / "voxel",
                                                             "patches": tmp_path / "patches"},
                       console=Console(quiet=True))
    with pytest.raises(UserError, match="a voxel_unet checkpoint, not UpPoinTr"):
        STAGE.run(ctx)
    ctx.close()


def test_auto_checkpoint_by_kind_and_model() -> None:
    from stages.complete.stage import DEFAULT_CHECKPOINT, REAL_CHECKPOINT, VOXEL_CHECKPOINT, default_checkpoint

    assert default_checkpoint("simulated") == DEFAULT_CHECKPOINT
    assert default_checkpoint("rmap") == REAL_CHECKPOINT
    assert default_checkpoint("rmap", "voxel") == VOXEL_CHECKPOINT
    assert default_checkpoint("simulated", "voxel") == VOXEL_CHECKPOINT


def test_shipped_voxel_checkpoint_loads_with_its_validation_choices() -> None:
    from core.paths import PROJECT_ROOT
    from stages.complete.stage import VOXEL_CHECKPOINT
    from stages.complete.voxel_checkpoint import checkpoint_kind, load_voxel_checkpoint

    path = PROJECT_ROOT / VOXEL_CHECKPOINT
    assert checkpoint_kind(path) == "voxel_unet"
    _model, meta = load_voxel_checkpoint(path)
    assert meta.resolution == RES and 0 < meta.threshold < 1 and meta.union_radar
    assert not set(meta.train["val_scenes"]) & set(meta.train["train_scenes"])
    # the union (and its gate) was decided on the validation scenes by the gate rule, which the checkpoint records
    gate = meta.train["gate_decision"]
    assert gate["val_scenes"] == meta.train["val_scenes"]
    assert gate["gate"] == meta.union_gate
    united = gate["overall"][f"voxel + prefiltered radar, gate {meta.union_gate:.2f}"]
    assert united["cd_l2"] < gate["overall"]["voxel"]["cd_l2"]


def test_a_threshold_overrides_the_checkpoints_and_keeps_the_gate_below_it(tmp_path: Path) -> None:
    """``complete.threshold``: the map is the checkpoint's decision at that threshold (a higher one keeps a subset
    of the voxels), recorded in the stats; the union gate never exceeds it."""
    from stages.complete.stage import STAGE, CompleteParams

    _maps(tmp_path)
    ckpt = str(_ckpt(tmp_path))
    maps = {}
    for name, thr in (("default", None), ("low", 0.05), ("high", 0.95)):
        (tmp_path / name).mkdir()
        ctx = _context(tmp_path / name, CompleteParams(model="voxel", models=["voxel"], checkpoint=ckpt,
                                                        runtime={"tile": 16}, threshold=thr))
        ctx.input_dirs["voxel"] = tmp_path / "voxel"
        STAGE.run(ctx)
        ctx.close()
        t = read_artifact(ctx.output("completed_map.parquet"), "completed_map")
        maps[name] = {tuple(np.round(r, 4)) for r in np.stack([t.column(c).to_numpy() for c in "xyz"], 1)}
        if thr is not None:
            assert ctx.stats["threshold"] == thr and ctx.stats["union_gate"] <= thr
    assert maps["high"] <= maps["default"] <= maps["low"] and maps["high"] != maps["low"]
