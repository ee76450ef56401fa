"""Stacked information-form map posteriors of all particles, with per-map BLAS-3 kernels.

numpy batches ``matmul`` but has no batched triangular solve, symmetric rank-k update or Cholesky
that run at BLAS-3 speed (``np.linalg.cholesky`` and scipy's batched wrappers loop in Python and
copy). These kernels call the BLAS/LAPACK routines directly on each particle's matrices in place,
in a tight loop, with no copies: the matrices stay C-ordered ``(Np, M, M)`` stacks and each slice is
handed to Fortran as its (F-contiguous) transpose.

Storage convention: ``info[k].T`` (Fortran view) holds ``Y_k = cov_k^-1`` in its lower triangle and
``eta[k] = Y_k theta_k``; the Cholesky factor ``L_k`` (``Y_k = L_k L_k^T``) is recomputed per scan.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.linalg.blas import get_blas_funcs
from scipy.linalg.lapack import get_lapack_funcs

FloatArray = npt.NDArray[np.floating[Any]]


def select_rows(a: npt.NDArray[Any], indices: npt.ArrayLike) -> None:
    """``a[:] = a[indices]`` in place, copying only the rows that change (resampling keeps most of
    the survivors where they are) and holding only overwritten sources in a temporary, instead of a
    full copy of the stack. Duplicates never share memory: each row is its own copy."""
    idx = np.asarray(indices, dtype=np.int64)
    if idx.shape != (len(a),):
        raise ValueError(f"need {len(a)} indices, got shape {idx.shape}")
    dest = np.flatnonzero(idx != np.arange(len(idx)))
    if dest.size == 0:
        return
    src = idx[dest]
    clobbered = np.isin(src, dest)
    saved_ids = np.unique(src[clobbered])
    saved = a[saved_ids]
    slot = np.searchsorted(saved_ids, src)
    for d, s, c, j in zip(dest.tolist(), src.tolist(), clobbered.tolist(), slot.tolist(), strict=True):
        a[d] = saved[j] if c else a[s]


class StackedInformation:
    """Information matrices ``Y_k = cov_k^-1`` and vectors ``eta_k = Y_k theta_k`` of ``Np`` maps.

    No factor is stored. :meth:`scan` factors each ``Y_k`` into one scratch matrix and, while that
    matrix and ``Y_k`` are still in cache, solves the mean, whitens the scan's rows and applies the
    rank-N update (eq. 15-19 in information form: ``Y += H H^T / s2``, ``eta += H z / s2``): one pass
    over the stack per scan instead of one per kernel, and half the memory of storing the factors.
    """

    def __init__(
        self,
        prior_info_diag: npt.ArrayLike,
        n_maps: int,
        dtype: npt.DTypeLike = np.float64,
        arrays: tuple[FloatArray, FloatArray] | None = None,
    ) -> None:
        """Maps at the prior ``Y = diag(prior_info_diag)``, ``eta = 0``, or wrapping ``(info, eta)``."""
        d = np.asarray(prior_info_diag, dtype=np.float64)
        self.dtype = np.dtype(dtype)
        M = d.size
        if arrays is not None:
            self.info, self.eta = arrays
        else:
            self.info = np.zeros((n_maps, M, M), dtype=self.dtype)
            self.info[:, np.arange(M), np.arange(M)] = d.astype(self.dtype)
            self.eta = np.zeros((n_maps, M), dtype=self.dtype)
        self._syrk, self._trsm, self._trsv = get_blas_funcs(("syrk", "trsm", "trsv"), dtype=self.dtype)
        self._potrf, = get_lapack_funcs(("potrf",), dtype=self.dtype)

    @property
    def n(self) -> int:
        return int(self.info.shape[0])

    def _solve(self, L: FloatArray, b: FloatArray) -> FloatArray:
        """``Y^-1 b = L^-T L^-1 b`` (two BLAS trsv; LAPACK potrs costs twice as much at this size)."""
        u = self._trsv(L, b, lower=1)
        return self._trsv(L, u, lower=1, trans=1, overwrite_x=1)

    def _factor(self, k: int, out: FloatArray) -> FloatArray:
        """``L_k`` (lower, Fortran order; the strict upper triangle of ``out`` is left as it was)."""
        out[...] = self.info[k].T
        _, err = self._potrf(out, lower=1, overwrite_a=1, clean=0)
        if err != 0:
            raise np.linalg.LinAlgError(f"information matrix of particle {k} is not positive definite ({err})")
        return out

    def scan(
        self,
        rows: FloatArray,
        gram: FloatArray | None = None,
        gram_scale: float = 1.0,
        eta_coef: FloatArray | None = None,
        out: FloatArray | None = None,
        first: int = 0,
        mean_rows: int = 0,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per map, before any update: ``theta_k = Y_k^-1 eta_k``, the means ``v^T theta_k`` of the first
        ``mean_rows`` rows and rows ``L_k^-1 v`` of ``rows (Np, K, M)`` (then ``v^T cov_k v =
        ||L_k^-1 v||^2``); if ``gram (Np, N, M)`` is given, also ``Y_k += gram_scale gram_k^T gram_k`` and
        ``eta_k += gram_k^T eta_coef_k`` (the update reads ``gram`` before the rows are whitened, so
        ``gram`` may be a view of ``rows``). Returns ``(theta, whitened rows, means)``.

        ``out`` (C-contiguous, shape of ``rows``) receives the whitened rows; ``out is rows`` whitens in
        place. ``rows`` and ``gram`` need only be C-contiguous per map (views into a larger buffer are
        fine). The rows belong to maps ``first, first + 1, ...`` (a block of particles at a time keeps
        the scan's rows in cache).
        """
        rows = np.asarray(rows, dtype=self.dtype)
        Np, M = len(rows), self.info.shape[-1]
        theta = np.empty((Np, M), dtype=self.dtype)
        if out is None:
            out = np.empty(rows.shape, dtype=self.dtype)
        inplace = out is rows
        if out.shape != rows.shape or (out.size and out.strides[1:] != (M * out.itemsize, out.itemsize)):
            # trsm solves out[k] in place: a copy made for Fortran would be written and dropped
            raise ValueError(f"out must have the rows' shape {rows.shape} and C-contiguous maps")
        means = np.empty((Np, mean_rows), dtype=self.dtype)
        if gram is not None:
            gram = np.asarray(gram, dtype=self.dtype)
            assert eta_coef is not None
            coef = np.asarray(eta_coef, dtype=self.dtype)
        L = np.zeros((M, M), dtype=self.dtype, order="F")
        trsm, syrk = self._trsm, self._syrk
        for k in range(Np):
            j = first + k
            self._factor(j, L)
            theta[k] = self._solve(L, self.eta[j])
            if mean_rows:
                means[k] = rows[k, :mean_rows] @ theta[k]
            if gram is not None and gram.shape[1]:
                syrk(gram_scale, gram[k].T, beta=1.0, c=self.info[j].T, trans=0, lower=1, overwrite_c=1)
                self.eta[j] += coef[k] @ gram[k]
            if out.shape[1]:
                if not inplace:
                    out[k] = rows[k]  # copied while in cache, then solved in place
                trsm(1.0, L, out[k].T, side=0, lower=1, overwrite_b=1)
        return theta, out, means

    def whiten(self, V: FloatArray) -> FloatArray:
        """Rows ``L_k^-1 v`` for ``V (Np, K, M)`` (no update)."""
        return self.scan(V)[1]

    def add(self, phi: FloatArray, weights: FloatArray | float, eta_coef: FloatArray) -> None:
        """``Y_k += Phi_k^T diag(w_k) Phi_k`` (symmetric rank-N update, lower triangle) and
        ``eta_k += Phi_k^T eta_coef_k``."""
        phi = np.asarray(phi, dtype=self.dtype)
        if phi.shape[1] == 0:
            return
        w = np.broadcast_to(np.asarray(weights, dtype=self.dtype), phi.shape[:2])
        scaled = phi * np.sqrt(w)[..., None]
        self.eta += np.einsum("kn,knm->km", np.asarray(eta_coef, dtype=self.dtype), phi)
        syrk = self._syrk
        for k in range(self.n):
            syrk(1.0, scaled[k].T, beta=1.0, c=self.info[k].T, trans=0, lower=1, overwrite_c=1)

    def select(self, indices: npt.NDArray[np.int64]) -> None:
        """Keep maps ``indices`` (in place; duplicates never share memory)."""
        select_rows(self.info, indices)
        select_rows(self.eta, indices)

    def posterior(self, k: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """``theta_k = Y_k^-1 eta_k`` and ``L_k`` (C-ordered lower triangle), float64, from one factorisation."""
        L = self._factor(k, np.zeros(self.info.shape[1:], dtype=self.dtype, order="F"))
        theta = np.asarray(self._solve(L, self.eta[k]), dtype=np.float64)
        return theta, np.ascontiguousarray(np.tril(L), dtype=np.float64)

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
        select_rows(self.cov, indices)

    def full(self, k: int) -> npt.NDArray[np.float64]:
        """The full symmetric ``cov_k`` (float64)."""
        low = np.tril(self.cov[k].T.astype(np.float64))
        return low + np.tril(low, -1).T
