"""The proposal from the odometry's covariance and the particles' yaw-rate bias (issue 27, items 3-4)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import sample_beams
from stages.slam.heading_fusion import informed
from stages.slam.methods import OdometryMotion, SlamConfig, domain_from_trajectory, fused_estimate, run_method
from stages.slam.rbpf import MotionNoise, Proposal, WideMode, YawBias, propagate, weighted_mean_pose
from stages.slam.se2 import compose, wrap_angle
from stages.slam.synthetic import make_run


def test_gmapping_proposal_draws_what_propagate_draws() -> None:
    poses = np.random.default_rng(1).normal(size=(30, 3))
    u = np.array([0.1, 0.01, 0.02])
    a = propagate(poses, u, MotionNoise(0.01, 0.002, 0.05), np.random.default_rng(4))
    rng = np.random.default_rng(4)
    b = compose(poses, Proposal(MotionNoise(0.01, 0.002, 0.05), 30, rng).draw(u, 30))
    np.testing.assert_array_equal(a, b)


def test_odometry_covariance_proposal_has_that_covariance_and_bias_corrects_yaw() -> None:
    cov = np.array([[4e-4, 1e-4, 2e-5], [1e-4, 2e-4, -1e-5], [2e-5, -1e-5, 1e-5]])
    n = 20000
    p = Proposal(MotionNoise(), n, np.random.default_rng(0), cov=np.stack([np.zeros((3, 3)), cov]),
                 dt=np.array([0.0, 0.1]), bias=YawBias(sigma0=0.02, walk=0.0))
    assert p.bias is not None
    b = p.bias.copy()
    d = p.draw([0.1, 0.0, 0.01], n)
    np.testing.assert_allclose(np.cov(d[:, :2].T), cov[:2, :2], rtol=0.05)
    # yaw: the increment less each particle's bias times dt, plus the yaw noise
    r = d[:, 2] - (0.01 - b * 0.1)
    assert abs(np.var(r) / cov[2, 2] - 1) < 0.05 and abs(np.mean(r)) < 1e-4
    with pytest.raises(ValueError, match="scan intervals"):
        Proposal(MotionNoise(), 3, np.random.default_rng(0), bias=YawBias())


def test_a_share_of_the_particles_carries_the_bias_the_rest_none_through_walks_and_resampling() -> None:
    """``YawBias.share``: the first share of the particles draw a bias and walk it; the others keep b = 0 (their
    heading is the odometry's plus noise), and resampling carries which is which. share = 1 draws as before."""
    n, dt = 10, np.full(6, 0.1)
    full = Proposal(MotionNoise(), n, np.random.default_rng(3), dt=dt, bias=YawBias(0.01, 1e-3))
    half = Proposal(MotionNoise(), n, np.random.default_rng(3), dt=dt, bias=YawBias(0.01, 1e-3, share=0.5))
    assert full.carries is None and half.carries is not None and half.bias is not None and full.bias is not None
    np.testing.assert_array_equal(half.bias[:5], full.bias[:5])  # the same draws, the rest zeroed
    assert np.all(half.bias[5:] == 0.0) and np.all(full.bias[5:] != 0.0)
    for _ in range(3):
        half.draw([0.1, 0.0, 0.0], n)
    assert np.all(half.bias[5:] == 0.0) and np.all(half.bias[:5] != 0.0)
    idx = np.array([9, 9, 0, 1, 5, 6, 2, 3, 4, 8])
    half.select(idx)
    np.testing.assert_array_equal(half.carries, idx < 5)
    half.draw([0.1, 0.0, 0.0], n)
    assert np.all(half.bias[idx >= 5] == 0.0)


def test_the_wide_mode_draws_gmapping_noise_for_its_particles_and_keeps_its_share() -> None:
    """``WideMode``: the particles in the wide mode draw GMapping's noise, the others the odometry's covariance;
    the mode is resampled with the particle, and switching draws it afresh from the stationary share."""
    n = 40000
    cov = np.tile(np.diag([0.002, 0.002, 0.0005]) ** 2, (2, 1, 1))
    noise = MotionNoise(0.02, 0.005, 0.05, 0.0, 0.03, 0.0)
    u = [0.1, 0.0, 0.0]
    p = Proposal(noise, n, np.random.default_rng(0), cov=cov, wide=WideMode(share=0.3, switch=0.0))
    assert p.wide_mode is not None and abs(p.wide_mode.mean() - 0.3) < 0.01
    mode = p.wide_mode.copy()
    d = p.draw(u, n) - np.asarray(u)
    np.testing.assert_array_equal(p.wide_mode, mode)  # switch 0: nobody changes mode
    s_xy, s_yaw = noise.std(u)
    np.testing.assert_allclose(d[mode].std(axis=0), [s_xy, s_xy, s_yaw], rtol=0.03)
    np.testing.assert_allclose(d[~mode].std(axis=0), np.sqrt(np.diag(cov[1])), rtol=0.03)
    w = np.full(n, 1.0 / n)
    assert p.wide_share(w) == pytest.approx(mode.mean())
    idx = np.flatnonzero(mode)[np.arange(n) % int(mode.sum())]  # resampled onto the wide particles only
    p.select(idx)
    assert p.wide_mode.all() and p.wide_share(w) == pytest.approx(1.0)
    q = Proposal(noise, n, np.random.default_rng(1), cov=cov, wide=WideMode(share=0.3, switch=0.1))
    q.select(np.zeros(n, np.int64))  # everyone a copy of particle 0: all in one mode
    assert q.wide_mode is not None and q.wide_mode.mean() in (0.0, 1.0)
    for _ in range(60):  # switching pulls the share back to 0.3: 1 - 0.9^60 of the particles redrawn
        q.draw(u, n)
    assert abs(q.wide_mode.mean() - 0.3) < 0.02
    # without the mode: the draws of before, to the bit
    a = Proposal(noise, 50, np.random.default_rng(5), cov=cov).draw(u, 50)
    b = Proposal(noise, 50, np.random.default_rng(5), cov=cov, wide=None).draw(u, 50)
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="needs cov"):
        Proposal(noise, 3, np.random.default_rng(0), wide=WideMode())
    with pytest.raises(ValueError, match="Laplace"):
        Proposal(noise, 3, np.random.default_rng(0), cov=cov, wide=WideMode()).prior(u, 3)


def test_run_method_refuses_the_odometry_covariance_without_it() -> None:
    run = make_run(5, np.random.default_rng(0))
    basis = hm.make_basis([10.0, 10.0], [0.0, 0.0], 16)
    scans = [sample_beams(p, np.zeros(2), 1.0, 5.0) for p in run.scans]
    with pytest.raises(ValueError, match="increment covariance"):
        run_method("fastslam_grid", run.odometry, scans, basis, SlamConfig(proposal="odometry_covariance"), 0)
    run_method("rich_slam_paper", run.odometry, scans, basis, SlamConfig(proposal="odometry_covariance",
                                                                          n_particles=2, workers=0), 0)


def _drifting_run(bias: float, yaw_std: float, n: int = 600) -> tuple[Any, list[Any], hm.HilbertBasis,
                                                                     OdometryMotion]:
    """A synthetic run whose odometry yaw drifts by ``bias`` rad/s (scans at 10 Hz) with per-scan yaw noise
    ``yaw_std``, which its increment covariance states; its scans, a basis over it and that covariance."""
    run = make_run(n, np.random.default_rng(1), beams_per_scan=30, outlier_fraction=0.0, odo_trans_noise=0.005,
                   odo_yaw_noise=yaw_std, odo_yaw_bias=bias * 0.1)
    scans = [sample_beams(p, np.zeros(2), 1.0, 5.0) for p in run.scans]
    half, centre = domain_from_trajectory(run.odometry[:, :2], 5.0)
    motion = OdometryMotion(np.tile(np.diag([0.005, 0.005, yaw_std]) ** 2, (n, 1, 1)), np.full(n, 0.1))
    return run, scans, hm.make_basis(half, centre, 256), motion


def test_bias_state_converges_to_a_constant_gyro_bias_and_bounds_the_heading_error() -> None:
    """Odometry whose yaw drifts linearly (0.01 rad/s = 0.57 deg/s over 60 s): the particles' bias converges to
    it and the filter's heading error stays bounded while the odometry's grows to ~27 deg."""
    bias = 0.01
    run, scans, basis, motion = _drifting_run(bias, 0.002)
    # a walk well above the datasheet's keeps the 50 particles' biases diverse (stages/slam/README.md)
    cfg = SlamConfig(n_particles=50, workers=0, proposal="odometry_covariance", yaw_bias=YawBias(0.02, 3e-4))
    r = run_method("fastslam_grid", run.odometry, scans, basis, cfg, seed=0, motion=motion)
    assert r.yaw_bias is not None
    err = np.abs(np.degrees(wrap_angle(r.poses[:, 2] - run.groundtruth[:, 2])))
    odo = np.abs(np.degrees(wrap_angle(run.odometry[:, 2] - run.groundtruth[:, 2])))
    assert odo[-1] > 20.0
    assert abs(r.yaw_bias[-1] - bias) < 0.2 * bias  # converged within 20 %
    assert abs(np.mean(r.yaw_bias[-100:]) - bias) < 0.2 * bias
    assert err.max() < 0.3 * odo[-1] and err[-100:].max() < 3.0


def test_the_wide_mode_follows_an_odometry_that_drifts_beyond_its_covariance() -> None:
    """An odometry whose yaw drifts 0.57 deg/s while its covariance claims 0.017 deg per scan: the narrow proposal
    cannot leave it, the wide mode's particles can, and the weights move onto them."""
    run, scans, basis, motion = _drifting_run(0.01, 0.0003)
    final = {}
    for wide in (None, WideMode(share=0.2, switch=0.01)):
        cfg = SlamConfig(n_particles=50, workers=0, proposal="odometry_covariance", wide=wide,
                         noise=MotionNoise(0.002, 0.0005, 0.05, 0.005, 0.03, 0.06), estimate="weighted_mean")
        r = run_method("fastslam_grid", run.odometry, scans, basis, cfg, seed=0, motion=motion)
        final[wide is not None] = abs(np.degrees(wrap_angle(r.poses[-1, 2] - run.groundtruth[-1, 2])))
        assert (r.wide_share is None) == (wide is None)
        if r.wide_share is not None:
            assert np.mean(r.wide_share[300:]) > 2 * 0.2  # the weights favour the wide particles
    odo = abs(np.degrees(wrap_angle(run.odometry[-1, 2] - run.groundtruth[-1, 2])))
    assert odo > 30 and final[False] > 0.9 * odo  # the narrow proposal stays with the odometry
    assert final[True] < 0.75 * final[False]


def test_weighted_mean_pose_is_circular_in_yaw_and_picks_a_one_hot_particle() -> None:
    poses = np.array([[1.0, 2.0, np.pi - 0.1], [3.0, -2.0, -np.pi + 0.1], [0.0, 0.0, 0.5]])
    np.testing.assert_allclose(weighted_mean_pose(poses, np.array([0.5, 0.5, 0.0])), [2.0, 0.0, np.pi], atol=1e-12)
    np.testing.assert_allclose(weighted_mean_pose(poses, np.array([0.0, 0.0, 1.0])), poses[2], atol=1e-12)
    w = np.array([0.2, 0.3, 0.5])
    m = weighted_mean_pose(poses, w)
    np.testing.assert_allclose(m[:2], w @ poses[:, :2])
    # the circular mean: the weighted resultant's direction
    assert abs(wrap_angle(m[2] - np.angle(np.sum(w * np.exp(1j * poses[:, 2]))))) < 1e-12


def test_weighted_mean_stays_on_the_odometry_where_the_weights_say_nothing() -> None:
    """Scans without beams give every particle the same weight: the filter then has no information beyond the
    odometry, and the posterior mean stays on it (to the Monte Carlo error of the particles' mean), while the
    largest-weight particle is one random particle of the cloud, as far off as the proposal's spread."""
    n = 300
    run = make_run(n, np.random.default_rng(2))
    empty = sample_beams(np.zeros((0, 2)), np.zeros(2), 1.0, 5.0)
    basis = hm.make_basis([30.0, 30.0], [0.0, 0.0], 16)
    motion = OdometryMotion(np.tile(np.diag([0.01, 0.01, 0.004]) ** 2, (n, 1, 1)), np.full(n, 0.1))
    cfg = SlamConfig(n_particles=100, workers=0, proposal="odometry_covariance", estimate="weighted_mean")
    r = run_method("rich_slam", run.odometry, [empty] * n, basis, cfg, seed=0, motion=motion)
    assert set(r.estimates) == {"best_per_scan", "final_best_history", "weighted_mean", "smoothed", "fused"}
    np.testing.assert_array_equal(r.poses, r.estimates["weighted_mean"])
    # the fused estimate is the smoother's heading fused with the odometry's, the odometry's steps along it
    # a weight without any heading information (empty scans): the filter's error model at its widest
    assert r.heading_information == 0.0
    assert r.fusion_filter_sigma_deg == pytest.approx(100 * np.degrees(cfg.fusion.filter_sigma))
    fused, jumps = fused_estimate(run.odometry, r.estimates["smoothed"], motion, informed(cfg.fusion, np.zeros(n)))[:2]
    np.testing.assert_array_equal(r.estimates["fused"], fused)
    assert r.fusion_jumps == jumps
    yaw = {k: np.abs(wrap_angle(v[:, 2] - run.odometry[:, 2])) for k, v in r.estimates.items()}
    spread = 0.004 * np.sqrt(n)  # the particles' heading spread at the end (rad)
    assert yaw["weighted_mean"][-1] < 0.35 * spread  # Monte Carlo error ~ spread / sqrt(100)
    assert np.mean(yaw["best_per_scan"][-50:]) > 2 * np.mean(yaw["weighted_mean"][-50:])
    # the paper's configuration keeps Algorithm 1's estimate whatever slam.estimate says
    paper = run_method("rich_slam_paper", run.odometry, [empty] * n, basis, cfg, seed=0, motion=motion)
    np.testing.assert_array_equal(paper.poses, paper.estimates["best_per_scan"])


def test_the_paper_configuration_keeps_eq22_and_the_grid_its_own_exponent() -> None:
    from stages.slam.stage import SlamParams

    cfg = SlamParams().config()
    assert cfg.weighting("rich_slam").exponent == SlamParams().likelihood_exponent != 1.0
    paper = cfg.for_method("rich_slam_paper")  # the paper's eq. 22 and proposal whatever the settings
    assert paper.weighting("rich_slam_paper").exponent == 1.0
    assert paper.map_model("rich_slam_paper").weighting.exponent == 1.0
    assert (paper.proposal, paper.estimate, paper.yaw_bias) == ("gmapping", "best_per_scan", None)
    # r_e: off by default for rich_slam (stop 39), the paper's 0.25 m for rich_slam_paper, 0 for the ablation
    assert cfg.weighting("rich_slam").endpoint_tolerance == 0.0
    assert paper.weighting("rich_slam_paper").endpoint_tolerance == 0.25
    assert cfg.weighting("rich_slam_no_et").endpoint_tolerance == 0.0
    assert cfg.for_method("rich_slam") is cfg
    assert cfg.grid_likelihood_exponent == SlamParams().grid_likelihood_exponent
    # the stage's defaults are the calibrated ones, SlamConfig's pure defaults the paper's
    assert (cfg.proposal, cfg.estimate, cfg.yaw_bias) == ("odometry_covariance", "fused", None)
    assert SlamConfig().proposal == "gmapping" and SlamConfig().likelihood_exponent == 1.0
