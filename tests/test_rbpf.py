"""RBPF pieces: propagation, posterior-aware weights vs a brute-force loop, N_eff, resampling, map copies."""

from __future__ import annotations

import numpy as np
import pytest

from core import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, sample_beams, stencil_offsets, to_world
from stages.slam.rbpf import (
    RBPF,
    RESAMPLERS,
    HilbertParticleMaps,
    HilbertWeighting,
    MapModel,
    MotionNoise,
    compose,
    effective_sample_size,
    hilbert_log_likelihood,
    normalize_log_weights,
    odometry_increments,
    propagate,
)
from stages.slam.se2 import wrap_angle
from stages.slam.synthetic import make_run


def _trained_maps(n_particles: int, rng: np.random.Generator) -> tuple[hm.HilbertBasis, np.ndarray, np.ndarray]:
    b = hm.make_basis([6.0, 5.0], [0.5, 0.0], 64)
    theta, cov = hm.prior(b, 1.2, 16.0, batch=(n_particles,))
    for _ in range(3):
        p = rng.uniform(-5, 5, (n_particles, 20, 2))
        y = np.where(p[..., 0] > 1.0, 1.0, -1.0)
        theta, cov = hm.kalman_update(theta, cov, hm.features(b, p), y, 0.36)
    return b, theta, cov


def _brute_force_loglik(b, theta, cov, poses, samples, r_e, offs, use_var):  # type: ignore[no-untyped-def]
    out = np.zeros(len(poses))
    for k in range(len(poses)):
        c, s = np.cos(poses[k, 2]), np.sin(poses[k, 2])
        R = np.array([[c, -s], [s, c]])

        def o(q, k=k):  # type: ignore[no-untyped-def]
            phi = hm.features(b, q[None])[0]
            mu = phi @ theta[k]
            var = phi @ cov[k] @ phi if use_var else 0.0
            return 1.0 / (1.0 + np.exp(-mu / np.sqrt(1.0 + np.pi * var / 8.0)))

        for pb, lab in zip(samples.points, samples.labels, strict=True):
            p = R @ pb + poses[k, :2]
            if lab < 0:
                out[k] += np.log(1.0 - o(p))
            elif r_e > 0:
                out[k] += np.log(max(o(p + d) for d in offs))
            else:
                out[k] += np.log(o(p))
    return out


@pytest.mark.parametrize("r_e,use_var", [(0.25, True), (0.0, True), (0.25, False)])
def test_batched_weights_equal_brute_force_loop(r_e: float, use_var: bool) -> None:
    rng = np.random.default_rng(0)
    b, theta, cov = _trained_maps(5, rng)
    poses = np.column_stack([rng.uniform(-1, 1, (5, 2)), rng.uniform(-np.pi, np.pi, 5)])
    samples = sample_beams(rng.uniform(-4, 4, (6, 2)), [0.2, 0.1], 1.0, 5.0)
    assert samples.n > 6
    w = HilbertWeighting(use_variance=use_var, endpoint_tolerance=r_e, ring_points=8)
    got = hilbert_log_likelihood(b, theta, cov, poses, samples, w)
    ref = _brute_force_loglik(b, theta, cov, poses, samples, r_e, stencil_offsets(r_e, 8), use_var)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10)


def test_endpoint_tolerance_stencil_approximates_disc_max_and_taylor_variance() -> None:
    rng = np.random.default_rng(1)
    b, theta, cov = _trained_maps(4, rng)
    poses = np.column_stack([rng.uniform(-1, 1, (4, 2)), rng.uniform(-np.pi, np.pi, 4)])
    samples = sample_beams(rng.uniform(-4, 4, (8, 2)), [0.0, 0.0], 1.0, 6.0)
    exact = hilbert_log_likelihood(b, theta, cov, poses, samples, HilbertWeighting(ring_points=8))
    dense = hilbert_log_likelihood(b, theta, cov, poses, samples, HilbertWeighting(ring_points=64, rings=8))
    lin = hilbert_log_likelihood(b, theta, cov, poses, samples, HilbertWeighting(et_variance="taylor"))
    # ET raises the endpoint terms: never below the no-ET likelihood
    none = hilbert_log_likelihood(b, theta, cov, poses, samples, HilbertWeighting(endpoint_tolerance=0))
    assert np.all(exact >= none - 1e-12) and np.all(dense >= exact - 1e-12)
    # the 8-point ring captures the dense-disc gain of eq. 29 to a few percent; so does the linearised variance
    gain = dense - none
    assert np.all(gain > 0.1)
    assert np.all(np.abs(dense - exact) < 0.05 * gain)
    assert np.all(np.abs(lin - exact) < 0.1 * gain)


def test_ess_formula_and_weight_normalisation() -> None:
    assert effective_sample_size(np.ones(10)) == pytest.approx(10)
    assert effective_sample_size(np.eye(10)[3]) == pytest.approx(1)
    w = np.array([1.0, 2.0, 3.0, 4.0])
    assert effective_sample_size(w) == pytest.approx(effective_sample_size(7 * w))
    assert effective_sample_size(w) == pytest.approx(100 / 30)
    lw = np.array([-1000.0, -1001.0, -1e9])  # no underflow to nan
    nw = normalize_log_weights(lw)
    np.testing.assert_allclose(nw, [1 / (1 + np.exp(-1)), np.exp(-1) / (1 + np.exp(-1)), 0.0])


@pytest.mark.parametrize("kind", sorted(RESAMPLERS))
def test_resampling_is_unbiased(kind: str) -> None:
    rng = np.random.default_rng(2)
    w = rng.random(20) ** 3
    w /= w.sum()
    draws = 4000
    counts = np.zeros(20)
    for _ in range(draws):
        idx = RESAMPLERS[kind](w, rng)
        assert idx.shape == (20,) and idx.min() >= 0 and idx.max() < 20
        counts += np.bincount(idx, minlength=20)
    mean = counts / draws
    # multinomial variance bounds the others; 5 sigma
    sd = np.sqrt(20 * w * (1 - w) / draws)
    assert np.all(np.abs(mean - 20 * w) < 5 * sd + 1e-9), (mean, 20 * w)
    if kind == "systematic":  # low variance: every count is floor or ceil of N w
        idx = RESAMPLERS[kind](w, rng)
        c = np.bincount(idx, minlength=20)
        assert np.all((c >= np.floor(20 * w)) & (c <= np.ceil(20 * w)))


def test_odometry_increments_and_propagation() -> None:
    rng = np.random.default_rng(3)
    poses = np.cumsum(rng.normal(0, 0.3, (30, 3)), axis=0)
    poses[:, 2] = wrap_angle(poses[:, 2])
    u = odometry_increments(poses)
    x = poses[0]
    for i in range(1, 30):
        x = compose(x, u[i])
    np.testing.assert_allclose(x, poses[-1], atol=1e-10)
    zero = propagate(np.tile(poses[0], (5, 1)), u[1], MotionNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), rng)
    np.testing.assert_allclose(zero, np.tile(compose(poses[0], u[1]), (5, 1)), atol=1e-12)
    noise = MotionNoise(std_xy=0.1, std_yaw=0.02, rel_trans=0.0, rel_rot=0.0, rot_per_trans=0.0, trans_per_rot=0.0)
    many = propagate(np.zeros((20000, 3)), [1.0, 0.0, 0.0], noise, rng)
    np.testing.assert_allclose(many.std(axis=0), [0.1, 0.1 * 1.0 + 0.0, 0.02], rtol=0.05, atol=3e-3)


@pytest.mark.parametrize("form", ["information", "covariance"])
def test_resampled_maps_do_not_alias(form: str) -> None:
    rng = np.random.default_rng(4)
    b = hm.make_basis([5.0, 5.0], [0.0, 0.0], 36)
    maps = HilbertParticleMaps(b, 3, MapModel(1.0, 4.0, 0.36, HilbertWeighting(), form=form))  # type: ignore[arg-type]
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [0.0, 1.0, 1.0]])
    s = sample_beams(rng.uniform(-3, 3, (5, 2)), [0, 0], 1.0, 5.0)
    maps.update(poses, s)
    maps.select(np.array([1, 1, 0]))
    st = maps.stack
    stored = [a for a in (maps.cov, maps.theta, st and st.info, st and st.eta) if a is not None]
    for a in stored:
        assert not np.shares_memory(a[0], a[1])
        np.testing.assert_array_equal(a[0], a[1])
    theta1, cov1 = maps.map_of(1)
    new_poses = np.array([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    maps.log_likelihood(new_poses, s)
    maps.update(new_poses, s)  # the two copies now see different poses (in-place batched update)
    assert not np.allclose(maps.map_of(0)[1], maps.map_of(1)[1])
    # particle 1 equals a fresh update of its own copy: nothing leaked from particle 0
    t_ref, c_ref = hm.kalman_update(theta1, cov1, hm.features(b, to_world(new_poses[1], s.points)), s.labels, 0.36)
    np.testing.assert_allclose(maps.map_of(1)[0], t_ref, atol=1e-10)
    np.testing.assert_allclose(maps.map_of(1)[1], c_ref, atol=1e-10)


@pytest.mark.parametrize("et_variance,update", [("exact", "kalman"), ("taylor", "kalman"), ("exact", "laplace")])
def test_information_and_covariance_particle_maps_agree(et_variance: str, update: str) -> None:
    rng = np.random.default_rng(7)
    b = hm.make_basis([8.0, 8.0], [0.0, 0.0], 64)
    w = HilbertWeighting(et_variance=et_variance)  # type: ignore[arg-type]
    a = HilbertParticleMaps(b, 4, MapModel(1.5, 16.0, 0.36, w, form="information", update=update))  # type: ignore[arg-type]
    c = HilbertParticleMaps(b, 4, MapModel(1.5, 16.0, 0.36, w, form="covariance", update=update))  # type: ignore[arg-type]
    for _ in range(20):
        poses = np.column_stack([rng.uniform(-2, 2, (4, 2)), rng.uniform(-3, 3, 4)])
        s = sample_beams(rng.uniform(-4, 4, (6, 2)), [0.1, 0.0], 1.0, 5.0)
        np.testing.assert_allclose(a.log_likelihood(poses, s), c.log_likelihood(poses, s), rtol=1e-8, atol=1e-8)
        a.update(poses, s)
        c.update(poses, s)
    for k in range(4):
        np.testing.assert_allclose(a.map_of(k)[0], c.map_of(k)[0], atol=1e-8)
        np.testing.assert_allclose(a.map_of(k)[1], c.map_of(k)[1], atol=1e-8)


class _FixedMaps:
    """A map model whose scan log-likelihood is a fixed function of the particle pose."""

    def __init__(self, target: np.ndarray) -> None:
        self.target = target
        self.selected: list[np.ndarray] = []

    def log_likelihood(self, poses: np.ndarray, samples: BeamSamples) -> np.ndarray:
        return -0.5 * np.sum((poses[:, :2] - self.target) ** 2, axis=1) / 0.05**2

    def update(self, poses: np.ndarray, samples: BeamSamples) -> None:
        pass

    def select(self, indices: np.ndarray) -> None:
        self.selected.append(indices)


def test_filter_tracks_a_likelihood_and_ancestry_is_consistent() -> None:
    rng = np.random.default_rng(5)
    empty = sample_beams(np.zeros((0, 2)), [0, 0], 1.0, 5.0)
    maps = _FixedMaps(np.array([0.3, 0.0]))
    f = RBPF(maps, [0.0, 0.0, 0.0], 100, MotionNoise(0.05, 0.01, 0.0, 0.0, 0.0, 0.0), rng)
    for i in range(30):
        f.step([0.01, 0.0, 0.0], empty, first=i == 0)
        maps.target = maps.target + np.array([0.01, 0.0])
    h = f.history
    assert any(h.resampled) and len(maps.selected) == sum(h.resampled)
    assert np.linalg.norm(h.best_trajectory()[-1, :2] - maps.target + [0.01, 0]) < 0.1
    # the ancestry is a chain of propagations: the final best particle's parents differ by ~ one step
    k, hist = h.best_index[-1], []
    for i in range(len(h.particles) - 1, -1, -1):
        hist.append(h.particles[i][k])
        k = int(h.parents[i][k])
    steps = np.linalg.norm(np.diff(np.array(hist[::-1])[:, :2], axis=0), axis=1)
    assert steps.max() < 0.01 + 6 * 0.05 * np.sqrt(2)
    assert all(np.isfinite(h.n_eff)) and min(h.n_eff) >= 1 - 1e-9


def test_map_weight_prefers_true_pose() -> None:
    """On a revisit, a map built from ground truth scores the true pose above perturbed ones.

    Perturbations are across the corridor and in yaw; along a straight corridor translation is
    unobservable (the paper's Sec. V-C2), so it is not tested.
    """
    rng = np.random.default_rng(6)
    run = make_run(480, rng, outlier_fraction=0.0)
    b = hm.make_basis([20.0, 16.0], [0.0, 0.0], 256)
    theta, cov = hm.prior(b, 2.0, 16.0)
    scans = [sample_beams(s, [0, 0], 1.0, 5.0) for s in run.scans]
    for i in range(446):  # one loop
        theta, cov = hm.kalman_update(theta, cov, hm.features(b, to_world(run.groundtruth[i], scans[i].points)),
                                      scans[i].labels, 0.36)
    for w in (HilbertWeighting(), HilbertWeighting(endpoint_tolerance=0), HilbertWeighting(use_variance=False)):
        wins = 0
        for i in range(450, 480):
            truth = run.groundtruth[i]
            cand = compose(truth, np.array([[0, 0, 0], [0, 0.5, 0], [0, -0.5, 0], [0, 0, 0.1], [0, 0, -0.1]]))
            ll = hilbert_log_likelihood(b, np.tile(theta, (5, 1)), np.tile(cov, (5, 1, 1)), cand, scans[i], w)
            wins += int(np.argmax(ll) == 0)
        assert wins >= 27, wins


@pytest.mark.parametrize("form", ["information", "covariance"])
def test_parallel_workers_equal_in_process_filter(form: str) -> None:
    from stages.slam.parallel import ParallelHilbertMaps

    rng = np.random.default_rng(8)
    run = make_run(25, rng)
    scans = [sample_beams(s, [0, 0], 1.0, 5.0) for s in run.scans]
    b = hm.make_basis([14.0, 10.0], [0.0, 0.0], 64)
    u = odometry_increments(run.odometry)
    serial = HilbertParticleMaps(b, 7, MapModel(2.0, 16.0, 0.36, HilbertWeighting(), form=form))  # type: ignore[arg-type]
    f1 = RBPF(serial, run.odometry[0], 7, MotionNoise(), np.random.default_rng(0))
    h1 = f1.run(u, scans)
    with ParallelHilbertMaps(b, 7, MapModel(2.0, 16.0, 0.36, HilbertWeighting(), form=form),  # type: ignore[arg-type]
                             workers=2) as par:
        f2 = RBPF(par, run.odometry[0], 7, MotionNoise(), np.random.default_rng(0))
        h2 = f2.run(u, scans)
        assert any(h2.resampled)
        np.testing.assert_allclose(h2.best_trajectory(), h1.best_trajectory(), atol=1e-9)
        np.testing.assert_allclose(h2.n_eff, h1.n_eff, rtol=1e-9)
        for k in (0, 6):
            np.testing.assert_allclose(par.map_of(k)[1], serial.map_of(k)[1], atol=1e-9)


def test_stacked_covariance_stays_symmetric_pd_over_thousands_of_updates() -> None:
    """The in-place syrk downdates of the covariance form vs the information form after 2000 scans."""
    rng = np.random.default_rng(9)
    b = hm.make_basis([6.0, 6.0], [0.0, 0.0], 64)
    w = HilbertWeighting(endpoint_tolerance=0.0)
    c = HilbertParticleMaps(b, 2, MapModel(1.0, 16.0, 0.36, w, form="covariance"))
    i = HilbertParticleMaps(b, 2, MapModel(1.0, 16.0, 0.36, w, form="information"))
    for _ in range(2000):
        poses = np.column_stack([rng.uniform(-1, 1, (2, 2)), rng.uniform(-3, 3, 2)])
        s = sample_beams(rng.uniform(-3, 3, (int(rng.integers(1, 6)), 2)), [0, 0], 0.5, 5.0)
        c.update(poses, s)
        i.update(poses, s)
    for k in range(2):
        cov = c.map_of(k)[1]
        assert np.linalg.eigvalsh(cov).min() > 0
        np.testing.assert_allclose(cov, i.map_of(k)[1], rtol=1e-6, atol=1e-9 * np.abs(cov).max())
        np.testing.assert_allclose(c.theta[k], i.map_of(k)[0], rtol=1e-6, atol=1e-8)


def test_select_rows_equals_fancy_indexing_and_copies() -> None:
    """In-place resampling of a stack (only changed rows copied) against ``a[idx]``, for index arrays from
    every resampler and adversarial permutations with duplicates."""
    from stages.slam.particle_linalg import select_rows

    rng = np.random.default_rng(11)
    cases = [np.array([1, 1, 2, 3]), np.array([0, 0, 1, 2]), np.array([3, 2, 1, 0]), np.array([2, 0, 0, 1]),
             np.arange(6)]
    for kind in ("systematic", "stratified", "multinomial"):
        for _ in range(20):
            cases.append(RESAMPLERS[kind](rng.dirichlet(np.full(30, 0.3)), rng))
    cases += [rng.integers(0, 30, 30) for _ in range(20)]
    for idx in cases:
        a = rng.standard_normal((len(idx), 3, 2))
        ref = a[idx]
        select_rows(a, idx)
        np.testing.assert_array_equal(a, ref)
    with pytest.raises(ValueError, match="indices"):
        select_rows(np.zeros((3, 2)), np.array([0, 1]))


@pytest.mark.parametrize("weighting", [HilbertWeighting(et_variance="taylor"), HilbertWeighting(et_variance="exact"),
                                       HilbertWeighting(use_variance=False), HilbertWeighting(endpoint_tolerance=0.0)])
def test_fused_blocked_step_equals_weight_then_update(weighting: HilbertWeighting) -> None:
    """``weigh_and_update`` (information form: one pass, blocks of particles) against ``log_likelihood``
    followed by ``update`` on the unblocked maps."""
    rng = np.random.default_rng(12)
    b = hm.make_basis([8.0, 8.0], [0.0, 0.0], 64)
    fused = HilbertParticleMaps(b, 5, MapModel(1.5, 16.0, 0.36, weighting, form="information"))
    fused.block_bytes = 1  # one particle per block
    plain = HilbertParticleMaps(b, 5, MapModel(1.5, 16.0, 0.36, weighting, form="information"))
    for _ in range(15):
        poses = np.column_stack([rng.uniform(-2, 2, (5, 2)), rng.uniform(-3, 3, 5)])
        s = sample_beams(rng.uniform(-4, 4, (int(rng.integers(0, 7)), 2)), [0.1, 0.0], 1.0, 5.0)
        ll = fused.weigh_and_update(poses, s)
        np.testing.assert_allclose(ll, plain.log_likelihood(poses, s), rtol=1e-10, atol=1e-10)
        plain.update(poses, s)
    for k in range(5):
        np.testing.assert_allclose(fused.map_of(k)[0], plain.map_of(k)[0], atol=1e-10)
        np.testing.assert_allclose(fused.map_of(k)[1], plain.map_of(k)[1], atol=1e-10)


def test_information_scan_whitens_in_place_and_refuses_non_contiguous_output() -> None:
    """``scan`` with ``out is rows`` equals the copying scan; an output whose maps are not C-contiguous
    (trsm would solve a temporary copy) is refused."""
    from stages.slam.particle_linalg import StackedInformation

    rng = np.random.default_rng(13)
    M = 16
    A = rng.standard_normal((3, M, 2 * M))
    st = StackedInformation(np.ones(M), 3)
    st.info[...] = np.eye(M) + A @ np.swapaxes(A, 1, 2) / M
    rows = rng.standard_normal((3, 5, M))
    theta, white, _ = st.scan(rows)
    for k in range(3):
        L = np.linalg.cholesky(st.info[k])
        np.testing.assert_allclose(white[k], np.linalg.solve(L, rows[k].T).T, atol=1e-12)
    same = rows.copy()
    _, white2, means = st.scan(same, out=same, mean_rows=2)
    assert white2 is same
    np.testing.assert_allclose(white2, white, atol=1e-13)
    np.testing.assert_allclose(means, np.einsum("knm,km->kn", rows[:, :2], theta), atol=1e-12)
    with pytest.raises(ValueError, match="C-contiguous"):
        st.scan(rows, out=np.asfortranarray(np.empty_like(rows)))
