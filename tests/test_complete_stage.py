"""The `complete` stage and its numpy helpers: normalisation round trip, downsampling, reading patches,
the paper's split, the stage on a tiny synthetic patches artifact, and importing without torch."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from core.errors import UserError
from core.paths import PROJECT_ROOT
from core.stage import StageContext
from pipeline.sequences import SequenceInfo
from schemas import read_artifact, write_artifact
from stages.complete.data import (
    denormalize,
    normalize,
    read_patches,
    resample,
    split_by_sequence,
    voxel_downsample,
)
from stages.complete.synthetic import make_patches, patches_table

SEQ = SequenceInfo(name="tinyseq", kind="source", source=Path("/nonexistent"))


def test_normalisation_round_trip_is_exact() -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(1000, 3)) * 30 + np.array([120.0, -40.0, 2.0])
    seed = np.array([118.25, -41.5, 1.75])
    for scale in (1.0, 4.3157, 25.0):
        q = normalize(pts, seed, scale)
        np.testing.assert_allclose(denormalize(q, seed, scale), pts, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(normalize(seed[None], seed, 3.0), np.zeros((1, 3)))


def test_resample_sizes() -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(10, 3))
    assert resample(pts, 10, rng) is pts
    sub = resample(pts, 4, rng)
    assert len(sub) == 4 and len({tuple(p) for p in sub}) == 4
    up = resample(pts, 25, rng)
    assert len(up) == 25 and {tuple(p) for p in up} == {tuple(p) for p in pts}


def test_crop_target() -> None:
    from stages.complete.data import Patch, crop_target

    rng = np.random.default_rng(2)
    seed = np.array([1.0, 2.0, 0.0])
    radar = seed + rng.normal(size=(200, 3))
    lidar = seed + rng.normal(size=(1000, 3)) * 3
    out = crop_target(Patch("s", 0, seed, radar, lidar), min_points=10)
    r = np.linalg.norm(radar - seed, axis=1).max()
    d = np.linalg.norm(lidar - seed, axis=1)
    np.testing.assert_array_equal(out.lidar, lidar[d <= r])
    far = Patch("s", 1, seed, seed + rng.normal(size=(5, 3)) * 0.01, lidar)  # tiny radar ball: nearest 10 kept
    got = crop_target(far, min_points=10).lidar
    assert len(got) == 10 and np.linalg.norm(got - seed, axis=1).max() <= np.sort(d)[9]


def test_voxel_downsample_matches_loop() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1, (3000, 3))
    res = 0.15
    got, counts = voxel_downsample(pts, res)
    groups: dict[tuple[int, ...], list[np.ndarray]] = {}
    for p in pts:
        groups.setdefault(tuple(np.floor(p / res).astype(int)), []).append(p)
    ref = np.array([np.mean(groups[k], axis=0) for k in sorted(groups)])
    np.testing.assert_allclose(got, ref, atol=1e-12)
    assert counts.sum() == len(pts) and len(got) == len(groups)
    empty, c = voxel_downsample(np.zeros((0, 3)), res)
    assert empty.shape == (0, 3) and c.shape == (0,)
    with pytest.raises(ValueError, match="resolution must be > 0"):
        voxel_downsample(pts, 0.0)


def test_split_by_sequence_follows_the_paper() -> None:
    runs = [(f"s{i}", f"2_23_2021_edgar_classroom_run{i}") for i in range(6)]  # run0..run5: test run0..run2
    runs += [(f"a{i}", f"12_21_2020_arpg_lab_run{i}") for i in range(5)]  # run0..run4: test run0..run2
    runs += [("o0", "outdoors_run0")]  # a single run is test
    train, test = split_by_sequence(runs)
    assert sorted(test) == ["a0", "a1", "a2", "o0", "s0", "s1", "s2"]
    assert sorted(train) == ["a3", "a4", "s3", "s4", "s5"]
    with pytest.raises(UserError, match="_run<N>"):
        split_by_sequence([("demo", "demo")])


def _write_patches(path: Path, n: int = 3, n_radar: int = 256, n_lidar: int = 512) -> list:
    patches = make_patches(n, seed=5, n_radar=n_radar, n_lidar=n_lidar, seq="tinyseq")
    write_artifact(patches_table(patches), path, "patches")
    return patches


def test_read_patches_round_trip(tmp_path: Path) -> None:
    patches = _write_patches(tmp_path / "patches.parquet")
    back = read_patches(tmp_path / "patches.parquet", "tinyseq", need_lidar=True)
    assert [p.patch for p in back] == [p.patch for p in patches]
    for a, b in zip(patches, back, strict=True):
        np.testing.assert_allclose(b.radar, a.radar, atol=1e-4)
        np.testing.assert_allclose(b.lidar, a.lidar, atol=1e-4)
        np.testing.assert_allclose(b.seed, a.seed, atol=1e-6)


def _context(tmp_path: Path, params: object, voxel_params: dict | None = None) -> StageContext:
    patches_dir = tmp_path / "patches"
    voxel_dir = tmp_path / "voxel"
    patches_dir.mkdir(exist_ok=True)
    voxel_dir.mkdir(exist_ok=True)
    if voxel_params is not None:
        (voxel_dir / "manifest.json").write_text(json.dumps({"params": voxel_params}))
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    return StageContext(stage="complete", seq=SEQ, params=params, out_dir=out,
                        input_dirs={"patches": patches_dir, "voxel": voxel_dir}, console=Console(quiet=True))


def test_stage_identity_model_puts_patches_back_in_world(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With a network that returns its input, the completed map is the downsampled radar map exactly."""
    torch = pytest.importorskip("torch")
    from stages.complete import checkpoint
    from stages.complete.checkpoint import CheckpointMeta
    from stages.complete.model import ModelConfig
    from stages.complete.stage import STAGE, CompleteParams

    class Identity(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
            return [x]

    scale = 3.7
    meta = CheckpointMeta(ModelConfig(n_input=256), scale)
    monkeypatch.setattr(checkpoint, "load_checkpoint", lambda path, device="cpu": (Identity(), meta))
    ckpt = tmp_path / "dummy.safetensors"
    ckpt.write_bytes(b"x")
    ctx = _context(tmp_path, CompleteParams(checkpoint=str(ckpt), resolution=0.15))
    patches = _write_patches(tmp_path / "patches" / "patches.parquet", n=3, n_radar=256)
    STAGE.run(ctx)
    ctx.close()
    table = read_artifact(ctx.output("completed_map.parquet"), "completed_map")
    got = np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1)
    back = read_patches(tmp_path / "patches" / "patches.parquet", "tinyseq")
    expected, _ = voxel_downsample(np.concatenate([p.radar for p in back]), 0.15)
    np.testing.assert_allclose(got, expected, atol=2e-5)
    assert ctx.stats["n_patches"] == len(patches) and ctx.stats["n_points"] == len(expected)



def test_stage_with_tiny_checkpoint(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from core.recording import entity_paths_in
    from stages.complete.checkpoint import CheckpointMeta, save_checkpoint
    from stages.complete.model import ModelConfig, UpPoinTr
    from stages.complete.stage import STAGE, CompleteParams

    torch.manual_seed(0)
    cfg = ModelConfig(n_input=256, n_query=64, up_factors=(1, 2, 2), centers=(128, 64), grouper_k=8, embed_dim=32,
                      encoder_depth=1, decoder_depth=1, num_heads=4, graph_k=4, global_dim=64, hidden_dim=64,
                      up_dim=16, up_k=4)
    ckpt = save_checkpoint(tmp_path / "tiny.safetensors", UpPoinTr(cfg), CheckpointMeta(cfg, 3.0, {"config": {}}))
    ctx = _context(tmp_path, CompleteParams(checkpoint=str(ckpt), runtime={"batch_size": 2}),
                   voxel_params={"resolution": 0.2})
    _write_patches(tmp_path / "patches" / "patches.parquet", n=3, n_radar=300)  # resampled to 256
    STAGE.run(ctx)
    ctx.close()
    table = read_artifact(ctx.output("completed_map.parquet"), "completed_map")
    assert table.num_rows == ctx.stats["n_points"] > 0
    assert ctx.stats["resolution"] == 0.2 and ctx.stats["n_points_predicted"] == 3 * 256
    assert ctx.stats["seconds_per_patch"] > 0
    assert "/world/complete" in entity_paths_in(ctx.output("complete.rrd"))
    key = STAGE.key_material(SEQ, CompleteParams(checkpoint=str(ckpt)))
    assert len(key["checkpoint_sha256"]) == 64


def test_stage_missing_checkpoint_is_user_error(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    from stages.complete.stage import STAGE, CompleteParams

    ctx = _context(tmp_path, CompleteParams(checkpoint=str(tmp_path / "nope.safetensors")))
    _write_patches(tmp_path / "patches" / "patches.parquet", n=1)
    with pytest.raises(UserError, match="checkpoint not found"):
        STAGE.run(ctx)
    ctx.close()


def test_stage_module_does_not_import_torch() -> None:
    code = ("import sys; import stages.complete.stage, stages.complete.data, pipeline.cli; "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=PROJECT_ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_shipped_checkpoint_loads() -> None:
    pytest.importorskip("torch")
    from stages.complete.checkpoint import load_checkpoint
    from stages.complete.stage import DEFAULT_CHECKPOINT

    path = PROJECT_ROOT / DEFAULT_CHECKPOINT
    if not path.exists():
        pytest.skip("no shipped checkpoint yet")
    assert path.stat().st_size < 8 * 2**20
    _, meta = load_checkpoint(path)
    assert meta.config.n_input == 2048 and meta.config.n_output == 8192 and meta.norm_scale > 0
    assert meta.train.get("train_seqs")
