"""Training pieces of the voxel model: augmentation by the lattice's symmetries, the imbalance-aware loss,
the learning-rate schedule, validation counts, the union rule (decided on validation scenes only)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stages.complete.train_voxel import (  # noqa: E402
    Crop,
    SceneData,
    VoxelTrainConfig,
    augment,
    coverage_loss,
    loss_fn,
    lr_at,
    make_crop,
    validate,
)
from stages.complete.voxel_grid import Band  # noqa: E402
from stages.complete.voxel_net import VoxelNetConfig, VoxelUNet  # noqa: E402


def _scene() -> SceneData:
    rng = np.random.default_rng(0)
    t = np.linspace(0, 1, 40)
    traj = np.stack([t * 3, t, np.ones_like(t)], 1)
    lid = np.unique(np.floor((traj[rng.integers(40, size=400)] + rng.normal(0, 0.8, (400, 3))) / 0.15), axis=0)
    return SceneData("toy", lid[::3].astype(np.int64), lid.astype(np.int64), traj)


def test_augment_keeps_features_labels_and_mask_aligned() -> None:
    cfg = VoxelTrainConfig(crop_xy=32, crop_z=16, margin=4)
    crop = make_crop(_scene(), np.array([1.5, 0.5, 1.0]), cfg, Band(2.0, -1.0, 1.0), 8)
    rng = np.random.default_rng(3)
    for _ in range(6):
        a = augment(crop, rng)
        assert a.features.shape == crop.features.shape and a.label.shape == crop.label.shape
        assert a.label.sum() == crop.label.sum() and a.mask.sum() == crop.mask.sum()
        # a radar voxel stays where its label is: the same symmetry moved both
        assert np.sum(a.features[0] * a.label) == np.sum(crop.features[0] * crop.label)


def test_loss_prefers_the_truth_and_ignores_unmasked_voxels() -> None:
    lab = torch.zeros(1, 8, 8, 8)
    lab[0, 2:4, 2:4, 2:4] = 1
    mask = torch.ones_like(lab)
    mask[0, 6:] = 0
    good = (lab * 2 - 1) * 12
    bad = -good
    assert loss_fn(good, lab, mask, 2.0, 1.0) < 0.05 < loss_fn(bad, lab, mask, 2.0, 1.0)
    noisy = good.clone()
    noisy[0, 6:] = 10.0  # outside the mask: no effect
    assert torch.isclose(loss_fn(noisy, lab, mask, 2.0, 1.0), loss_fn(good, lab, mask, 2.0, 1.0))


def _brute_coverage(logits: np.ndarray, label: np.ndarray, mask: np.ndarray, cell: int, pos_weight: float) -> float:
    """The coverage term of one cell size by loops over the cells (the reference)."""
    total, n = 0.0, 0
    nx, ny, nz = label.shape
    for i in range(0, nx, cell):
        for j in range(0, ny, cell):
            for k in range(0, nz, cell):
                sl = (slice(i, i + cell), slice(j, j + cell), slice(k, k + cell))
                m = mask[sl] > 0
                if not m.any():
                    continue
                z = float(logits[sl][m].max())
                y = float((label[sl][m] > 0).any())
                w = 1.0 + (pos_weight - 1.0) * y
                total += w * (max(z, 0) - z * y + np.log1p(np.exp(-abs(z))))
                n += 1
    return total / n


def test_coverage_term_equals_a_loop_over_cells_and_forgives_a_voxel_off_by_one() -> None:
    rng = np.random.default_rng(1)
    lab = (rng.random((1, 10, 12, 7)) < 0.05).astype(np.float32)  # sides not multiples of the cells
    mask = (rng.random(lab.shape) < 0.8).astype(np.float32)
    logits = rng.normal(0, 3, lab.shape).astype(np.float32)
    got = coverage_loss(torch.from_numpy(logits), torch.from_numpy(lab), torch.from_numpy(mask), (4, 8), 2.0)
    want = np.mean([_brute_coverage(logits[0], lab[0], mask[0], c, 2.0) for c in (4, 8)])
    assert float(got) == pytest.approx(want, rel=1e-5)
    # a wall predicted one voxel off costs the voxel loss dearly and the coverage term nothing
    lab2 = torch.zeros(1, 16, 16, 8)
    lab2[0, 5, 5, 3] = 1
    ones = torch.ones_like(lab2)
    off = torch.full_like(lab2, -10.0)
    off[0, 6, 5, 3] = 10.0
    none = torch.full_like(lab2, -10.0)
    assert float(coverage_loss(off, lab2, ones, (4,), 2.0)) < 1e-3 < float(coverage_loss(none, lab2, ones, (4,), 2.0))
    assert float(loss_fn(off, lab2, ones, 2.0, 1.0)) > float(loss_fn(none, lab2, ones, 2.0, 1.0))
    # the weight adds it to the loss
    both = loss_fn(none, lab2, ones, 2.0, 1.0, coverage_weight=0.5, coverage_cells=(4,))
    assert float(both) == pytest.approx(float(loss_fn(none, lab2, ones, 2.0, 1.0))
                                        + 0.5 * float(coverage_loss(none, lab2, ones, (4,), 2.0)), rel=1e-6)


def test_lr_follows_a_cosine_over_the_time_budget() -> None:
    cfg = VoxelTrainConfig(lr=1e-3, time_limit=100.0)
    assert lr_at(cfg, 0) == pytest.approx(1e-3)
    assert lr_at(cfg, 100) == pytest.approx(5e-5)
    assert lr_at(cfg, 50) == pytest.approx(1e-3 * (0.05 + 0.95 * 0.5))


def test_validate_reports_f1_at_its_best_threshold() -> None:
    model = VoxelUNet(VoxelNetConfig(widths=(3, 4))).eval()
    cfg = VoxelTrainConfig(crop_xy=16, crop_z=8)
    rng = np.random.default_rng(0)
    lab = (rng.random((16, 16, 8)) < 0.2).astype(np.float32)
    crop = Crop(rng.random((5, 16, 16, 8)).astype(np.float32), lab, np.ones_like(lab))
    v = validate(model, [crop], cfg)
    assert 0 <= v["val_f1"] <= 1 and v["val_threshold"] in np.round(np.arange(0.05, 0.951, 0.05), 2)
    assert v["val_f1"] == max(v["val_f1_by_threshold"]) or abs(v["val_f1"] - max(v["val_f1_by_threshold"])) < 1e-4


def test_crop_stream_workers_are_seeded_and_repeatable() -> None:
    """With workers, batches come from generators seeded by (seed, start step, worker): the same run gives the
    same batches, and the two workers (and another start step) draw different crops."""
    from stages.complete.train_voxel import CropStream

    cfg = VoxelTrainConfig(crop_xy=32, crop_z=16, margin=4, batch_size=2, seed=5)
    scenes = [_scene()]

    def first(start: int, n: int = 4) -> list[tuple]:
        loader = torch.utils.data.DataLoader(CropStream(scenes, cfg, Band(2.0, -1.0, 1.0), 8, start),
                                             batch_size=None, num_workers=2)
        it = iter(loader)
        return [next(it) for _ in range(n)]

    a, b = first(0), first(0)
    for (xa, la, ma), (xb, lb, mb) in zip(a, b, strict=True):
        assert torch.equal(xa, xb) and torch.equal(la, lb) and torch.equal(ma, mb)
        assert xa.shape == (2, 5, 32, 32, 16) and la.shape == ma.shape == (2, 32, 32, 16)
    assert not torch.equal(a[0][0], a[1][0])  # worker 0 and worker 1
    assert not torch.equal(first(100, 1)[0][0], a[0][0])  # a resumed run draws anew


def test_training_runs_from_an_initial_checkpoint_and_counts_its_time(tmp_path) -> None:
    """``--init``: the weights and config of a checkpoint, a fresh schedule, and the checkpoint's own training
    seconds added to the new record (the CPU training budget is cumulative)."""
    from stages.complete.voxel_checkpoint import VoxelMeta, load_voxel_checkpoint, save_voxel_checkpoint

    root = _toy_map_set(tmp_path)
    init = tmp_path / "init.safetensors"
    model = VoxelUNet(VoxelNetConfig(widths=(4, 6)))
    save_voxel_checkpoint(init, model, VoxelMeta(model.config, 0.15, 0.5, Band(),
                                                 train={"selected": {"step": 7, "elapsed_s": 100.0}}))
    out = tmp_path / "out.safetensors"
    r = _pipeline("train", "--model", "voxel", "--maps", str(root), "--out", str(out), "--init", str(init),
                  "--time-limit", "0.01", "-o", "val_every=1", "--device", "cpu")
    assert r.returncode == 0, r.stderr
    m, meta = load_voxel_checkpoint(out)
    assert m.config.widths == (4, 6)
    assert meta.train["init"]["selected_step"] == 7
    assert meta.train["total_elapsed_s"] >= 100.0


def test_cuda_device_without_cuda_is_a_one_line_error(tmp_path) -> None:
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    r = _pipeline("train", "--model", "voxel", "--maps", str(tmp_path), "--device", "cuda")
    assert r.returncode == 2 and "no CUDA device" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_voxel_training_settings_are_checked_by_name(tmp_path) -> None:
    r = _pipeline("train", "--model", "voxel", "--maps", str(_toy_map_set(tmp_path)), "-o", "jiter=4")
    assert r.returncode == 2 and "--option jiter: not a voxel training setting" in r.stderr
    r = _pipeline("train", "--model", "voxel", "--seqs", "demo")
    assert r.returncode == 2 and "give --maps" in r.stderr


def _pipeline(*args: str):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True)


def _toy_map_set(tmp_path):
    """A map set of one train and one validation scene (per environment, the highest run is validation)."""
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    root = tmp_path / "maps"
    s = _scene()
    for name in ("toy_run0", "toy_run1"):
        d = root / name
        d.mkdir(parents=True)
        t = s.trajectory
        for kind, c in (("radar", (s.radar_keys + 0.5) * 0.15), ("lidar_filtered", (s.lidar_keys + 0.5) * 0.15),
                        ("poses", t), ("trajectory", t)):
            pq.write_table(pa.table({"x": c[:, 0], "y": c[:, 1], "z": c[:, 2]}), d / f"{kind}.parquet")
    (root / "index.json").write_text(json.dumps({n: {"split": "train", "environment": "toy"}
                                                 for n in ("toy_run0", "toy_run1")}))
    return root


def test_the_voxel_model_needs_no_fpsample() -> None:
    """The voxel model's training and Table III import without fpsample (only the patch path needs it): a GPU
    machine without that wheel runs them (it failed there once, through a module-level import)."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['fpsample'] = None; "
            "import stages.complete.train_voxel, experiments.rmap_voxel_table3, stages.complete.maps")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
