"""Exact GP regression with the squared-exponential kernel (eq. 3): the reference the Hilbert-GP
approximation converges to (Solin and Sarkka 2020). Pure numpy/scipy, O(n^3); for tests and studies.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.linalg import cho_factor, cho_solve

F64 = npt.NDArray[np.float64]


def se_kernel(a: npt.ArrayLike, b: npt.ArrayLike, lengthscale: float, signal_variance: float) -> F64:
    """``sigma_f^2 exp(-|a - b|^2 / (2 l^2))`` between point sets ``(n, 2)`` and ``(m, 2)``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    d2 = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)
    return signal_variance * np.exp(-0.5 * d2 / lengthscale**2)


def gp_posterior(
    train_x: npt.ArrayLike,
    train_y: npt.ArrayLike,
    test_x: npt.ArrayLike,
    lengthscale: float,
    signal_variance: float,
    noise_variance: float,
) -> tuple[F64, F64]:
    """Posterior mean and latent variance of a zero-mean GP at ``test_x`` (Rasmussen and Williams 2.25-26)."""
    K = se_kernel(train_x, train_x, lengthscale, signal_variance)
    K[np.diag_indices_from(K)] += noise_variance
    c = cho_factor(K, lower=True)
    Ks = se_kernel(train_x, test_x, lengthscale, signal_variance)
    mean = Ks.T @ cho_solve(c, np.asarray(train_y, dtype=np.float64))
    var = signal_variance - np.sum(Ks * cho_solve(c, Ks), axis=0)
    return mean, var
