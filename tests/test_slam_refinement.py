"""Pose refinement against a particle's own Hilbert map (issue 17): derivatives, convergence, the weight."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import sample_beams, to_world
from stages.slam.methods import SlamConfig, domain_from_trajectory, run_method
from stages.slam.pose_refinement import (
    PoseRefinement,
    log_gaussian,
    mean_and_pose_jacobian,
    refine,
    sample_proposal,
)
from stages.slam.rbpf import HilbertParticleMaps, MotionNoise, compose
from stages.slam.synthetic import make_run


@pytest.mark.parametrize("kind, M", [("tensor", 256), ("circular", 200)])
def test_pose_jacobian_matches_finite_differences(kind: str, M: int) -> None:
    rng = np.random.default_rng(0)
    basis = hm.make_basis([10.0, 8.0], [1.0, 2.0], M, kind)  # type: ignore[arg-type]
    theta = rng.standard_normal((4, M))
    poses = np.array([[0.0, 0.0, 0.3], [1.0, 2.0, -1.0], [2.0, -1.0, 2.0], [0.5, 0.5, 3.0]])
    pts = rng.uniform(-3, 3, (7, 2))

    def mean(p: np.ndarray) -> np.ndarray:
        return np.einsum("knm,km->kn", hm.features(basis, to_world(p, pts)), theta)

    m, J = mean_and_pose_jacobian(basis, theta, poses, pts)
    np.testing.assert_allclose(m, mean(poses), atol=1e-12)
    for d in range(3):
        e = np.zeros(3)
        e[d] = 1e-6
        fd = (mean(poses + e) - mean(poses - e)) / 2e-6
        np.testing.assert_allclose(J[..., d], fd, atol=1e-6 * np.abs(J).max())


def test_refinement_returns_a_scan_to_the_pose_its_map_was_built_from() -> None:
    """A map built from one scan at a known pose fits it there: Gauss-Newton on the map's own (Gaussian)
    model from offsets returns to it. (The logistic term does not: it rewards overshooting labels.)"""
    run = make_run(40, np.random.default_rng(3), beams_per_scan=40, outlier_fraction=0.0, range_noise=0.0,
                   angle_noise_deg=0.0)
    scans = [sample_beams(p, np.zeros(2), 1.0, 5.0) for p in run.scans]
    half, centre = domain_from_trajectory(run.groundtruth[:, :2], 5.0)
    basis = hm.make_basis(half, centre, 256)
    cfg = SlamConfig()
    maps = HilbertParticleMaps(basis, 1, cfg.map_model("rich_slam", "covariance"))
    k = 30
    for _ in range(5):
        maps.update(run.groundtruth[k : k + 1], scans[k])
    offsets = np.array([[0.0, 0.15, 0.0], [0.0, -0.15, 0.0], [0.0, 0.0, np.radians(3)], [0.0, 0.0, -np.radians(3)],
                        [0.1, 0.1, np.radians(2)]])
    start = compose(np.repeat(run.groundtruth[k : k + 1], len(offsets), 0), offsets)
    wide = np.array([1.0, 1.0, 0.1])  # the prior barely holds the start: the map decides
    mode, A = refine(basis, np.repeat(maps.theta, len(start), 0), start, wide, scans[k],
                     PoseRefinement(iterations=8, objective="gaussian"))

    def err(x: np.ndarray) -> np.ndarray:
        d = x - run.groundtruth[k]
        return np.hypot(d[:, 0], d[:, 1]) + 2.0 * np.abs(np.angle(np.exp(1j * d[:, 2])))  # m + 2 m per rad

    before, after = err(start), err(mode)
    assert np.all(after < 0.5 * before), (before, after)
    assert np.all(np.linalg.eigvalsh(A) > 0)


def test_empty_map_gives_the_motion_model_and_no_weight_correction() -> None:
    basis = hm.make_basis([10.0, 10.0], [0.0, 0.0], 64)
    rng = np.random.default_rng(1)
    x_pred = rng.normal(size=(6, 3))
    var = np.array([0.02, 0.02, 0.005]) ** 2
    s = sample_beams(rng.uniform(-3, 3, (5, 2)), np.zeros(2), 1.0, 5.0)
    mode, A = refine(basis, np.zeros((6, 64)), x_pred, var, s, PoseRefinement(iterations=3))
    np.testing.assert_allclose(mode, x_pred, atol=1e-12)
    np.testing.assert_allclose(A, np.broadcast_to(np.diag(1 / var), (6, 3, 3)))
    x, log_q = sample_proposal(mode, A, 1.0, rng)
    np.testing.assert_allclose(log_gaussian(x, x_pred, var) - log_q, 0.0, atol=1e-9)


def test_proposal_density_is_the_gaussian_it_samples() -> None:
    rng = np.random.default_rng(2)
    mode = rng.normal(size=(4, 3)) * 0.1
    B = rng.normal(size=(4, 3, 3))
    A = B @ np.swapaxes(B, 1, 2) + 3 * np.eye(3)
    x, log_q = sample_proposal(mode, A, 2.0, np.random.default_rng(5))
    for k in range(4):
        ref = multivariate_normal(mode[k], 2.0 * np.linalg.inv(A[k])).logpdf(x[k])
        assert log_q[k] == pytest.approx(ref, abs=1e-9)
    draws = np.stack([sample_proposal(mode[:1], A[:1], 2.0, np.random.default_rng(s))[0][0] for s in range(2000)])
    want = 2.0 * np.linalg.inv(A[0])
    np.testing.assert_allclose(np.cov(draws.T), want, atol=0.15 * np.abs(want).max())


def test_motion_noise_gmapping_terms() -> None:
    n = MotionNoise(0.01, 0.002, rel_trans=0.1, rel_rot=0.2, rot_per_trans=0.05, trans_per_rot=0.3)
    s_xy, s_yaw = n.std([0.3, 0.4, -0.1])
    assert s_xy == pytest.approx(0.01 + 0.1 * 0.5 + 0.3 * 0.1)
    assert s_yaw == pytest.approx(0.002 + 0.2 * 0.1 + 0.05 * 0.5)


def test_refined_method_without_iterations_is_the_papers_filter() -> None:
    """``iterations = 0`` turns the Laplace proposal off: the same draws and trajectory as rich_slam."""
    from dataclasses import replace

    run = make_run(60, np.random.default_rng(7), beams_per_scan=20)
    scans = [sample_beams(p, np.zeros(2), 1.0, 5.0) for p in run.scans]
    half, centre = domain_from_trajectory(run.odometry[:, :2], 5.0)
    basis = hm.make_basis(half, centre, 64)
    cfg = SlamConfig(n_particles=8, workers=0, map_form="covariance", refinement=PoseRefinement(iterations=0))
    a = run_method("rich_slam_refined", run.odometry, scans, basis, cfg, seed=3)
    b = run_method("rich_slam", run.odometry, scans, basis, cfg, seed=3)
    np.testing.assert_array_equal(a.poses, b.poses)
    on = run_method("rich_slam_refined", run.odometry, scans, basis, replace(cfg, refinement=PoseRefinement(3)), seed=3)
    assert np.all(np.isfinite(on.poses)) and not np.array_equal(on.poses, b.poses)


def test_stage_parameters_reach_the_refinement_by_name() -> None:
    """Every refinement setting of the stage lands in its own field (a positional call once put the map's
    noise variance into ``free_weight``)."""
    from stages.slam.stage import SlamParams

    r = SlamParams(free_weight=0.7, noise_variance=0.25, endpoint_noise_variance=0.09, refine_iterations=5,
                   refine_max_step_xy=0.3, refine_max_step_yaw=0.02, refine_objective="gaussian",
                   refine_covariance_scale=2.0).config().refinement
    assert r == PoseRefinement(iterations=5, max_step_xy=0.3, max_step_yaw=0.02, covariance_scale=2.0,
                               objective="gaussian", free_weight=0.7, noise_variance=0.25,
                               endpoint_noise_variance=0.09)
    # the refinement's own free weight, when set, leaves the weights' alone
    p = SlamParams(free_weight=0.7, refine_free_weight=0.36)
    assert p.config().refinement.free_weight == 0.36 and p.config().free_weight == 0.7


def test_gaussian_refinement_weighs_each_label_with_its_own_noise() -> None:
    """With per-label noise the Gauss-Newton Hessian is sum_j (c_j / s2_j) J_j J_j^T + prior, and a
    single noise value equal for both labels gives the one-value objective."""
    rng = np.random.default_rng(5)
    basis = hm.make_basis([8.0, 8.0], [0.0, 0.0], 64)
    theta = rng.standard_normal((3, 64))
    poses = rng.uniform(-1, 1, (3, 3))
    s = sample_beams(rng.uniform(-4, 4, (12, 2)), np.zeros(2), 1.0, 5.0)
    var = np.array([1.0, 1.0, 0.1])
    _, J = mean_and_pose_jacobian(basis, theta, poses, s.points)
    s2 = np.where(s.labels > 0, 0.09, 0.36)
    expected = np.einsum("n,knd,kne->kde", 1.0 / s2, J, J) + np.diag(1.0 / var)
    per_label = PoseRefinement(objective="gaussian", noise_variance=0.36, endpoint_noise_variance=0.09)
    _, A = refine(basis, theta, poses, var, s, per_label)  # iterations = 0: the Hessian at the start
    np.testing.assert_allclose(A, expected, rtol=1e-10)
    _, A1 = refine(basis, theta, poses, var, s, PoseRefinement(objective="gaussian", noise_variance=0.36))
    _, A2 = refine(basis, theta, poses, var, s, PoseRefinement(objective="gaussian", noise_variance=0.36,
                                                               endpoint_noise_variance=0.36))
    np.testing.assert_allclose(A1, A2, rtol=1e-12)
    assert not np.allclose(A, A1)
