"""Continuous waypoint refinement under RICH-SLAM eq. 34 (SLSQP with analytic gradients).

The K+1 waypoints ``p_0 .. p_K`` (ends fixed) minimise ``alpha sum ||p_{k+1} - p_k|| + beta sum c_s(p_k)``
subject to the step bound ``||p_{k+1} - p_k|| <= d_max``, the occupancy bound ``o(p_k) <= o_max``
(eq. 28) and the domain bound ``p_k in Omega`` (box bounds). ``scipy.optimize.minimize(method="SLSQP")``
gets the objective and constraint Jacobians in closed form (``field.MapField``). The result is kept
only when it satisfies every constraint and does not cost more than the initial guess; otherwise the
initial guess is returned.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize

from core.map_field import MapField, Strategy, strategy_cost

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class PlanProblem:
    """Eq. 34 for one strategy."""

    field: MapField
    strategy: Strategy
    alpha: float
    beta: float
    eps: float
    d_max: float
    o_max: float
    lo: F64  # the domain box Omega
    hi: F64

    def cost(self, path: F64) -> float:
        """The objective of eq. 34 for a full path (K+1, 2)."""
        seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
        c, _ = strategy_cost(self.field.values(path, gradients=False), self.strategy, self.eps)
        return float(self.alpha * seg.sum() + self.beta * c.sum())

    def violations(self, path: F64) -> dict[str, float]:
        """Largest violation of each constraint (<= 0 means satisfied)."""
        seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
        o = self.field.values(path, gradients=False).o
        inner = path[1:-1]
        dom = np.max(np.r_[self.lo - inner.min(0, initial=np.inf), inner.max(0, initial=-np.inf) - self.hi]) \
            if len(inner) else -np.inf
        return {"step": float(seg.max() - self.d_max) if len(seg) else -np.inf,
                "occupancy": float(o.max() - self.o_max),
                "domain": float(dom)}

    def feasible(self, path: F64, tol_step: float = 1e-3, tol_occupancy: float = 1e-4) -> bool:
        """All constraints hold, the step bound to ``tol_step`` metres and the occupancy to ``tol_occupancy``."""
        v = self.violations(path)
        return v["step"] <= tol_step and v["occupancy"] <= tol_occupancy and v["domain"] <= 1e-9


@dataclass(frozen=True)
class RefineResult:
    path: F64
    initial_cost: float
    cost: float
    accepted: bool
    message: str
    iterations: int


def refine(problem: PlanProblem, initial: F64, max_iter: int = 200, ftol: float = 1e-7) -> RefineResult:
    """Optimise the interior waypoints of ``initial`` (K+1, 2) under eq. 34."""
    init = np.asarray(initial, np.float64).copy()
    K = len(init) - 1
    c0 = problem.cost(init)
    if K < 2:
        return RefineResult(init, c0, c0, False, "nothing to refine (fewer than 3 waypoints)", 0)
    p0, pK = init[0], init[-1]
    n = K - 1
    a, b = problem.alpha, problem.beta

    def full(x: F64) -> F64:
        return np.vstack([p0, x.reshape(n, 2), pK])

    def objective(x: F64) -> tuple[float, F64]:
        P = full(x)
        d = np.diff(P, axis=0)
        L = np.sqrt(np.sum(d * d, axis=1) + 1e-12)
        u = d / L[:, None]
        inner = P[1:-1]
        c, dc = strategy_cost(problem.field.values(inner), problem.strategy, problem.eps)
        g = a * (u[:-1] - u[1:]) + b * dc  # d/dp_k of ||p_k - p_{k-1}|| + ||p_{k+1} - p_k||
        ends = problem.field.values(np.vstack([p0, pK]), gradients=False)
        c_ends, _ = strategy_cost(ends, problem.strategy, problem.eps)
        return float(a * L.sum() + b * (c.sum() + c_ends.sum())), g.ravel()

    def step_con(x: F64) -> F64:
        d = np.diff(full(x), axis=0)
        return problem.d_max**2 - np.sum(d * d, axis=1)

    def step_jac(x: F64) -> F64:
        d = np.diff(full(x), axis=0)  # d_k = p_{k+1} - p_k, k = 0..K-1
        J = np.zeros((K, n, 2))
        k = np.arange(K)
        # d/dp_{k+1} of -||d_k||^2 = -2 d_k (interior index k), d/dp_k = +2 d_k (interior index k-1)
        m = k < n
        J[k[m], k[m]] = -2.0 * d[m]
        m = k >= 1
        J[k[m], k[m] - 1] = 2.0 * d[m]
        return J.reshape(K, 2 * n)

    def occ_con(x: F64) -> F64:
        return problem.o_max - problem.field.values(x.reshape(n, 2), gradients=False).o

    def occ_jac(x: F64) -> F64:
        do = problem.field.values(x.reshape(n, 2)).do
        J = np.zeros((n, n, 2))
        J[np.arange(n), np.arange(n)] = -do
        return J.reshape(n, 2 * n)

    bounds = [(problem.lo[i % 2], problem.hi[i % 2]) for i in range(2 * n)]
    x0 = np.clip(init[1:-1].ravel(), [bd[0] for bd in bounds], [bd[1] for bd in bounds])
    # eq. 34 sums the cost over waypoints, so waypoints may keep sliding towards cheap cells up to the step
    # bound and SLSQP can stop at its iteration limit slightly outside the constraints: keep the best
    # feasible iterate seen, not only the last one
    best: dict[str, Any] = {"path": init, "cost": c0 if problem.feasible(init) else np.inf, "iter": 0}
    it = [0]

    def consider(x: F64) -> None:
        it[0] += 1
        P = full(np.asarray(x))
        if problem.feasible(P):
            c = problem.cost(P)
            if c < best["cost"]:
                best.update(path=P, cost=c, iter=it[0])

    res = minimize(objective, x0, jac=True, method="SLSQP", bounds=bounds,
                   constraints=[{"type": "ineq", "fun": step_con, "jac": step_jac},
                                {"type": "ineq", "fun": occ_con, "jac": occ_jac}],
                   options={"maxiter": max_iter, "ftol": ftol}, callback=consider)
    consider(np.asarray(res.x))
    msg = str(res.message)
    if best["path"] is init:
        why = "no feasible iterate" if not np.isfinite(best["cost"]) else "no cheaper feasible iterate"
        return RefineResult(init, c0, c0, False, f"kept the initial guess: {why} ({msg})", int(res.nit))
    note = "" if res.success else f"; best feasible iterate {best['iter']} of {res.nit}"
    return RefineResult(best["path"], c0, float(best["cost"]), True, msg + note, int(res.nit))


def resample_polyline(points: F64, spacing: float) -> F64:
    """Points evenly spaced along a polyline, ends kept, at most ``spacing`` apart."""
    p = np.asarray(points, np.float64)
    if len(p) < 2:
        return p.copy()
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    total = s[-1]
    k = max(1, int(np.ceil(total / spacing - 1e-9)))
    t = np.linspace(0.0, total, k + 1)
    return np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], axis=1)
