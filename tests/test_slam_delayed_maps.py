"""The delayed map (slam.map_delay, stages/slam/delayed_maps.py): what each scan is weighed against, resampling
of the pending scans, and the parameter's checks."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, sample_beams
from stages.slam.delayed_maps import DelayedMaps
from stages.slam.methods import OdometryMotion, SlamConfig, make_hilbert_maps, run_method
from stages.slam.rbpf import HilbertParticleMaps, MapModel, compose
from stages.slam.stage import SlamParams
from stages.slam.synthetic import make_run

MODEL = MapModel(1.0, 16.0, 0.36, form="information")
BASIS = hm.make_basis([10.0, 10.0], [0.0, 0.0], 64)


def _walk(seed: int, steps: int, n: int = 4) -> list[tuple[np.ndarray, BeamSamples]]:
    rng = np.random.default_rng(seed)
    pose: np.ndarray = np.zeros(3)
    out = []
    for _ in range(steps):
        pose = compose(pose, np.array([0.3, 0.0, 0.02]))
        a, r = rng.uniform(-1.0, 1.0, 10), rng.uniform(1.0, 5.0, 10)
        scan = sample_beams(np.column_stack([r * np.cos(a), r * np.sin(a)]), np.zeros(2), 1.0, 5.0)
        out.append((pose + rng.normal(0.0, [0.05, 0.05, 0.01], (n, 3)), scan))
    return out


def test_each_scan_is_weighed_against_the_map_without_its_last_d_scans() -> None:
    """With a delay of 3, scan k scores exactly as against a plain map that holds scans 0..k-4, each at its own
    particle's pose; a resampling in between carries the pending scans' poses with the particles."""
    steps, d = 9, 3
    walk = _walk(0, steps)
    delayed = DelayedMaps(HilbertParticleMaps(BASIS, 4, MODEL), d)
    history: list[tuple[np.ndarray, BeamSamples]] = []
    idx = np.array([2, 2, 0, 3])
    for k, (poses, scan) in enumerate(walk):
        ll = delayed.log_likelihood(poses, scan)
        ref = HilbertParticleMaps(BASIS, 4, MODEL)
        for p, s in history[: max(0, k - d)]:
            ref.update(p, s)
        np.testing.assert_allclose(ll, ref.log_likelihood(poses, scan), rtol=1e-9, atol=1e-9)
        history.append((poses, scan))
        if k == 5:
            delayed.select(idx)
            history = [(p[idx], s) for p, s in history]
    assert len(delayed.pending) == d
    delayed.flush()
    full = HilbertParticleMaps(BASIS, 4, MODEL)
    for p, s in history:
        full.update(p, s)
    for k in range(4):
        np.testing.assert_allclose(delayed.maps.map_of(k)[0], full.map_of(k)[0], rtol=1e-8, atol=1e-10)


def test_delay_is_wired_for_rich_slam_only_and_checked() -> None:
    cfg = SlamConfig(n_particles=4, workers=0, map_delay=5)
    assert isinstance(make_hilbert_maps(cfg, BASIS, "rich_slam", 4), DelayedMaps)
    assert isinstance(make_hilbert_maps(cfg.for_method("rich_slam_paper"), BASIS, "rich_slam_paper", 4),
                      HilbertParticleMaps)
    # the refined method reads the map's means for its Laplace proposal: it keeps the undelayed global map
    assert cfg.for_method("rich_slam_refined").map_delay == 0
    with pytest.raises(ValueError, match="at least one scan"):
        DelayedMaps(HilbertParticleMaps(BASIS, 4, MODEL), 0)
    with pytest.raises(ValidationError, match="map_delay = 10 runs on the numpy backend"):
        SlamParams(map_delay=10, map="submaps")
    assert SlamParams(map_delay=10).config().map_delay == 10


def test_filter_runs_with_a_delay() -> None:
    n = 80
    run = make_run(n, np.random.default_rng(2))
    scans = [sample_beams(p, np.zeros(2), 1.0, 5.0) for p in run.scans]
    motion = OdometryMotion(np.tile(np.diag([0.01, 0.01, 0.005]) ** 2, (n, 1, 1)), np.full(n, 0.1))
    cfg = SlamConfig(n_particles=10, workers=0, proposal="odometry_covariance", map_delay=10)
    basis = hm.make_basis([15.0, 15.0], [0.0, 0.0], 64)
    r = run_method("rich_slam", run.odometry, scans, basis, cfg, seed=0, motion=motion)
    assert r.poses.shape == (n, 3) and np.all(np.isfinite(r.poses)) and r.theta is not None
    # the other methods of the same run (the slam stage runs them all with one configuration)
    for method in ("rich_slam_refined", "rich_slam_paper"):
        other = run_method(method, run.odometry, scans, basis, cfg, seed=0, motion=motion)
        assert other.poses.shape == (n, 3) and np.all(np.isfinite(other.poses))
