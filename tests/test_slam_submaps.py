"""Local submaps of the Hilbert filters (issue 27 item 3): geometry, equality with one map, worker maps, the stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, sample_beams, to_world
from stages.slam.methods import OdometryMotion, SlamConfig, run_method
from stages.slam.rbpf import HilbertParticleMaps, MapModel, compose
from stages.slam.submaps import ClosedSubmap, SubmapModel, SubmapParticleMaps
from stages.slam.synthetic import make_run

MODEL = MapModel(1.0, 16.0, 0.36, form="information")


def _scan(rng: np.random.Generator, n: int = 10, max_range: float = 5.0) -> BeamSamples:
    a = rng.uniform(-1.0, 1.0, n)
    r = rng.uniform(1.0, max_range, n)
    return sample_beams(np.column_stack([r * np.cos(a), r * np.sin(a)]), np.zeros(2), 1.0, max_range)


def _walk(seed: int, steps: int) -> list[tuple[np.ndarray, BeamSamples]]:
    """Four particles' poses scattered about a robot driving a gentle arc, and a random scan at each step."""
    rng = np.random.default_rng(seed)
    pose: np.ndarray = np.zeros(3)
    out = []
    for _ in range(steps):
        pose = compose(pose, np.array([0.3, 0.0, 0.02]))
        out.append((pose + rng.normal(0.0, [0.05, 0.05, 0.01], (4, 3)), _scan(rng)))
    return out


def test_submaps_follow_the_robot_and_hold_every_sample_they_take() -> None:
    """Along a 40 m path every scan inserted into a submap lies inside its domain (the window rule), at most
    ``max_open`` are open, one is opened about every half window, and the weight comes from a submap with data."""
    rng = np.random.default_rng(0)
    g = SubmapModel(half_width=7.0, n_basis=16, reach=5.0, margin=0.5)
    maps = SubmapParticleMaps.create(g, 4, MODEL)
    pose: np.ndarray = np.zeros(3)
    weighed_from_data = 0
    for i in range(200):
        pose = compose(pose, np.array([0.2, 0.0, 0.004]))
        poses = pose + rng.normal(0.0, [0.05, 0.05, 0.01], (4, 3))
        s = _scan(rng)
        before = [(sm, sm.scans) for sm in maps.open]  # hold the objects: a freed submap's id() can be reused
        ll = maps.weigh_and_update(poses, s)
        assert 1 <= len(maps.open) <= g.max_open
        for sm in maps.open:
            assert np.all(sm.basis.contains(to_world(poses, s.points).reshape(-1, 2)))
        if i and np.ptp(ll) > 0:
            weighed_from_data += 1
        assert ll.shape == (4,) and np.all(np.isfinite(ll))
        held = [next((n for old, n in before if old is sm), 0) for sm in maps.open]
        assert [sm.scans for sm in maps.open] == [n + 1 for n in held]  # every open submap took the scan
    travelled = 200 * 0.2
    assert travelled / g.window <= maps.opened <= 2 * travelled / g.window + 2
    assert weighed_from_data >= 190  # every scan but the first is weighed against a map that has seen scans


def test_one_submap_weighs_and_updates_as_the_global_map_on_its_basis() -> None:
    """While the robot stays in the first submap's window, the submaps are that one map: weights equal
    :class:`HilbertParticleMaps` on the same basis, scan after scan, through resampling."""
    rng = np.random.default_rng(1)
    g = SubmapModel(half_width=9.0, n_basis=64, reach=5.0)
    sub = SubmapParticleMaps.create(g, 5, MODEL)
    poses: np.ndarray = rng.normal(0.0, 0.05, (5, 3))
    s0 = _scan(rng)
    assert np.all(sub.weigh_and_update(poses, s0) == 0.0)  # the first scan has no map to be weighed against
    ref = HilbertParticleMaps(sub.open[0].basis, 5, MODEL)
    ref.update(poses, s0)
    for i in range(20):
        poses = compose(poses, rng.normal([0.05, 0.0, 0.0], 0.01, (5, 3)))
        s = _scan(rng)
        np.testing.assert_allclose(sub.weigh_and_update(poses, s), ref.weigh_and_update(poses, s), rtol=1e-9)
        if i % 7 == 6:
            idx = rng.integers(0, 5, 5)
            sub.select(idx)
            ref.select(idx)
            poses = poses[idx]
    assert sub.opened == 1


def test_the_paper_and_the_refined_filter_keep_the_global_map() -> None:
    from stages.slam.stage import SlamParams

    cfg = SlamParams(map="submaps").config()
    assert cfg.submaps is not None and cfg.for_method("rich_slam").submaps == cfg.submaps
    assert cfg.submap_lengthscale_m == pytest.approx(1.0)
    assert cfg.for_method("rich_slam_paper").submaps is None
    assert cfg.for_method("rich_slam_refined").submaps is None
    assert SlamParams().config().submaps is None


def test_bad_submap_parameters_are_one_line_errors() -> None:
    from pydantic import ValidationError

    from stages.slam.stage import SlamParams

    with pytest.raises(ValidationError, match=r"submap_half_width = 5\.0: submap half width 5\.0 m leaves no window"):
        SlamParams(map="submaps", submap_half_width=5.0)
    with pytest.raises(ValidationError, match="submap_n_basis = 200 is not a perfect square"):
        SlamParams(map="submaps", submap_n_basis=200)
    with pytest.raises(ValidationError, match="numpy backend only"):
        SlamParams(map="submaps", backend="torch")
    SlamParams(map="submaps", backend="torch", method="rich_slam_paper", methods=["odometry", "rich_slam_paper"])


def test_submap_filter_corrects_a_drifting_heading_on_the_corridor() -> None:
    """The synthetic corridor, odometry whose heading drifts by 0.005 rad per metre: the submap filter with
    the endpoint-only weight keeps its heading RMSE well below the odometry's (0.054 against 0.128 rad when
    written; the paper's free-sample terms on the same submaps: 0.125)."""
    n = 400
    run = make_run(n, np.random.default_rng(3), odo_yaw_bias=0.0005)
    scans = [sample_beams(p, np.zeros(2), 1.0, 5.0) for p in run.scans]
    motion = OdometryMotion(np.tile(np.diag([0.01, 0.01, 0.005]) ** 2, (n, 1, 1)), np.full(n, 0.1))
    cfg = SlamConfig(n_particles=40, workers=0, proposal="odometry_covariance", estimate="weighted_mean",
                     likelihood_exponent=0.5, free_weight=0.0, submaps=SubmapModel(9.0, 256, 5.25))
    basis = hm.make_basis([15.0, 15.0], [0.0, 0.0], 16)  # unused by the submaps
    r = run_method("rich_slam", run.odometry, scans, basis, cfg, seed=0, motion=motion)
    err = np.abs(np.angle(np.exp(1j * (r.poses[:, 2] - run.groundtruth[:, 2]))))
    odo = np.abs(np.angle(np.exp(1j * (run.odometry[:, 2] - run.groundtruth[:, 2]))))
    assert np.sqrt(np.mean(err**2)) < 0.6 * np.sqrt(np.mean(odo**2))


def test_stage_runs_with_submaps(tmp_path: Path) -> None:
    from schemas.io import read_artifact
    from tests.test_slam_stage import _ctx, _run, _write_inputs

    inp = _write_inputs(tmp_path / "in", 40)
    ctx = _ctx(tmp_path / "out", inp["dirs"], n_particles=6, n_basis=64, workers=0, n_map_snapshots=2,
               stats_every=4, grid_spacing=1.0, map="submaps", submap_n_basis=64,
               methods=["odometry", "rich_slam", "rich_slam_paper"])
    _run(ctx)
    t = read_artifact(tmp_path / "out" / "trajectory.parquet", "trajectory")
    assert t.num_rows == 40 and np.all(np.isfinite(t["x"].to_numpy()))
    post = read_artifact(tmp_path / "out" / "map_posterior.parquet", "map_posterior").to_pylist()[0]
    assert post["M"] == 64  # the global map, replayed along the trajectory
    assert ctx.stats["methods"]["rich_slam"]["submaps_opened"] >= 1


def test_worker_submaps_equal_in_process_submaps_and_reuse_their_processes() -> None:
    """Submaps in worker processes (``parallel.submap_factory``: a closed submap's processes are reset to the
    next basis, update-only scans sent as such) give the in-process weights, scan after scan."""
    from stages.slam.parallel import ParallelHilbertMaps, submap_factory

    rng = np.random.default_rng(4)
    g = SubmapModel(half_width=7.0, n_basis=16, reach=5.0, margin=0.5)
    mine = SubmapParticleMaps.create(g, 6, MODEL)
    theirs = SubmapParticleMaps(g, submap_factory(6, MODEL, workers=2))
    pose: np.ndarray = np.zeros(3)
    try:
        for i in range(60):
            pose = compose(pose, np.array([0.25, 0.0, 0.01]))
            poses = pose + rng.normal(0.0, [0.05, 0.05, 0.01], (6, 3))
            s = _scan(rng)
            np.testing.assert_allclose(theirs.weigh_and_update(poses, s), mine.weigh_and_update(poses, s),
                                       rtol=1e-8, atol=1e-10)
            if i % 9 == 8:
                idx = rng.integers(0, 6, 6)
                mine.select(idx)
                theirs.select(idx)
        assert theirs.opened == mine.opened >= 4
        pools = {id(s.maps) for s in theirs.open} | {id(m) for m in theirs.spare}
        assert len(pools) <= g.max_open + 1  # processes started once per slot, not once per submap
        assert all(isinstance(s.maps, ParallelHilbertMaps) for s in theirs.open)
    finally:
        theirs.close()


def test_hybrid_maps_weigh_half_against_each_and_the_stage_builds_them() -> None:
    """``slam.map = hybrid``: every scan's log-likelihood is half the global map's and half the submaps', each
    map updated as when it runs alone."""
    from stages.slam.methods import make_hilbert_maps
    from stages.slam.stage import SlamParams
    from stages.slam.submaps import HybridParticleMaps

    cfg = SlamParams(map="hybrid", workers=0, submap_n_basis=16, n_basis=16).config()
    assert cfg.submap_share == 0.5 and SlamParams(map="submaps").config().submap_share == 1.0
    basis = hm.make_basis([20.0, 20.0], [0.0, 0.0], 16)
    hyb = make_hilbert_maps(cfg, basis, "rich_slam", 4, "information")
    assert isinstance(hyb, HybridParticleMaps)
    glob = make_hilbert_maps(SlamParams(workers=0, n_basis=16).config(), basis, "rich_slam", 4, "information")
    local = make_hilbert_maps(SlamParams(map="submaps", workers=0, submap_n_basis=16).config(), basis, "rich_slam", 4,
                              "information")
    for poses, s in _walk(5, 30):
        expect = 0.5 * glob.weigh_and_update(poses, s) + 0.5 * local.weigh_and_update(poses, s)
        np.testing.assert_allclose(hyb.weigh_and_update(poses, s), expect, rtol=1e-10, atol=1e-12)


def test_kept_submaps_weigh_a_revisit_against_the_first_visit() -> None:
    """With ``keep_closed``, a robot that drives away and comes back is weighed against the submap of its first
    visit (the oldest whose window holds it), by that submap's posterior means; resampling only moves row
    indices, and a closed submap's weight equals the mean-only weight of the open maps it was closed from."""
    rng = np.random.default_rng(3)
    g = SubmapModel(half_width=7.0, n_basis=16, reach=5.0, margin=0.5, keep_closed=True)
    maps = SubmapParticleMaps.create(g, 4, MODEL)
    pose: np.ndarray = np.zeros(3)
    path = [np.array([0.2, 0.0, 0.0])] * 60 + [np.array([0.0, 0.0, np.pi / 10])] * 10 + [np.array([0.2, 0.0, 0.0])] * 60
    for i, u in enumerate(path):
        pose = compose(pose, u)
        poses = pose + rng.normal(0.0, [0.02, 0.02, 0.005], (4, 3))
        maps.weigh_and_update(poses, _scan(rng))
        if i == 60:
            maps.select(np.array([0, 0, 2, 3]))
    assert maps.closed and maps.revisits > 0
    # at the end the robot is back at the start: the first submap (order 0) is what it is weighed against
    end = maps.weighing(pose + np.zeros((4, 3)))
    assert isinstance(end, ClosedSubmap) and end.order == 0
    assert len(end.theta) <= 3 and end.rows[0] == end.rows[1]  # particles 0 and 1 share one parent's row


def test_a_closed_submap_weighs_as_its_open_maps_mean_only() -> None:
    """The means a closed submap keeps are the open maps' exact posterior means (solved anew from the
    information form), and its weight equals the mean-only weight of those maps."""
    from dataclasses import replace

    from stages.slam.rbpf import hilbert_log_likelihood
    from stages.slam.submaps import posterior_means

    rng = np.random.default_rng(4)
    basis = hm.make_basis([7.0, 7.0], [0.0, 0.0], 16)
    maps = HilbertParticleMaps(basis, 3, MODEL)
    poses: np.ndarray = rng.normal(0.0, 0.05, (3, 3))
    for _ in range(4):
        maps.weigh_and_update(poses, _scan(rng))
    theta = posterior_means(maps)
    for k in range(3):
        np.testing.assert_allclose(theta[k], maps.map_of(k)[0], rtol=1e-10, atol=1e-12)
    closed = ClosedSubmap(basis, theta, np.arange(3), 4, 0)
    s = _scan(rng)
    want = hilbert_log_likelihood(basis, theta, np.empty(0), poses, s, replace(MODEL.weighting, use_variance=False))
    np.testing.assert_allclose(closed.log_likelihood(poses, s, MODEL.weighting), want)
    closed.select(np.array([2, 2, 0]))
    np.testing.assert_allclose(closed.theta[closed.rows], theta[[2, 2, 0]])
    assert len(closed.theta) == 2


def test_grid_share_weighs_a_share_against_each_particles_grid() -> None:
    """``slam.grid_share = s``: rich_slam's scan log-likelihood is (1 - s) times its Hilbert map's plus s times
    the FastSLAM grid's that each particle carries beside it, each map updated as when it runs alone; the paper's
    configuration keeps the Hilbert map alone; bad combinations are one-line errors."""
    from pydantic import ValidationError

    from stages.slam.grid_map import GridParticleMaps, make_grid_spec
    from stages.slam.methods import make_hilbert_maps
    from stages.slam.stage import SlamParams
    from stages.slam.submaps import HybridParticleMaps

    cfg = SlamParams(grid_share=0.3, workers=0, n_basis=16).config()
    basis = hm.make_basis([20.0, 20.0], [0.0, 0.0], 16)
    hyb = make_hilbert_maps(cfg, basis, "rich_slam", 4, "information")
    assert isinstance(hyb, HybridParticleMaps) and hyb.share == 0.3
    assert isinstance(make_hilbert_maps(cfg, basis, "rich_slam_paper", 4, "information"), HilbertParticleMaps)
    glob = make_hilbert_maps(SlamParams(workers=0, n_basis=16).config(), basis, "rich_slam", 4, "information")
    grid = GridParticleMaps(make_grid_spec(basis.centre, basis.half_widths, cfg.grid_resolution), 4, cfg.grid,
                            cfg.grid_likelihood_exponent)
    for poses, s in _walk(6, 20):
        g = grid.log_likelihood(poses, s)
        grid.update(poses, s)
        expect = 0.7 * glob.weigh_and_update(poses, s) + 0.3 * g
        got = hyb.weigh_and_update(poses, s)
        np.testing.assert_allclose(got, expect, rtol=1e-10, atol=1e-12)
    assert np.ptp(g) > 0  # the grid's term tells the particles apart
    with pytest.raises(ValidationError, match=r"grid_share = 0\.3 runs on the numpy backend with the global map"):
        SlamParams(grid_share=0.3, backend="torch", methods=["odometry", "rich_slam"])
    with pytest.raises(ValidationError, match=r"grid_share = 0\.3 runs on the numpy backend with the global map"):
        SlamParams(grid_share=0.3, map="submaps")
