"""Map metrics (RMap Sec. IV-A) against brute-force distance matrices on random clouds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import map_metrics as mm


def _brute(pred: np.ndarray, gt: np.ndarray) -> dict[str, object]:
    D = np.linalg.norm(pred[:, None, :] - gt[None, :, :], axis=2)
    d_pg, d_gp = D.min(axis=1), D.min(axis=0)
    i_pg, i_gp = D.argmin(axis=1), D.argmin(axis=0)
    return {"d_pg": d_pg, "d_gp": d_gp, "i_pg": i_pg, "i_gp": i_gp}


@pytest.fixture
def clouds() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 3, size=(700, 3))
    pred = np.concatenate([gt[:300] + 0.05 * rng.standard_normal((300, 3)), rng.uniform(0, 3, size=(150, 3))])
    return pred, gt


def test_chamfer_against_brute_force(clouds: tuple[np.ndarray, np.ndarray]) -> None:
    pred, gt = clouds
    b = _brute(pred, gt)
    assert mm.chamfer_l1(pred, gt) == pytest.approx((b["d_pg"].mean() + b["d_gp"].mean()) / 2, rel=1e-12)
    assert mm.chamfer_l2(pred, gt) == pytest.approx(np.mean(b["d_pg"] ** 2) + np.mean(b["d_gp"] ** 2), rel=1e-12)
    per_axis = mm.chamfer_per_axis(pred, gt)
    ref = np.mean((pred - gt[b["i_pg"]]) ** 2, axis=0) + np.mean((pred[b["i_gp"]] - gt) ** 2, axis=0)
    assert np.allclose(per_axis, ref, rtol=1e-12)
    assert per_axis.sum() == pytest.approx(mm.chamfer_l2(pred, gt), rel=1e-12)  # eq. 7 sums to eq. 1


def test_fscore_and_ddist_against_brute_force(clouds: tuple[np.ndarray, np.ndarray]) -> None:
    pred, gt = clouds
    b = _brute(pred, gt)
    for d in (0.05, 0.15, 0.3):
        p, r = np.mean(b["d_pg"] < d), np.mean(b["d_gp"] < d)
        assert mm.fscore(pred, gt, d) == pytest.approx(2 * p * r / (p + r), rel=1e-12)
    assert np.allclose(mm.deviation_distribution(pred, gt), np.percentile(b["d_gp"], [50, 75, 90, 95]))
    m = mm.map_metrics(pred, gt)
    assert m["cd_l1_x1000"] == pytest.approx(1000 * m["cd_l1"])
    assert m["ddist_p95"] == pytest.approx(np.percentile(b["d_gp"], 95))
    assert {"cd_l1", "cd_l2", "fscore_0.15", "ddist_p50", "ddist_p75", "ddist_p90", "ddist_p95", "cd_x", "cd_y",
            "cd_z"} <= set(m)


def test_voxel_grid_ties_and_identities() -> None:
    rng = np.random.default_rng(1)
    keys = np.unique(rng.integers(0, 40, size=(2000, 3)), axis=0)
    grid = ((keys + 0.5) * 0.15).astype(np.float32).astype(np.float64)
    assert mm.chamfer_l1(grid, grid) == 0 and mm.fscore(grid, grid) == 1.0
    assert mm.fscore_robust(grid, grid) == 1.0
    # shifted by one voxel: distances are 0.15 up to rounding of the stored values
    for scale in (1, 600):  # also far from the origin (coordinates ~ 3.6 km), where float32 rounding is larger
        k = keys * [scale, 1, 1]
        shifted_k = k + np.array([1, 0, 0])
        shifted = ((shifted_k + 0.5) * 0.15).astype(np.float32).astype(np.float64)
        ref_grid = ((k + 0.5) * 0.15).astype(np.float32).astype(np.float64)
        # the robust variant: the ties never count, only coinciding voxels match
        kset, sset = set(map(tuple, k.tolist())), set(map(tuple, shifted_k.tolist()))
        p = np.mean([tuple(x) in kset for x in shifted_k.tolist()])
        r = np.mean([tuple(x) in sset for x in k.tolist()])
        expected = 2 * p * r / (p + r) if p + r else 0.0
        assert mm.fscore_robust(shifted, ref_grid) == pytest.approx(expected, abs=1e-12)
        # the paper-compatible value: strict '<' on the float64 values as stored, each tie decided by rounding
        b = _brute(shifted, ref_grid)
        p64, r64 = np.mean(b["d_pg"] < 0.15), np.mean(b["d_gp"] < 0.15)
        assert mm.fscore(shifted, ref_grid) == pytest.approx(2 * p64 * r64 / (p64 + r64), abs=1e-12)
        assert mm.fscore(shifted, ref_grid) > expected  # some ties fall below 0.15 after rounding
        assert mm.fscore(shifted, ref_grid, tie_tol=-2e-3) == 1.0  # counting every tie, every voxel matches
    assert mm.lr_ratio(grid, grid[:500]) == pytest.approx(len(grid) / 500)
    assert mm.lr_ratio(10, 4) == 2.5 and np.isnan(mm.lr_ratio(3, 0))
    empty = np.zeros((0, 3))
    assert np.isnan(mm.chamfer_l2(empty, grid)) and np.isnan(mm.deviation_distribution(grid, empty)).all()
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        mm.chamfer_l1(np.zeros((4, 2)), grid)


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 60), st.integers(1, 60), st.integers(0, 10_000))
def test_random_sizes_match_brute_force(n_p: int, n_g: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pred, gt = rng.normal(size=(n_p, 3)), rng.normal(size=(n_g, 3))
    b = _brute(pred, gt)
    m = mm.map_metrics(pred, gt, d=0.5)
    assert m["cd_l2"] == pytest.approx(np.mean(b["d_pg"] ** 2) + np.mean(b["d_gp"] ** 2), rel=1e-9)
    p, r = np.mean(b["d_pg"] < 0.5), np.mean(b["d_gp"] < 0.5)
    f = 2 * p * r / (p + r) if p + r else 0.0
    assert m["fscore_0.5"] == pytest.approx(f, abs=1e-12)


def test_recall_by_path_distance_against_brute_force() -> None:
    """Each lidar point's bin by its horizontal distance to the nearest path point, the recall in the bin by the
    strict ``dist < d`` to the nearest prediction, both by brute force."""
    from core.map_metrics import MapComparison, path_bin_names, recall_by_path_distance

    rng = np.random.default_rng(4)
    gt = np.column_stack([rng.uniform(-10, 10, (400, 2)), rng.uniform(0, 3, 400)])
    pred = np.concatenate([gt[:150] + 0.01, rng.uniform(-10, 10, (50, 3))])
    path = np.column_stack([np.linspace(-9, 9, 40), np.zeros(40), np.full(40, 5.0)])  # z is ignored
    got = recall_by_path_distance(MapComparison(pred, gt), path, 0.15)
    d_path = np.min(np.hypot(*(gt[:, None, :2] - path[None, :, :2]).transpose(2, 0, 1)), axis=1)
    d_pred = np.min(np.linalg.norm(gt[:, None] - pred[None], axis=2), axis=1)
    edges = [0, 1, 2, 3, 4, 5, 6, 7, np.inf]
    for name, lo, hi in zip(path_bin_names(), edges[:-1], edges[1:], strict=True):
        m = (d_path >= lo) & (d_path < hi)
        assert got[f"n_gt_path_{name}"] == m.sum()
        if m.any():
            assert got[f"recall_path_{name}"] == pytest.approx(np.mean(d_pred[m] < 0.15))
        else:
            assert np.isnan(got[f"recall_path_{name}"])
    assert sum(got[f"n_gt_path_{n}"] for n in path_bin_names()) == len(gt)
    assert recall_by_path_distance(MapComparison(pred, gt), np.zeros((0, 3))) == {}


def test_recall_table_pools_hits_over_sequences() -> None:
    from stages.evaluate.recall_distance import pooled_recall, recall_table

    recs = [{"seq": "a", "method": "radar_map", "metric": "recall_path_0-1m", "value": 0.5},
            {"seq": "a", "method": "radar_map", "metric": "n_gt_path_0-1m", "value": 10},
            {"seq": "b", "method": "radar_map", "metric": "recall_path_0-1m", "value": 1.0},
            {"seq": "b", "method": "radar_map", "metric": "n_gt_path_0-1m", "value": 30},
            {"seq": "b", "method": "radar_map", "metric": "recall_path_>7m", "value": 0.2},
            {"seq": "b", "method": "radar_map", "metric": "n_gt_path_>7m", "value": 10}]
    assert pooled_recall(recs)["radar_map"]["0-1m"] == (pytest.approx((5 + 30) / 40), 40)
    title, head, rows = recall_table(recs)
    assert "2 sequence(s)" in title and head[1] == "0-1m" and head[-1] == ">=5m"
    assert rows[0][0] == "radar_map" and rows[0][-1] == "0.200"  # the far field: the >7 m bin alone here
    assert rows[-1][0] == "(share of lidar points)" and rows[-1][1] == "0.800"
    assert recall_table([]) is None
