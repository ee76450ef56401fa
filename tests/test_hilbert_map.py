"""Hilbert-GP map core: basis, prior, Kalman and Laplace updates, queries, against independent references."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from core import hilbert_map as hm
from stages.slam.gp_reference import gp_posterior, se_kernel


def test_tensor_index_matrix_matches_eq7() -> None:
    b = hm.make_basis([3.0, 2.0], [0.0, 0.0], 9)
    assert b.indices.tolist() == [[1, 1], [1, 2], [1, 3], [2, 1], [2, 2], [2, 3], [3, 1], [3, 2], [3, 3]]
    with pytest.raises(ValueError, match="perfect square"):
        hm.make_basis([3.0, 2.0], [0.0, 0.0], 10)


def test_features_match_eq6_literal_and_are_orthonormal() -> None:
    L = np.array([2.0, 3.0])
    c = np.array([1.0, -1.0])
    b = hm.make_basis(L, c, 16)
    rng = np.random.default_rng(0)
    p = c + (rng.random((5, 2)) * 2 - 1) * L * 0.99
    phi = hm.features(b, p)
    for j, (j1, j2) in enumerate(b.indices):
        lit = np.prod([np.sin(np.pi * jj * (p[:, d] - c[d] + L[d]) / (2 * L[d])) / np.sqrt(L[d])
                       for d, jj in enumerate((j1, j2))], axis=0)
        np.testing.assert_allclose(phi[:, j], lit, atol=1e-12)
    # orthonormal on the domain (midpoint rule on a fine grid)
    n = 200
    xs = c[0] - L[0] + (np.arange(n) + 0.5) * 2 * L[0] / n
    ys = c[1] - L[1] + (np.arange(n) + 0.5) * 2 * L[1] / n
    g = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    F = hm.features(b, g)
    gram = F.T @ F * (4 * L[0] * L[1] / n**2)
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-6)
    # zero outside the domain
    assert np.all(hm.features(b, c + L * 1.01) == 0)


def test_spectral_density_is_fourier_transform_of_se_kernel() -> None:
    # S(w) = int k(r) exp(-i w.r) dr in 2D; check numerically at a few |w|
    ell, sf2 = 0.7, 2.5
    h = 0.02
    x = np.arange(-8, 8, h)
    X, Y = np.meshgrid(x, x, indexing="ij")
    k = sf2 * np.exp(-(X**2 + Y**2) / (2 * ell**2))
    for w in (0.0, 0.5, 2.0):
        num = np.sum(k * np.cos(w * X)) * h * h
        np.testing.assert_allclose(hm.spectral_density_se(w**2, ell, sf2), num, rtol=1e-6)


def test_kernel_approximation_converges_to_se_kernel() -> None:
    ell, sf2 = 1.0, 1.7
    b = hm.make_basis([6.0, 6.0], [0.0, 0.0], 30 * 30)
    lam = hm.prior_variances(b, ell, sf2)
    rng = np.random.default_rng(1)
    p = rng.uniform(-2, 2, (40, 2))
    phi = hm.features(b, p)
    approx = phi @ np.diag(lam) @ phi.T
    exact = se_kernel(p, p, ell, sf2)
    assert np.max(np.abs(approx - exact)) < 1e-3 * sf2


@pytest.mark.parametrize("kind", ["tensor", "circular"])
def test_posterior_approaches_exact_gp_regression(kind: str) -> None:
    """Kalman-updated Hilbert posterior vs exact GP regression on the same +-1 labels, same kernel."""
    ell, sf2, sn2 = 1.0, 4.0, 0.36
    rng = np.random.default_rng(2)
    x = rng.uniform(-3, 3, (120, 2))
    y = np.where(np.hypot(x[:, 0] - 0.5, x[:, 1]) < 1.5, 1.0, -1.0)
    test = rng.uniform(-3, 3, (60, 2))
    mu_gp, var_gp = gp_posterior(x, y, test, ell, sf2, sn2)
    errs = []
    for m in (8, 16, 28):
        b = hm.make_basis([7.0, 7.0], [0.0, 0.0], m * m, kind=kind)
        theta, cov = hm.prior(b, ell, sf2)
        for s in range(0, len(x), 30):  # sequential scans
            phi = hm.features(b, x[s : s + 30])
            theta, cov = hm.kalman_update(theta, cov, phi, y[s : s + 30], sn2)
        mu, var, _ = hm.query(b, theta, cov, test)
        errs.append((np.max(np.abs(mu - mu_gp)), np.max(np.abs(var - var_gp))))
    # converges as M grows
    assert errs[0][0] > errs[-1][0] and errs[0][1] > errs[-1][1]
    assert errs[-1][0] < 2e-3 and errs[-1][1] < 2e-3, errs


def test_kalman_sequence_equals_batch_posterior_and_stays_pd() -> None:
    b = hm.make_basis([10.0, 8.0], [1.0, 2.0], 64)
    ell, sf2, sn2 = 2.0, 16.0, 0.36
    lam = hm.prior_variances(b, ell, sf2)
    theta, cov = hm.prior(b, ell, sf2)
    rng = np.random.default_rng(3)
    all_phi, all_y = [], []
    for i in range(3000):
        n = int(rng.integers(0, 12))
        p = np.array([1.0, 2.0]) + rng.uniform(-6, 6, (n, 2)) * (1 if i % 2 else 0.3)
        y = np.sign(rng.standard_normal(n))
        phi = hm.features(b, p)
        theta, cov = hm.kalman_update(theta, cov, phi, y, sn2, inplace=i % 2 == 0)
        all_phi.append(phi)
        all_y.append(y)
    # exactly symmetric, positive definite after thousands of updates
    assert np.array_equal(cov, cov.T)
    assert np.linalg.eigvalsh(cov).min() > 0
    tb, cb = hm.batch_posterior(lam, np.concatenate(all_phi), np.concatenate(all_y), sn2)
    np.testing.assert_allclose(theta, tb, rtol=1e-7, atol=1e-8 * np.abs(tb).max())
    np.testing.assert_allclose(cov, cb, rtol=1e-6, atol=1e-9 * np.abs(cb).max())


def test_batched_kalman_equals_per_map_loop() -> None:
    b = hm.make_basis([5.0, 5.0], [0.0, 0.0], 49)
    theta, cov = hm.prior(b, 1.5, 2.0, batch=(4,))
    rng = np.random.default_rng(4)
    theta = theta + rng.standard_normal(theta.shape)
    phi = hm.features(b, rng.uniform(-4, 4, (4, 7, 2)))
    y = np.sign(rng.standard_normal((4, 7)))
    tB, cB = hm.kalman_update(theta, cov, phi, y, 0.3)
    for k in range(4):
        t1, c1 = hm.kalman_update(theta[k], cov[k], phi[k], y[k], 0.3)
        # the textbook gain form of eq. 15-19
        P, H = cov[k], phi[k].T
        S = H.T @ P @ H + 0.3 * np.eye(7)
        K = P @ H @ np.linalg.inv(S)
        np.testing.assert_allclose(t1, theta[k] + K @ (y[k] - H.T @ theta[k]), atol=1e-10)
        np.testing.assert_allclose(c1, P - K @ S @ K.T, atol=1e-10)
        np.testing.assert_allclose(tB[k], t1, atol=1e-12)
        np.testing.assert_allclose(cB[k], c1, atol=1e-12)


def _direct_newton(theta0, cov0, phi, labels, iters=50):  # type: ignore[no-untyped-def]
    """eq. 40-42 literally: Newton in weight space with the M x M Hessian."""
    y = (labels + 1) / 2
    Pinv = np.linalg.inv(cov0)
    th = theta0.copy()
    for _ in range(iters):
        s = hm.sigmoid(phi @ th)
        g = phi.T @ (y - s) - Pinv @ (th - theta0)
        Hs = -(phi.T * (s * (1 - s))) @ phi - Pinv
        th = th - np.linalg.solve(Hs, g)
    s = hm.sigmoid(phi @ th)
    Hs = -(phi.T * (s * (1 - s))) @ phi - Pinv
    return th, np.linalg.inv(-Hs)


def test_laplace_update_matches_direct_newton_and_optimizer() -> None:
    b = hm.make_basis([4.0, 4.0], [0.0, 0.0], 36)
    theta0, cov0 = hm.prior(b, 1.0, 4.0)
    rng = np.random.default_rng(5)
    # a non-trivial prior from an earlier scan
    theta0, cov0 = hm.kalman_update(theta0, cov0, hm.features(b, rng.uniform(-3, 3, (10, 2))),
                                    np.sign(rng.standard_normal(10)), 0.36)
    p = rng.uniform(-3, 3, (15, 2))
    z = np.where(p[:, 0] > 0, 1.0, -1.0)
    phi = hm.features(b, p)
    th, cv = hm.laplace_update(theta0, cov0, phi, z, max_iter=50, tol=1e-12)
    th_ref, cv_ref = _direct_newton(theta0, cov0, phi, z)
    np.testing.assert_allclose(th, th_ref, atol=1e-8)
    np.testing.assert_allclose(cv, cv_ref, atol=1e-8 * np.abs(cv_ref).max())
    # and an independent optimiser on -Psi(theta) (eq. 36-39)
    Pinv = np.linalg.inv(cov0)
    y = (z + 1) / 2

    def negpsi(t: np.ndarray) -> tuple[float, np.ndarray]:
        f = phi @ t
        ll = np.sum(y * hm.log_sigmoid(f) + (1 - y) * hm.log_sigmoid(-f))
        d = t - theta0
        return -(ll - 0.5 * d @ Pinv @ d), -(phi.T @ (y - hm.sigmoid(f)) - Pinv @ d)

    res = minimize(negpsi, theta0, jac=True, method="BFGS", options={"gtol": 1e-10, "maxiter": 5000})
    np.testing.assert_allclose(phi @ th, phi @ res.x, atol=1e-5)
    # batched form equals the single-map form
    thB, cvB = hm.laplace_update(np.stack([theta0, theta0]), np.stack([cov0, cov0]),
                                 np.stack([phi, phi[::-1]]), np.stack([z, z[::-1]]), max_iter=50, tol=1e-12)
    np.testing.assert_allclose(thB[0], th, atol=1e-10)
    np.testing.assert_allclose(thB[1], th, atol=1e-8)
    np.testing.assert_allclose(cvB[0], cv, atol=1e-10 * np.abs(cv).max())


def test_queries_and_resolution_independence() -> None:
    b = hm.make_basis([6.0, 6.0], [0.0, 0.0], 144)
    theta, cov = hm.prior(b, 1.0, 4.0)
    rng = np.random.default_rng(6)
    p = rng.uniform(-5, 5, (80, 2))
    theta, cov = hm.kalman_update(theta, cov, hm.features(b, p), np.where(p[:, 1] > 1, 1.0, -1.0), 0.36)
    grids = {}
    for spacing in (2.0, 1.0, 0.25):
        xs = np.arange(-4.0, 4.0 + 1e-9, spacing)
        g = np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
        grids[spacing] = dict(zip(map(tuple, np.round(g, 6)), zip(*hm.query(b, theta, cov, g), strict=True),
                                  strict=True))
    shared = set(grids[2.0])
    assert shared <= set(grids[1.0]) and shared <= set(grids[0.25])
    for key in shared:
        np.testing.assert_allclose(grids[2.0][key], grids[0.25][key], atol=1e-12)
        np.testing.assert_allclose(grids[1.0][key], grids[0.25][key], atol=1e-12)
    # eq. 28: occupancy is the probit-scaled sigmoid of the mean; variance shrinks it to 0.5
    mu, var, occ = hm.query(b, theta, cov, p[:5])
    np.testing.assert_allclose(occ, 1 / (1 + np.exp(-mu / np.sqrt(1 + np.pi * var / 8))))
    assert np.all(np.abs(occ - 0.5) <= np.abs(hm.sigmoid(mu) - 0.5) + 1e-15)


def test_prior_variance_equals_kernel_diagonal_far_from_boundary() -> None:
    b = hm.make_basis([8.0, 8.0], [0.0, 0.0], 32 * 32)
    lam = hm.prior_variances(b, 1.0, 3.0)
    v = hm.prior_variance_at(b, lam, np.array([[0.0, 0.0], [2.0, -3.0]]))
    np.testing.assert_allclose(v, 3.0, rtol=1e-3)


def test_feature_gradients_match_finite_differences() -> None:
    b = hm.make_basis([3.0, 4.0], [0.5, 0.0], 25)
    p = np.array([[0.3, 1.1], [-1.0, -2.0]])
    g = hm.feature_gradients(b, p)
    h = 1e-6
    for d in range(2):
        e = np.zeros(2)
        e[d] = h
        fd = (hm.features(b, p + e) - hm.features(b, p - e)) / (2 * h)
        np.testing.assert_allclose(g[..., d], fd, atol=1e-7)


def test_information_form_equals_covariance_form_and_stays_pd() -> None:
    b = hm.make_basis([10.0, 8.0], [1.0, 2.0], 64)
    ell, sf2, sn2 = 2.0, 16.0, 0.36
    theta_c, cov = hm.prior(b, ell, sf2, batch=(3,))
    theta_i, info, chol = hm.prior_information(b, ell, sf2, batch=(3,))
    rng = np.random.default_rng(7)
    for i in range(1500):
        n = int(rng.integers(0, 40))
        p = np.array([1.0, 2.0]) + rng.uniform(-6, 6, (3, n, 2)) * (1 if i % 2 else 0.3)
        y = np.sign(rng.standard_normal((3, n)))
        phi = hm.features(b, p)
        theta_c, cov = hm.kalman_update(theta_c, cov, phi, y, sn2, inplace=True)
        theta_i, info, chol = hm.information_update(theta_i, info, phi, y, sn2)
    np.testing.assert_allclose(theta_i, theta_c, rtol=1e-7, atol=1e-8 * np.abs(theta_c).max())
    cov_i = hm.covariance_from_information(chol)
    np.testing.assert_allclose(cov_i, cov, rtol=1e-6, atol=1e-9 * np.abs(cov).max())
    assert np.all(np.linalg.eigvalsh(cov_i) > 0)
    # variances from the whitened features equal phi^T cov phi
    q = hm.features(b, rng.uniform(-5, 5, (3, 9, 2)))
    v_i = np.sum(hm.whiten(chol, q) ** 2, axis=-1)
    v_c = np.einsum("knm,kmj,knj->kn", q, cov, q)
    np.testing.assert_allclose(v_i, v_c, rtol=1e-8, atol=1e-12)


def test_information_laplace_equals_covariance_laplace() -> None:
    b = hm.make_basis([4.0, 4.0], [0.0, 0.0], 36)
    rng = np.random.default_rng(8)
    theta, cov = hm.prior(b, 1.0, 4.0, batch=(2,))
    theta_i, info, chol = hm.prior_information(b, 1.0, 4.0, batch=(2,))
    for _ in range(3):
        p = rng.uniform(-3, 3, (2, 15, 2))
        z = np.where(p[..., 0] + 0.3 * rng.standard_normal((2, 15)) > 0, 1.0, -1.0)
        phi = hm.features(b, p)
        theta, cov = hm.laplace_update(theta, cov, phi, z, max_iter=50, tol=1e-12)
        theta_i, info, chol = hm.laplace_update_information(theta_i, info, chol, phi, z, max_iter=50, tol=1e-12)
    np.testing.assert_allclose(theta_i, theta, atol=1e-8)
    np.testing.assert_allclose(hm.covariance_from_information(chol), cov, atol=1e-8 * np.abs(cov).max())


def test_information_prior_floor_handles_metre_lengthscale() -> None:
    # l = 20 m on a 30 m domain: most prior variances underflow to 0 (the unit question)
    b = hm.make_basis([15.0, 15.0], [0.0, 0.0], 256)
    lam = hm.prior_variances(b, 20.0, 16.0)
    assert lam.min() == 0.0
    theta, info, chol = hm.prior_information(b, 20.0, 16.0)
    assert np.all(np.isfinite(info)) and np.all(np.isfinite(chol))
    phi = hm.features(b, np.random.default_rng(9).uniform(-10, 10, (50, 2)))
    theta, info, chol = hm.information_update(theta, info, phi, np.ones(50), 0.36)
    assert np.all(np.isfinite(theta))


@pytest.mark.parametrize("kind", ["tensor", "circular"])
def test_mean_at_and_gradients_match_features(kind: str) -> None:
    b = hm.make_basis([3.0, 4.0], [0.5, 0.0], 25, kind=kind)  # type: ignore[arg-type]
    rng = np.random.default_rng(10)
    theta = rng.standard_normal((3, 25))
    p = rng.uniform(-4, 4, (3, 7, 2))  # some outside the domain
    np.testing.assert_allclose(hm.mean_at(b, theta, p), np.einsum("kqm,km->kq", hm.features(b, p), theta),
                               atol=1e-12)
    g = hm.feature_gradients(b, p[0])
    h = 1e-6
    for d in range(2):
        e = np.zeros(2)
        e[d] = h
        fd = (hm.features(b, p[0] + e) - hm.features(b, p[0] - e)) / (2 * h)
        np.testing.assert_allclose(g[..., d], fd, atol=1e-7)
