"""Mapping accuracy (RICH-SLAM Q1/Q2, Fig. 6, 7, 10): occupancy AUC of HILBERT-GP and the Hilbert-map baselines.

Pure functions on numpy arrays. HILBERT-GP uses the map core of the slam stage
(``core/hilbert_map.py``): the basis of eq. 6-7, the prior of eq. 10 and the Kalman update of
eq. 15-19, applied scan by scan to the training samples in time order. The baselines are logistic
Hilbert maps trained by SGD (``baselines.py``); an occupancy-count grid is a reference.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from core import hilbert_map as hm
from stages.evaluate import baselines
from stages.evaluate.occupancy import LabelledSamples, grid_counts_fit, grid_counts_predict, roc_auc
from stages.evaluate.params import BaselineParams

F64 = npt.NDArray[np.float64]
METHODS = ("hilbert_gp", "rff", "sparse", "nystrom", "grid")


@dataclass(frozen=True)
class GPConfig:
    """Domain and hyperparameters of HILBERT-GP, all lengths in metres."""

    half_widths: tuple[float, float]
    centre: tuple[float, float]
    lengthscale_m: float
    signal_variance: float
    noise_variance: float
    basis_kind: hm.BasisKind = "tensor"

    def basis(self, M: int) -> hm.HilbertBasis:
        return hm.make_basis(self.half_widths, self.centre, M, self.basis_kind)


@dataclass
class GPFit:
    """A HILBERT-GP posterior trained on samples, with its per-scan uncertainty summary."""

    basis: hm.HilbertBasis
    theta: hm.FloatArray
    cov: hm.FloatArray
    prior_diag: F64
    #: rows (scan, p25, p50, p75) of the normalised predictive variance over the tracked cells
    uncertainty: F64 = field(default_factory=lambda: np.zeros((0, 4)))

    def query(self, points: npt.ArrayLike) -> tuple[hm.FloatArray, hm.FloatArray, hm.FloatArray]:
        """Latent mean, variance and occupancy (eq. 28, 32-33) at points (N, 2)."""
        return hm.query(self.basis, self.theta, self.cov, points)


def fit_hilbert_gp(
    train: LabelledSamples, cfg: GPConfig, M: int,
    track_points: F64 | None = None, track_every: int = 10,
    on_scan: Callable[[int], None] | None = None,
) -> GPFit:
    """Sequential Kalman updates (eq. 15-19), one per training scan in scan order.

    With ``track_points`` (K, 2), every ``track_every``-th scan (and the last) records the quartiles
    of the normalised predictive variance ``u(p) / u_prior(p)`` (eq. 33) over those points (Fig. 10).
    """
    basis = cfg.basis(M)
    theta, cov = hm.prior(basis, cfg.lengthscale_m, cfg.signal_variance)
    prior_diag = hm.prior_variances(basis, cfg.lengthscale_m, cfg.signal_variance)
    scans, starts = np.unique(train.scan, return_index=True)
    ends = np.r_[starts[1:], len(train)]
    track_phi = track_prior = None
    if track_points is not None and len(track_points):
        track_phi = hm.features(basis, track_points)
        track_prior = np.einsum("km,m,km->k", track_phi, prior_diag, track_phi)
    rows = []
    for i, (scan, a, b) in enumerate(zip(scans, starts, ends, strict=True)):
        phi = hm.features(basis, train.points[a:b])
        theta, cov = hm.kalman_update(theta, cov, phi, train.labels[a:b], cfg.noise_variance)
        if track_phi is not None and (i % track_every == 0 or i == len(scans) - 1):
            u = np.einsum("km,km->k", track_phi @ cov, track_phi) / np.maximum(track_prior, 1e-300)  # type: ignore[arg-type]
            rows.append([float(scan), *np.percentile(u, [25, 50, 75])])
        if on_scan is not None:
            on_scan(1)
    unc = np.asarray(rows, np.float64).reshape(-1, 4)
    return GPFit(basis, theta, cov, prior_diag, unc)


def _per_scan(samples: LabelledSamples) -> list[tuple[int, int]]:
    _, starts = np.unique(samples.scan, return_index=True)
    ends = np.r_[starts[1:], len(samples)]
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def _predict_chunked(fn: Callable[[F64], F64], points: F64, chunk: int = 8192) -> F64:
    if not len(points):
        return np.zeros(0)
    return np.concatenate([fn(points[s : s + chunk]) for s in range(0, len(points), chunk)])


def method_rng(seed: int, method: str, dim: int) -> np.random.Generator:
    """The random stream of one (method, feature count): independent of which other fits ran."""
    return np.random.default_rng([seed, METHODS.index(method), dim])


def fit_baseline(
    kind: baselines.BaselineKind, dim: int, train: LabelledSamples, lo: F64, hi: F64,
    cfg: BaselineParams, rng: np.random.Generator,
) -> tuple[baselines.FeatureMap, baselines.LogisticModel]:
    """Build a ``dim``-component feature map and train its logistic weights scan by scan."""
    if kind == "rff":
        fmap = baselines.make_rff(dim, cfg.lengthscale_m, rng)
    elif kind == "sparse":
        fmap = baselines.make_sparse(dim, lo, hi, cfg.sparse_support_factor, cfg.lengthscale_m)
    else:
        fmap = baselines.make_nystrom(dim, cfg.lengthscale_m, train.points, rng)
    batches = ((fmap(train.points[a:b]), train.labels[a:b]) for a, b in _per_scan(train))
    model = baselines.sgd_logistic(batches, fmap.dim, cfg.alpha, cfg.epochs)
    return fmap, model


@dataclass(frozen=True)
class AucRow:
    """One method at one feature count."""

    method: str
    features: int
    auc: float
    seconds: float


def auc_suite(
    train: LabelledSamples, test: LabelledSamples, gp: GPConfig, base: BaselineParams,
    counts: Sequence[int], methods: Sequence[str], seed: int,
    on_fit: Callable[[str, int], None] | None = None,
) -> list[AucRow]:
    """AUC on the held-out samples for every method at every feature count (Fig. 6).

    HILBERT-GP scores with the posterior-predictive occupancy (eq. 28); the baselines with their
    logistic probability; the grid with ``hits / (hits + frees)``. Each random feature map draws from
    its own stream (``method_rng``), so a result does not depend on the other fits of the call.
    """
    lo = np.asarray(gp.centre) - np.asarray(gp.half_widths)
    hi = np.asarray(gp.centre) + np.asarray(gp.half_widths)
    rows: list[AucRow] = []
    for method in methods:
        if method == "grid":
            t0 = time.perf_counter()
            model = grid_counts_fit(train, base.grid_resolution)
            score = grid_counts_predict(model, test.points, base.grid_resolution)
            rows.append(AucRow("grid", 0, roc_auc(test.labels, score), time.perf_counter() - t0))
            continue
        for dim in counts:
            t0 = time.perf_counter()
            if method == "hilbert_gp":
                fit = fit_hilbert_gp(train, gp, dim)
                score = np.asarray(fit.query(test.points)[2], np.float64)
            elif method in ("rff", "sparse", "nystrom"):
                fmap, lm = fit_baseline(method, dim, train, lo, hi, base,  # type: ignore[arg-type]
                                        method_rng(seed, method, dim))

                def proba(p: F64, fmap: baselines.FeatureMap = fmap, lm: baselines.LogisticModel = lm) -> F64:
                    return lm.predict_proba(fmap(p))

                score = _predict_chunked(proba, test.points)
            else:
                raise ValueError(f"unknown mapping method {method!r}; known: {', '.join(METHODS)}")
            rows.append(AucRow(method, dim, roc_auc(test.labels, score), time.perf_counter() - t0))
            if on_fit is not None:
                on_fit(method, dim)
    return rows


def observed_cells(
    lo: F64, hi: F64, spacing: float, positions: F64, radius: float
) -> F64:
    """Grid cell centres in [lo, hi] within ``radius`` of any of ``positions`` (the mapped area)."""
    from scipy.spatial import cKDTree

    gx = np.arange(lo[0] + spacing / 2, hi[0], spacing)
    gy = np.arange(lo[1] + spacing / 2, hi[1], spacing)
    g = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    if len(positions) == 0 or len(g) == 0:
        return np.zeros((0, 2))
    d, _ = cKDTree(np.asarray(positions, np.float64)).query(g, distance_upper_bound=radius)
    return g[np.isfinite(d)]
