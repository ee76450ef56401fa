"""Stacked information-form map posteriors of all particles, with per-map BLAS-3 kernels.

numpy batches ``matmul`` but has no batched triangular solve, symmetric rank-k update or Cholesky
that run at BLAS-3 speed (``np.linalg.cholesky`` and scipy's batched wrappers loop in Python and
copy). These kernels call the BLAS/LAPACK routines directly on each particle's matrices in place,
in a tight loop, with no copies: the matrices stay C-ordered ``(Np, M, M)`` stacks and each slice is
handed to Fortran as its (F-contiguous) transpose.

Storage convention: ``info[k].T`` (Fortran view) holds ``Y_k = cov_k^-1`` in its lower triangle;
``chol[k].T`` holds the lower Cholesky factor ``L_k`` (``Y_k = L_k L_k^T``), so ``chol[k]`` is the
upper factor ``L_k^T`` in C order with zeros below the diagonal.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.linalg.blas import get_blas_funcs
from scipy.linalg.lapack import get_lapack_funcs

FloatArray = npt.NDArray[np.floating[Any]]


class StackedInformation:
    """Information matrices and Cholesky factors of ``Np`` maps."""

    def __init__(
        self,
        prior_info_diag: npt.ArrayLike,
        n_maps: int,
        dtype: npt.DTypeLike = np.float64,
        arrays: tuple[FloatArray, FloatArray] | None = None,
    ) -> None:
        """Maps at the prior ``Y = diag(prior_info_diag)``, or wrapping existing ``(info, chol)`` arrays."""
        d = np.asarray(prior_info_diag, dtype=np.float64)
        self.dtype = np.dtype(dtype)
        M = d.size
        if arrays is not None:
            self.info, self.chol = arrays
        else:
            self.info = np.zeros((n_maps, M, M), dtype=self.dtype)
            self.chol = np.zeros((n_maps, M, M), dtype=self.dtype)
            idx = np.arange(M)
            self.info[:, idx, idx] = d.astype(self.dtype)
            self.chol[:, idx, idx] = np.sqrt(d).astype(self.dtype)
        self._syrk, self._trsm = get_blas_funcs(("syrk", "trsm"), dtype=self.dtype)
        self._potrf, self._potrs = get_lapack_funcs(("potrf", "potrs"), dtype=self.dtype)

    @property
    def n(self) -> int:
        return int(self.info.shape[0])

    def whiten(self, V: FloatArray) -> FloatArray:
        """Rows ``L_k^-1 v`` for ``V (Np, K, M)``: then ``v^T cov_k v = ||L_k^-1 v||^2``."""
        V = np.asarray(V, dtype=self.dtype)
        out = np.empty(V.shape, dtype=self.dtype)
        if V.shape[1] == 0:
            return out
        trsm = self._trsm
        for k in range(self.n):
            out[k].T[...] = trsm(1.0, self.chol[k].T, V[k].T, side=0, lower=1, trans_a=0)
        return out

    def add_gram(self, phi: FloatArray, weights: FloatArray | float) -> None:
        """``Y_k += Phi_k^T diag(w_k) Phi_k`` (symmetric rank-N update, lower triangle only)."""
        phi = np.asarray(phi, dtype=self.dtype)
        if phi.shape[1] == 0:
            return
        w = np.broadcast_to(np.asarray(weights, dtype=self.dtype), phi.shape[:2])
        scaled = phi * np.sqrt(w)[..., None]
        syrk = self._syrk
        for k in range(self.n):
            syrk(1.0, scaled[k].T, beta=1.0, c=self.info[k].T, trans=0, lower=1, overwrite_c=1)

    def factorize(self) -> None:
        """``L_k = chol(Y_k)`` for every map (copy, then LAPACK potrf in place)."""
        potrf = self._potrf
        for k in range(self.n):
            c = self.chol[k]
            c[...] = self.info[k]
            _, err = potrf(c.T, lower=1, overwrite_a=1, clean=1)
            if err != 0:
                raise np.linalg.LinAlgError(f"information matrix of particle {k} is not positive definite ({err})")

    def solve(self, b: FloatArray) -> FloatArray:
        """``Y_k^-1 b_k`` for ``b (Np, M)``."""
        b = np.asarray(b, dtype=self.dtype)
        out = np.empty_like(b)
        potrs = self._potrs
        for k in range(self.n):
            out[k], _ = potrs(self.chol[k].T, b[k], lower=1)
        return out

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        """Keep maps ``indices`` (fancy indexing copies: duplicates never share memory)."""
        self.info = self.info[indices]
        self.chol = self.chol[indices]

    def lower_factor(self, k: int) -> npt.NDArray[np.float64]:
        """``L_k`` as a C-ordered float64 lower-triangular matrix."""
        return np.ascontiguousarray(self.chol[k].T, dtype=np.float64)

    def information(self, k: int) -> npt.NDArray[np.float64]:
        """The full symmetric ``Y_k`` (float64)."""
        low = np.tril(self.info[k].T.astype(np.float64))
        return low + np.tril(low, -1).T


class StackedCovariance:
    """Covariances of ``Np`` maps, updated by symmetric rank-N downdates in place.

    ``cov[k].T`` (Fortran view) holds ``cov_k`` in its lower triangle: ``transform`` multiplies with
    BLAS ``symm`` and ``downdate`` subtracts ``W^T W`` with ``syrk``, each reading the map once, where
    ``P - W^T W`` with numpy would write a temporary and make three passes over the stack.
    """

    def __init__(self, prior_diag: npt.ArrayLike, n_maps: int, dtype: npt.DTypeLike = np.float64,
                 array: FloatArray | None = None) -> None:
        d = np.asarray(prior_diag, dtype=np.float64)
        self.dtype = np.dtype(dtype)
        M = d.size
        if array is not None:
            self.cov = array
        else:
            self.cov = np.zeros((n_maps, M, M), dtype=self.dtype)
            self.cov[:, np.arange(M), np.arange(M)] = d.astype(self.dtype)
        self._symm, self._syrk = get_blas_funcs(("symm", "syrk"), dtype=self.dtype)

    @property
    def n(self) -> int:
        return int(self.cov.shape[0])

    def transform(self, V: FloatArray) -> FloatArray:
        """Rows ``v^T cov_k`` for ``V (Np, K, M)``."""
        V = np.asarray(V, dtype=self.dtype)
        out = np.empty(V.shape, dtype=self.dtype)
        if V.shape[1] == 0:
            return out
        symm = self._symm
        for k in range(self.n):
            out[k].T[...] = symm(1.0, self.cov[k].T, V[k].T, side=0, lower=1)
        return out

    def downdate(self, W: FloatArray) -> None:
        """``cov_k -= W_k^T W_k`` for ``W (Np, N, M)`` (lower triangle)."""
        W = np.asarray(W, dtype=self.dtype)
        if W.shape[1] == 0:
            return
        syrk = self._syrk
        for k in range(self.n):
            syrk(-1.0, W[k].T, beta=1.0, c=self.cov[k].T, trans=0, lower=1, overwrite_c=1)

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        self.cov = self.cov[indices]

    def full(self, k: int) -> npt.NDArray[np.float64]:
        """The full symmetric ``cov_k`` (float64)."""
        low = np.tril(self.cov[k].T.astype(np.float64))
        return low + np.tril(low, -1).T
