"""Hilbert-map baselines (Ramos and Ott 2016): feature maps trained as logistic classifiers by SGD.

Three feature maps with ``D`` components, compared with HILBERT-GP in RICH-SLAM Fig. 6:

- ``rff``: random Fourier features of the squared-exponential kernel (Rahimi and Recht 2007),
  ``sqrt(2/D) cos(W p + b)``, ``W ~ N(0, l^-2 I)``, ``b ~ U[0, 2 pi)``;
- ``sparse``: the compactly supported sparse kernel of Melkumyan and Ramos (2009) evaluated against
  ``D`` inducing points on a regular grid over the domain;
- ``nystrom``: Nystrom features of the SE kernel on ``D`` landmarks drawn from the training samples,
  ``k(p, Z) K_ZZ^{-1/2}``.

The classifier is logistic regression with an L2 penalty trained online, one minibatch per scan in
scan order (the Hilbert-maps ``partial_fit`` scheme), with the learning rate
``eta_t = 1 / (alpha (t0 + t))`` of Bottou's SGD (scikit-learn's ``optimal`` schedule), ``t`` counting
samples. Pure numpy.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
BaselineKind = Literal["rff", "sparse", "nystrom"]


@dataclass(frozen=True)
class FeatureMap:
    """A fixed feature map ``p -> phi(p)`` of ``dim`` components."""

    kind: BaselineKind
    params: dict[str, F64]
    lengthscale: float

    @property
    def dim(self) -> int:
        key = {"rff": "W", "sparse": "centres", "nystrom": "landmarks"}[self.kind]
        return int(self.params[key].shape[0])

    def __call__(self, points: npt.ArrayLike) -> F64:
        p = np.asarray(points, np.float64).reshape(-1, 2)
        if self.kind == "rff":
            W, b = self.params["W"], self.params["b"]
            return np.sqrt(2.0 / len(b)) * np.cos(p @ W.T + b)
        if self.kind == "sparse":
            return sparse_kernel(_dist(p, self.params["centres"]), self.lengthscale)
        k = np.exp(-0.5 * _sqdist(p, self.params["landmarks"]) / self.lengthscale**2)
        return k @ self.params["whiten"]


def _sqdist(a: F64, b: F64) -> F64:
    return np.maximum(np.sum(a * a, 1)[:, None] + np.sum(b * b, 1)[None, :] - 2.0 * a @ b.T, 0.0)


def _dist(a: F64, b: F64) -> F64:
    return np.sqrt(_sqdist(a, b))


def sparse_kernel(r: npt.ArrayLike, support: float) -> F64:
    """Melkumyan-Ramos sparse covariance, zero beyond ``support``.

    ``k(u) = ((2 + cos 2 pi u) / 3)(1 - u) + sin(2 pi u) / (2 pi)`` for ``u = r / support < 1``.
    """
    u = np.asarray(r, np.float64) / support
    k = (2.0 + np.cos(2 * np.pi * u)) / 3.0 * (1.0 - u) + np.sin(2 * np.pi * u) / (2 * np.pi)
    return np.where(u < 1.0, k, 0.0)


def make_rff(dim: int, lengthscale: float, rng: np.random.Generator) -> FeatureMap:
    """Random Fourier features of the SE kernel with length scale ``lengthscale`` [m]."""
    W = rng.normal(0.0, 1.0 / lengthscale, size=(dim, 2))
    b = rng.uniform(0.0, 2 * np.pi, size=dim)
    return FeatureMap("rff", {"W": W, "b": b}, lengthscale)


def grid_points(lo: F64, hi: F64, count: int) -> F64:
    """About ``count`` points on a regular grid over the box [lo, hi], exactly ``count`` returned.

    The per-axis numbers follow the box's aspect ratio; extra points of the rounded-up grid are
    dropped evenly.
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    ext = np.maximum(hi - lo, 1e-9)
    nx = max(1, round(np.sqrt(count * ext[0] / ext[1])))
    ny = max(1, int(np.ceil(count / nx)))
    gx = lo[0] + (np.arange(nx) + 0.5) * ext[0] / nx
    gy = lo[1] + (np.arange(ny) + 0.5) * ext[1] / ny
    g = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    keep = np.round(np.linspace(0, len(g) - 1, count)).astype(np.int64)
    return g[keep]


def make_sparse(dim: int, lo: F64, hi: F64, support_factor: float, min_support: float) -> FeatureMap:
    """Sparse-kernel features on ``dim`` inducing points on a grid over [lo, hi].

    The kernel support is ``max(min_support, support_factor * grid spacing)`` so that the features
    cover the whole domain at every ``dim``.
    """
    centres = grid_points(lo, hi, dim)
    spacing = float(np.sqrt(np.prod(np.maximum(np.asarray(hi) - np.asarray(lo), 1e-9)) / dim))
    return FeatureMap("sparse", {"centres": centres}, max(min_support, support_factor * spacing))


def make_nystrom(dim: int, lengthscale: float, candidates: F64, rng: np.random.Generator,
                 jitter: float = 1e-8) -> FeatureMap:
    """Nystrom features of the SE kernel on ``dim`` landmarks drawn from ``candidates`` (N, 2)."""
    cand = np.asarray(candidates, np.float64)
    idx = rng.choice(len(cand), size=min(dim, len(cand)), replace=False)
    Z = cand[idx]
    K = np.exp(-0.5 * _sqdist(Z, Z) / lengthscale**2)
    w, V = np.linalg.eigh(K)
    w = np.maximum(w, jitter * max(float(w.max()), 1.0))
    whiten = (V / np.sqrt(w)) @ V.T  # K^{-1/2}
    return FeatureMap("nystrom", {"landmarks": Z, "whiten": whiten}, lengthscale)


@dataclass
class LogisticModel:
    """Weights and bias of ``p(occupied | phi) = sigmoid(w . phi + b)``; ``t`` counts samples seen (from 1)."""

    w: F64
    b: float = 0.0
    t: float = 1.0

    def decision(self, phi: F64) -> F64:
        return phi @ self.w + self.b

    def predict_proba(self, phi: F64) -> F64:
        return 1.0 / (1.0 + np.exp(-np.clip(self.decision(phi), -500, 500)))


def optimal_t0(alpha: float) -> float:
    """Bottou's offset so that the first learning rate is ``sqrt(1 / sqrt(alpha))`` (scikit-learn's ``optimal``)."""
    typw = np.sqrt(1.0 / np.sqrt(alpha))
    return float(1.0 / (alpha * typw))


def sgd_logistic(
    batches: Iterable[tuple[F64, F64]], dim: int, alpha: float, epochs: int = 1,
    model: LogisticModel | None = None,
) -> LogisticModel:
    """Plain per-sample SGD on the L2-penalised log loss, batches in order, samples in order.

    ``batches`` yields ``(phi (n, D), labels (n,) in {-1, +1})``. For each sample: ``eta = 1 / (alpha
    (t0 + t - 1))``, ``w *= max(0, 1 - eta alpha)``, ``w -= eta dloss phi``, ``b -= eta dloss`` with
    ``dloss = -y / (1 + exp(y z))`` evaluated before the update: the update of scikit-learn's
    ``SGDClassifier(loss="log_loss", penalty="l2", learning_rate="optimal", shuffle=False)``.
    """
    m = model or LogisticModel(np.zeros(dim))
    t0 = optimal_t0(alpha)
    batch_list = list(batches)
    w = m.w.copy()
    b, t = m.b, m.t
    for _ in range(epochs):
        for phi, y in batch_list:
            rows = np.ascontiguousarray(phi, dtype=np.float64)
            labels = np.asarray(y, np.float64).tolist()
            for i, yi in enumerate(labels):
                x = rows[i]
                eta = 1.0 / (alpha * (t0 + t - 1.0))
                z = float(x @ w) + b
                yz = yi * z
                dloss = -yi / (1.0 + np.exp(yz)) if yz < 500.0 else -yi * float(np.exp(-yz))
                w *= max(0.0, 1.0 - eta * alpha)
                w -= (eta * dloss) * x
                b -= eta * dloss
                t += 1.0
    return LogisticModel(w, b, t)
