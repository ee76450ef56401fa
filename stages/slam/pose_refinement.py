"""Pose refinement against a particle's own Hilbert-GP map: a Laplace (improved) proposal (issue 17).

The Hilbert map's latent mean ``m(p) = Phi(p)^T theta`` (eq. 26) is a closed-form, differentiable function
of the position, so every particle can move its propagated pose towards the scan's best fit on its own map
before it is weighted: GMapping's improved proposal (Grisetti et al. 2007), which a grid map offers only
by sampling or numerical scan matching. Per particle, a few Gauss-Newton steps maximise

    l(x) = e * sum_j log sigma(y_j m(T(x) p_j)) + log N(x; x_pred, Sigma)

(the mean-only scan log-likelihood of eq. 28 with labels ``y_j = +-1`` and exponent ``e``, and the
motion prior of eq. 21 about the odometry prediction ``x_pred``). The proposal is then the Gaussian
``q = N(x*, s A^-1)`` at the best iterate ``x*``, with ``A`` the Gauss-Newton Hessian of ``-l``; a pose is
drawn from it and the importance weight gains ``log N(x; x_pred, Sigma) - log q(x)`` on top of the scan
likelihood, so the filter stays a correct importance sampler whatever the refinement found. Where the map
is empty, ``A = Sigma^-1`` and ``x* = x_pred``: the proposal is the motion model and the weight is eq. 22.

Pure numpy; batched over particles (``(Np, N)`` samples, ``3 x 3`` systems).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, to_world
from stages.slam.se2 import wrap_angle

F64 = npt.NDArray[np.floating[Any]]
LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True)
class PoseRefinement:
    """Settings of the Laplace proposal; ``iterations = 0`` is the paper's proposal (eq. 21)."""

    #: Gauss-Newton iterations per scan (0: off)
    iterations: int = 0
    #: largest step per iteration on x, y [m] and yaw [rad] (a step is shortened to fit)
    max_step_xy: float = 0.25
    max_step_yaw: float = 0.05
    #: scale ``s`` of the proposal covariance ``s A^-1`` (1: the Laplace approximation itself)
    covariance_scale: float = 1.0
    #: the scan term matched: "logistic", eq. 28's ``log sigma(y m)`` mean-only term; "gaussian", the map's
    #: own regression model of the +-1 labels (eq. 15-19: residuals ``(y - m) / sigma_n``, least squares)
    objective: Literal["gaussian", "logistic"] = "logistic"
    #: weight of the free samples' terms against the endpoints' (as the weights' ``free_weight``)
    free_weight: float = 1.0
    #: sigma_n^2 of the Gaussian term (the map's noise variance; set by the method from the map settings)
    noise_variance: float = 0.36
    #: sigma_n^2 of the endpoints' terms when the map gives its +1 labels their own (None: ``noise_variance``)
    endpoint_noise_variance: float | None = None

    @property
    def enabled(self) -> bool:
        return self.iterations > 0


def mean_and_pose_jacobian(basis: hm.HilbertBasis, theta: F64, poses: F64, points_body: F64) -> tuple[F64, F64]:
    """Latent means ``m (Np, N)`` of the body-frame points seen from each pose and ``dm/dx (Np, N, 3)``.

    With the tensor basis (eq. 7) ``m = a^T Theta b`` from the per-axis tables, without forming ``Phi``;
    ``dm/dyaw = grad m . R'(yaw) p_body``.
    """
    pw = to_world(poses, points_body)  # (Np, N, 2)
    if basis.kind == "tensor":
        a, b, da, db = hm.axis_tables(basis, pw, derivative=True)
        assert da is not None and db is not None
        T = theta.reshape(len(poses), a.shape[-1], b.shape[-1]).astype(np.float64)
        aT = np.matmul(a, T)
        m = np.einsum("kna,kna->kn", aT, b)
        gx = np.einsum("kna,kna->kn", np.matmul(da, T), b)
        gy = np.einsum("kna,kna->kn", aT, db)
    else:
        th = theta.astype(np.float64)
        m = np.einsum("knm,km->kn", hm.features(basis, pw), th)
        g = np.einsum("kndm,km->knd", hm.feature_gradient_rows(basis, pw), th)
        gx, gy = g[..., 0], g[..., 1]
    rx = pw[..., 0] - poses[:, None, 0]
    ry = pw[..., 1] - poses[:, None, 1]
    return m, np.stack([gx, gy, gx * -ry + gy * rx], axis=-1)


def _objective_terms(basis: hm.HilbertBasis, theta: F64, x: F64, samples: BeamSamples, exponent: float,
                     settings: PoseRefinement) -> tuple[F64, F64, F64]:
    """Scan term of ``l``: value ``(Np,)``, gradient ``(Np, 3)``, Gauss-Newton Hessian of ``-l`` ``(Np, 3, 3)``."""
    m, J = mean_and_pose_jacobian(basis, theta, x, samples.points)
    y = np.where(samples.labels > 0, 1.0, -1.0)
    c = np.where(samples.labels > 0, exponent, exponent * settings.free_weight)  # per-sample weight
    if settings.objective == "gaussian":
        # the map's own per-label sigma_n^2 (eq. 15), so that the refinement fits the model the map was fit with
        c = c / hm.label_noise_variance(samples.labels, settings.noise_variance, settings.endpoint_noise_variance)
        res = y - m
        value = -0.5 * np.sum(c * res * res, axis=1)
        r = c * res  # d/dm of -c (y - m)^2 / 2, c = weight / s2
        w = np.broadcast_to(c, m.shape)  # exact Gauss-Newton weight
    else:
        ym = y * m
        value = np.sum(c * hm.log_sigmoid(ym), axis=1)
        r = c * y * hm.sigmoid(-ym)  # d/dm of c log sigma(y m)
        w = c * hm.sigmoid(m) * hm.sigmoid(-m)  # Fisher weight of the logistic term
    grad = np.einsum("kn,knd->kd", r, J)
    hess = np.einsum("kn,knd,kne->kde", w, J, J)
    return value, grad, hess


def _prior_delta(x: F64, x_pred: F64) -> F64:
    d = x - x_pred
    d[:, 2] = wrap_angle(d[:, 2])
    return d


def log_gaussian(x: F64, mean: F64, cov: F64) -> F64:
    """``log N(x; mean, cov)`` per row, yaw differences wrapped; ``cov (3,)`` diagonal or ``(Np, 3, 3)``."""
    d = _prior_delta(x, mean)
    if cov.ndim == 1:
        return -0.5 * (np.sum(d * d / cov, axis=1) + np.sum(np.log(cov)) + 3 * LOG_2PI)
    L = np.linalg.cholesky(cov)
    z = np.linalg.solve(L, d[..., None])[..., 0]
    logdet = 2.0 * np.sum(np.log(np.diagonal(L, axis1=1, axis2=2)), axis=1)
    return -0.5 * (np.sum(z * z, axis=1) + logdet + 3 * LOG_2PI)


def refine(basis: hm.HilbertBasis, theta: F64, x_pred: F64, prior_var: F64, samples: BeamSamples,
           settings: PoseRefinement, exponent: float = 1.0) -> tuple[F64, F64]:
    """Gauss-Newton on ``l(x)`` from ``x_pred``: the best iterate ``x* (Np, 3)`` and ``A (Np, 3, 3)`` there.

    ``prior_var (3,)``: the motion prior's variances on x, y, yaw. Each step solves ``A d = grad l`` and is
    shortened to ``max_step_*``; the iterate with the largest ``l`` is kept (``l`` never gets worse).
    """
    P = np.diag(1.0 / prior_var)
    x = x_pred.copy()
    best_x, best_l, best_A = x.copy(), np.full(len(x), -np.inf), np.broadcast_to(P, (len(x), 3, 3)).copy()
    if samples.n == 0:
        return best_x, best_A
    lim = np.array([settings.max_step_xy, settings.max_step_xy, settings.max_step_yaw])
    for it in range(settings.iterations + 1):
        val, g, H = _objective_terms(basis, theta, x, samples, exponent, settings)
        d = _prior_delta(x, x_pred)
        val = val - 0.5 * np.sum(d * d / prior_var, axis=1)
        A = H + P
        better = val > best_l
        best_x[better], best_l[better], best_A[better] = x[better], val[better], A[better]
        if it == settings.iterations:
            break
        step = np.linalg.solve(A, (g - d / prior_var)[..., None])[..., 0]
        shrink = np.min(np.minimum(1.0, lim / np.maximum(np.abs(step), 1e-300)), axis=1)
        x = x + step * shrink[:, None]
        x[:, 2] = wrap_angle(x[:, 2])
    return best_x, best_A


def sample_proposal(mode: F64, A: F64, scale: float, rng: np.random.Generator) -> tuple[F64, F64]:
    """Draw ``x ~ N(mode, scale A^-1)`` per particle; returns ``x`` and ``log q(x)`` (3 normals per particle)."""
    cov = scale * np.linalg.inv(A)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    L = np.linalg.cholesky(cov)
    eps = rng.standard_normal((len(mode), 3))
    x = mode + np.einsum("kij,kj->ki", L, eps)
    x[:, 2] = wrap_angle(x[:, 2])
    logdet = 2.0 * np.sum(np.log(np.diagonal(L, axis1=1, axis2=2)), axis=1)
    log_q = -0.5 * (np.sum(eps * eps, axis=1) + logdet + 3 * LOG_2PI)
    return x, log_q
