"""The Hilbert map as a planning field: latent occupancy, uncertainty, costs and their gradients.

``z(p) = Phi(p)^T theta`` (eq. 32), ``u(p) = Phi(p)^T cov Phi(p)`` (eq. 33), the occupancy of eq. 28 and
the strategy costs of eq. 35, each with its analytic gradient from ``dPhi/dp`` (the derivative of the
sines of eq. 6, ``stages/slam/hilbert_map.feature_gradients``). Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from core import hilbert_map as hm

F64 = npt.NDArray[np.float64]
Strategy = Literal["greedy", "uncertainty"]


@dataclass(frozen=True)
class FieldValues:
    """Values and gradients at N points: ``z``, ``u``, ``o`` (N,) and ``dz``, ``du``, ``do`` (N, 2)."""

    z: F64
    u: F64
    o: F64
    dz: F64
    du: F64
    do: F64


@dataclass(frozen=True)
class MapField:
    """One Hilbert-GP map posterior (basis, mean, covariance)."""

    basis: hm.HilbertBasis
    theta: F64
    cov: F64
    #: the prior weight variances (eq. 10), for normalising the uncertainty
    prior_diag: F64 | None = None

    @property
    def lo(self) -> F64:
        return self.basis.centre - self.basis.half_widths

    @property
    def hi(self) -> F64:
        return self.basis.centre + self.basis.half_widths

    def values(self, points: npt.ArrayLike, gradients: bool = True) -> FieldValues:
        """Field values (and gradients) at points (N, 2)."""
        p = np.asarray(points, np.float64).reshape(-1, 2)
        phi = hm.features(self.basis, p)
        a = phi @ self.cov
        z = phi @ self.theta
        u = np.maximum(np.einsum("nm,nm->n", a, phi), 0.0)
        scale = np.asarray(hm.probit_scale(u), np.float64)
        o = np.asarray(hm.sigmoid(z * scale), np.float64)
        if not gradients:
            zero = np.zeros((len(p), 2))
            return FieldValues(z, u, o, zero, zero, zero)
        J = hm.feature_gradients(self.basis, p)  # (N, M, 2)
        dz = np.einsum("nmd,m->nd", J, self.theta)
        du = 2.0 * np.einsum("nm,nmd->nd", a, J)
        dscale = (-0.5 * (np.pi / 8.0) * scale**3)[:, None] * du
        do = (o * (1.0 - o))[:, None] * (scale[:, None] * dz + z[:, None] * dscale)
        return FieldValues(z, u, o, dz, du, do)


def strategy_cost(v: FieldValues, strategy: Strategy, eps: float) -> tuple[F64, F64]:
    """``c_s(p)`` of eq. 35 and its gradient: ``z`` (greedy) or ``z / (sqrt(u) + eps)`` (uncertainty-aware)."""
    if strategy == "greedy":
        return v.z, v.dz
    if strategy != "uncertainty":
        raise ValueError(f"unknown strategy {strategy!r} (greedy or uncertainty)")
    s = np.sqrt(v.u)
    den = s + eps
    c = v.z / den
    ds = v.du / (2.0 * np.maximum(s, 1e-12))[:, None]
    dc = v.dz / den[:, None] - (v.z / den**2)[:, None] * ds
    return c, dc


def field_from_posterior(table: Any) -> MapField:
    """The map field of a ``map_posterior.parquet`` table (one row)."""
    row = {c: table[c][0].as_py() for c in table.column_names}
    M = int(row["M"])
    kind: hm.BasisKind = "circular" if row.get("basis_kind") == "circular" else "tensor"
    basis = hm.make_basis((row["L1"], row["L2"]), (row["cx"], row["cy"]), M, kind)
    theta = np.asarray(row["theta"], np.float64)
    cov = np.asarray(row["cov"], np.float64).reshape(M, M)
    lengthscale_m = float(row["lengthscale"]) * float(row.get("length_unit_m") or 1.0)
    prior_diag = hm.prior_variances(basis, lengthscale_m, float(row["signal_variance"]))
    return MapField(basis, theta, cov, prior_diag)


def grid_axes(lo: F64, hi: F64, spacing: float) -> tuple[F64, F64]:
    """Cell-centre coordinates of a grid covering [lo, hi]."""
    return (np.arange(lo[0] + spacing / 2, hi[0], spacing), np.arange(lo[1] + spacing / 2, hi[1], spacing))
