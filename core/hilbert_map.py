"""Hilbert-space reduced-rank GP occupancy map (RICH-SLAM Sec. III-C, IV-C, Appendix).

Pure numpy, no I/O. All lengths are metres: the paper's length scale is converted to metres by the
stage (see README: ``lengthscale_m = lengthscale * length_unit_m``). The kernel approximation is
invariant to the unit in which positions are written as long as the length scale is converted with
them, so only the length scale in metres matters.

Every map function works on a batch of maps: ``theta`` is ``(..., M)`` and ``cov`` is ``(..., M, M)``
(one map is a batch of shape ``()``); points are ``(..., N, 2)`` with the same leading shape.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.floating]
BasisKind = Literal["tensor", "circular"]

#: the map's domain: the trajectory's envelope padded by this (m)
DOMAIN_PADDING = 10.0


@dataclass(frozen=True)
class HilbertBasis:
    """Laplacian eigenfunctions on the rectangle ``centre + [-L1, L1] x [-L2, L2]`` (eq. 6-7)."""

    half_widths: npt.NDArray[np.float64]  # (2,) L1, L2 [m]
    centre: npt.NDArray[np.float64]  # (2,) domain centre [m]
    indices: npt.NDArray[np.int64]  # (M, 2) the index matrix J, entries >= 1
    kind: BasisKind = "tensor"

    @property
    def M(self) -> int:
        return int(self.indices.shape[0])

    @property
    def frequencies(self) -> npt.NDArray[np.float64]:
        """``pi J_{j,d} / (2 L_d)``, shape (M, 2); ``lambda_j`` is the row-wise sum of squares."""
        return np.pi * self.indices / (2.0 * self.half_widths)

    @property
    def eigenvalues(self) -> npt.NDArray[np.float64]:
        """``lambda_j`` of eq. 6."""
        return np.sum(self.frequencies**2, axis=1)

    def contains(self, points: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """True for points strictly inside the domain."""
        d = np.abs(np.asarray(points, dtype=np.float64) - self.centre)
        return np.all(d < self.half_widths, axis=-1)


def make_basis(
    half_widths: npt.ArrayLike, centre: npt.ArrayLike, M: int, kind: BasisKind = "tensor"
) -> HilbertBasis:
    """The basis of eq. 6-7.

    ``tensor`` (the paper): all pairs of 1..sqrt(M) per axis, M a perfect square, first index slow.
    ``circular`` (Solin and Sarkka's reference code): the M pairs with the smallest ``lambda_j``.
    """
    L = np.asarray(half_widths, dtype=np.float64).reshape(2)
    c = np.asarray(centre, dtype=np.float64).reshape(2)
    if np.any(L <= 0) or not np.all(np.isfinite(L)):
        raise ValueError(f"half widths must be positive and finite, got {L}")
    if M < 1:
        raise ValueError(f"M must be >= 1, got {M}")
    if kind == "tensor":
        m = round(np.sqrt(M))
        if m * m != M:
            raise ValueError(f"M = {M} is not a perfect square (the tensor basis of eq. 7 needs one)")
        a, b = np.meshgrid(np.arange(1, m + 1), np.arange(1, m + 1), indexing="ij")
        J = np.stack([a.ravel(), b.ravel()], axis=1)
    elif kind == "circular":
        # enough candidates per axis to hold the M smallest eigenvalues for any aspect ratio
        n1 = int(np.ceil(2 * np.sqrt(M) * max(1.0, L[0] / L[1]))) + 1
        n2 = int(np.ceil(2 * np.sqrt(M) * max(1.0, L[1] / L[0]))) + 1
        a, b = np.meshgrid(np.arange(1, n1 + 1), np.arange(1, n2 + 1), indexing="ij")
        cand = np.stack([a.ravel(), b.ravel()], axis=1)
        lam = np.sum((np.pi * cand / (2 * L)) ** 2, axis=1)
        J = cand[np.argsort(lam, kind="stable")[:M]]
    else:
        raise ValueError(f"unknown basis kind {kind!r} (tensor or circular)")
    return HilbertBasis(L, c, J.astype(np.int64), kind)


def spectral_density_se(
    eigenvalues: npt.ArrayLike, lengthscale: float, signal_variance: float
) -> npt.NDArray[np.float64]:
    """``S(sqrt(lambda)) = sigma_f^2 (2 pi l^2) exp(-lambda l^2 / 2)`` (eq. 8, 2D SE kernel)."""
    lam = np.asarray(eigenvalues, dtype=np.float64)
    return signal_variance * (2.0 * np.pi * lengthscale**2) * np.exp(-0.5 * lam * lengthscale**2)


def prior_variances(basis: HilbertBasis, lengthscale: float, signal_variance: float) -> npt.NDArray[np.float64]:
    """Diagonal of the weight prior ``Lambda`` (eq. 10)."""
    return spectral_density_se(basis.eigenvalues, lengthscale, signal_variance)


def prior(
    basis: HilbertBasis,
    lengthscale: float,
    signal_variance: float,
    batch: tuple[int, ...] = (),
    dtype: npt.DTypeLike = np.float64,
) -> tuple[FloatArray, FloatArray]:
    """Zero mean and ``diag(S(sqrt(lambda_j)))`` covariance (eq. 10), repeated over ``batch``."""
    lam = prior_variances(basis, lengthscale, signal_variance)
    theta = np.zeros((*batch, basis.M), dtype=dtype)
    cov = np.zeros((*batch, basis.M, basis.M), dtype=dtype)
    idx = np.arange(basis.M)
    cov[..., idx, idx] = lam.astype(dtype)
    return theta, cov


def sin_cos_multiples(theta: npt.ArrayLike, m: int, cos: bool = True) -> tuple[FloatArray, FloatArray | None]:
    """``sin(k theta)`` and (``cos``) ``cos(k theta)`` for ``k = 1..m``, shape ``(..., m)``.

    One complex exponential and ``m - 1`` complex products (``e^{ik theta} = e^{i(k-1) theta} e^{i theta}``,
    error about ``k`` ulp) instead of ``2 m`` transcendental calls: an order of magnitude faster for the
    eigenfunction tables, which dominate the cost of building features.
    """
    t = np.asarray(theta, dtype=np.float64)
    e = np.exp(1j * t.ravel())
    E = np.empty((m, e.size), dtype=np.complex128)  # k-major: every product is one contiguous pass
    if m:
        E[0] = e
    for k in range(1, m):
        np.multiply(E[k - 1], e, out=E[k])
    S = np.ascontiguousarray(E.imag.T).reshape(*t.shape, m)
    C = np.ascontiguousarray(E.real.T).reshape(*t.shape, m) if cos else None
    return S, C


def axis_tables(
    basis: HilbertBasis, points: npt.ArrayLike, derivative: bool = False
) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray | None]:
    """Per-axis factors of the eigenfunctions: ``phi_j(p) = a_{J_j1}(p_1) b_{J_j2}(p_2)`` (eq. 6).

    ``a`` carries the normalisation ``1 / sqrt(L1 L2)`` and is zero outside the domain, so products
    of the tables are the features. With ``derivative`` also ``da/dp_1`` and ``db/dp_2``.
    """
    p = np.asarray(points, dtype=np.float64)
    m1 = int(basis.indices[:, 0].max())
    m2 = int(basis.indices[:, 1].max())
    rel = p - basis.centre
    inside = np.all(np.abs(rel) < basis.half_widths, axis=-1)
    x = rel + basis.half_widths
    w1 = np.pi * np.arange(1, m1 + 1) / (2.0 * basis.half_widths[0])
    w2 = np.pi * np.arange(1, m2 + 1) / (2.0 * basis.half_widths[1])
    scale = (inside / np.sqrt(basis.half_widths[0] * basis.half_widths[1]))[..., None]
    s1, c1 = sin_cos_multiples(x[..., 0] * w1[0], m1, cos=derivative)
    s2, c2 = sin_cos_multiples(x[..., 1] * w2[0], m2, cos=derivative)
    a, b = s1 * scale, s2
    if c1 is None or c2 is None:
        return a, b, None, None
    return a, b, c1 * (w1 * scale), c2 * w2


def _combine(basis: HilbertBasis, a: FloatArray, b: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """Tensor products of the axis tables, written into ``out (..., M)`` when given."""
    lead = a.shape[:-1]
    if basis.kind == "tensor":
        if out is None:
            out = np.empty((*lead, a.shape[-1] * b.shape[-1]), dtype=np.result_type(a, b))
        np.multiply(a[..., :, None], b[..., None, :], out=np.reshape(out, (*lead, a.shape[-1], b.shape[-1]),
                                                                      copy=False))
        return out
    prod = a[..., basis.indices[:, 0] - 1] * b[..., basis.indices[:, 1] - 1]
    if out is None:
        return prod
    out[...] = prod
    return out


def features(basis: HilbertBasis, points: npt.ArrayLike, dtype: npt.DTypeLike = np.float64,
             out: FloatArray | None = None) -> FloatArray:
    """``Phi(p)``, shape ``(..., M)`` (eq. 6, 9); zero outside the domain (Dirichlet boundary).

    Built from per-axis sine tables: O(N (sqrt(M) + M)) and one pass over the output (``out``, if given).
    """
    a, b, _, _ = axis_tables(basis, points)
    dt = np.dtype(dtype) if out is None else out.dtype
    return _combine(basis, a.astype(dt, copy=False), b.astype(dt, copy=False), out)


def feature_gradient_rows(basis: HilbertBasis, points: npt.ArrayLike, dtype: npt.DTypeLike = np.float64,
                          out: FloatArray | None = None) -> FloatArray:
    """``d Phi / d p`` as rows, shape ``(..., 2, M)`` (x then y derivative); zero outside the domain."""
    a, b, da, db = axis_tables(basis, points, derivative=True)
    assert da is not None and db is not None
    dt = np.dtype(dtype) if out is None else out.dtype
    if out is None:
        out = np.empty((*a.shape[:-1], 2, basis.M), dtype=dt)
    _combine(basis, da.astype(dt, copy=False), b.astype(dt, copy=False), out[..., 0, :])
    _combine(basis, a.astype(dt, copy=False), db.astype(dt, copy=False), out[..., 1, :])
    return out


def feature_gradients(basis: HilbertBasis, points: npt.ArrayLike, dtype: npt.DTypeLike = np.float64) -> FloatArray:
    """``d Phi / d p``, shape ``(..., M, 2)``; zero outside the domain."""
    return np.swapaxes(feature_gradient_rows(basis, points, dtype), -1, -2)


def mean_at(basis: HilbertBasis, theta: FloatArray, points: npt.ArrayLike) -> FloatArray:
    """``Phi(p)^T theta`` without forming ``Phi`` (tensor basis: ``a^T Theta b``), ``theta (..., M)``.

    ``points`` are ``(..., K, 2)`` with the same leading shape as ``theta``.
    """
    if basis.kind != "tensor":
        return np.einsum("...km,...m->...k", features(basis, points, theta.dtype), theta)
    a, b, _, _ = axis_tables(basis, points)
    m1, m2 = a.shape[-1], b.shape[-1]
    T = theta.reshape(*theta.shape[:-1], m1, m2)
    return np.einsum("...ka,...ka->...k", np.matmul(a.astype(theta.dtype), T), b.astype(theta.dtype))


# -- queries ---------------------------------------------------------------------------------------------


def predict(theta: FloatArray, cov: FloatArray, phi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Latent mean ``Phi^T theta`` and variance ``Phi^T cov Phi`` (eq. 26-27, 32-33).

    ``phi`` is ``(..., N, M)`` for maps ``theta (..., M)``, ``cov (..., M, M)``.
    """
    mean = np.einsum("...nm,...m->...n", phi, theta)
    a = np.matmul(phi, cov)
    var = np.einsum("...nm,...nm->...n", a, phi)
    return mean, np.maximum(var, 0.0)


def probit_scale(var: npt.ArrayLike) -> FloatArray:
    """``1 / sqrt(1 + pi var / 8)``, the probit approximation factor of eq. 28."""
    return 1.0 / np.sqrt(1.0 + (np.pi / 8.0) * np.asarray(var))


def sigmoid(x: npt.ArrayLike) -> FloatArray:
    """Logistic function, overflow-free."""
    x = np.asarray(x, dtype=np.float64)
    return np.exp(-np.logaddexp(0.0, -x))


def log_sigmoid(x: npt.ArrayLike) -> FloatArray:
    """``log(sigmoid(x))`` without overflow."""
    return -np.logaddexp(0.0, -np.asarray(x, dtype=np.float64))


def occupancy(mean: npt.ArrayLike, var: npt.ArrayLike) -> FloatArray:
    """Posterior-predictive occupancy ``sigmoid(mu / sqrt(1 + pi s^2 / 8))`` (eq. 28)."""
    return sigmoid(np.asarray(mean) * probit_scale(var))


def query(
    basis: HilbertBasis, theta: FloatArray, cov: FloatArray, points: npt.ArrayLike, chunk: int = 8192
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mean, variance and occupancy of ONE map at arbitrary points ``(N, 2)`` (resolution-free).

    Works in chunks so a fine grid never materialises a huge feature matrix.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    mean = np.empty(len(pts))
    var = np.empty(len(pts))
    for s in range(0, len(pts), chunk):
        phi = features(basis, pts[s : s + chunk], dtype=cov.dtype)
        mean[s : s + chunk], var[s : s + chunk] = predict(theta, cov, phi)
    return mean, var, occupancy(mean, var)


def prior_variance_at(basis: HilbertBasis, prior_diag: npt.ArrayLike, points: npt.ArrayLike) -> FloatArray:
    """Prior latent variance ``Phi^T Lambda Phi`` at points (the normaliser of Fig. 10)."""
    phi = features(basis, points)
    return np.einsum("...m,m,...m->...", phi, np.asarray(prior_diag, dtype=np.float64), phi)


# -- updates ---------------------------------------------------------------------------------------------


def kalman_update(
    theta: FloatArray,
    cov: FloatArray,
    phi: FloatArray,
    labels: FloatArray,
    noise_variance: float | FloatArray,
    phi_cov: FloatArray | None = None,
    symmetrize: bool = False,
    inplace: bool = False,
) -> tuple[FloatArray, FloatArray]:
    """Sequential PLSC update of eq. 15-19 in a square-root-gain form, batched over maps.

    ``phi`` is ``H^T``, shape ``(..., N, M)``; ``labels`` are ``(..., N)`` in {-1, +1};
    ``phi_cov`` (optional) is ``H^T cov`` when the caller already has it (the particle weights need
    the same product). With ``S = H^T cov H + sigma_n^2 I = R R^T`` (Cholesky) and ``W = R^-1 H^T cov``:
    ``theta += W^T R^-1 (z - H^T theta)`` and ``cov -= W^T W``, which equals ``K S K^T`` of eq. 15 and
    is symmetric by construction. Returns new arrays, or the updated inputs when ``inplace``.
    """
    dtype = cov.dtype
    A = np.matmul(phi, cov) if phi_cov is None else phi_cov  # (..., N, M) = H^T cov
    n = phi.shape[-2]
    if n == 0:
        return theta.copy(), cov.copy()
    S = np.matmul(A, np.swapaxes(phi, -1, -2)).astype(np.float64)  # (..., N, N) = H^T cov H
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    S[..., np.arange(n), np.arange(n)] += noise_variance
    R = np.linalg.cholesky(S)
    Rinv = np.linalg.inv(R).astype(dtype)  # small (N x N) triangular inverse
    innov = (labels - np.einsum("...nm,...m->...n", phi, theta)).astype(dtype)
    W = np.matmul(Rinv, A)  # (..., N, M)
    v = np.einsum("...ij,...j->...i", Rinv, innov)
    dtheta = np.einsum("...nm,...n->...m", W, v)
    WtW = np.matmul(np.swapaxes(W, -1, -2), W)
    if inplace:
        theta += dtheta
        cov -= WtW
        theta_new, cov_new = theta, cov
    else:
        theta_new, cov_new = theta + dtheta, cov - WtW
    if symmetrize:
        cov_new[...] = 0.5 * (cov_new + np.swapaxes(cov_new, -1, -2))
    return theta_new, cov_new


def batch_posterior(
    prior_diag: npt.ArrayLike, phi: FloatArray, labels: FloatArray, noise_variance: float
) -> tuple[FloatArray, FloatArray]:
    """All data at once in information form: ``cov = (Lambda^-1 + H H^T / s^2)^-1`` (reference)."""
    lam = np.asarray(prior_diag, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    info = np.diag(1.0 / lam) + phi.T @ phi / noise_variance
    cov = np.linalg.inv(info)
    cov = 0.5 * (cov + cov.T)
    theta = cov @ (phi.T @ np.asarray(labels, dtype=np.float64)) / noise_variance
    return theta, cov


def laplace_mode(
    K: FloatArray, m: FloatArray, labels: FloatArray, max_iter: int = 20, tol: float = 1e-9
) -> tuple[FloatArray, FloatArray]:
    """Newton's method (eq. 40) on the latent values of one scan, batched.

    ``f = H^T theta`` has the Gaussian prior ``N(m, K)`` (``K = H^T cov H``); the likelihood is the
    Bernoulli of eq. 39 with ``y = (z + 1) / 2`` (eq. 38). Rasmussen and Williams Alg. 3.1 with a prior
    mean. Returns the mode ``f`` and ``W = sigma(f)(1 - sigma(f))`` there.
    """
    K = np.asarray(K, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    y = (np.asarray(labels, dtype=np.float64) + 1.0) / 2.0
    eye = np.eye(K.shape[-1])
    f = m.copy()
    for _ in range(max_iter):
        pi = sigmoid(f)
        w = pi * (1.0 - pi)
        sw = np.sqrt(w)
        b = w * (f - m) + (y - pi)
        L = np.linalg.cholesky(eye + sw[..., :, None] * K * sw[..., None, :])
        c = np.einsum("...ij,...j->...i", K, b) * sw
        t = np.linalg.solve(np.swapaxes(L, -1, -2), np.linalg.solve(L, c[..., None]))[..., 0]
        f_new = np.einsum("...ij,...j->...i", K, b - sw * t) + m
        step = float(np.max(np.abs(f_new - f))) if f.size else 0.0
        f = f_new
        if step < tol:
            break
    pi = sigmoid(f)
    return f, pi * (1.0 - pi)


def laplace_update(
    theta: FloatArray,
    cov: FloatArray,
    phi: FloatArray,
    labels: FloatArray,
    phi_cov: FloatArray | None = None,
    max_iter: int = 20,
    tol: float = 1e-9,
) -> tuple[FloatArray, FloatArray]:
    """Recursive Laplace update (Appendix, eq. 36-43) in its exact N-dimensional form, batched.

    The mode of eq. 36 lies in ``theta0 + cov H a`` (stationarity of eq. 41), so Newton's method of
    eq. 40 runs on the latent values (:func:`laplace_mode`). At the mode ``a = y - sigma(f)``,
    ``theta_MAP = theta0 + cov H a`` and ``-(grad grad Psi)^-1 = cov - cov H W^1/2 B^-1 W^1/2 H^T cov``
    (Woodbury, eq. 43) with ``B = I + W^1/2 K W^1/2``. Cost ``O(M^2 N)`` once plus ``O(N^3)`` per
    iteration instead of the ``O(M^3)`` of a Newton step in weight space.
    """
    dtype = cov.dtype
    A = np.matmul(phi, cov) if phi_cov is None else phi_cov
    n = phi.shape[-2]
    if n == 0:
        return theta.copy(), cov.copy()
    K = np.matmul(A, np.swapaxes(phi, -1, -2)).astype(np.float64)
    K = 0.5 * (K + np.swapaxes(K, -1, -2))
    m = np.einsum("...nm,...m->...n", phi, theta)
    f, w = laplace_mode(K, m, labels, max_iter, tol)
    a = (np.asarray(labels, dtype=np.float64) + 1.0) / 2.0 - sigmoid(f)
    sw = np.sqrt(w)
    L = np.linalg.cholesky(np.eye(n) + sw[..., :, None] * K * sw[..., None, :])
    V = np.matmul(np.linalg.inv(L).astype(dtype), (sw[..., :, None] * A).astype(dtype))  # (..., N, M)
    theta_new = theta + np.einsum("...nm,...n->...m", A, a.astype(dtype))
    cov_new = cov - np.matmul(np.swapaxes(V, -1, -2), V)
    return theta_new, cov_new


# -- information (square-root) form -------------------------------------------------------------------------------
#
# The same posterior stored as the information matrix Y = cov^-1 and its Cholesky factor Y = R R^T
# (R lower). Adding a scan is Y += H H^T / sigma_n^2 (a sum of positive semi-definite terms, so Y stays
# positive definite by construction), and every variance is a squared norm ||R^-1 phi||^2 >= 0. The
# cost is O(N M^2 + M^3 / 3) per scan and map instead of the O(N M^2 + N^2 M + N^3) of eq. 15-19, the
# better choice when a scan has hundreds of samples; both give the same posterior (tests).


def prior_information(
    basis: HilbertBasis,
    lengthscale: float,
    signal_variance: float,
    batch: tuple[int, ...] = (),
    dtype: npt.DTypeLike = np.float64,
    floor: float = 1e-12,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``theta = 0``, ``Y = Lambda^-1`` and ``R = Lambda^-1/2`` (eq. 10 inverted).

    Prior variances below ``floor * max(Lambda)`` are raised to it (they are numerically zero; a
    literal metre length scale of 20 underflows them to exactly 0).
    """
    lam = prior_variances(basis, lengthscale, signal_variance)
    lam = np.maximum(lam, floor * lam.max())
    theta = np.zeros((*batch, basis.M), dtype=dtype)
    info = np.zeros((*batch, basis.M, basis.M), dtype=dtype)
    chol = np.zeros_like(info)
    idx = np.arange(basis.M)
    info[..., idx, idx] = (1.0 / lam).astype(dtype)
    chol[..., idx, idx] = (1.0 / np.sqrt(lam)).astype(dtype)
    return theta, info, chol


def whiten(chol: FloatArray, vectors: FloatArray) -> FloatArray:
    """``R^-1 v`` for every row ``v`` of ``vectors (..., K, M)`` (so ``v^T cov v = ||R^-1 v||^2``)."""
    from scipy.linalg import solve_triangular

    out = solve_triangular(chol, np.swapaxes(vectors, -1, -2), lower=True, check_finite=False)
    return np.swapaxes(out, -1, -2)


def cho_solve_vec(chol: FloatArray, b: FloatArray) -> FloatArray:
    """``Y^-1 b`` for ``Y = R R^T``, batched over maps (``b`` is ``(..., M)``)."""
    from scipy.linalg import solve_triangular

    t = solve_triangular(chol, b[..., None], lower=True, check_finite=False)
    return solve_triangular(chol, t, lower=True, trans=1, check_finite=False)[..., 0]


def covariance_from_information(chol: FloatArray) -> FloatArray:
    """``cov = Y^-1 = R^-T R^-1`` (for output and queries of single maps)."""
    eye = np.broadcast_to(np.eye(chol.shape[-1], dtype=chol.dtype), chol.shape)
    rinv = whiten(chol, eye)  # rows: R^-1 e_i, i.e. (R^-1)^T
    cov = np.matmul(rinv, np.swapaxes(rinv, -1, -2))
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


def information_update(
    theta: FloatArray,
    info: FloatArray,
    phi: FloatArray,
    labels: FloatArray,
    noise_variance: float,
    weights: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The Kalman update of eq. 15-19 in information form, batched and in place on ``theta``, ``info``.

    ``Y += H diag(w) H^T`` (``w = 1 / sigma_n^2``, or ``weights``), ``R = chol(Y)``,
    ``theta += Y^-1 H (z - H^T theta) / sigma_n^2`` (``K = cov_new H / sigma_n^2``). Returns
    ``(theta, info, chol)``.
    """
    if phi.shape[-2] == 0:
        return theta, info, np.linalg.cholesky(info)
    w = np.full(phi.shape[:-1], 1.0 / noise_variance, dtype=phi.dtype) if weights is None else weights
    info += np.matmul(np.swapaxes(phi, -1, -2), phi * w[..., None])
    chol = np.linalg.cholesky(info)
    innov = labels - np.einsum("...nm,...m->...n", phi, theta)
    b = np.einsum("...nm,...n->...m", phi, innov) / noise_variance
    theta += cho_solve_vec(chol, b).astype(theta.dtype)
    return theta, info, chol


def laplace_update_information(
    theta: FloatArray,
    info: FloatArray,
    chol: FloatArray,
    phi: FloatArray,
    labels: FloatArray,
    whitened: FloatArray | None = None,
    max_iter: int = 20,
    tol: float = 1e-9,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The recursive Laplace update (eq. 36-43) in information form, in place.

    With ``X = R^-1 H`` (rows ``whitened``): ``K = X^T X``, the mode from :func:`laplace_mode`,
    ``theta_MAP = theta0 + cov H a`` and ``Y_new = Y + H W H^T`` (minus the Hessian of eq. 42 at the mode).
    """
    if phi.shape[-2] == 0:
        return theta, info, chol
    X = whiten(chol, phi) if whitened is None else whitened
    K = np.matmul(X, np.swapaxes(X, -1, -2)).astype(np.float64)
    m = np.einsum("...nm,...m->...n", phi, theta)
    f, w = laplace_mode(K, m, labels, max_iter, tol)
    a = (np.asarray(labels, dtype=np.float64) + 1.0) / 2.0 - sigmoid(f)
    theta += cho_solve_vec(chol, np.einsum("...nm,...n->...m", phi, a.astype(phi.dtype))).astype(theta.dtype)
    info += np.matmul(np.swapaxes(phi, -1, -2), phi * w[..., None].astype(phi.dtype))
    return theta, info, np.linalg.cholesky(info)
