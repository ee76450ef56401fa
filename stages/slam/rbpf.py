"""Rao-Blackwellised particle filter of RICH-SLAM (Sec. IV-D, Algorithm 1), batched across particles.

Pure numpy. Poses are ``(Np, 3)`` arrays (x, y, yaw). A particle-map model implements
:class:`ParticleMaps`: per-particle log-likelihoods of a scan against the maps *before* the update
(eq. 22), then the map update (eq. 15), then selection of survivors after resampling. The Hilbert-GP
model (:class:`HilbertParticleMaps`) keeps every particle's weight posterior in one stack
``theta (Np, M)``, ``cov (Np, M, M)`` so that weights and Kalman updates are batched matrix products.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
import numpy.typing as npt

from stages.odometry.metrics import se2_increments
from stages.slam import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, stencil_offsets, to_world
from stages.slam.particle_linalg import StackedCovariance, StackedInformation
from stages.slam.pose_refinement import PoseRefinement, log_gaussian, refine, sample_proposal
from stages.slam.se2 import compose, wrap_angle

Resampling = Literal["systematic", "stratified", "multinomial"]
F64 = npt.NDArray[np.floating[Any]]


def odometry_increments(poses: npt.ArrayLike) -> F64:
    """Body-frame increments ``u[i] = x[i-1]^-1 (+) x[i]`` of an odometry trajectory ``(T, 3)``.

    Row 0 is zero (the filter starts at the first odometry pose); the odometry stage's own definition.
    """
    return se2_increments(np.asarray(poses, dtype=np.float64))


@dataclass(frozen=True)
class MotionNoise:
    """Process noise ``v`` of eq. 21, added to the body-frame odometry increment.

    Standard deviations per step, in GMapping's motion-model form (srr, srt, str, stt):
    ``std_xy + rel_trans * |translation| + trans_per_rot * |rotation|`` on x and y,
    ``std_yaw + rel_rot * |rotation| + rot_per_trans * |translation|`` on yaw.
    """

    std_xy: float = 0.02
    std_yaw: float = 0.005
    rel_trans: float = 0.0
    rel_rot: float = 0.0
    rot_per_trans: float = 0.0
    trans_per_rot: float = 0.0

    def std(self, u: npt.ArrayLike) -> tuple[float, float]:
        """``(std on x and y, std on yaw)`` of the step with body-frame increment ``u``."""
        u = np.asarray(u, dtype=np.float64).reshape(3)
        trans, rot = float(np.hypot(u[0], u[1])), abs(float(u[2]))
        return (self.std_xy + self.rel_trans * trans + self.trans_per_rot * rot,
                self.std_yaw + self.rel_rot * rot + self.rot_per_trans * trans)


def propagate(poses: F64, u: npt.ArrayLike, noise: MotionNoise, rng: np.random.Generator) -> F64:
    """Draw ``x_k[i] ~ f(x_k[i-1], u[i], v_k[i])`` for every particle (eq. 21; the proposal q)."""
    u = np.asarray(u, dtype=np.float64).reshape(3)
    s_xy, s_yaw = noise.std(u)
    v = rng.standard_normal((len(poses), 3)) * np.array([s_xy, s_xy, s_yaw])
    return compose(poses, u + v)


@dataclass(frozen=True)
class YawBias:
    """Each particle's yaw-rate bias b (rad/s): what is left of the gyro z bias in the odometry's heading.

    Prior ``b_0 ~ N(0, sigma0^2)``; a random walk ``b_k = b_{k-1} + walk sqrt(dt) n``. The motion applied to a
    particle is the odometry increment with its yaw corrected by its own bias, ``dyaw - b dt``, so a particle
    with the right bias keeps the right heading and the weights gather evidence for it scan after scan.
    """

    #: prior std, rad/s (the EKF's gyro-bias prior: a MEMS turn-on bias left after the start)
    sigma0: float = 0.005
    #: random-walk density, rad/s/sqrt(s): 3DM-GX5 in-run bias instability 8 deg/h (3.9e-5 rad/s) over a
    #: 100 s correlation time, 3.9e-5 / sqrt(100)
    walk: float = 3.9e-6
    #: the share of the particles that carry a bias; the others keep b = 0 (the odometry's heading as it is),
    #: so the weights choose between "the odometry drifts" and "it does not" (1: every particle)
    share: float = 1.0


@dataclass(frozen=True)
class WideMode:
    """A second motion mode for a share of the particles: GMapping's wide fitted noise (:class:`MotionNoise`)
    instead of the odometry's own increment covariance, for when the odometry drifts more than its covariance
    says (stages/slam/README.md, stop 54).

    Each particle is in one of the two modes; the mode is resampled with it, so where the weights favour the wide
    particles (the odometry's heading is off) they take over the cloud, and where the odometry is honest the narrow
    ones do. Every scan a particle's mode is drawn afresh from the stationary ``share`` with probability
    ``switch``, so neither mode dies out for good. The motion model is then a two-state Markov mixture, and the
    filter samples from it exactly: the weights stay eq. 22's likelihoods.
    """

    #: stationary share of the particles in the wide mode (also the share at the start)
    share: float = 0.1
    #: per-scan probability that a particle's mode is drawn afresh from ``share``
    switch: float = 0.01


class Proposal:
    """The proposal q of eq. 21 for every particle: the odometry increment plus noise, either GMapping's
    fitted form (:class:`MotionNoise`, ``cov`` None) or the odometry's own increment covariance ``cov[i]``
    (``(T, 3, 3)``, body frame), optionally each particle's yaw-rate bias (:class:`YawBias`, needs the
    scan intervals ``dt``) and a wide mode for a share of the particles (:class:`WideMode`: ``noise`` for them,
    ``cov`` for the others). Draws come from ``rng`` in a fixed order, so that the numpy and torch filters
    draw the same; with ``cov``, ``bias`` and ``wide`` None they are :func:`propagate`'s.
    """

    def __init__(self, noise: MotionNoise, n_particles: int, rng: np.random.Generator, cov: F64 | None = None,
                 dt: F64 | None = None, bias: YawBias | None = None, wide: WideMode | None = None) -> None:
        if bias is not None and dt is None:
            raise ValueError("the yaw-rate bias state needs the scan intervals dt")
        if wide is not None and cov is None:
            raise ValueError("the wide mode is GMapping's noise beside the odometry's covariance: it needs cov")
        self.noise, self.rng, self.model, self.wide = noise, rng, bias, wide
        self.dt = None if dt is None else np.asarray(dt, dtype=np.float64)
        self.chol: F64 | None = None
        if cov is not None:
            c = np.asarray(cov, dtype=np.float64).reshape(-1, 3, 3)
            w, V = np.linalg.eigh(0.5 * (c + np.swapaxes(c, 1, 2)))
            self.chol = V * np.sqrt(np.maximum(w, 0.0))[:, None, :]  # L L^T = cov, also when singular
        self.bias: F64 | None = None if bias is None else rng.normal(0.0, bias.sigma0, n_particles)
        #: which particles carry a bias (``YawBias.share``: the first of them); resampled with them
        self.carries: npt.NDArray[np.bool_] | None = None
        if bias is not None and self.bias is not None and bias.share < 1.0:
            self.carries = np.arange(n_particles) < round(bias.share * n_particles)
            self.bias = np.where(self.carries, self.bias, 0.0)
        #: which particles are in the wide mode (:class:`WideMode`); resampled with them
        self.wide_mode: npt.NDArray[np.bool_] | None = None if wide is None else rng.random(n_particles) < wide.share
        self._i = 0

    def _step(self) -> tuple[int, float]:
        self._i += 1
        return self._i, 0.0 if self.dt is None else float(self.dt[min(self._i, len(self.dt) - 1)])

    def _walk(self, dt: float) -> None:
        if self.bias is not None and self.model is not None and self.model.walk > 0:
            step = self.model.walk * np.sqrt(max(dt, 0.0)) * self.rng.standard_normal(len(self.bias))
            self.bias = self.bias + (step if self.carries is None else np.where(self.carries, step, 0.0))

    def corrected(self, u: npt.ArrayLike, n: int, dt: float) -> F64:
        """``(n, 3)``: the increment with each particle's bias taken off its yaw."""
        d = np.tile(np.asarray(u, dtype=np.float64).reshape(1, 3), (n, 1))
        if self.bias is not None:
            d[:, 2] -= self.bias * dt
        return d

    def draw(self, u: npt.ArrayLike, n: int) -> F64:
        """The next step's increments ``(n, 3)`` (bias-corrected, with noise), to compose onto the poses."""
        i, dt = self._step()
        self._walk(dt)
        u = np.asarray(u, dtype=np.float64).reshape(3)
        if self.chol is None:
            s_xy, s_yaw = self.noise.std(u)
            v = self.rng.standard_normal((n, 3)) * np.array([s_xy, s_xy, s_yaw])
        else:
            v = self.rng.standard_normal((n, 3)) @ self.chol[min(i, len(self.chol) - 1)].T
        if self.wide is not None and self.wide_mode is not None:
            redraw = self.rng.random(n) < self.wide.switch
            self.wide_mode = np.where(redraw, self.rng.random(n) < self.wide.share, self.wide_mode)
            s_xy, s_yaw = self.noise.std(u)
            vw = self.rng.standard_normal((n, 3)) * np.array([s_xy, s_xy, s_yaw])
            v = np.where(self.wide_mode[:, None], vw, v)
        return self.corrected(u, n, dt) + v

    def prior(self, u: npt.ArrayLike, n: int) -> tuple[F64, F64]:
        """The next step's bias-corrected increments ``(n, 3)`` and the diagonal of their variance ``(3,)``
        (for the Laplace proposal of :mod:`pose_refinement`, which takes the prior as diagonal)."""
        if self.wide is not None:
            raise ValueError("the Laplace proposal takes one prior for every particle: no wide mode (WideMode)")
        i, dt = self._step()
        self._walk(dt)
        if self.chol is None:
            s_xy, s_yaw = self.noise.std(u)
            var = np.array([s_xy, s_xy, s_yaw]) ** 2
        else:
            L = self.chol[min(i, len(self.chol) - 1)]
            var = np.sum(L * L, axis=1)
        return self.corrected(u, n, dt), np.maximum(var, 1e-12)

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        """Survivors after resampling carry their biases."""
        if self.bias is not None:
            self.bias = self.bias[np.asarray(indices)]
        if self.carries is not None:
            self.carries = self.carries[np.asarray(indices)]
        if self.wide_mode is not None:
            self.wide_mode = self.wide_mode[np.asarray(indices)]

    def wide_share(self, w: F64) -> float:
        """The weight on the wide mode's particles (nan without it)."""
        return float("nan") if self.wide_mode is None else float(np.dot(w, self.wide_mode))

    def bias_mean(self, w: F64) -> float:
        """The weighted mean bias (nan without the bias state)."""
        return float("nan") if self.bias is None else float(np.dot(w, self.bias))


# -- weights and resampling ------------------------------------------------------------------------------


def normalize_log_weights(logw: npt.ArrayLike) -> F64:
    """Normalised weights from log weights (max-shifted)."""
    lw = np.asarray(logw, dtype=np.float64)
    w = np.exp(lw - np.max(lw))
    return w / w.sum()


def effective_sample_size(weights: npt.ArrayLike) -> float:
    """``N_eff = (sum w)^2 / sum w^2`` (eq. 31)."""
    w = np.asarray(weights, dtype=np.float64)
    return float(w.sum() ** 2 / np.sum(w**2))


def _search(w: F64, positions: F64) -> npt.NDArray[np.int64]:
    c = np.cumsum(w)
    c /= c[-1]
    c[-1] = 1.0
    return np.minimum(np.searchsorted(c, positions, side="right"), len(w) - 1).astype(np.int64)


def systematic_resample(w: npt.ArrayLike, rng: np.random.Generator) -> npt.NDArray[np.int64]:
    """Low-variance (systematic) resampling: one uniform offset, N evenly spaced pointers."""
    w = np.asarray(w, dtype=np.float64)
    n = len(w)
    return _search(w, (rng.random() + np.arange(n)) / n)


def stratified_resample(w: npt.ArrayLike, rng: np.random.Generator) -> npt.NDArray[np.int64]:
    """Stratified resampling: one uniform draw per stratum."""
    w = np.asarray(w, dtype=np.float64)
    n = len(w)
    return _search(w, (rng.random(n) + np.arange(n)) / n)


def multinomial_resample(w: npt.ArrayLike, rng: np.random.Generator) -> npt.NDArray[np.int64]:
    """Multinomial resampling (i.i.d. draws)."""
    w = np.asarray(w, dtype=np.float64)
    return _search(w, np.sort(rng.random(len(w))))


RESAMPLERS: dict[str, Callable[[npt.ArrayLike, np.random.Generator], npt.NDArray[np.int64]]] = {
    "systematic": systematic_resample,
    "stratified": stratified_resample,
    "multinomial": multinomial_resample,
}


# -- the Hilbert-GP particle likelihood (eq. 22-30) -----------------------------------------------------------


@dataclass(frozen=True)
class HilbertWeighting:
    """How a particle scores a scan against its map posterior."""

    #: use the map variance (eq. 28); False gives the mean-only weighting of H-SLAM
    use_variance: bool = True
    #: endpoint tolerance radius r_e [m] (eq. 29); 0 disables it
    endpoint_tolerance: float = 0.25
    #: points per ring of the discretised tolerance disc (Fig. 3b); the centre is always included
    ring_points: int = 8
    rings: int = 1
    #: variance at the tolerance points: "exact" Phi(q)^T cov Phi(q); "taylor" with Phi(q) ~ Phi(p) + J (q - p)
    #: (the mean is always exact)
    et_variance: Literal["exact", "taylor"] = "exact"
    #: exponent on the scan likelihood (1 = the paper)
    exponent: float = 1.0
    #: weight of the free samples' log terms against the endpoints' (1 = the paper, eq. 23)
    free_weight: float = 1.0
    #: common support: score a scan only on the samples that every particle's map has seen, i.e. whose predictive
    #: variance (eq. 27) is below this for every particle (None: every sample, the paper)
    support_variance: float | None = None
    #: probability that a sample is not explained by the map (clutter, multipath, a moving object): its
    #: likelihood is then 1/2 whatever the map says (:func:`log_occupancy_terms`); 0 = the paper (eq. 28)
    outlier: float = 0.0


@dataclass(frozen=True)
class MapModel:
    """The Hilbert-GP particle maps' model and numerics: one parameter object for every backend
    (:class:`HilbertParticleMaps`, ``parallel.ParallelHilbertMaps``, ``torch_maps.TorchHilbertMaps``)."""

    #: SE length scale l (m) and signal variance sigma_f^2 of the prior (eq. 9), label noise sigma_n^2 (eq. 15)
    lengthscale: float
    signal_variance: float
    noise_variance: float
    weighting: HilbertWeighting = field(default_factory=HilbertWeighting)
    update: Literal["kalman", "laplace"] = "kalman"
    dtype: npt.DTypeLike = np.float64
    laplace_iterations: int = 20
    form: Literal["information", "covariance"] = "information"
    #: sigma_n^2 of the +1 samples (None: ``noise_variance`` for all, eq. 15)
    endpoint_noise_variance: float | None = None


class CovarianceMetric:
    """Quadratic forms ``u^T cov v`` with the covariance stored: ``transform(V) = V cov``."""

    def __init__(self, cov: F64) -> None:
        self.cov = cov

    def transform(self, V: F64) -> F64:
        return np.matmul(V, self.cov)

    @staticmethod
    def inner(Ta: F64, Va: F64, Tb: F64, Vb: F64) -> F64:
        return np.einsum("...m,...m->...", Ta, Vb)


class StackedCovarianceMetric:
    """Quadratic forms with a :class:`StackedCovariance` (lower triangles, BLAS symm)."""

    def __init__(self, stack: StackedCovariance) -> None:
        self.stack = stack

    def transform(self, V: F64) -> F64:
        return self.stack.transform(V)

    inner = staticmethod(CovarianceMetric.inner)


class InformationMetric:
    """Quadratic forms with the information factor stored (``Y = L L^T``): ``transform(V)`` has rows ``L^-1 v``.

    Built from a numpy stack of lower factors or from a :class:`StackedInformation`.
    """

    def __init__(self, chol: F64 | StackedInformation) -> None:
        self.chol = chol

    def transform(self, V: F64) -> F64:
        if isinstance(self.chol, StackedInformation):
            return self.chol.whiten(V)
        return hm.whiten(self.chol, V)

    @staticmethod
    def inner(Ta: F64, Va: F64, Tb: F64, Vb: F64) -> F64:
        return np.einsum("...m,...m->...", Ta, Tb)


Metric = CovarianceMetric | StackedCovarianceMetric | InformationMetric


def log_occupancy_terms(mean: F64, var: F64 | None, outlier: float = 0.0) -> tuple[F64, F64]:
    """``log o`` and ``log (1 - o)`` with ``o`` of eq. 28 (mean-only when ``var`` is None).

    ``outlier`` = e > 0: each sample is, with probability e, not explained by the map (a clutter detection, a
    multipath ghost, the free space in front of one) and then scores 1/2 whatever the map: ``log((1 - e) o +
    e / 2)``. A sample the map calls impossible then costs at most ``log(e / 2)``, as the grid's likelihood
    field bounds it with ``z_rand`` (Probabilistic Robotics, the beam model's p_rand), instead of outweighing
    the scan's other samples."""
    x = mean if var is None else mean * hm.probit_scale(var)
    lo, lf = hm.log_sigmoid(x), hm.log_sigmoid(-x)
    if outlier <= 0:
        return lo, lf
    a, b = np.log1p(-outlier), np.log(0.5 * outlier)
    return np.logaddexp(a + lo, b), np.logaddexp(a + lf, b)


def endpoint_index(samples: BeamSamples) -> npt.NDArray[np.int64] | slice:
    """Positions of the endpoints among the samples: a slice (views, not copies, of per-sample arrays)
    when they are contiguous, as :func:`sample_beams` writes them."""
    pos = np.flatnonzero(samples.labels > 0)
    if pos.size and pos[-1] - pos[0] + 1 == pos.size:
        return slice(int(pos[0]), int(pos[-1]) + 1)
    return pos


def endpoint_jacobians(basis: hm.HilbertBasis, poses: F64, samples: BeamSamples, dtype: npt.DTypeLike,
                       out: F64 | None = None) -> F64:
    """``d Phi / d p`` at every endpoint, as rows ``(Np, B, 2, M)`` (x then y derivative)."""
    ends_w = to_world(poses, samples.points[samples.labels > 0])
    return hm.feature_gradient_rows(basis, ends_w, dtype=dtype, out=out)


def hilbert_log_likelihood(
    basis: hm.HilbertBasis,
    theta: F64,
    cov: F64 | Metric,
    poses: F64,
    samples: BeamSamples,
    weighting: HilbertWeighting,
    phi: F64 | None = None,
    phi_t: F64 | None = None,
    jac: F64 | None = None,
    jac_t: F64 | None = None,
    ring: tuple[F64, F64] | None = None,
    mean: F64 | None = None,
    per_sample: bool = False,
) -> Any:
    """Per-particle ``log Pr(z~[i] | x_k[i], D_k[i-1])`` (eq. 23-30), batched over particles.

    ``per_sample``: instead, every sample's term ``(Np, N)`` (free samples times ``free_weight``, endpoints with
    their tolerance; no exponent) and the predictive variances ``(Np, N)`` (None for the mean-only weight), for
    :func:`common_support_total`.

    ``cov`` is the stack of covariances ``(Np, M, M)`` or a metric of the information form.
    ``phi`` ``(Np, N, M)``, ``phi_t`` (its metric transform) and, for the Taylor tolerance, the endpoint
    Jacobians ``jac (Np, B, 2, M)`` and their transform, or for the exact tolerance the ring points'
    features ``(Np, B K, M)`` and their transform (``ring``), may be passed in when already computed,
    and so may the latent means ``mean (Np, N)`` (eq. 26). An information-form metric reads only the
    transforms: then, with ``mean`` given, ``phi`` and the ring features are not read.
    """
    metric: Metric = CovarianceMetric(cov) if isinstance(cov, np.ndarray) else cov
    if samples.n == 0:
        return np.zeros(len(poses))
    if phi is None:
        phi = hm.features(basis, to_world(poses, samples.points), dtype=theta.dtype)
    if mean is None:
        mean = np.einsum("knm,km->kn", phi, theta)
    var = None
    if weighting.use_variance:
        if phi_t is None:
            phi_t = metric.transform(phi)
        var = np.maximum(metric.inner(phi_t, phi, phi_t, phi), 0.0)
    log_o, log_free = log_occupancy_terms(mean, var, weighting.outlier)
    pos = samples.labels > 0
    if per_sample:
        terms = np.where(pos, log_o, weighting.free_weight * log_free)
        if weighting.endpoint_tolerance > 0 and np.any(pos):
            terms[:, pos] = _endpoint_tolerant_log_o(basis, theta, metric, poses, samples, weighting, phi, phi_t,
                                                     mean, var, jac, jac_t, ring)
        return terms, var
    total = weighting.free_weight * np.sum(log_free[:, ~pos], axis=1)
    if weighting.endpoint_tolerance > 0 and np.any(pos):
        et = _endpoint_tolerant_log_o(basis, theta, metric, poses, samples, weighting, phi, phi_t, mean, var,
                                      jac, jac_t, ring)
        total = total + np.sum(et, axis=1)
    else:
        total = total + np.sum(log_o[:, pos], axis=1)
    return weighting.exponent * total


def common_support_total(terms: F64, var: F64 | None, weighting: HilbertWeighting) -> F64:
    """The scan's log-likelihood per particle from its per-sample terms: summed over the samples whose predictive
    variance is below ``weighting.support_variance`` for *every* particle (all samples when unset or without
    variances), times the exponent. Scoring every particle on the same samples keeps a hypothesis that turns the
    scan towards space its map has not seen (o = 0.5, eq. 28) from scoring better than one whose samples fall on a
    map that is only approximately right."""
    if weighting.support_variance is not None and var is not None:
        keep = np.all(var < weighting.support_variance, axis=0)
        return np.asarray(weighting.exponent * (terms @ keep.astype(terms.dtype)))
    return np.asarray(weighting.exponent * np.sum(terms, axis=1))


def _endpoint_tolerant_log_o(
    basis: hm.HilbertBasis,
    theta: F64,
    metric: Metric,
    poses: F64,
    samples: BeamSamples,
    weighting: HilbertWeighting,
    phi: F64,
    phi_t: F64 | None,
    mean: F64,
    var: F64 | None,
    jac: F64 | None,
    jac_t: F64 | None,
    ring: tuple[F64, F64] | None = None,
) -> F64:
    """``log max_{|q - p| <= r_e} o_k(q)`` at every endpoint (eq. 29), shape ``(Np, B)``.

    The disc is discretised as its centre plus rings (:func:`stencil_offsets`); the centre term is the
    endpoint's own sample. Means at the ring points are exact; variances exact or Taylor.
    """
    dtype = theta.dtype
    pos = endpoint_index(samples)
    ends_w = to_world(poses, samples.points[pos])  # (Np, B, 2)
    offs = stencil_offsets(weighting.endpoint_tolerance, weighting.ring_points, weighting.rings)[1:]  # (K, 2)
    q = ends_w[:, :, None, :] + offs  # (Np, B, K, 2)
    Np, B, K = q.shape[:3]
    mean_q = hm.mean_at(basis, theta, q.reshape(Np, B * K, 2)).reshape(Np, B, K)
    var_q: F64 | None = None
    var_c = None if var is None else var[:, pos]
    if var_c is not None:
        assert phi_t is not None
        if weighting.et_variance == "exact":
            if ring is not None:
                phi_q, t_q = ring
            else:
                phi_q = hm.features(basis, q.reshape(Np, B * K, 2), dtype=dtype)
                t_q = metric.transform(phi_q)
            var_q = np.maximum(metric.inner(t_q, phi_q, t_q, phi_q), 0.0).reshape(Np, B, K)
        else:
            # Phi(p + d) ~ Phi(p) + J d: var ~ v + 2 g.d + d^T G d (a Gauss-Newton quadratic, >= 0)
            if jac is None:
                jac = endpoint_jacobians(basis, poses, samples, dtype)
            if jac_t is None:
                jac_t = metric.transform(jac.reshape(Np, B * 2, -1)).reshape(jac.shape)
            pc, tc = phi[:, pos], phi_t[:, pos]
            g = metric.inner(tc[:, :, None, :], pc[:, :, None, :], jac_t, jac)  # (Np, B, 2)
            G = metric.inner(jac_t[:, :, :, None, :], jac[:, :, :, None, :], jac_t[:, :, None, :, :],
                             jac[:, :, None, :, :])
            var_q = (var_c[:, :, None] + 2.0 * np.einsum("kbd,qd->kbq", g, offs)
                     + np.einsum("qd,kbde,qe->kbq", offs, G, offs))
            var_q = np.maximum(var_q, 0.0)
    log_q, _ = log_occupancy_terms(mean_q, var_q, weighting.outlier)
    log_c, _ = log_occupancy_terms(mean[:, pos], var_c, weighting.outlier)
    return np.maximum(np.max(log_q, axis=2), log_c)


# -- particle-map models ---------------------------------------------------------------------------------------


class ParticleMaps(Protocol):
    """Per-particle maps driven by the filter."""

    def log_likelihood(self, poses: F64, samples: BeamSamples) -> F64: ...

    def update(self, poses: F64, samples: BeamSamples) -> None: ...

    def select(self, indices: npt.NDArray[np.int64]) -> None: ...


def weigh_and_update(maps: ParticleMaps, poses: F64, samples: BeamSamples) -> F64:
    """``maps.log_likelihood`` then ``maps.update`` on the same poses, fused where the model offers it."""
    fused = getattr(maps, "weigh_and_update", None)
    if fused is not None:
        return np.asarray(fused(poses, samples))
    ll = maps.log_likelihood(poses, samples)
    maps.update(poses, samples)
    return ll


class HilbertParticleMaps:
    """Every particle's Hilbert-GP weight posterior (eq. 20), stacked for batched products.

    ``form = "covariance"`` stores ``cov`` and applies eq. 15-19 (square-root gain, symmetric rank-N
    downdate in place); ``"information"`` stores ``Y = cov^-1`` and its Cholesky factor (positive
    definite by construction, cheaper for scans with many samples). ``log_likelihood`` caches the scan's
    features (samples, and the tolerance ring points or endpoint Jacobians) with their metric transform,
    computed in one BLAS call per particle, so the following ``update`` (same poses) reuses them.
    """

    def __init__(self, basis: hm.HilbertBasis, n_particles: int, model: MapModel,
                 arrays: tuple[F64, ...] | None = None) -> None:
        """``arrays``: existing stacks to work on in place: ``(theta, info, eta)`` (information form) or
        ``(theta, cov)`` (covariance form, lower triangles). ``model.endpoint_noise_variance``: sigma_n^2 of
        the +1 samples (the free samples keep ``noise_variance``); None: one value for both, as in eq. 15."""
        self.model = model
        lengthscale, signal_variance, noise_variance = model.lengthscale, model.signal_variance, model.noise_variance
        weighting, update, dtype, form = model.weighting, model.update, model.dtype, model.form
        laplace_iterations, endpoint_noise_variance = model.laplace_iterations, model.endpoint_noise_variance
        self.basis = basis
        self.noise_variance = noise_variance
        self.endpoint_noise_variance = endpoint_noise_variance
        self.weighting = weighting
        self.update_kind = update
        self.laplace_iterations = laplace_iterations
        self.dtype = np.dtype(dtype)
        self.form = form
        self.prior_diag = hm.prior_variances(basis, lengthscale, signal_variance)
        self.stack: StackedInformation | None = None
        self.cstack: StackedCovariance | None = None
        if form == "information":
            _, info, _ = hm.prior_information(basis, lengthscale, signal_variance)
            pair = None if arrays is None else (arrays[1], arrays[2])
            self.stack = StackedInformation(np.diag(info), n_particles, self.dtype, arrays=pair)
        else:
            self.cstack = StackedCovariance(self.prior_diag, n_particles, self.dtype,
                                            array=None if arrays is None else arrays[1])
        #: map means; in the information form, those the last weighting used (before that scan's update)
        self.theta = np.zeros((n_particles, basis.M), dtype=self.dtype) if arrays is None else arrays[0]
        self._cache: tuple[Any, ...] | None = None
        self._buffers: dict[str, F64] = {}
        #: target size of one block of :meth:`weigh_and_update` (rows and whitened rows)
        self.block_bytes = 16 * 2**20

    def _workspace(self, name: str, shape: tuple[int, ...]) -> F64:
        """A C-contiguous scratch array of ``shape``, reusing the memory of the last scans'."""
        size = int(np.prod(shape))
        buf = self._buffers.get(name)
        if buf is None or buf.size < size:
            buf = self._buffers[name] = np.empty(max(size, int(1.25 * size)), dtype=self.dtype)
        return buf[:size].reshape(shape)

    @property
    def cov(self) -> F64 | None:
        """The covariance stack (lower triangles in the Fortran view), covariance form only."""
        return None if self.cstack is None else self.cstack.cov

    @property
    def metric(self) -> Metric:
        if self.stack is not None:
            return InformationMetric(self.stack)
        assert self.cstack is not None
        return StackedCovarianceMetric(self.cstack)

    def map_of(self, k: int) -> tuple[F64, F64]:
        """Mean and covariance of particle k's map (float64)."""
        if self.stack is not None:
            theta, L = self.stack.posterior(k)
            return theta, hm.covariance_from_information(L)
        assert self.cstack is not None
        return self.theta[k].astype(np.float64), self.cstack.full(k)

    def row_noise(self, labels: F64) -> F64 | float:
        """sigma_n^2 of each sample (eq. 15's noise): per label when ``endpoint_noise_variance`` is set."""
        s2 = hm.label_noise_variance(labels, self.noise_variance, self.endpoint_noise_variance)
        return s2 if isinstance(s2, float) else s2.astype(self.dtype)

    def _cached(self, poses: F64, samples: BeamSamples) -> tuple[Any, ...] | None:
        """The cached products of this scan at these poses, if any."""
        c = self._cache
        return c[2:] if c is not None and c[0] is poses and c[1] is samples else None

    def _products(self, poses: F64, samples: BeamSamples, fuse_update: bool = False,
                  first: int | None = None) -> tuple[Any, ...]:
        """``(phi, phi_t, jac, jac_t, ring, mean)`` of the scan, transformed by one call per particle.

        Information form: the same per-particle pass factors the map, solves its mean into ``theta``
        and, with ``fuse_update`` (Kalman), applies the scan's update (eq. 15-19) right after; then the
        rows are whitened in place (``phi`` and ``jac`` hold their transforms) and ``mean`` holds the
        latent means of the samples (else None).
        ``first``: ``poses`` are those of the block of particles starting there (not cached).
        """
        c = self._cached(poses, samples) if first is None else None
        if c is not None:
            return c
        w = self.weighting
        Np, N, M = len(poses), samples.n, self.basis.M
        pos = samples.labels > 0
        B, ring_offs, extra_rows = self._tolerance_rows(samples)
        # samples, then Jacobian or ring rows, in one reused buffer (fresh pages cost more than the fill)
        rows = self._workspace("rows", (Np, N + extra_rows, M))
        phi = hm.features(self.basis, to_world(poses, samples.points), out=rows[:, :N])
        jac = ring = None
        extra: F64 | None = rows[:, N:] if extra_rows else None
        if extra is not None and ring_offs is None:
            jac = endpoint_jacobians(self.basis, poses, samples, self.dtype,
                                     out=np.reshape(extra, (Np, B, 2, M), copy=False))
        elif extra is not None:
            assert ring_offs is not None
            q = to_world(poses, samples.points[pos])[:, :, None, :] + ring_offs
            hm.features(self.basis, q.reshape(Np, -1, 2), out=extra)
        if self.stack is not None:
            s2 = self.noise_variance
            fuse = fuse_update and self.update_kind == "kalman"
            whiten = w.use_variance or self.update_kind == "laplace"  # mean-only Kalman needs no transform
            # fused: the update reads the features first, so the rows are whitened in place
            theta, out, mean = self.stack.scan(
                rows if whiten else rows[:, :0], gram=phi if fuse else None, gram_scale=1.0 / s2,
                out=(rows if fuse else self._workspace("white", rows.shape)) if whiten else None,
                eta_coef=np.broadcast_to(samples.labels.astype(self.dtype) / s2, (Np, N)) if fuse else None,
                first=first or 0, mean_rows=N if fuse and whiten else 0)
            mean_out = mean if fuse and whiten else None
            if first is None:
                self.theta = theta
            else:
                self.theta[first : first + Np] = theta
            both = out if whiten else rows
        else:
            both = self.metric.transform(rows)
            mean_out = None
        phi_t, extra_t = both[:, :N], both[:, N:]
        jac_t = None if jac is None else extra_t.reshape(jac.shape)
        if extra is not None and jac is None:
            ring = (extra, extra_t)
        # fused products are of a block and already updated: never cached for a later ``update``
        cache = first is None and not fuse_update
        self._cache = (poses, samples, phi, phi_t, jac, jac_t, ring, mean_out) if cache else None
        return phi, phi_t, jac, jac_t, ring, mean_out

    def _tolerance_rows(self, samples: BeamSamples) -> tuple[int, F64 | None, int]:
        """Endpoints ``B``, ring offsets (exact tolerance variance, else None) and the number of extra
        rows the tolerance adds to the scan's samples (``2 B`` Jacobian or ``B K`` ring rows)."""
        w = self.weighting
        B = int(np.count_nonzero(samples.labels > 0))
        if not (w.use_variance and w.endpoint_tolerance > 0 and B):
            return B, None, 0
        if w.et_variance == "taylor":
            return B, None, 2 * B
        offs = stencil_offsets(w.endpoint_tolerance, w.ring_points, w.rings)[1:]
        return B, offs, B * len(offs)

    def log_likelihood(self, poses: F64, samples: BeamSamples) -> F64:
        if samples.n == 0:
            return np.zeros(len(poses))
        phi, phi_t, jac, jac_t, ring, mean = self._products(poses, samples)
        if self.weighting.support_variance is not None:
            terms, var = hilbert_log_likelihood(self.basis, self.theta, self.metric, poses, samples, self.weighting,
                                                phi=phi, phi_t=phi_t, jac=jac, jac_t=jac_t, ring=ring, mean=mean,
                                                per_sample=True)
            return common_support_total(terms, var, self.weighting)
        return hilbert_log_likelihood(self.basis, self.theta, self.metric, poses, samples, self.weighting,
                                      phi=phi, phi_t=phi_t, jac=jac, jac_t=jac_t, ring=ring, mean=mean)

    def weigh_and_update(self, poses: F64, samples: BeamSamples) -> F64:
        """``log_likelihood`` then ``update`` on the same poses (the RBPF step).

        Information form with the Kalman update: one pass over the maps, a block of particles at a
        time, so that each block's rows, whitened rows and maps stay in cache from the features to the
        weights (memory traffic, not arithmetic, is what the unblocked version waits on).
        """
        if samples.n == 0:
            return np.zeros(len(poses))
        if self.stack is None or self.update_kind != "kalman" or self.endpoint_noise_variance is not None:
            # per-label noise: the fused pass takes one gram scale, so weigh, then update
            ll = self.log_likelihood(poses, samples)
            self.update(poses, samples)
            return ll
        out = np.empty(len(poses))
        support = self.weighting.support_variance is not None
        terms = np.empty((len(poses), samples.n)) if support else out
        var: F64 | None = np.empty((len(poses), samples.n)) if support else None
        step = self.block_size(samples)
        for lo in range(0, len(poses), step):
            p = poses[lo : lo + step]
            phi, phi_t, jac, jac_t, ring, mean = self._products(p, samples, fuse_update=True, first=lo)
            res = hilbert_log_likelihood(
                self.basis, self.theta[lo : lo + step], self.metric, p, samples, self.weighting,
                phi=phi, phi_t=phi_t, jac=jac, jac_t=jac_t, ring=ring, mean=mean, per_sample=support)
            if support:
                terms[lo : lo + step] = res[0]
                if var is not None and res[1] is not None:
                    var[lo : lo + step] = res[1]
                else:
                    var = None
            else:
                out[lo : lo + step] = res
        self._cache = None
        return common_support_total(terms, var, self.weighting) if support else out

    def block_size(self, samples: BeamSamples) -> int:
        """Particles per block of :meth:`weigh_and_update`: about ``block_bytes`` of rows (samples and
        tolerance rows, and their whitened copy)."""
        rows = samples.n + self._tolerance_rows(samples)[2]
        per = 2 * rows * self.basis.M * self.dtype.itemsize
        return max(1, int(self.block_bytes // max(per, 1)))

    def insert(self, poses: F64, samples: BeamSamples) -> None:
        """The map update alone, without weights (as :meth:`update`; the name the worker maps share)."""
        self.update(poses, samples)

    def update(self, poses: F64, samples: BeamSamples) -> None:
        if samples.n == 0:
            return
        labels = samples.labels.astype(self.dtype)
        if self.stack is not None:
            self._update_information(self.stack, poses, samples, labels)
        else:
            assert self.cstack is not None
            phi, phi_t = self._products(poses, samples)[:2]
            self._update_covariance(self.cstack, phi, phi_t, labels)
        self._cache = None

    def _update_covariance(self, st: StackedCovariance, phi: F64, A: F64, labels: F64) -> None:
        """eq. 15-19 with ``A = H^T cov``: ``S = R R^T``, ``W = R^-1 A``, ``cov -= W^T W`` (syrk)."""
        n = phi.shape[1]
        if self.update_kind == "kalman":
            S = np.matmul(A, np.swapaxes(phi, -1, -2)).astype(np.float64)
            S = 0.5 * (S + np.swapaxes(S, -1, -2))
            S[:, np.arange(n), np.arange(n)] += self.row_noise(labels)
            Rinv = np.linalg.inv(np.linalg.cholesky(S)).astype(self.dtype)
            W = np.matmul(Rinv, A)
            innov = labels - np.einsum("knm,km->kn", phi, self.theta)
            self.theta += np.einsum("knm,kn->km", W, np.einsum("kij,kj->ki", Rinv, innov))
        else:
            # Appendix, eq. 43 by Woodbury: cov -= V^T V, V = L^-1 W^1/2 A, B = I + W^1/2 K W^1/2 = L L^T
            K = np.matmul(A, np.swapaxes(phi, -1, -2)).astype(np.float64)
            K = 0.5 * (K + np.swapaxes(K, -1, -2))
            m = np.einsum("knm,km->kn", phi, self.theta)
            f, w = hm.laplace_mode(K, m, labels, self.laplace_iterations)
            a = (labels + 1.0) / 2.0 - hm.sigmoid(f)
            sw = np.sqrt(w)
            L = np.linalg.cholesky(np.eye(n) + sw[:, :, None] * K * sw[:, None, :])
            W = np.matmul(np.linalg.inv(L).astype(self.dtype), (sw[:, :, None] * A).astype(self.dtype))
            self.theta += np.einsum("knm,kn->km", A, a.astype(self.dtype))
        st.downdate(W)

    def _update_information(self, st: StackedInformation, poses: F64, samples: BeamSamples, labels: F64) -> None:
        if self.update_kind == "kalman":
            # eq. 15-19 in information form: Y += H H^T / s2, eta += H z / s2 (then theta = Y^-1 eta)
            s2 = self.row_noise(labels)
            c = self._cached(poses, samples)
            phi = c[0] if c is not None else hm.features(self.basis, to_world(poses, samples.points), dtype=self.dtype)
            st.add(phi, np.broadcast_to(1.0 / s2, phi.shape[:2]), np.broadcast_to(labels / s2, phi.shape[:2]))
            return
        # Appendix: mode on the latent values with K = X X^T (X = L^-1 H) and prior mean m = H^T theta;
        # theta' = theta + cov H a and Y' = Y + H W H^T give eta' = eta + H (a + W m + W K a)
        phi, phi_t = (self._cached(poses, samples) or self._products(poses, samples))[:2]
        K = np.matmul(phi_t, np.swapaxes(phi_t, -1, -2)).astype(np.float64)
        m = np.einsum("knm,km->kn", phi, self.theta).astype(np.float64)
        f, w = hm.laplace_mode(K, m, labels, self.laplace_iterations)
        a = (labels + 1.0) / 2.0 - hm.sigmoid(f)
        coef = a + w * (m + np.einsum("kij,kj->ki", K, a))
        st.add(phi, w.astype(self.dtype), coef.astype(self.dtype))

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        """Survivors after resampling (in place; duplicates never share memory)."""
        self.theta = self.theta[indices]
        if self.stack is not None:
            self.stack.select(indices)
        else:
            assert self.cstack is not None
            self.cstack.select(indices)
        self._cache = None


# -- the filter ------------------------------------------------------------------------------------------


def weighted_mean_pose(poses: F64, w: F64) -> F64:
    """The weighted mean of particle poses ``(N, 3)``: x, y arithmetic, yaw circular (``atan2`` of the weighted
    sines and cosines). The minimum-mean-square estimate of the pose under the particle approximation of
    p(x_k | z_1:k, u_1:k) (eq. 20), where Algorithm 1 line 9 takes the largest-weight particle instead."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    w = np.asarray(w, dtype=np.float64).reshape(-1)
    xy = w @ p[:, :2]
    yaw = np.arctan2(w @ np.sin(p[:, 2]), w @ np.cos(p[:, 2]))
    return np.array([xy[0], xy[1], yaw])


def restore_mean(resampled: F64, target: F64) -> tuple[F64, F64]:
    """Shift the resampled (equally weighted) poses so that their mean (:func:`weighted_mean_pose`) is
    ``target``, the weighted mean before resampling; returns the shifted poses and the shift (dx, dy, dyaw).

    Resampling adds no information: it only replaces weights by copies. Its Monte Carlo error moves the
    cloud's mean by about the cloud's spread over sqrt(N) each time, and where the weights are nearly flat
    these moves add up to a random walk away from the odometry (genetic drift). Restoring the first moment
    removes that walk and leaves the spread's resampling as it was. The yaw shift is exact on the circular
    mean (every unit vector turns by the same angle); positions move by the same vector."""
    p = np.asarray(resampled, dtype=np.float64).reshape(-1, 3)
    now = weighted_mean_pose(p, np.full(len(p), 1.0 / len(p)))
    d = np.asarray(target, dtype=np.float64) - now
    d[2] = wrap_angle(d[2])
    return p + d, d


@dataclass
class StepResult:
    best: int
    pose: F64
    n_eff: float
    resampled: bool


@dataclass
class FilterHistory:
    """Everything recorded per scan."""

    best_pose: list[F64] = field(default_factory=list)
    best_index: list[int] = field(default_factory=list)
    n_eff: list[float] = field(default_factory=list)
    resampled: list[bool] = field(default_factory=list)
    particles: list[F64] = field(default_factory=list)
    parents: list[npt.NDArray[np.int64]] = field(default_factory=list)
    #: weighted mean of the particles' yaw-rate bias per scan (nan without the bias state)
    yaw_bias: list[float] = field(default_factory=list)
    #: the weight on the wide mode's particles per scan (:class:`WideMode`; nan without it)
    wide_share: list[float] = field(default_factory=list)
    #: the weighted mean pose per scan (:func:`weighted_mean_pose`, before resampling)
    mean_pose: list[F64] = field(default_factory=list)
    #: at each resampling, the mean of the resampled poses minus the weighted mean before it (dx, dy, dyaw):
    #: resampling's own Monte Carlo error of the first moment (removed with ``keep_mean``)
    resample_shift: list[F64] = field(default_factory=list)
    #: the normalised weights of the last scan, before its resampling (the smoother's weights)
    final_weights: F64 = field(default_factory=lambda: np.zeros(0))

    def best_trajectory(self) -> F64:
        """Algorithm 1 line 9: the largest-weight particle's pose at every step."""
        return np.asarray(self.best_pose).reshape(-1, 3)

    def mean_trajectory(self) -> F64:
        """The posterior-mean pose at every step (:func:`weighted_mean_pose` of the weighted particles)."""
        return np.asarray(self.mean_pose).reshape(-1, 3)

    def smoothed_trajectory(self) -> F64:
        """The particle smoother's mean (Kitagawa's genealogy smoother): at every scan, the weighted mean
        (:func:`weighted_mean_pose`) of the final particles' ancestors, with the final weights: an estimate
        of E[x_k | z_1:T], which uses the scans after k (a loop closed later moves the poses before it), where
        :meth:`mean_trajectory` is E[x_k | z_1:k]."""
        T = len(self.particles)
        out = np.zeros((T, 3))
        if T == 0:
            return out
        w = np.asarray(self.final_weights, dtype=np.float64)
        a = np.arange(len(w))
        for i in range(T - 1, -1, -1):
            out[i] = weighted_mean_pose(self.particles[i][a], w)
            a = np.asarray(self.parents[i])[a]
        return out

    def final_best_history(self) -> F64:
        """The trajectory history ``x_k*[1:T]`` of the final best particle (ancestry traced back)."""
        T = len(self.particles)
        out = np.zeros((T, 3))
        if T == 0:
            return out
        k = self.best_index[-1]
        for i in range(T - 1, -1, -1):
            out[i] = self.particles[i][k]
            k = int(self.parents[i][k])
        return out


class RBPF:
    """Algorithm 1: propagate, weight against the prior maps, update maps, select, resample."""

    def __init__(
        self,
        maps: ParticleMaps,
        initial_pose: npt.ArrayLike,
        n_particles: int,
        noise: MotionNoise,
        rng: np.random.Generator,
        resampling: Resampling = "systematic",
        resample_threshold: float = 0.5,
        refinement: PoseRefinement | None = None,
        basis: hm.HilbertBasis | None = None,
        exponent: float = 1.0,
        proposal: Proposal | None = None,
        keep_mean: bool = False,
    ) -> None:
        """``refinement`` (with the maps' ``basis``; Hilbert maps only): the Laplace proposal of
        :mod:`pose_refinement` instead of eq. 21's; ``exponent`` is the scan likelihood's, as in the weights.
        ``proposal``: the motion noise and bias state (default: GMapping's form with ``noise``, no bias).
        ``keep_mean``: resampling keeps the weighted mean pose (:func:`restore_mean`)."""
        if refinement is not None and refinement.enabled and (basis is None or not hasattr(maps, "theta")):
            raise ValueError("pose refinement needs Hilbert-GP particle maps and their basis")
        self.refinement = refinement if refinement is not None and refinement.enabled else None
        self.basis = basis
        self.exponent = exponent
        self.maps = maps
        self.poses: F64 = np.tile(np.asarray(initial_pose, dtype=np.float64).reshape(1, 3), (n_particles, 1))
        self.logw: F64 = np.full(n_particles, -np.log(n_particles))
        self.noise = noise
        self.rng = rng
        self.proposal = proposal if proposal is not None else Proposal(noise, n_particles, rng)
        self.resampler = RESAMPLERS[resampling]
        self.resample_threshold = resample_threshold
        self.keep_mean = keep_mean
        self.history = FilterHistory()
        self._parents = np.arange(n_particles)

    @property
    def n_particles(self) -> int:
        return len(self.poses)

    def weights(self) -> F64:
        return normalize_log_weights(self.logw)

    def step(
        self,
        u: npt.ArrayLike,
        samples: BeamSamples,
        first: bool = False,
        observer: Callable[[RBPF, int], None] | None = None,
    ) -> StepResult:
        """One iteration of Algorithm 1; ``observer(self, best)`` sees the maps before resampling."""
        correction: F64 | float = 0.0
        if not first and self.refinement is not None:
            self.poses, correction = self._refined_proposal(u, samples)
        elif not first:
            self.poses = compose(self.poses, self.proposal.draw(u, self.n_particles))
        # eq. 22 against the prior maps, then eq. 15 (the update does not depend on the weights)
        self.logw = self.logw + weigh_and_update(self.maps, self.poses, samples) + correction
        w = self.weights()
        self.logw = np.log(np.maximum(w, np.finfo(np.float64).tiny))  # keep them normalised
        best = int(np.argmax(w))
        n_eff = effective_sample_size(w)
        pose = self.poses[best].copy()
        self.history.best_pose.append(pose)
        self.history.best_index.append(best)
        self.history.n_eff.append(n_eff)
        self.history.particles.append(self.poses.copy())
        self.history.parents.append(self._parents)
        self.history.yaw_bias.append(self.proposal.bias_mean(w))
        self.history.wide_share.append(self.proposal.wide_share(w))
        self.history.mean_pose.append(weighted_mean_pose(self.poses, w))
        self.history.final_weights = w
        if observer is not None:
            observer(self, best)
        resampled = n_eff < self.resample_threshold * self.n_particles
        self._parents = np.arange(self.n_particles)
        if resampled:
            idx = self.resampler(w, self.rng)
            survivors = self.poses[idx]
            shifted, shift = restore_mean(survivors, self.history.mean_pose[-1])
            self.history.resample_shift.append(-shift)
            self.poses = shifted if self.keep_mean else survivors
            self.maps.select(idx)
            self.proposal.select(idx)
            self.logw = np.full(self.n_particles, -np.log(self.n_particles))
            self._parents = idx  # particle k of the next step continues particle idx[k] of this step
        self.history.resampled.append(resampled)
        return StepResult(best, pose, n_eff, resampled)

    def _refined_proposal(self, u: npt.ArrayLike, samples: BeamSamples) -> tuple[F64, F64]:
        """Poses drawn from the Laplace proposal about each particle's refined pose, and the weight
        correction ``log p(x | x_prev, u) - log q(x)`` (:mod:`pose_refinement`).

        The map means are those the maps hold now: in the information form the mean the last weighting
        solved, one scan behind the map (solving the current one would cost a second factorisation).
        """
        assert self.refinement is not None and self.basis is not None
        d, var = self.proposal.prior(u, self.n_particles)
        x_pred = compose(self.poses, d)
        theta = np.asarray(self.maps.theta)  # type: ignore[attr-defined]  # Hilbert maps (checked in __init__)
        mode, A = refine(self.basis, theta, x_pred, var, samples, self.refinement, self.exponent)
        x, log_q = sample_proposal(mode, A, self.refinement.covariance_scale, self.rng)
        return x, log_gaussian(x, x_pred, var) - log_q

    def run(
        self,
        increments: npt.ArrayLike,
        scans: Sequence[BeamSamples],
        observer: Callable[[int, RBPF, int], None] | None = None,
        on_step: Callable[[], None] | None = None,
    ) -> FilterHistory:
        """Run over all scans; ``increments[i]`` is the odometry increment into scan i (row 0 unused).

        ``observer(i, filter, best)`` runs at every step before resampling; ``on_step()`` after it.
        """
        run_steps(self.step, increments, scans, observer, on_step)
        return self.history


def run_steps(step: Callable[..., Any], increments: npt.ArrayLike, scans: Sequence[BeamSamples],
              observer: Callable[[int, Any, int], None] | None, on_step: Callable[[], None] | None) -> None:
    """The scan loop of :meth:`RBPF.run` (and the torch filter's): ``step(u[i], scan, first, observer)``
    per scan, ``observer(i, filter, best)`` before resampling, ``on_step()`` after it."""
    u = np.asarray(increments, dtype=np.float64).reshape(-1, 3)
    for i, samples in enumerate(scans):
        obs = None if observer is None else (lambda f, best, i=i: observer(i, f, best))
        step(u[i], samples, first=(i == 0), observer=obs)
        if on_step is not None:
            on_step()
