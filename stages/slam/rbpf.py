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

from core import hilbert_map as hm
from core.trajectory_metrics import se2_increments
from stages.slam.beam_sampling import BeamSamples, stencil_offsets, to_world
from stages.slam.particle_linalg import StackedCovariance, StackedInformation
from stages.slam.se2 import compose

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

    std_xy: float = 0.002  # m per scan
    std_yaw: float = 0.0005  # rad per scan
    rel_trans: float = 0.05  # m per metre translated (GMapping's srr)
    rel_rot: float = 0.005  # rad per radian turned (stt)
    rot_per_trans: float = 0.03  # rad per metre translated (str)
    trans_per_rot: float = 0.06  # m per radian turned (srt)

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


def log_occupancy_terms(mean: F64, var: F64 | None) -> tuple[F64, F64]:
    """``log o`` and ``log (1 - o)`` with ``o`` of eq. 28 (mean-only when ``var`` is None)."""
    x = mean if var is None else mean * hm.probit_scale(var)
    return hm.log_sigmoid(x), hm.log_sigmoid(-x)


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
) -> Any:
    """Per-particle ``log Pr(z~[i] | x_k[i], D_k[i-1])`` (eq. 23-30), batched over particles.

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
    log_o, log_free = log_occupancy_terms(mean, var)
    pos = samples.labels > 0
    total = np.sum(log_free[:, ~pos], axis=1)
    if weighting.endpoint_tolerance > 0 and np.any(pos):
        et = _endpoint_tolerant_log_o(basis, theta, metric, poses, samples, weighting, phi, phi_t, mean, var,
                                      jac, jac_t, ring)
        total = total + np.sum(et, axis=1)
    else:
        total = total + np.sum(log_o[:, pos], axis=1)
    return total


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
    log_q, _ = log_occupancy_terms(mean_q, var_q)
    log_c, _ = log_occupancy_terms(mean[:, pos], var_c)
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
        ``(theta, cov)`` (covariance form, lower triangles)."""
        self.model = model
        lengthscale, signal_variance, noise_variance = model.lengthscale, model.signal_variance, model.noise_variance
        weighting, update, dtype, form = model.weighting, model.update, model.dtype, model.form
        laplace_iterations = model.laplace_iterations
        self.basis = basis
        self.noise_variance = noise_variance
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

    def row_noise(self, labels: F64) -> float:
        """sigma_n^2 of the samples (eq. 15's noise)."""
        return float(self.noise_variance)

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
        if self.stack is None or self.update_kind != "kalman":
            ll = self.log_likelihood(poses, samples)
            self.update(poses, samples)
            return ll
        out = np.empty(len(poses))
        step = self.block_size(samples)
        for lo in range(0, len(poses), step):
            p = poses[lo : lo + step]
            phi, phi_t, jac, jac_t, ring, mean = self._products(p, samples, fuse_update=True, first=lo)
            out[lo : lo + step] = hilbert_log_likelihood(
                self.basis, self.theta[lo : lo + step], self.metric, p, samples, self.weighting,
                phi=phi, phi_t=phi_t, jac=jac, jac_t=jac_t, ring=ring, mean=mean)
        self._cache = None
        return out

    def block_size(self, samples: BeamSamples) -> int:
        """Particles per block of :meth:`weigh_and_update`: about ``block_bytes`` of rows (samples and
        tolerance rows, and their whitened copy)."""
        rows = samples.n + self._tolerance_rows(samples)[2]
        per = 2 * rows * self.basis.M * self.dtype.itemsize
        return max(1, int(self.block_bytes // max(per, 1)))

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
    def best_trajectory(self) -> F64:
        """Algorithm 1 line 9: the largest-weight particle's pose at every step."""
        return np.asarray(self.best_pose).reshape(-1, 3)


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
    ) -> None:
        """Particles start at ``initial_pose`` with equal weights; ``noise`` is eq. 21's proposal."""
        self.maps = maps
        self.poses: F64 = np.tile(np.asarray(initial_pose, dtype=np.float64).reshape(1, 3), (n_particles, 1))
        self.logw: F64 = np.full(n_particles, -np.log(n_particles))
        self.noise = noise
        self.rng = rng
        self.resampler = RESAMPLERS[resampling]
        self.resample_threshold = resample_threshold
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
        if not first:
            self.poses = propagate(self.poses, u, self.noise, self.rng)
        # eq. 22 against the prior maps, then eq. 15 (the update does not depend on the weights)
        self.logw = self.logw + weigh_and_update(self.maps, self.poses, samples)
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
        if observer is not None:
            observer(self, best)
        resampled = n_eff < self.resample_threshold * self.n_particles
        self._parents = np.arange(self.n_particles)
        if resampled:
            idx = self.resampler(w, self.rng)
            self.poses = self.poses[idx]
            self.maps.select(idx)
            self.logw = np.full(self.n_particles, -np.log(self.n_particles))
            self._parents = idx  # particle k of the next step continues particle idx[k] of this step
        self.history.resampled.append(resampled)
        return StepResult(best, pose, n_eff, resampled)

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
