"""The completion network: shapes per level, both heads, learning on one batch, checkpoints, training."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stages.complete.checkpoint import CheckpointMeta, load_checkpoint, save_checkpoint  # noqa: E402
from stages.complete.model import SIZES, ModelConfig, UpPoinTr, count_parameters  # noqa: E402
from stages.complete.ops import chamfer_l2  # noqa: E402
from stages.complete.synthetic import make_patches  # noqa: E402
from stages.complete.train import TrainConfig, build_tensors, level_targets, plot_curve, train  # noqa: E402

TINY = ModelConfig(
    n_input=256, n_query=64, up_factors=(1, 2, 2), centers=(128, 64), grouper_k=8, embed_dim=32,
    encoder_depth=2, decoder_depth=2, num_heads=4, graph_k=4, global_dim=64, hidden_dim=64, up_dim=16, up_k=4,
)


@pytest.fixture(autouse=True)
def _one_thread() -> object:
    """One torch thread: on a shared 2-core machine this is several times faster than two."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_levels_upsample_head() -> None:
    torch.manual_seed(0)
    out = UpPoinTr(TINY)(torch.randn(3, 256, 3))
    assert [tuple(o.shape) for o in out] == [(3, 64, 3), (3, 64, 3), (3, 128, 3), (3, 256, 3)]
    assert TINY.level_sizes() == [64, 64, 128, 256] and TINY.n_output == 256


def test_levels_fold_head() -> None:
    cfg = dataclasses.replace(TINY, head="fold", up_factors=(1, 4))
    out = UpPoinTr(cfg)(torch.randn(2, 256, 3))
    assert [tuple(o.shape) for o in out] == [(2, 64, 3), (2, 256, 3)]
    with pytest.raises(ValueError, match="square"):
        UpPoinTr(dataclasses.replace(TINY, head="fold", up_factors=(1, 2)))


def test_paper_sizes() -> None:
    paper = SIZES["paper"]
    assert paper.n_input == 2048 and paper.n_query == 512 and paper.up_factors == (1, 4, 4)
    assert paper.level_sizes() == [512, 512, 2048, 8192]
    assert SIZES["small"].level_sizes() == paper.level_sizes()


def test_small_size_is_small() -> None:
    n = count_parameters(UpPoinTr(SIZES["small"]))
    assert n < 2_000_000


def test_overfits_one_batch() -> None:
    """On one fixed batch the finest level's CD (eq. 1) and the total J (eq. 2) fall substantially."""
    torch.manual_seed(0)
    patches = make_patches(2, seed=0, n_radar=256, n_lidar=256)
    data = build_tensors(patches, TINY, 3.0, np.random.default_rng(0))
    model = UpPoinTr(TINY)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    targets = level_targets(data.g, data.fps_idx, TINY.level_sizes())
    fine, total = [], []
    for _ in range(100):
        levels = [chamfer_l2(p, t).mean() for p, t in zip(model(data.x), targets, strict=True)]
        loss = torch.stack(levels).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        fine.append(levels[-1].item())
        total.append(loss.item())
    assert min(fine[-10:]) < 0.4 * fine[0], fine[::10]
    assert min(total[-10:]) < 0.6 * total[0], total[::10]


def test_level_targets_are_fps_prefixes() -> None:
    patches = make_patches(2, seed=1, n_radar=256, n_lidar=256)
    data = build_tensors(patches, TINY, 3.0, np.random.default_rng(0))
    from stages.complete.ops import fps, gather_points

    t = level_targets(data.g, data.fps_idx, TINY.level_sizes())
    assert [x.shape[1] for x in t] == [64, 64, 128, 256]
    torch.testing.assert_close(t[0], gather_points(data.g, fps(data.g, 64, backend="torch")))
    assert torch.equal(t[-1], data.g)


@pytest.mark.parametrize("suffix", [".safetensors", ".pt"])
def test_checkpoint_round_trip(tmp_path: Path, suffix: str) -> None:
    torch.manual_seed(0)
    model = UpPoinTr(TINY).eval()
    meta = CheckpointMeta(TINY, 2.5, {"epochs": 3, "seqs": ["a", "b"]})
    path = save_checkpoint(tmp_path / f"m{suffix}", model, meta)
    if suffix == ".pt":  # the file must load with the safe unpickler
        blob = torch.load(path, weights_only=True)
        assert set(blob) == {"state_dict", "meta_json"}
    loaded, meta2 = load_checkpoint(path)
    assert meta2.config == TINY and meta2.norm_scale == 2.5 and meta2.train == {"epochs": 3, "seqs": ["a", "b"]}
    x = torch.randn(2, 256, 3)
    with torch.no_grad():
        for a, b in zip(model(x), loaded(x), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_checkpoint_half_precision(tmp_path: Path) -> None:
    model = UpPoinTr(TINY).eval()
    path = save_checkpoint(tmp_path / "h.safetensors", model, CheckpointMeta(TINY, 1.0), half=True)
    loaded, _ = load_checkpoint(path)
    for (k, a), b in zip(model.state_dict().items(), loaded.state_dict().values(), strict=True):
        assert b.dtype == a.dtype, k
        torch.testing.assert_close(a, b, rtol=2e-3, atol=1e-4)


def test_bad_checkpoint_is_user_error(tmp_path: Path) -> None:
    from core.errors import UserError

    with pytest.raises(UserError, match="not found"):
        load_checkpoint(tmp_path / "none.safetensors")
    from safetensors.torch import save_file

    save_file({"w": torch.zeros(2)}, str(tmp_path / "other.safetensors"), metadata={"format": "x"})
    with pytest.raises(UserError, match="not a completion-network checkpoint"):
        load_checkpoint(tmp_path / "other.safetensors")


def test_train_reduces_loss_and_writes_curve(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(SIZES, "tiny", TINY)
    tr = make_patches(4, seed=2, n_radar=256, n_lidar=256)
    va = make_patches(2, seed=3, n_radar=256, n_lidar=256)
    cfg = TrainConfig(size="tiny", epochs=6, batch_size=2, lr=2e-3, seed=0)
    res = train(tr, va, cfg, torch.device("cpu"))
    h = res.history
    assert len(h) == 6 and h[-1]["train_loss"] < h[0]["train_loss"]
    assert {"val_cd_l1_m", "val_cd_l2_m2"} <= set(h[-1])
    assert res.meta.train["n_train_patches"] == 4 and res.meta.norm_scale > 0
    png = plot_curve(h, tmp_path / "curve.png")
    assert png.stat().st_size > 1000
    # same seed, same result
    res2 = train(tr, va, cfg, torch.device("cpu"))
    assert res2.history[-1]["train_loss"] == pytest.approx(h[-1]["train_loss"], rel=1e-5)
