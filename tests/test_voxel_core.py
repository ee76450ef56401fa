"""Voxel stage building blocks against brute-force references: log-odds map, ray traversal, radar fan, poses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from stages.voxel import voxel_map as vm
from stages.voxel.poses import horizontal_fov_mask, interpolate_se2, interpolate_se3
from stages.voxel.radar_model import fan_directions, radar_scan_keys
from stages.voxel.raycast import ray_keys, scan_update_keys
from stages.voxel.voxel_map import SensorModel, VoxelMap, coord_to_key, logit, pack_keys, unpack_keys

RES = 0.15


# -- a literal port of OctoMap's OcTreeBaseImpl::computeRayKeys (3D-DDA), one ray at a time ----------------
def dda_ray_keys(origin: np.ndarray, end: np.ndarray, res: float) -> set[tuple[int, int, int]]:
    ko = tuple(int(v) for v in np.floor(origin / res))
    ke = tuple(int(v) for v in np.floor(end / res))
    if ko == ke:
        return set()
    out = {ko}
    direction = end - origin
    length = float(np.linalg.norm(direction))
    direction = direction / length
    step, t_max, t_delta = [0, 0, 0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    for i in range(3):
        step[i] = 1 if direction[i] > 0 else (-1 if direction[i] < 0 else 0)
        if step[i]:
            border = (ko[i] + 0.5) * res + step[i] * res * 0.5
            t_max[i] = (border - origin[i]) / direction[i]
            t_delta[i] = res / abs(direction[i])
        else:
            t_max[i] = t_delta[i] = np.inf
    cur = list(ko)
    while True:
        dim = int(np.argmin(t_max))
        cur[dim] += step[dim]
        t_max[dim] += t_delta[dim]
        if tuple(cur) == ke or min(t_max) > length:
            break
        out.add((cur[0], cur[1], cur[2]))
    return out


def test_keys_pack_roundtrip_and_octomap_discretisation() -> None:
    rng = np.random.default_rng(0)
    keys = rng.integers(-(1 << 19), 1 << 19, size=(1000, 3))
    assert np.array_equal(unpack_keys(pack_keys(keys)), keys)
    order = np.argsort(pack_keys(keys))
    assert np.array_equal(order, np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0])))
    # floor(x * (1/res)) as OctoMap's coordToKey; centres at (k + 0.5) * res
    assert coord_to_key([[0.0, -0.01, 0.149999]], RES).tolist() == [[0, -1, 0]]
    assert np.allclose(vm.key_to_coord([[0, -1, 2]], RES), [[0.075, -0.075, 0.375]])


def _reference_map(scans: list[tuple[np.ndarray, np.ndarray]], model: SensorModel, need_free: bool) -> dict:
    """Per-voxel clamped log-odds with Python sets and floats (OctoMap updateNodeLogOdds)."""
    values: dict[tuple[int, ...], np.float32] = {}
    for free, hit in scans:
        f = {tuple(k) for k in free.tolist()}
        h = {tuple(k) for k in hit.tolist()}
        if need_free:
            h &= f
        f -= h
        for keys, upd in ((f, model.miss), (h, model.hit)):
            for k in keys:
                v = np.float32(values.get(k, np.float32(0)) + upd)
                values[k] = np.float32(min(max(v, model.lo), model.hi))
    return values


@pytest.mark.parametrize("need_free", [False, True])
def test_voxel_map_matches_scalar_reference(need_free: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(1)
    model = SensorModel()
    scans = []
    for _ in range(40):  # overlapping random key sets with duplicates: clamping, hit-over-miss, once per scan
        free = rng.integers(-20, 20, size=(300, 3))
        hit = np.concatenate([free[rng.integers(0, 300, 20)], rng.integers(-20, 20, size=(20, 3))])
        hit = np.concatenate([hit, hit[:5]])
        scans.append((free, hit))
    ref = _reference_map(scans, model, need_free)
    for window in (vm.MAX_WINDOW_CELLS, 4096 * 2):  # the dense window and the tiled fallback
        monkeypatch.setattr(vm, "MAX_WINDOW_CELLS", window)
        m = VoxelMap(RES, model)
        for free, hit in scans:
            m.integrate(free, hit, hits_need_free=need_free)
        keys, vals = m.voxels(occupied_only=False)
        got = {tuple(k): v for k, v in zip(keys.tolist(), vals, strict=True)}
        assert got.keys() == ref.keys()
        assert all(got[k] == ref[k] for k in ref)
        occ_keys, _occ_vals = m.voxels()
        assert {tuple(k) for k in occ_keys.tolist()} == {k for k, v in ref.items() if v > model.threshold}
        assert m.counts()["known"] == len(ref)


def test_clamping_thresholds_are_octomap_defaults() -> None:
    m = VoxelMap(RES)
    for _ in range(30):
        m.integrate(np.zeros((0, 3), np.int64), [[1, 2, 3]])
    assert m.voxels()[1][0] == pytest.approx(logit(0.97), abs=1e-6)
    for _ in range(30):
        m.integrate([[1, 2, 3]], np.zeros((0, 3), np.int64))
    assert m.voxels(occupied_only=False)[1][0] == pytest.approx(logit(0.12), abs=1e-6)
    with pytest.raises(ValueError, match="clamp_min"):
        SensorModel(clamp_min=0.9, clamp_max=0.5)


def test_ray_keys_equal_literal_dda() -> None:
    rng = np.random.default_rng(2)
    origins = rng.uniform(-3, 3, size=(400, 3))
    ends = origins + rng.normal(size=(400, 3)) * rng.uniform(0.05, 6, size=(400, 1))
    mismatched = 0
    for o, e in zip(origins, ends, strict=True):
        got = {tuple(k) for k in ray_keys(o, e[None], RES).tolist()}
        mismatched += got != dda_ray_keys(o, e, RES)
    assert mismatched == 0
    # all rays at once: the union over rays equals the union of the per-ray references
    many = {tuple(k) for k in ray_keys(origins, ends, RES).tolist()}
    assert many == set().union(*(dda_ray_keys(o, e, RES) for o, e in zip(origins, ends, strict=True)))


def test_ray_keys_axis_aligned_and_degenerate() -> None:
    # along +x from the centre of voxel 0 to inside voxel 4: voxels 0..3
    got = ray_keys([0.075, 0.075, 0.075], [[0.65, 0.075, 0.075]], RES)
    assert sorted(map(tuple, got.tolist())) == [(i, 0, 0) for i in range(4)]
    assert len(ray_keys([0.01, 0.01, 0.01], [[0.02, 0.1, 0.14]], RES)) == 0  # same voxel: nothing
    back = ray_keys([0.65, 0.075, 0.075], [[0.075, 0.075, 0.075]], RES)
    assert sorted(map(tuple, back.tolist())) == [(i, 0, 0) for i in range(1, 5)]


def test_scan_update_keys_max_range_and_discretize() -> None:
    origin = np.zeros(3)
    pts = np.array([[1.0, 0.01, 0.02], [5.0, 0.3, 0.1]])
    free, hit = scan_update_keys(pts, origin, RES, max_range=2.0)
    assert {tuple(k) for k in hit.tolist()} == {tuple(coord_to_key(pts[:1], RES)[0])}  # far point: no hit
    far_free = {tuple(k) for k in free.tolist()}
    truncated = origin + (pts[1] - origin) * (2.0 / np.linalg.norm(pts[1]))
    assert dda_ray_keys(origin, truncated, RES) <= far_free
    assert max(k[0] for k in far_free) <= int(2.0 / RES)
    # discretize: one ray to the centre of each distinct end voxel, the same hit set
    dup = np.array([[1.0, 0.01, 0.02], [1.01, 0.02, 0.03], [2.0, 1.0, 0.5]])
    f1, h1 = scan_update_keys(dup, origin, RES, discretize=True)
    _f0, h0 = scan_update_keys(dup, origin, RES)
    assert {tuple(k) for k in h1.tolist()} == {tuple(k) for k in h0.tolist()}
    centres = vm.key_to_coord(np.unique(coord_to_key(dup, RES), axis=0), RES)
    ref = set().union(*(dda_ray_keys(origin, c, RES) for c in centres))
    assert {tuple(k) for k in f1.tolist()} == ref


def test_radar_fan_geometry_and_keys() -> None:
    max_range = 4.0
    dirs = fan_directions(np.radians(45), np.radians(30), RES, max_range)
    delta = 2 * np.arctan(0.5 * RES / max_range)
    assert len(dirs) == int(np.radians(90) / delta) * int(np.radians(60) / delta)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1)
    az = np.degrees(np.arctan2(dirs[:, 1], dirs[:, 0]))
    el = np.degrees(np.arcsin(dirs[:, 2]))
    assert az.min() == pytest.approx(-45) and az.max() < 45 and el.min() == pytest.approx(-30) and el.max() < 30
    # world keys of the fan = union of literal DDA rays from the posed sensor
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [0.7, 0.1, -0.05]).as_matrix()
    T[:3, 3] = [0.31, -1.2, 0.4]
    pts = np.array([[2.0, 0.1, 0.0], [3.0, 3.0, 0.0], [5.0, 0.0, 0.0]])  # inside, outside (az), too far
    fan, hits = radar_scan_keys(pts, T, dirs[::37], RES, 0.0, max_range)
    ends = T[:3, 3] + dirs[::37] @ T[:3, :3].T * max_range
    ref = set().union(*(dda_ray_keys(T[:3, 3], e, RES) for e in ends))
    assert {tuple(k) for k in fan.tolist()} == ref
    world = pts @ T[:3, :3].T + T[:3, 3]
    assert np.array_equal(hits, coord_to_key(world, RES))


def test_interpolate_se3_against_scipy_slerp() -> None:
    rng = np.random.default_rng(3)
    t = np.sort(rng.integers(0, 10**10, 20))
    q = Rotation.random(20, random_state=4).as_quat()
    xyz = rng.normal(size=(20, 3))
    tq = np.r_[t[0] - 1, rng.integers(t[0], t[-1], 50), t[-1], t[-1] + 5]
    T, valid = interpolate_se3(tq, t, xyz, q)
    assert valid.tolist() == [False] + [True] * 51 + [False]
    ref_rot = Slerp(t.astype(float), Rotation.from_quat(q))(tq[valid].astype(float)).as_matrix()
    assert np.allclose(T[valid, :3, :3], ref_rot, atol=1e-9)
    i = np.searchsorted(t, tq[5], side="right") - 1
    w = (tq[5] - t[i]) / (t[i + 1] - t[i])
    assert np.allclose(T[5, :3, 3], (1 - w) * xyz[i] + w * xyz[i + 1])


def test_interpolate_se2_unwraps_yaw() -> None:
    T, valid = interpolate_se2([5, 15], [0, 10, 20], [0, 1, 2], [0, 0, 0], [3.1, -3.1, -3.0], z=0.4)
    assert valid.all()
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    assert abs(abs(yaw[0]) - np.pi) < 1e-6  # halfway between 3.1 and -3.1 across the wrap is pi
    assert np.allclose(T[:, 2, 3], 0.4) and np.allclose(T[:, :2, 3], [[0.5, 0], [1.5, 0]])


def test_horizontal_fov_mask() -> None:
    pts = np.array([[1, 0, 0], [0, 1, 0], [-1, 0.01, 0], [0.1, -1, 5]], float)
    assert horizontal_fov_mask(pts, [0, 1, 0], np.pi).tolist() == [True, True, True, False]
    assert horizontal_fov_mask(pts, [1, 0, 0], np.pi).tolist() == [True, True, False, True]
    assert horizontal_fov_mask(pts, [1, 0, 0], 2 * np.pi).all()
