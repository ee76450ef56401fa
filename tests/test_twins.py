"""ColoRadar twins: voxel-map ray casting, recorded-path trajectories, the registered twin sequences.

The real maps are read from ``../shared/data/coloradar_maps`` (beside the clone, as in CI); tests that need
them skip with a message when it is absent.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.errors import UserError
from pipeline.sequences import load_registry
from simulator.path_trajectory import PathTrajectory
from simulator.raycast import cast
from simulator.sensor_errors import SensorErrors
from simulator.twin import COLORADAR_ERRORS, PAPER_DURATIONS_S, TwinParams, carve_path, twin_world
from simulator.voxel_scatterers import VoxelScatterParams, build_voxel_scatterers
from simulator.voxel_world import VoxelGrid, cast_rays, cast_voxels_brute, grid_from_points, voxel_scene

ROOT = Path(__file__).resolve().parents[1]
SHARED_MAPS = ROOT.parent / "shared" / "data" / "coloradar_maps"
needs_shared = pytest.mark.skipif(not (SHARED_MAPS / "aspen_run0" / "lidar.parquet").is_file(),
                                  reason=f"the shared ColoRadar maps are not at {SHARED_MAPS} (CI puts shared/ "
                                         "beside the clone)")
RES = 0.15


def _random_grid(seed: int, n: int = 250, size: int = 10) -> tuple[np.ndarray, VoxelGrid]:
    rng = np.random.default_rng(seed)
    pts = (rng.integers(0, size, (n, 3)) + 0.5) * RES + np.array([1.03, -2.4, 0.37])
    return pts, grid_from_points(pts, RES)


def test_grid_holds_exactly_the_voxel_centres() -> None:
    pts, g = _random_grid(0)
    cells = np.argwhere(g.occupied)
    got = g.centres(cells)
    want = np.unique(np.round(pts, 6), axis=0)
    assert len(got) == len(want)
    np.testing.assert_allclose(np.unique(np.round(got, 6), axis=0), want, atol=1e-9)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_dda_hits_equal_the_brute_force_reference(seed: int) -> None:
    """Random rays from inside and outside the grid, some axis-aligned: same first voxel, same range."""
    _, g = _random_grid(seed)
    rng = np.random.default_rng(100 + seed)
    n = 1500
    span = np.asarray(g.shape) * RES
    o = g.origin + rng.uniform(0.0, 1.0, (n, 3)) * span
    o[n // 2:] = g.origin + rng.uniform(-0.5, 1.5, (n - n // 2, 3)) * span  # many outside the grid
    d = rng.normal(size=(n, 3))
    d[n // 2:] += 2 * (g.origin + span / 2 - o[n // 2:]) / np.linalg.norm(span)  # ... mostly aimed at it
    d[: n // 5, rng.integers(0, 3)] = 0.0  # rays in an axis plane
    d[n // 5: n // 4, :] = np.eye(3)[rng.integers(0, 3, n // 4 - n // 5)]  # axis-aligned rays
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = cast_rays(g, o, d, max_range=4.0)
    r, c = cast_voxels_brute(g, o, d, max_range=4.0)
    hit = np.isfinite(r)
    assert hit.sum() > n // 4  # the test exercises hits and misses
    assert (~hit).sum() > n // 10
    np.testing.assert_array_equal(np.isfinite(h.range), hit)
    np.testing.assert_allclose(h.range[hit], r[hit], atol=1e-9)
    np.testing.assert_array_equal(h.cell[hit], c[hit])


def test_raycast_dispatches_to_the_voxel_scene() -> None:
    """A flat voxel wall at x = 3 m: the scene caster's ranges, kinds and incidence."""
    yy, zz = np.meshgrid(np.arange(-20, 20), np.arange(-10, 10), indexing="ij")
    wall = np.column_stack([np.full(yy.size, 20), yy.ravel(), zz.ravel()]).astype(float) * RES + RES / 2
    sc = voxel_scene("wall", grid_from_points(wall, RES))
    x_face = 20 * RES
    heading = np.deg2rad([0.0, 20.0, -30.0])
    hits = cast(sc, np.zeros((3, 3)), np.column_stack([np.cos(heading), np.sin(heading)]), np.array([0.0, 0.1]))
    expect = x_face / np.cos(heading)[:, None] * np.sqrt(1 + np.array([0.0, 0.1]) ** 2)[None]
    np.testing.assert_allclose(hits.range, expect, atol=1e-9)
    np.testing.assert_allclose(hits.cos_incidence, x_face / expect, atol=1e-9)
    np.testing.assert_array_equal(hits.normal_xy[..., 0], -1.0)
    assert (hits.material == 0).all()


def test_voxel_surface_scatterers_are_one_sided() -> None:
    """A two-voxel-thick wall: a radar on one side gets only that side's surface scatterers."""
    from simulator.params import RadarParams

    yy, zz = np.meshgrid(np.arange(-15, 15), np.arange(-5, 10), indexing="ij")
    wall = np.concatenate([np.column_stack([np.full(yy.size, i), yy.ravel(), zz.ravel()]) for i in (20, 21)])
    g = grid_from_points(wall.astype(float) * RES + RES / 2, RES)
    scat = build_voxel_scatterers(g, RadarParams(scatterer_density=40.0), VoxelScatterParams(edge_density=0.0),
                                  np.random.default_rng(0))
    near_side = scat.pt_pos[:, 0] < 21 * RES
    assert near_side.any() and (~near_side).any()
    front = scat.returns(np.array([1.0, 0.0, 0.5]), 20.0)
    back = scat.returns(np.array([5.0, 0.0, 0.5]), 20.0)
    assert len(front.pos) and len(back.pos)
    assert (front.pos[:, 0] <= 20 * RES + 1e-9).all()
    assert (back.pos[:, 0] >= 22 * RES - 1e-9).all()


def test_path_trajectory_is_smooth_and_faces_its_direction_of_travel() -> None:
    """A noisy 15 Hz figure with a stop: uniform time, bounded accelerations, heading along the tangent."""
    rng = np.random.default_rng(4)
    duration = 60.0
    n = int(duration * 15) + 1
    t = np.linspace(0, duration, n)
    s = np.where(t < 30, t, np.where(t < 35, 30.0, t - 5.0)) * 0.8  # a 5 s stop
    pos = np.column_stack([6 * np.cos(s / 6), 4 * np.sin(s / 6), 0.1 * np.sin(t / 7)])
    pos += rng.normal(0, 0.02, pos.shape)
    tr = PathTrajectory(pos, duration)
    tt = np.arange(0, duration, 1 / 300)
    st = tr.state(tt)
    for a in (st.position, st.velocity, st.acceleration, st.yaw, st.yaw_rate, st.yaw_acc):
        assert np.isfinite(a).all()
    assert np.abs(st.acceleration).max() < 3.0  # walking: no spikes from the 2 cm jitter
    assert np.abs(st.yaw_acc).max() < 10.0
    np.testing.assert_allclose(tr.t_samples[[0, -1]], [0.0, duration])
    err = np.linalg.norm(tr.state(tr.t_samples).position - pos, axis=1)
    assert np.median(err) < 0.05
    moving = np.hypot(st.velocity[:, 0], st.velocity[:, 1]) > 0.3
    travel = np.arctan2(st.velocity[moving, 1], st.velocity[moving, 0])
    facing = st.yaw[moving] + np.pi / 2  # the rig's forward axis is base +y
    assert np.abs(np.angle(np.exp(1j * (facing - travel)))).max() < np.deg2rad(10)
    stopped = (tt > 31) & (tt < 34)
    assert np.ptp(np.unwrap(st.yaw[stopped])) < np.deg2rad(15)  # heading held through the stop


def test_carving_removes_only_voxels_near_the_path() -> None:
    path = np.column_stack([np.linspace(0, 5, 50), np.zeros(50), np.zeros(50)])
    pts = np.array([[1.0, 0.2, 0.0], [2.0, 0.0, 0.44], [3.0, 0.5, 0.0], [2.0, 0.0, -1.0]])
    np.testing.assert_array_equal(carve_path(pts, path, 0.45), [False, False, True, True])


def test_twins_carry_the_coloradar_error_model() -> None:
    """The twins' rig has the datasheet error model (the drifting worlds' terms); ``errors={}`` turns it off."""
    path = np.column_stack([np.linspace(0, 5, 50), np.zeros(50), np.full(50, 0.5)])
    wall = np.array([[x, 2.0, z] for x in np.arange(0, 5, 0.15) for z in np.arange(0, 1.5, 0.15)])
    w = twin_world("x_run0", wall, path, duration=10.0)
    e = SensorErrors(**w.spec.errors)
    assert e.active and e.radar_time_offset_s == COLORADAR_ERRORS["radar_time_offset_s"] > 0
    assert e.radar_mount_sigma_deg > 0 and e.gyro_bias_instability > 0
    off = twin_world("x_run0", wall, path, duration=10.0, params=TwinParams(errors={}))
    assert not SensorErrors(**off.spec.errors).active


def test_registered_twins_match_the_coloradar_sequences() -> None:
    reg = load_registry()
    for i in range(1, 7):
        twin, real = reg[f"coloradar_{i}_twin"], reg[f"coloradar_{i}"]
        assert twin.kind == "simulated" and twin.format == "bag"
        assert real.run is not None and real.run.split("_", 3)[3] == twin.scene
        assert twin.duration == PAPER_DURATIONS_S[str(twin.scene)]


def test_twin_without_rmap_root_is_a_one_line_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    seq = load_registry()["coloradar_3_twin"]
    monkeypatch.delenv("RMAP_ROOT", raising=False)
    with pytest.raises(UserError, match=r"RMAP_ROOT is not set.*'edgar_classroom_run0'") as exc:
        seq.resolve_source()
    assert "\n" not in str(exc.value)
    monkeypatch.setenv("RMAP_ROOT", str(tmp_path))
    with pytest.raises(UserError, match=r"RMAP_ROOT=.*no maps of scene 'edgar_classroom_run0'"):
        seq.resolve_source()


@needs_shared
def test_twin_geometry_on_the_real_maps() -> None:
    """All six twins: the path lies in free space of its map after carving, with bounded accelerations."""
    from sources.mapset import read_map_set

    for scene, duration in PAPER_DURATIONS_S.items():
        maps = read_map_set(SHARED_MAPS, scene)
        points = maps.lidar if maps.lidar is not None else maps.lidar_filtered
        w = twin_world(scene, points, maps.trajectory)
        assert w.duration == duration
        st = w.trajectory.state(np.arange(0, duration, 0.01))
        assert np.abs(st.acceleration).max() < 5.0, scene
        cells = w.grid.cell_of(st.position)
        assert w.grid.inside(cells).all(), scene
        assert not w.grid.occupied[cells[:, 0], cells[:, 1], cells[:, 2]].any(), scene


@needs_shared
def test_short_twin_piece_is_generated_and_ingested(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Three seconds of coloradar_1_twin from the shared maps, through the registry, the simulator and ingest."""
    from pipeline.config import Workflow
    from pipeline.registry import load_stages
    from pipeline.runner import Runner
    from schemas.io import read_artifact
    from sources.mapset import read_map_set

    monkeypatch.setenv("RMAP_ROOT", str(SHARED_MAPS))
    monkeypatch.setenv("RADAR_PIPELINE_CACHE", str(tmp_path / "cache"))
    seq = dataclasses.replace(load_registry()["coloradar_1_twin"], duration=3.0)
    Runner(seq, tmp_path / "runs", load_stages(), Workflow("test", ["ingest"]), {}).run(["ingest"])
    out = tmp_path / "runs" / seq.name / "ingest"
    radar = read_artifact(out / "radar.parquet", "radar")
    lidar = read_artifact(out / "lidar.parquet", "lidar")
    gt = read_artifact(out / "groundtruth.parquet", "groundtruth")
    assert radar.num_rows > 100 and lidar.num_rows > 10_000 and gt.num_rows >= 20
    assert len(np.unique(radar.column("scan").to_numpy())) >= 25  # 10 Hz
    # ground truth follows the recorded path (time uniform over the paper's 86 s)
    path = read_map_set(SHARED_MAPS, "aspen_run0").trajectory
    t = (gt.column("t_ns").to_numpy() - gt.column("t_ns").to_numpy()[0]) / 1e9
    xyz = np.column_stack([gt.column(c).to_numpy() for c in ("x", "y", "z")])
    k = np.clip(np.round(t / (86.0 / (len(path) - 1))).astype(int), 0, len(path) - 1)
    assert np.median(np.linalg.norm(xyz - path[k], axis=1)) < 0.3


def _cli(*args: str, env: dict[str, str]) -> Any:
    import os
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, **env, "COLUMNS": "200"}, timeout=300)


@needs_shared
def test_pipeline_simulate_writes_a_twin(tmp_path: Path) -> None:
    """``pipeline simulate --world coloradar_1_twin`` (registered) and ``<scene>_twin`` (any scene): the twin's
    ground truth follows the scene's recorded path; past the path's end, or without the maps, one-line errors."""
    import json

    from sources.mapset import read_map_set

    env = {"RMAP_ROOT": str(SHARED_MAPS)}
    r = _cli("simulate", "--world", "coloradar_1_twin", "--out", str(tmp_path / "a"), "--duration", "2",
             "--format", "folder", env=env)
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()) == tmp_path / "a"
    meta = json.loads((tmp_path / "a" / "sim" / "meta.json").read_text())
    assert meta["world"] == "aspen_run0_twin" and meta["duration_s"] == 2.0
    rows = np.loadtxt(tmp_path / "a" / "groundtruth" / "groundtruth_poses.txt", ndmin=2)  # x y z qx qy qz qw
    start = read_map_set(SHARED_MAPS, "aspen_run0").trajectory[0]
    assert len(rows) >= 10 and np.linalg.norm(rows[0, :3] - start) < 0.3
    r = _cli("simulate", "--world", "arpg_lab_run2_twin", "--out", str(tmp_path / "b"), "--duration", "1",
             env=env)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "b.bag").is_file() and not list(tmp_path.glob(".tmp-*"))
    r = _cli("simulate", "--world", "coloradar_1_twin", "--out", str(tmp_path / "c"), "--duration", "90", env=env)
    assert r.returncode == 2 and "recorded path of 86 s" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "c.bag").exists()
    r = _cli("simulate", "--world", "atlantis_run0_twin", "--out", str(tmp_path / "d"), env=env)
    assert r.returncode == 2 and "no maps of scene 'atlantis_run0'" in r.stderr
    r = _cli("simulate", "--world", "coloradar_1_twin", "--out", str(tmp_path / "e"), env={"RMAP_ROOT": ""})
    assert r.returncode == 2 and "RMAP_ROOT is not set" in r.stderr


def _wall_twin(params: TwinParams | None = None) -> Any:
    path = np.column_stack([np.linspace(0, 5, 50), np.zeros(50), np.full(50, 0.5)])
    wall = np.array([[x, 2.0, z] for x in np.arange(-1, 6, 0.15) for z in np.arange(0, 1.5, 0.15)])
    return twin_world("x_run0", wall, path, duration=10.0, params=params)


def test_twin_radar_overrides_reach_the_simulation_only_for_twins() -> None:
    """TwinParams.radar (default: the tuned TWIN_RADAR) sets the twin's RadarParams; other worlds keep theirs."""
    from simulator.params import RadarParams
    from simulator.simulate import Simulation
    from simulator.twin import TWIN_RADAR

    sim = Simulation(_wall_twin(), 2.0, 0, workers=1)
    assert sim.radar_p == RadarParams(**TWIN_RADAR)
    sim = Simulation(_wall_twin(TwinParams(radar={"clutter_rate": 33.0})), 2.0, 0, workers=1)
    assert sim.radar_p.clutter_rate == 33.0
    assert RadarParams().clutter_rate == 3.0  # the built-in worlds' default is not the twins' tuning


def test_tuning_radar_map_equals_the_voxel_stage_sensor_model() -> None:
    """experiments.twins_tune_radar.radar_map = the voxel stage's fan model with radar_prob_miss 0.5."""
    from experiments.twins_tune_radar import radar_map
    from simulator import rig
    from simulator.simulate import Simulation
    from stages.voxel.radar_model import fan_directions, radar_scan_keys
    from stages.voxel.voxel_map import SensorModel, VoxelMap, coord_to_key

    sim = Simulation(_wall_twin(TwinParams(errors={})), 3.0, 1, workers=1)
    fast = {tuple(k) for k in coord_to_key(radar_map(sim), RES)}
    vmap = VoxelMap(RES, SensorModel(0.7, 0.5, 0.12, 0.97, 0.5))
    dirs = fan_directions(np.radians(45), np.radians(45), RES, 10.0)
    for k in range(sim.n_windows):
        for scan in sim.radar_scans(k):
            st = sim.traj.state(np.array([scan.t]))
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = st.rotation.as_matrix()[0], st.position[0]
            xyz = np.column_stack([scan.points[c] for c in ("x", "y", "z")]).astype(np.float64)
            fan, hits = radar_scan_keys(xyz, T @ rig.BASE_TO_RADAR.matrix(), dirs, RES, 0.0, 10.0)
            vmap.integrate(fan, hits, hits_need_free=True)
    stage = {tuple(k) for k in coord_to_key(vmap.centres()[0], RES)}
    assert len(stage) > 50
    assert len(fast & stage) / len(fast | stage) > 0.95  # the cone test against the fan's voxels: edge ties only


def test_tuning_pick_rule_and_refusal_of_the_twin_scenes(capsys: pytest.CaptureFixture[str]) -> None:
    from experiments.twins_tune_radar import GRID, main, pick, score, trials

    real = {"lr_ratio": 4.0, "cd_l2": 1.0}
    assert score({"lr_ratio": 4.0, "cd_l2": 1.0}, real) == 0.0
    assert score({"lr_ratio": 2.0, "cd_l2": 2.0}, real) == pytest.approx(2 * np.log(2))
    rows = [{"trial": 0, "score": 1.0}, {"trial": 0, "score": 0.2}, {"trial": 1, "score": 0.5},
            {"trial": 1, "score": 0.6}]
    assert pick(rows)["trial"] == 1
    ts = trials(GRID)
    assert len(ts) == int(np.prod([len(v) for v in GRID.values()])) and ts[0] == {k: v[0] for k, v in GRID.items()}
    assert main(["aspen_run0"]) == 2
    assert "train scenes only" in capsys.readouterr().err
