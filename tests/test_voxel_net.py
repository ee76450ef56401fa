"""The voxel completion model: lattice, features, receptive radius, tiled inference = one pass."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from core.errors import UserError  # noqa: E402
from stages.complete.voxel_grid import (  # noqa: E402
    CHANNELS,
    Band,
    LatticeError,
    band_grid,
    box_sum,
    in_band,
    key_centres,
    lattice_keys,
    trajectory_band,
    trajectory_columns,
    voxel_features,
)
from stages.complete.voxel_net import (  # noqa: E402
    VoxelNetConfig,
    VoxelUNet,
    map_domain,
    predict_tiles,
    reuse_freed_memory,
)

RES = 0.15


def _scene(seed: int = 0, n: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """Radar voxel keys scattered around an L-shaped path, and the path (m)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, 60)
    path = np.concatenate([np.stack([t * 6, np.zeros_like(t), np.full_like(t, 1.0)], 1),
                           np.stack([np.full_like(t, 6.0), t * 5, np.full_like(t, 1.0)], 1)])
    base = path[rng.integers(len(path), size=n)] + rng.normal(0, [1.5, 1.5, 0.8], (n, 3))
    keys = np.unique(np.floor(base / RES).astype(np.int64), axis=0)
    return keys, path


def test_lattice_keys_round_trip_and_off_lattice_error() -> None:
    keys = np.array([[0, -3, 7], [12, 5, -1]])
    pts = key_centres(keys, RES)
    assert np.array_equal(lattice_keys(pts, RES), keys)
    with pytest.raises(LatticeError, match=r"not on the 0\.15 m voxel lattice"):
        lattice_keys(pts + np.array([0.05, 0, 0]), RES, "radar map")


def test_box_sum_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    occ = (rng.random((9, 10, 11)) < 0.3).astype(np.float32)
    r = 2
    got = box_sum(occ, r)
    want = np.array([[[occ[i:i + 5, j:j + 5, k:k + 5].sum() for k in range(7)] for j in range(6)] for i in range(5)])
    assert np.array_equal(got, want)


@pytest.mark.parametrize("r", [1, 5])
def test_box_sum_of_uint8_matches_brute_force(r: int) -> None:
    rng = np.random.default_rng(r)
    occ = (rng.random((2 * r + 4, 2 * r + 3, 2 * r + 5)) < 0.4).astype(np.uint8)
    w = 2 * r + 1
    want = np.array([[[occ[i:i + w, j:j + w, k:k + w].sum() for k in range(5)] for j in range(3)] for i in range(4)])
    got = box_sum(occ, r)
    assert got.dtype == np.float32 and np.array_equal(got, want)


def test_precomputed_trajectory_columns_give_the_same_grids() -> None:
    keys, path = _scene()
    lo, shape, band = np.array([-8, -12, -4]), (40, 52, 24), Band(radius=2.0, z_below=-1.5, z_above=1.5)
    cols = trajectory_columns(lo, shape[:2], path, RES)
    assert np.array_equal(voxel_features(keys, path, lo, shape, RES, cols), voxel_features(keys, path, lo, shape, RES))
    assert np.array_equal(band_grid(lo, shape, path, RES, band, cols), band_grid(lo, shape, path, RES, band))


def test_reuse_freed_memory_changes_no_value() -> None:
    torch.manual_seed(0)
    model = VoxelUNet(VoxelNetConfig(widths=(3, 4), bottom_convs=1)).eval()
    x = torch.rand(1, len(CHANNELS), 16, 16, 8)
    with torch.no_grad():
        want = model(x)
        with reuse_freed_memory():
            got = model(x)
    assert torch.equal(got, want)


def test_features_of_a_tile_equal_the_whole_box() -> None:
    keys, path = _scene()
    lo = keys.min(0) - 2
    shape = tuple(int(v) for v in keys.max(0) - lo + 3)
    whole = voxel_features(keys, path, lo, (shape[0], shape[1], shape[2]), RES)
    assert whole.shape == (len(CHANNELS), *shape)
    off = np.array([7, 5, 3])
    sub_shape = (11, 13, 9)
    sub = voxel_features(keys, path, lo + off, sub_shape, RES)
    assert np.array_equal(sub, whole[:, 7:18, 5:18, 3:12])
    assert whole[0].sum() == len(keys)


def test_band_prefilter() -> None:
    path = np.stack([np.linspace(0, 10, 101), np.zeros(101), np.ones(101)], 1)  # distances to the points
    pts = np.array([[5.0, 6.9, 1.0], [5.0, 7.1, 1.0], [5.0, 0.0, -2.1], [5.0, 0.0, -2.0], [5.0, 0.0, 5.4]])
    band = Band(radius=7.0, z_below=-3.0, z_above=4.5)
    assert in_band(pts, path, band).tolist() == [True, False, False, True, True]
    assert len(trajectory_band(pts, path, band)) == 3


def test_receptive_radius_bounds_the_influence() -> None:
    torch.manual_seed(0)
    model = VoxelUNet(VoxelNetConfig(in_channels=1, widths=(2, 3, 4), bottom_convs=2, bottom_dilation=2)).eval()
    r = model.receptive_radius()
    n = 2 * r + 8
    n += (-n) % model.stride()
    x = torch.zeros(1, 1, n, 4, 4)
    c = n // 2
    with torch.no_grad():
        base = model(x)[0, c]
        far = x.clone()
        far[0, 0, c + r + 1] = 5.0
        far[0, 0, c - r - 1] = 5.0
        near = x.clone()
        near[0, 0, c + 3] = 5.0
        assert torch.equal(model(far)[0, c], base)
        assert not torch.equal(model(near)[0, c], base)


def _live_model(seed: int = 0) -> VoxelUNet:
    torch.manual_seed(seed)
    model = VoxelUNet(VoxelNetConfig(widths=(3, 4, 5), bottom_convs=1, bottom_dilation=2)).eval()
    with torch.no_grad():  # weights that keep the ReLUs alive, so that every layer shapes the output
        for p in model.parameters():
            if p.ndim > 1:
                p.normal_(0.0, (2.0 / p[0].numel()) ** 0.5)
            else:
                p.uniform_(-0.1, 0.3)
    return model


@pytest.mark.parametrize("core", [8, 16])
def test_tiled_inference_equals_one_pass(core: int) -> None:
    model = _live_model()
    keys, path = _scene()
    band = Band(radius=2.0, z_below=-1.5, z_above=1.5)
    dom = map_domain(path, RES, band, model.stride())
    one = predict_tiles(model, keys, path, RES, band, core=max(dom.shape[:2]) + model.stride())
    assert one.n_tiles - one.n_skipped == 1
    assert one.probs.std() > 0.02
    tiled = predict_tiles(model, keys, path, RES, band, core=core)
    assert tiled.n_tiles - tiled.n_skipped > 4
    a = np.lexsort(one.keys.T)
    b = np.lexsort(tiled.keys.T)
    assert np.array_equal(one.keys[a], tiled.keys[b])
    np.testing.assert_allclose(tiled.probs[b], one.probs[a], rtol=0, atol=1e-6)
    # a halo below the receptive radius is not exact
    short = predict_tiles(model, keys, path, RES, band, core=core, halo=model.stride())
    c = np.lexsort(short.keys.T)
    assert np.abs(short.probs[c] - one.probs[a]).max() > 1e-6


def test_bf16_inference_is_close_to_float32_and_the_default_is_exact() -> None:
    """``bf16`` runs the network under bfloat16 autocast: the same voxels, probabilities close but not equal;
    without it the float32 result is unchanged."""
    torch.manual_seed(0)
    model = VoxelUNet(VoxelNetConfig(widths=(3, 4, 5), bottom_convs=1, bottom_dilation=2)).eval()
    keys, path = _scene()
    band = Band(radius=2.0, z_below=-1.5, z_above=1.5)
    ref = predict_tiles(model, keys, path, RES, band)
    again = predict_tiles(model, keys, path, RES, band, bf16=False)
    half = predict_tiles(model, keys, path, RES, band, bf16=True)
    assert np.array_equal(ref.keys, half.keys) and np.array_equal(ref.probs, again.probs)
    diff = np.abs(half.probs - ref.probs)
    assert diff.max() < 0.02 and diff.max() > 0


def test_checkpoint_round_trip_and_kind_errors(tmp_path) -> None:
    from stages.complete.voxel_checkpoint import (
        VoxelMeta,
        checkpoint_kind,
        load_voxel_checkpoint,
        save_voxel_checkpoint,
    )

    model = VoxelUNet(VoxelNetConfig(widths=(3, 4)))
    meta = VoxelMeta(model.config, RES, 0.4, Band(), train={"note": "test"})
    path = save_voxel_checkpoint(tmp_path / "v.safetensors", model, meta, half=False)
    assert checkpoint_kind(path) == "voxel_unet"
    back, m2 = load_voxel_checkpoint(path)
    assert m2.threshold == 0.4 and m2.resolution == RES and m2.config == model.config
    strings = dict(meta.to_strings())
    assert VoxelMeta.from_strings(strings | {"tta": "1"}, "older").threshold == 0.4  # the network alone: as now
    with pytest.raises(UserError, match="averaged over 4 lattice symmetries"):
        VoxelMeta.from_strings(strings | {"tta": "4"}, "averaged")
    for k, v in model.state_dict().items():
        assert torch.equal(back.state_dict()[k], v)
    from safetensors.torch import save_file

    other = tmp_path / "u.safetensors"
    save_file({"w": torch.zeros(1)}, str(other), metadata={"format": "radar-pipeline/complete", "format_version": "1"})
    assert checkpoint_kind(other) == "uppointr"
    with pytest.raises(UserError, match="uppointr checkpoint, not a voxel model"):
        load_voxel_checkpoint(other)


def test_gated_union_keeps_the_radar_voxels_the_model_believes() -> None:
    """``completed_keys`` with a gate adds only the radar voxels whose own predicted probability reaches it
    (brute force over the keys); gate 0 is the plain union; a radar voxel the prediction does not hold counts as
    probability 0; the gate survives a checkpoint round trip (older checkpoints read as gate 0)."""
    from stages.complete.voxel_net import TilePrediction, completed_keys, probabilities_at

    rng = np.random.default_rng(2)
    keys = np.unique(rng.integers(-20, 20, (400, 3)), axis=0)
    probs = rng.random(len(keys)).astype(np.float32)
    pred = TilePrediction(keys, probs)
    radar = np.concatenate([keys[rng.choice(len(keys), 60, replace=False)], [[100, 100, 100]]])
    p = probabilities_at(pred, radar)
    want = [next((float(q) for k, q in zip(keys, probs, strict=True) if tuple(k) == tuple(r)), 0.0) for r in radar]
    np.testing.assert_array_equal(p, np.asarray(want, np.float32))
    for gate in (0.0, 0.2, 0.45):
        got = {tuple(k) for k in completed_keys(pred, 0.5, radar, gate)}
        expect = {tuple(k) for k, q in zip(keys, probs, strict=True) if q >= 0.5}
        expect |= {tuple(r) for r, q in zip(radar, want, strict=True) if gate == 0 or q >= gate}
        assert got == expect
    assert (100, 100, 100) in {tuple(k) for k in completed_keys(pred, 0.5, radar, 0.0)}


def test_gate_rule_takes_the_lowest_gate_that_passes_the_union_rule(tmp_path) -> None:
    from experiments.rmap_voxel_table3 import GATES, decide_gate, gate_row
    from stages.complete.voxel_checkpoint import VoxelMeta, load_voxel_checkpoint, save_voxel_checkpoint

    def table(split: str, f_by_gate: dict[float, tuple[float, float]]) -> dict:
        overall = {"voxel": {"cd_l2": 0.8, "fscore_0.15": 0.60}}
        overall |= {gate_row(g): {"cd_l2": cd, "fscore_0.15": f} for g, (cd, f) in f_by_gate.items()}
        return {"split": split, "scenes": ["a"], "overall": overall}

    gates = [g for g in GATES if g <= 0.3]
    # F recovers as the gate rises; the first gate within 0.01 of the model alone (and below its CD-l2) wins
    rows = {g: (0.3 + g, 0.5 + 0.4 * g) for g in gates}
    assert decide_gate(table("val", rows), 0.3) == 0.25
    assert decide_gate(table("val", {g: (0.9, 0.7) for g in gates}), 0.3) is None  # CD-l2 never better
    assert decide_gate(table("val", {g: (0.3, 0.6) for g in gates}), 0.3) == 0.0  # the plain union passes
    with pytest.raises(ValueError, match="validation scenes only"):
        decide_gate(table("test", rows), 0.3)
    with pytest.raises(ValueError, match="no row for gate"):
        decide_gate(table("val", {0.0: (0.9, 0.1)}), 0.3)
    model = VoxelUNet(VoxelNetConfig(widths=(3, 4)))
    path = save_voxel_checkpoint(tmp_path / "g.safetensors", model,
                                 VoxelMeta(model.config, RES, 0.4, Band(), union_radar=True, union_gate=0.25))
    assert load_voxel_checkpoint(path)[1].union_gate == 0.25


def test_the_checkpoints_own_output_row_follows_its_union_and_gate() -> None:
    """``output_row`` names the Table III row that ``complete.model = voxel`` writes (the benchmark quotes it):
    the model alone, the plain union, or the gated union, as the checkpoint's metadata says."""
    from experiments.rmap_voxel_table3 import ROWS, gate_row, output_row

    assert output_row({}) == output_row({"union": None}) == "voxel"
    assert output_row({"union": {"radar": False, "gate": 0.0}}) == "voxel"
    assert output_row({"union": {"radar": True, "gate": 0.0}}) == "voxel + prefiltered radar" and \
        "voxel + prefiltered radar" in ROWS
    gated = output_row({"union": {"radar": True, "gate": 0.01}})
    assert gated == gate_row(0.01) == "voxel + prefiltered radar, gate 0.01"
