"""The yaw information of a filter's scan weight along a path (stages/slam/heading_information.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, sample_beams
from stages.slam.grid_map import GridModel, GridParticleMaps, make_grid_spec
from stages.slam.heading_information import yaw_information
from stages.slam.methods import SlamConfig, make_hilbert_maps, weight_information

N_SCANS = 12


def _scans(endpoints: np.ndarray) -> list[BeamSamples]:
    """The same scan, from a robot standing at the origin, ``N_SCANS`` times."""
    return [sample_beams(endpoints, [0.0, 0.0], 1.0, 5.0) for _ in range(N_SCANS)]


def _ring() -> np.ndarray:
    """Beams in every direction to a circle of radius 3 m: turning the robot changes nothing it sees."""
    a = np.linspace(-np.pi, np.pi, 180, endpoint=False)
    return 3.0 * np.c_[np.cos(a), np.sin(a)]


def _corner() -> np.ndarray:
    """The same number of beams to two walls meeting in a corner (x = 3 and y = 2): turning moves every endpoint."""
    a = np.linspace(-0.3, 1.8, 180)
    d = np.minimum(np.where(np.cos(a) > 1e-9, 3.0 / np.maximum(np.cos(a), 1e-9), np.inf),
                   np.where(np.sin(a) > 1e-9, 2.0 / np.maximum(np.sin(a), 1e-9), np.inf))
    return d[:, None] * np.c_[np.cos(a), np.sin(a)]


def _hilbert(cfg: SlamConfig) -> object:
    basis = hm.make_basis(np.array([8.0, 8.0]), np.zeros(2), cfg.n_basis, cfg.basis_kind)
    return make_hilbert_maps(cfg, basis, "rich_slam", 3, "covariance")


def _grid(cfg: SlamConfig) -> object:
    return GridParticleMaps(make_grid_spec(np.zeros(2), np.array([8.0, 8.0]), 0.1), 3, GridModel())


@pytest.mark.parametrize("maps", [_hilbert, _grid])
def test_a_scan_that_turning_does_not_change_holds_no_heading_and_a_corner_does(maps: object) -> None:
    cfg = SlamConfig(endpoint_tolerance=0.0, workers=0)  # the stage's default tolerance (a disc turns with the robot)
    poses = np.zeros((N_SCANS, 3))
    ring = yaw_information(maps(cfg), poses, _scans(_ring()))  # type: ignore[operator]
    corner = yaw_information(maps(cfg), poses, _scans(_corner()))  # type: ignore[operator]
    assert ring[0] == corner[0] == 0.0  # no map before the first scan
    assert np.all(corner[1:] > 0)
    assert np.median(ring[1:]) < 0.05 * np.median(corner[1:])


def test_empty_scans_hold_nothing_and_mismatched_lengths_are_refused() -> None:
    cfg = SlamConfig(workers=0)
    scans = _scans(_corner())
    scans[5] = sample_beams(np.zeros((0, 2)), [0.0, 0.0], 1.0, 5.0)
    info = yaw_information(_hilbert(cfg), np.zeros((N_SCANS, 3)), scans)  # type: ignore[arg-type]
    assert info[5] == 0.0 and info[6] > 0
    with pytest.raises(ValueError, match="11 poses for 12 scans"):
        yaw_information(_hilbert(cfg), np.zeros((N_SCANS - 1, 3)), scans)  # type: ignore[arg-type]


def test_the_grid_weight_holds_more_heading_than_the_hilbert_weight_on_the_same_scans() -> None:
    """The measurement behind stop 47's change (the grid's likelihood field is far steeper in yaw)."""
    cfg = SlamConfig(workers=0)
    basis = hm.make_basis(np.array([8.0, 8.0]), np.zeros(2), cfg.n_basis, cfg.basis_kind)
    poses, scans = np.zeros((N_SCANS, 3)), _scans(_corner())
    grid = weight_information("fastslam_grid", cfg, basis, poses, scans)
    hil = weight_information("rich_slam", cfg, basis, poses, scans)
    assert np.median(grid[1:]) > 3 * np.median(hil[1:]) > 0
    with pytest.raises(ValueError, match="no scan weight"):
        weight_information("odometry", cfg, basis, poses, scans)


def test_informed_exponent_switches_on_the_weights_information_before_the_filter() -> None:
    """``informed_exponent_information``: a filter whose weight's median information along the odometry reaches
    the threshold runs exactly as one configured with ``informed_likelihood_exponent``; below it, as the default;
    ``rich_slam_paper`` never switches."""
    from stages.slam.methods import informed_exponent, run_method

    cfg = SlamConfig(endpoint_tolerance=0.0, workers=0, n_particles=8, n_basis=16, likelihood_exponent=0.5,
                     estimate="smoothed")
    scans, poses = _scans(_corner()), np.zeros((N_SCANS, 3))
    basis = hm.make_basis(np.array([8.0, 8.0]), np.zeros(2), cfg.n_basis, cfg.basis_kind)
    median = float(np.median(weight_information("rich_slam", cfg, basis, poses, scans)))
    assert median > 0
    on = replace(cfg, informed_exponent_information=0.5 * median, informed_likelihood_exponent=1.0)
    off = replace(cfg, informed_exponent_information=2.0 * median, informed_likelihood_exponent=1.0)
    assert informed_exponent("rich_slam", on, basis, poses, scans).likelihood_exponent == 1.0
    assert informed_exponent("rich_slam", off, basis, poses, scans).likelihood_exponent == 0.5
    assert informed_exponent("rich_slam_paper", on, basis, poses, scans) == cfg.for_method("rich_slam_paper")
    assert informed_exponent("fastslam_grid", on, basis, poses, scans) == on
    odometry = np.c_[0.05 * np.arange(N_SCANS), np.zeros(N_SCANS), np.zeros(N_SCANS)]
    runs = {k: run_method("rich_slam", odometry, scans, basis, c, seed=3)
            for k, c in {"on": on, "off": off, "one": replace(cfg, likelihood_exponent=1.0), "half": cfg}.items()}
    assert runs["on"].likelihood_exponent == 1.0 and runs["off"].likelihood_exponent == 0.5
    np.testing.assert_array_equal(runs["on"].poses, runs["one"].poses)
    np.testing.assert_array_equal(runs["off"].poses, runs["half"].poses)
    assert not np.array_equal(runs["on"].n_eff, runs["off"].n_eff)  # the exponent changed the weights
