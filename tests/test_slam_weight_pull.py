"""The weight-pull diagnostic (stages/slam/weight_pull.py): the pull's sign and size, and shadow weights that
leave the filter unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import sample_beams
from stages.slam.grid_map import GridModel, GridParticleMaps, make_grid_spec
from stages.slam.methods import OdometryMotion, SlamConfig, run_method
from stages.slam.rbpf import HilbertParticleMaps
from stages.slam.synthetic import make_run
from stages.slam.weight_pull import ShadowedMaps, endpoint_shadow, pull_toward_truth, window_table


def test_pull_is_positive_towards_the_truth_and_negative_away_from_it() -> None:
    e = np.radians(np.array([[-2.0, 0.0, 2.0, 4.0]]))  # mean error +1 deg
    towards = pull_toward_truth(e, -np.abs(np.degrees(e)))  # prefers small errors
    away = pull_toward_truth(e, np.degrees(e))  # prefers larger positive errors
    flat = pull_toward_truth(e, np.zeros_like(e))
    w = np.exp(-np.abs([-2.0, 0.0, 2.0, 4.0]))
    assert towards[0] == pytest.approx(-(np.sum(w / w.sum() * [-2.0, 0.0, 2.0, 4.0]) - 1.0))
    assert towards[0] > 0 > away[0] and flat[0] == pytest.approx(0.0)
    # the sign follows the side of the truth the cloud is on
    assert pull_toward_truth(-e, -np.abs(np.degrees(e)))[0] == pytest.approx(towards[0])
    with pytest.raises(ValueError, match="scans, particles"):
        pull_toward_truth(e[0], e[0])


def test_window_table_sums_each_window() -> None:
    t = np.arange(10.0)
    rows = window_table(t, np.ones(10), {"a": np.ones(10)}, [0.0, 4.0, 10.0])
    assert [(r["scans"], r["a"]) for r in rows] == [(4, 4.0), (6, 6.0)]


def test_shadow_weights_leave_the_filter_unchanged_and_record_every_scan() -> None:
    """rich_slam on the synthetic corridor with a grid and an endpoint-only shadow: the same trajectory to the bit
    as without them, one record per scan, and the endpoint shadow equal to the filter's own weight when the filter
    itself weighs endpoints only."""
    n = 60
    run = make_run(n, np.random.default_rng(1))
    scans = [sample_beams(p, np.zeros(2), 1.0, 5.0) for p in run.scans]
    motion = OdometryMotion(np.tile(np.diag([0.01, 0.01, 0.005]) ** 2, (n, 1, 1)), np.full(n, 0.1))
    basis = hm.make_basis([15.0, 15.0], [0.0, 0.0], 64)
    wrapped: list[ShadowedMaps] = []

    def shadow(maps: HilbertParticleMaps) -> ShadowedMaps:
        grid = GridParticleMaps(make_grid_spec(basis.centre, basis.half_widths, 0.1), len(maps.theta), GridModel())
        wrapped.append(ShadowedMaps(maps, {"grid": grid, "endpoints": endpoint_shadow(maps)}))
        return wrapped[-1]

    for free_weight in (1.0, 0.0):
        cfg = SlamConfig(n_particles=12, workers=0, proposal="odometry_covariance", free_weight=free_weight)
        plain = run_method("rich_slam", run.odometry, scans, basis, cfg, seed=0, motion=motion)
        shadowed = run_method("rich_slam", run.odometry, scans, basis, cfg, seed=0, motion=motion, wrap_maps=shadow)
        np.testing.assert_array_equal(plain.poses, shadowed.poses)
        rec = {k: np.stack(v) for k, v in wrapped[-1].record.items()}
        assert all(v.shape == (n, 12) for v in rec.values())
        assert np.all(np.isfinite(rec["grid"])) and np.ptp(rec["grid"][1:], axis=1).max() > 0
        if free_weight == 0.0:
            np.testing.assert_allclose(rec["endpoints"], rec["main"], rtol=1e-9, atol=1e-9)
        else:
            assert np.abs(rec["endpoints"] - rec["main"]).max() > 1e-3
