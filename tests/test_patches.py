"""FPS patches (RMap Algorithm 1): FPS, kNN, padding and outlier removal against brute force; the stage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core import fps_patches as fp
from core.recording import entity_paths_in
from schemas.io import read_artifact, write_artifact
from stages.patches.stage import STAGE, PatchesParams
from tests.test_voxel_synthetic import make_context


def brute_fps(points: np.ndarray, n: int, start: int) -> np.ndarray:
    idx = [start]
    d = np.linalg.norm(points - points[start], axis=1)
    for _ in range(n - 1):
        i = int(np.argmax(d))
        idx.append(i)
        d = np.minimum(d, np.linalg.norm(points - points[i], axis=1))
    return np.array(idx)


def test_fps_equals_brute_force() -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(3000, 3)).astype(np.float32).astype(np.float64)
    for start in (0, 1234):
        got = fp.farthest_point_sampling(pts, 40, start)
        assert np.array_equal(got, brute_fps(pts, 40, start))
    assert fp.farthest_point_sampling(pts[:3], 10, 1).tolist() == brute_fps(pts[:3], 3, 1).tolist()


def test_knn_and_padding() -> None:
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 5, size=(500, 3))
    seeds = pts[[3, 77]]
    idx, pad = fp.knn_padded(cKDTree(pts), len(pts), seeds, 32, rng)
    D = np.linalg.norm(pts[None] - seeds[:, None], axis=2)
    assert np.array_equal(idx, np.argsort(D, axis=1)[:, :32]) and not pad.any()
    assert idx[0, 0] == 3  # nearest first: a seed from the map is its own patch's first point
    # fewer points than N: all of them nearest first, then draws with replacement, marked as padded
    few = pts[:10]
    idx, pad = fp.knn_padded(cKDTree(few), len(few), seeds, 25, np.random.default_rng(2))
    assert idx.shape == (2, 25) and pad[:, 10:].all() and not pad[:, :10].any()
    assert np.array_equal(idx[0, :10], np.argsort(np.linalg.norm(few - seeds[0], axis=1)))
    assert set(idx[:, 10:].ravel()) <= set(range(10))


def test_statistical_outliers_against_brute_force() -> None:
    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.normal(size=(400, 3)) * 0.5, rng.uniform(5, 9, size=(8, 3))])
    keep = fp.statistical_outliers(pts, k=10, std_ratio=2.0)
    D = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    mean_d = np.sort(D, axis=1)[:, 1:11].mean(axis=1)
    assert np.array_equal(keep, mean_d <= mean_d.mean() + 2.0 * mean_d.std())
    assert not keep[-8:].any() and keep[:400].mean() > 0.95
    assert fp.statistical_outliers(pts, k=0, std_ratio=2.0).all()


def test_n_seeds_and_normalisation() -> None:
    assert fp.n_seeds(20480, 2048, 4) == 40 and fp.n_seeds(100, 2048, 4) == 1 and fp.n_seeds(0, 2048, 4) == 0
    assert fp.n_seeds(3000, 2048, 16) == 23  # floor(23.4): Table VI's counts (RMap README)
    p = np.array([[1.0, 2.0, 3.0], [4.0, 0.0, -1.0]])
    c, s = np.array([1.0, 1.0, 1.0]), 2.5
    assert np.allclose(fp.denormalise(fp.normalise(p, c, s), c, s), p)


def test_make_patches_covers_the_maps() -> None:
    rng = np.random.default_rng(4)
    lidar = rng.uniform(0, 20, size=(20000, 3)) * [1, 1, 0.1]
    radar = lidar[rng.choice(len(lidar), 5000, replace=False)] + 0.05 * rng.standard_normal((5000, 3))
    res = fp.make_patches(radar, lidar, a=4, n_radar=512, n_lidar=2048, seed=7)
    rad = radar[res.radar_inliers]
    assert len(res.seeds) == fp.n_seeds(len(rad), 512, 4)
    assert np.array_equal(res.seed_idx, brute_fps(rad.astype(np.float32).astype(np.float64), len(res.seeds),
                                                  int(res.seed_idx[0])))
    assert np.array_equal(rad[res.radar_idx[:, 0]], res.seeds)
    # with a = 4 every radar point lies in some patch
    assert len(np.unique(res.radar_idx)) == len(rad)
    assert np.allclose(res.scale, np.linalg.norm(rad[res.radar_idx] - res.seeds[:, None], axis=2).max(axis=1))
    again = fp.make_patches(radar, lidar, a=4, n_radar=512, n_lidar=2048, seed=7)
    assert np.array_equal(again.lidar_idx, res.lidar_idx)  # deterministic for a seed


def _write_maps(folder: Path, n_radar: int, n_lidar: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(5)
    folder.mkdir(parents=True, exist_ok=True)
    lidar = ((rng.integers(0, 120, size=(n_lidar, 3)) * [1, 1, 0.1]).astype(int) + 0.5) * 0.15
    radar = lidar[rng.choice(n_lidar, n_radar, replace=False)]
    for kind, pts in (("radar", radar), ("lidar", lidar)):
        write_artifact({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "log_odds": np.ones(len(pts))},
                       folder / f"{kind}_map.parquet", f"{kind}_map")
    return radar, lidar


def test_patches_stage(tmp_path: Path) -> None:
    _radar, lidar = _write_maps(tmp_path / "voxel", 3000, 6000)
    params = PatchesParams(n_radar=512, n_lidar=2048, a=4.0)
    ctx = make_context("patches", params, {"voxel": tmp_path / "voxel"}, tmp_path / "patches")
    STAGE.run(ctx)
    ctx.close()
    tab = read_artifact(tmp_path / "patches" / "patches.parquet", "patches").to_pandas()
    info = json.loads((tmp_path / "patches" / "patches.json").read_text())
    t = info["n_seeds"]
    assert t == fp.n_seeds(info["radar_points_after_outlier_removal"], 512, 4)
    assert len(tab) == t * (512 + 2048)
    assert (tab.groupby(["patch", "kind"]).size() == tab.groupby(["patch", "kind"])["rank"].max() + 1).all()
    r = tab[tab.kind == "radar"]
    first = r[r["rank"] == 0]
    assert np.allclose(first[["x", "y", "z"]].to_numpy(), first[["seed_x", "seed_y", "seed_z"]].to_numpy())
    # normalised radar patches lie in the unit ball; back to world coordinates exactly
    norm = fp.normalise(r[["x", "y", "z"]].to_numpy(), r[["seed_x", "seed_y", "seed_z"]].to_numpy(),
                        r[["scale"]].to_numpy())
    assert np.linalg.norm(norm, axis=1).max() <= 1 + 1e-5
    from scipy.spatial import cKDTree

    lp = tab[tab.kind == "lidar"][["x", "y", "z"]].to_numpy()
    assert cKDTree(lidar).query(lp)[0].max() < 1e-4  # patch points are lidar map points
    assert "/world/patches" in entity_paths_in(tmp_path / "patches" / "patches.rrd")


def test_patches_stage_pads_small_maps(tmp_path: Path) -> None:
    _write_maps(tmp_path / "voxel", 300, 900)
    ctx = make_context("patches", PatchesParams(), {"voxel": tmp_path / "voxel"}, tmp_path / "patches")
    STAGE.run(ctx)
    ctx.close()
    tab = read_artifact(tmp_path / "patches" / "patches.parquet", "patches").to_pandas()
    assert tab.patch.nunique() == 1
    lid = tab[tab.kind == "lidar"]
    assert len(lid) == 8192 and lid.padded.sum() == 8192 - 900
    assert not lid[lid["rank"] < 900].padded.any()


def test_patches_stage_empty_map(tmp_path: Path) -> None:
    from core.errors import UserError

    _write_maps(tmp_path / "voxel", 0, 100)
    ctx = make_context("patches", PatchesParams(), {"voxel": tmp_path / "voxel"}, tmp_path / "patches")
    with pytest.raises(UserError, match="radar map is empty"):
        STAGE.run(ctx)
