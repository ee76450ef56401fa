"""The RICH-SLAM particle maps as batched torch tensors on one device (CPU or CUDA).

The same model as :class:`stages.slam.rbpf.HilbertParticleMaps` with the Kalman update, in either
map form, but every particle's map lives in one ``(Np, M, M)`` tensor on the device and a scan is a
handful of batched kernels over a block of particles (no per-particle Python loop):

* **information** (eq. 15-19 in information form): ``L = cholesky(Y)``, ``theta = Y^-1 eta``
  (``cholesky_solve``), rows ``L^-1 v`` by ``solve_triangular`` (variances ``||L^-1 phi||^2``,
  eq. 27), then ``Y += H H^T / s2`` by ``baddbmm`` and ``eta += H z / s2``.
* **covariance** (eq. 15-19 with a square-root gain): ``A = V P`` (``bmm``), ``S = A_phi phi^T +
  s2 I = R R^T``, ``W = R^-1 A_phi``, ``theta += W^T R^-1 (z - H^T theta)``, ``P -= W^T W``
  (``baddbmm``).

Weights follow eq. 22-30 exactly as :func:`stages.slam.rbpf.hilbert_log_likelihood` (posterior-aware
occupancy, endpoint tolerance with an exact or Taylor ring variance). Only the scan's body-frame
samples go to the device; log-likelihoods stay there; :meth:`map_of` brings one map back.
Requires torch (the ``learn`` extra); import this module only when the torch backend is selected.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from core import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, stencil_offsets
from stages.slam.rbpf import MapModel

F64 = npt.NDArray[np.floating[Any]]
TORCH_DTYPES = {"float64": torch.float64, "float32": torch.float32}


def to_world_t(poses: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``T(x, Delta p^b)`` of eq. 13: poses ``(Np, 3)``, body points ``(N, 2)`` -> ``(Np, N, 2)``."""
    c, s = torch.cos(poses[:, 2:3]), torch.sin(poses[:, 2:3])
    wx = c * points[:, 0] - s * points[:, 1] + poses[:, 0:1]
    wy = s * points[:, 0] + c * points[:, 1] + poses[:, 1:2]
    return torch.stack([wx, wy], dim=-1)


class TorchBasis:
    """The Hilbert basis (eq. 6-7) on a device: per-axis sine tables and their tensor products."""

    def __init__(self, basis: hm.HilbertBasis, device: torch.device) -> None:
        self.basis = basis
        self.device = device
        f64 = torch.float64
        self.half = torch.as_tensor(basis.half_widths, dtype=f64, device=device)
        self.centre = torch.as_tensor(basis.centre, dtype=f64, device=device)
        m1, m2 = int(basis.indices[:, 0].max()), int(basis.indices[:, 1].max())
        self.w1 = torch.pi * torch.arange(1, m1 + 1, dtype=f64, device=device) / (2.0 * self.half[0])
        self.w2 = torch.pi * torch.arange(1, m2 + 1, dtype=f64, device=device) / (2.0 * self.half[1])
        self.norm = 1.0 / float(np.sqrt(basis.half_widths[0] * basis.half_widths[1]))
        self.tensor = basis.kind == "tensor"
        self.i1 = torch.as_tensor(basis.indices[:, 0] - 1, device=device)
        self.i2 = torch.as_tensor(basis.indices[:, 1] - 1, device=device)

    def tables(self, p: torch.Tensor, derivative: bool = False
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """``a (..., m1)``, ``b (..., m2)`` with ``phi_j = a_{J_j1} b_{J_j2}`` (zero outside the domain),
        and with ``derivative`` ``da/dp_1``, ``db/dp_2`` (as :func:`hilbert_map.axis_tables`)."""
        rel = p - self.centre
        inside = torch.all(rel.abs() < self.half, dim=-1)
        x = rel + self.half
        scale = (inside.to(torch.float64) * self.norm)[..., None]
        t1, t2 = x[..., 0:1] * self.w1, x[..., 1:2] * self.w2
        a, b = torch.sin(t1) * scale, torch.sin(t2)
        if not derivative:
            return a, b, None, None
        return a, b, torch.cos(t1) * (self.w1 * scale), torch.cos(t2) * self.w2

    def combine(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        if self.tensor:
            return (a[..., :, None] * b[..., None, :]).flatten(-2)
        return a[..., self.i1] * b[..., self.i2]

    def features(self, p: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """``Phi(p) (..., M)`` (eq. 6, 9)."""
        a, b, _, _ = self.tables(p)
        return self.combine(a, b).to(dtype)

    def gradient_rows(self, p: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """``d Phi / d p`` as rows ``(..., 2, M)`` (x then y derivative)."""
        a, b, da, db = self.tables(p, derivative=True)
        assert da is not None and db is not None
        return torch.stack([self.combine(da, b), self.combine(a, db)], dim=-2).to(dtype)

    def mean_at(self, theta: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """``Phi(p)^T theta`` for ``theta (Np, M)``, ``p (Np, K, 2)`` (tensor basis: ``a^T Theta b``)."""
        if not self.tensor:
            return torch.einsum("kqm,km->kq", self.features(p, theta.dtype), theta)
        a, b, _, _ = self.tables(p)
        T = theta.reshape(theta.shape[0], a.shape[-1], b.shape[-1])
        return torch.einsum("kqa,kab,kqb->kq", a.to(theta.dtype), T, b.to(theta.dtype))


def _log_sigmoid_pair(mean: torch.Tensor, var: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """``log o`` and ``log (1 - o)`` with ``o`` of eq. 28, in float64 (as :func:`rbpf.log_occupancy_terms`)."""
    x = mean.to(torch.float64)
    if var is not None:
        x = x / torch.sqrt(1.0 + (torch.pi / 8.0) * var.to(torch.float64))
    return torch.nn.functional.logsigmoid(x), torch.nn.functional.logsigmoid(-x)


class TorchHilbertMaps:
    """Every particle's Hilbert-GP weight posterior (eq. 20) as tensors on ``device``.

    ``form = "information"`` stores ``Y = cov^-1`` and ``eta = Y theta`` (positive definite by
    construction), ``"covariance"`` stores ``cov`` (full symmetric). ``weigh_and_update`` scores a scan
    against the maps before the update (eq. 22) and applies the Kalman update (eq. 15-19), a block of
    ``block_size`` particles at a time (``block_bytes`` of scratch) so that large ``Np * M^2`` fit.
    """

    def __init__(
        self,
        basis: hm.HilbertBasis,
        n_particles: int,
        model: MapModel,
        device: str | torch.device = "cpu",
        block_bytes: int | None = None,
    ) -> None:
        """The maps of :class:`rbpf.MapModel` on a device; the Kalman update only (else a ValueError)."""
        if model.update != "kalman":
            raise ValueError("the torch backend implements the Kalman map update; use backend = numpy for laplace")
        self.model = model
        lengthscale, signal_variance, noise_variance = model.lengthscale, model.signal_variance, model.noise_variance
        weighting, dtype, form = model.weighting, model.dtype, model.form
        self.device = torch.device(device)
        self.dtype = TORCH_DTYPES[str(np.dtype(dtype))]
        self.form = form
        self.weighting = weighting
        self.noise_variance = float(noise_variance)
        self.tb = TorchBasis(basis, self.device)
        self.M = basis.M
        M, dt, dev = basis.M, self.dtype, self.device
        idx = torch.arange(M, device=self.device)
        self.theta = torch.zeros((n_particles, M), dtype=dt, device=dev)
        self.info: torch.Tensor | None = None
        self.eta: torch.Tensor | None = None
        self.cov: torch.Tensor | None = None
        if form == "information":
            _, info0, _ = hm.prior_information(basis, lengthscale, signal_variance)
            self.info = torch.zeros((n_particles, M, M), dtype=dt, device=dev)
            self.info[:, idx, idx] = torch.as_tensor(np.diag(info0).copy(), dtype=dt, device=dev)
            self.eta = torch.zeros((n_particles, M), dtype=dt, device=dev)
        elif form == "covariance":
            lam = hm.prior_variances(basis, lengthscale, signal_variance)
            self.cov = torch.zeros((n_particles, M, M), dtype=dt, device=dev)
            self.cov[:, idx, idx] = torch.as_tensor(lam, dtype=dt, device=dev)
        else:
            raise ValueError(f"unknown map form {form!r} (information or covariance)")
        offs = stencil_offsets(weighting.endpoint_tolerance, weighting.ring_points, weighting.rings)[1:]
        self.offsets = torch.as_tensor(offs, dtype=torch.float64, device=self.device)  # (K, 2)
        #: scratch per block of particles (factor, rows and their transform); large on a GPU
        self.block_bytes = block_bytes or (2 * 2**30 if self.device.type == "cuda" else 32 * 2**20)
        #: largest Cholesky failure code of the scans since the last :meth:`check` (0: none)
        self._failed = torch.zeros((), dtype=torch.int64, device=self.device)

    @property
    def n(self) -> int:
        return int(self.theta.shape[0])

    def _tolerance_rows(self, B: int) -> int:
        w = self.weighting
        if not (w.use_variance and w.endpoint_tolerance > 0 and B):
            return 0
        return 2 * B if w.et_variance == "taylor" else B * len(self.offsets)

    def block_size(self, n_rows: int) -> int:
        """Particles per block: a factor or a covariance product (M^2) plus the rows and their transform."""
        per = (self.M * self.M + 3 * n_rows * self.M) * self.theta.element_size()
        return max(1, min(self.n, int(self.block_bytes // max(per, 1))))

    def weigh_and_update(self, poses: torch.Tensor, samples: BeamSamples) -> torch.Tensor:
        """Per-particle ``log Pr(z | x, D_prev)`` (eq. 22-30, float64, on the device), then eq. 15-19."""
        if samples.n == 0:
            return torch.zeros(self.n, dtype=torch.float64, device=self.device)
        pts = torch.as_tensor(samples.points, dtype=torch.float64, device=self.device)
        labels = torch.as_tensor(samples.labels, dtype=self.dtype, device=self.device)
        pos = np.flatnonzero(samples.labels > 0)
        free = torch.as_tensor(np.flatnonzero(samples.labels <= 0), device=self.device)
        ends = torch.as_tensor(pos, device=self.device)
        B = len(pos)
        out = torch.empty(self.n, dtype=torch.float64, device=self.device)
        step = self.block_size(samples.n + self._tolerance_rows(B))
        for lo in range(0, self.n, step):
            hi = min(lo + step, self.n)
            out[lo:hi] = self._block(lo, hi, poses[lo:hi], pts, labels, free, ends)
        return out

    def _block(self, lo: int, hi: int, poses: torch.Tensor, pts: torch.Tensor, labels: torch.Tensor,
               free: torch.Tensor, ends: torch.Tensor) -> torch.Tensor:
        w, tb, dt = self.weighting, self.tb, self.dtype
        N, B = len(pts), len(ends)
        pw = to_world_t(poses, pts)  # (b, N, 2)
        phi = tb.features(pw, dt)
        ends_w = pw[:, ends]
        q = ends_w[:, :, None, :] + self.offsets  # (b, B, K, 2)
        b_, K = len(poses), len(self.offsets)
        et = w.endpoint_tolerance > 0 and B > 0 and K > 0
        extra: torch.Tensor | None = None
        if w.use_variance and et:
            extra = (tb.gradient_rows(ends_w, dt).reshape(b_, 2 * B, -1) if w.et_variance == "taylor"
                     else tb.features(q.reshape(b_, B * K, 2), dt))
        rows = phi if extra is None else torch.cat([phi, extra], dim=1)
        if self.form == "information":
            theta, mean, var_rows = self._information(lo, hi, phi, rows, labels)
        else:
            theta, mean, var_rows = self._covariance(lo, hi, phi, rows, labels)
        # -- weights (eq. 22-30), against the maps before this scan's update
        var = None if var_rows is None else var_rows[0][:, :N]
        log_o, log_free = _log_sigmoid_pair(mean, var)
        total = log_free[:, free].sum(dim=1)
        if not et:
            return total + log_o[:, ends].sum(dim=1)
        mean_q = (torch.einsum("kqm,km->kq", extra, theta) if extra is not None and w.et_variance == "exact"
                  else tb.mean_at(theta, q.reshape(b_, B * K, 2))).reshape(b_, B, K)
        var_q = None
        if var_rows is not None:
            var_q = self._ring_variance(var_rows, ends, N, K)
        log_q, _ = _log_sigmoid_pair(mean_q, var_q)
        best = torch.maximum(log_q.amax(dim=2), log_o[:, ends])
        return total + best.sum(dim=1)

    def _ring_variance(self, var_rows: tuple[torch.Tensor, torch.Tensor, torch.Tensor], ends: torch.Tensor,
                       N: int, K: int) -> torch.Tensor:
        """Latent variance at the ring points (eq. 27): exact, or ``v + 2 g.d + d^T G d`` (Taylor)."""
        diag, T, V = var_rows  # variances of all rows; transformed rows T; rows V (inner = sum T_a V_b)
        b_, B = len(diag), len(ends)
        if self.weighting.et_variance == "exact":
            return diag[:, N:].reshape(b_, B, K)
        offs = self.offsets.to(torch.float64)
        tc = T[:, ends]
        tj = T[:, N:].reshape(b_, B, 2, -1)
        vj = V[:, N:].reshape(b_, B, 2, -1)
        g = torch.einsum("kbm,kbdm->kbd", tc, vj).to(torch.float64)
        G = torch.einsum("kbdm,kbem->kbde", tj, vj).to(torch.float64)
        vc = diag[:, ends]
        var_q = vc[:, :, None] + 2.0 * torch.einsum("kbd,qd->kbq", g, offs) + torch.einsum("qd,kbde,qe->kbq",
                                                                                          offs, G, offs)
        return var_q.clamp_min(0.0)

    def _information(self, lo: int, hi: int, phi: torch.Tensor, rows: torch.Tensor, labels: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None]:
        """Factor, mean, whitened rows (eq. 26-27) and the information update, for particles ``lo:hi``."""
        assert self.info is not None and self.eta is not None
        Y, eta = self.info[lo:hi], self.eta[lo:hi]
        L, err = torch.linalg.cholesky_ex(Y)
        self._failed = torch.maximum(self._failed, err.max())
        theta = torch.cholesky_solve(eta[:, :, None], L)[:, :, 0]
        self.theta[lo:hi] = theta
        mean = torch.einsum("knm,km->kn", phi, theta)
        var_rows = None
        if self.weighting.use_variance:
            X = torch.linalg.solve_triangular(L, rows.transpose(1, 2), upper=False).transpose(1, 2)
            var_rows = ((X * X).sum(dim=-1).to(torch.float64), X, X)
        s2 = self.noise_variance
        Y.baddbmm_(phi.transpose(1, 2), phi, alpha=1.0 / s2)
        eta.add_(torch.einsum("n,knm->km", labels, phi), alpha=1.0 / s2)
        return theta, mean, var_rows

    def _covariance(self, lo: int, hi: int, phi: torch.Tensor, rows: torch.Tensor, labels: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None]:
        """Products ``V P``, mean, variances (eq. 26-27) and the square-root-gain update (eq. 15-19)."""
        assert self.cov is not None
        P, theta = self.cov[lo:hi], self.theta[lo:hi]
        prior_theta = theta.clone()  # the weights read the map before this scan
        N = phi.shape[1]
        A = torch.bmm(rows, P)  # (b, K, M) = V P
        mean = torch.einsum("knm,km->kn", phi, theta)
        var_rows = None
        if self.weighting.use_variance:
            var_rows = ((A * rows).sum(dim=-1).to(torch.float64).clamp_min(0.0), A, rows)
        Ap = A[:, :N]
        S = torch.bmm(Ap, phi.transpose(1, 2)).to(torch.float64)
        S = 0.5 * (S + S.transpose(1, 2))
        S.diagonal(dim1=1, dim2=2).add_(self.noise_variance)
        R, err = torch.linalg.cholesky_ex(S)
        self._failed = torch.maximum(self._failed, err.max())
        R = R.to(self.dtype)
        W = torch.linalg.solve_triangular(R, Ap, upper=False)  # R^-1 A_phi
        v = torch.linalg.solve_triangular(R, (labels - mean)[:, :, None], upper=False)
        theta.add_(torch.bmm(W.transpose(1, 2), v)[:, :, 0])
        P.baddbmm_(W.transpose(1, 2), W, alpha=-1.0)
        return prior_theta, mean, var_rows

    def check(self) -> torch.Tensor:
        """The pending Cholesky failure code (a device scalar; read it with the scan's statistics)."""
        f, self._failed = self._failed, torch.zeros_like(self._failed)
        return f

    def select(self, indices: torch.Tensor) -> None:
        """Survivors after resampling, in place: only the rows whose slot changes are copied (the
        gathered sources are a copy, so duplicates never share memory)."""
        n = self.n
        dest = torch.nonzero(indices != torch.arange(n, device=self.device)).flatten()
        if dest.numel() == 0:
            return
        src = indices[dest]
        for a in (self.theta, self.info, self.eta, self.cov):
            if a is not None:
                a[dest] = a[src]

    def map_of(self, k: int) -> tuple[F64, F64]:
        """Mean and covariance of particle k's map after the last update (float64, on the host)."""
        if self.info is not None and self.eta is not None:
            Y = self.info[k].to(torch.float64)
            L = torch.linalg.cholesky(Y)
            theta = torch.cholesky_solve(self.eta[k].to(torch.float64)[:, None], L)[:, 0]
            cov = torch.cholesky_inverse(L)
        else:
            assert self.cov is not None
            theta, cov = self.theta[k].to(torch.float64), self.cov[k].to(torch.float64)
        cov = 0.5 * (cov + cov.T)
        return theta.cpu().numpy(), cov.cpu().numpy()
