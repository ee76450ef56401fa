"""`plan` stage: A* plus continuous refinement on the Hilbert map (RICH-SLAM Sec. V-D).

For each strategy (greedy ``c = z``, uncertainty-aware ``c = z / (sqrt(u) + eps)``, eq. 35): A* on the
occupancy grid queried from the slam posterior (obstacles where ``o > o_max``; cell costs are the
strategy cost shifted to be nonnegative, so A* solves a discretised eq. 34), resampled to waypoints,
then refined under eq. 34 by SLSQP (``refine.py``). Writes ``paths.parquet`` (strategy, k, x, y: the
refined paths ``greedy`` / ``uncertainty`` and the A* guesses ``astar_<strategy>``), ``plan.png``
(Fig. 12) and Rerun line strips under ``world/plan/<strategy>``.
"""

from __future__ import annotations

import time
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from pydantic import Field, model_validator

from core.errors import UserError
from core.map_field import MapField, field_from_posterior, grid_axes, strategy_cost
from core.stage import ParamGroup, Stage, StageContext, StageParams, blas_threads
from schemas import read_artifact, write_artifact
from stages.plan.astar import astar
from stages.plan.refine import PlanProblem, refine, resample_polyline

F64 = npt.NDArray[np.float64]
STRATEGIES = ("greedy", "uncertainty")


class AStarParams(ParamGroup):
    """The A* search on a grid of the map's occupancy that gives the initial path."""

    grid_spacing: float = Field(0.25, ge=0.01, description="spacing of the occupancy grid queried for A* (m)")
    waypoint_spacing: float = Field(0.5, gt=0, description="spacing of the waypoints resampled from the A* path "
                                    "(m); must not exceed objective.d_max")


class ObjectiveParams(ParamGroup):
    """The continuous refinement's cost and constraints (eqs. 34-35)."""

    o_max: float = Field(0.6, gt=0, lt=1, description="occupancy bound o_max of eq. 34 (eq. 28 occupancy); "
                         "grid cells above it are A* obstacles")
    d_max: float = Field(1.0, gt=0, description="step bound d_max of eq. 34 (m)")
    alpha: float = Field(1.0, ge=0, description="weight of the path length in eq. 34")
    beta: float = Field(1.0, ge=0, description="weight of the map cost in eq. 34")
    eps: float = Field(1e-3, gt=0, description="epsilon of the uncertainty-aware cost (eq. 35)")
    domain_margin: float = Field(0.5, ge=0, description="distance kept from the Hilbert domain's edge (m): the "
                                 "domain bound Omega of eq. 34")


class SolverParams(ParamGroup):
    """SLSQP."""

    max_iter: int = Field(300, ge=1, le=1_000_000, description="SLSQP iteration limit")
    blas_threads: int = Field(1, ge=0, le=256,
                              description="BLAS threads while planning (0: leave the library's default); "
                              "the matrices are small, and a multi-threaded BLAS on a busy machine spins")


class PlanParams(StageParams):
    """Parameters of the `plan` stage."""

    start: list[float] | None = Field(None, description="start [x, y] in the map frame (m); default: the first "
                                      "slam trajectory pose")
    goal: list[float] | None = Field(None, description="goal [x, y] in the map frame (m); default: the trajectory "
                                     "pose farthest from the start")
    strategies: list[Literal["greedy", "uncertainty"]] = Field(
        ["greedy", "uncertainty"], description="cost strategies of eq. 35 to plan with")
    astar: AStarParams = Field(default_factory=AStarParams, description="the initial path")
    objective: ObjectiveParams = Field(default_factory=ObjectiveParams, description="eqs. 34-35")
    solver: SolverParams = Field(default_factory=SolverParams, description="the refinement's solver")

    @model_validator(mode="after")
    def _check(self) -> PlanParams:
        for name in ("start", "goal"):
            v = getattr(self, name)
            if v is not None and len(v) != 2:
                raise ValueError(f"{name} must be [x, y]")
        if self.astar.waypoint_spacing > self.objective.d_max:
            raise ValueError(f"astar.waypoint_spacing {self.astar.waypoint_spacing} exceeds objective.d_max "
                             f"{self.objective.d_max}")
        return self


def nearest_free(blocked: npt.NDArray[np.bool_], cell: tuple[int, int]) -> tuple[int, int] | None:
    """The free cell closest to ``cell`` (Euclidean in cells), or None when all are blocked."""
    free = np.argwhere(~blocked)
    if len(free) == 0:
        return None
    i = int(np.argmin(np.sum((free - np.asarray(cell)) ** 2, axis=1)))
    return int(free[i, 0]), int(free[i, 1])


def default_endpoints(xy: F64) -> tuple[F64, F64]:
    """The first trajectory position and the one farthest from it."""
    if len(xy) == 0:
        raise ValueError("empty trajectory")
    start = xy[0]
    return start, xy[int(np.argmax(np.linalg.norm(xy - start, axis=1)))]


class PlanStage(Stage):
    name = "plan"
    description = "A* plus continuous refinement on the Hilbert map (RICH-SLAM Sec. V-D)"
    inputs = ("slam",)
    Params = PlanParams
    version = "1"
    outputs = ("paths.parquet",)

    def run(self, ctx: StageContext) -> None:
        with blas_threads(ctx.params.solver.blas_threads):
            self._run(ctx)

    def _run(self, ctx: StageContext) -> None:
        p: PlanParams = ctx.params
        obj = p.objective
        field = field_from_posterior(read_artifact(ctx.input("slam", "map_posterior.parquet"), "map_posterior"))
        lo = field.lo + p.objective.domain_margin
        hi = field.hi - p.objective.domain_margin
        if np.any(hi - lo <= 2 * p.astar.grid_spacing):
            raise UserError(f"plan.objective.domain_margin={obj.domain_margin}: leaves no room inside the Hilbert "
                            f"domain "
                            f"{field.lo.round(2).tolist()}..{field.hi.round(2).tolist()}")
        t0 = time.perf_counter()
        gx, gy = grid_axes(lo, hi, p.astar.grid_spacing)
        pts = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
        vals = field.values(pts, gradients=False)
        shape = (len(gx), len(gy))
        occ = vals.o.reshape(shape)
        blocked = occ > p.objective.o_max
        ctx.stats["grid"] = {"cells": int(blocked.size), "blocked": int(blocked.sum()), "spacing": p.astar.grid_spacing}

        start, goal = self._endpoints(ctx, p)
        cells = {}
        for name, xy in (("start", start), ("goal", goal)):
            if np.any(xy < lo) or np.any(xy > hi):
                raise UserError(f"plan.{name}={np.round(xy, 3).tolist()}: outside the planning domain "
                                f"{np.round(lo, 2).tolist()}..{np.round(hi, 2).tolist()}; pick a point inside")
            c = (int(np.argmin(np.abs(gx - xy[0]))), int(np.argmin(np.abs(gy - xy[1]))))
            if blocked[c]:
                free = nearest_free(blocked, c)
                if free is None:
                    raise UserError(f"plan.objective.o_max={obj.o_max}: every grid cell is an obstacle; raise it")
                ctx.warn(f"{name} {np.round(xy, 2).tolist()} lies in an obstacle cell (occupancy "
                         f"{occ[c]:.2f} > o_max {p.objective.o_max}); moved to the nearest free cell")
                c = free
                xy = np.array([gx[c[0]], gy[c[1]]])
            cells[name] = (c, np.asarray(xy, np.float64))
        ctx.stats["start"], ctx.stats["goal"] = cells["start"][1].tolist(), cells["goal"][1].tolist()

        rows: dict[str, list[Any]] = {"strategy": [], "k": [], "x": [], "y": [], "z_hat": [], "u": [], "occupancy": []}
        paths: dict[str, F64] = {}
        for strategy in p.strategies:
            cs, _ = strategy_cost(vals, strategy, p.objective.eps)
            cgrid = cs.reshape(shape)
            # eq. 34 per unit length: alpha + beta c / waypoint_spacing; shift so that every cell is >= 0
            shifted = cgrid - cgrid[~blocked].min()
            cell_cost = shifted * (obj.beta / obj.alpha / p.astar.waypoint_spacing) if obj.alpha > 0 else shifted
            ts = time.perf_counter()
            cell_path, _ = astar(blocked, cells["start"][0], cells["goal"][0], cell_cost)
            if not cell_path:
                raise UserError(f"plan: no collision-free path from {cells['start'][1].round(2).tolist()} to "
                                f"{cells['goal'][1].round(2).tolist()} with o_max={obj.o_max}; raise "
                                "plan.objective.o_max or choose other plan.start / plan.goal")
            idx = np.asarray(cell_path)
            poly = np.stack([gx[idx[:, 0]], gy[idx[:, 1]]], 1)
            poly[0], poly[-1] = cells["start"][1], cells["goal"][1]
            init = resample_polyline(poly, p.astar.waypoint_spacing)
            t_astar = time.perf_counter() - ts
            prob = PlanProblem(field, strategy, obj.alpha, obj.beta, obj.eps, obj.d_max, obj.o_max, lo, hi)
            res = refine(prob, init, max_iter=p.solver.max_iter)
            paths[f"astar_{strategy}"] = init
            paths[strategy] = res.path
            ctx.stats[strategy] = {
                "waypoints": len(res.path), "astar_seconds": round(t_astar, 3),
                "refine_iterations": res.iterations, "refined": res.accepted, "message": res.message,
                "initial_cost": res.initial_cost, "cost": res.cost,
                "length_m": float(np.linalg.norm(np.diff(res.path, axis=0), axis=1).sum()),
                "astar_length_m": float(np.linalg.norm(np.diff(init, axis=0), axis=1).sum()),
                "violations": prob.violations(res.path),
            }
            if not res.accepted:
                ctx.warn(f"{strategy}: {res.message}")
        for name, path in paths.items():
            v = field.values(path, gradients=False)
            rows["strategy"] += [name] * len(path)
            rows["k"] += list(range(len(path)))
            rows["x"] += path[:, 0].tolist()
            rows["y"] += path[:, 1].tolist()
            rows["z_hat"] += v.z.tolist()
            rows["u"] += v.u.tolist()
            rows["occupancy"] += v.o.tolist()
        write_artifact({k: np.asarray(v) for k, v in rows.items()}, ctx.output("paths.parquet"), "paths")
        ctx.stats["seconds"] = round(time.perf_counter() - t0, 3)

        from stages.plan.figures import plot_plan

        u_prior = _prior_variance(field, pts)
        norm_u = (vals.u / np.maximum(u_prior, 1e-300)).reshape(shape)
        plot_plan(ctx.output("plan.png"), gx, gy, occ, norm_u, paths, cells["start"][1], cells["goal"][1],
                  title=f"{ctx.seq.name}: planning on the Hilbert map (o_max {p.objective.o_max})")
        self._log(ctx, paths)

    def _endpoints(self, ctx: StageContext, p: PlanParams) -> tuple[F64, F64]:
        if p.start is not None and p.goal is not None:
            return np.asarray(p.start, np.float64), np.asarray(p.goal, np.float64)
        t = read_artifact(ctx.input("slam", "trajectory.parquet"), "trajectory", columns=["x", "y"])
        xy = np.stack([t["x"].to_numpy(), t["y"].to_numpy()], 1)
        if len(xy) == 0:
            raise UserError(f"{ctx.input('slam', 'trajectory.parquet')}: empty trajectory; set plan.start and "
                            "plan.goal")
        s, _ = default_endpoints(xy)
        start = np.asarray(p.start, np.float64) if p.start is not None else s
        goal = np.asarray(p.goal, np.float64) if p.goal is not None else default_endpoints(
            np.vstack([start, xy]))[1]
        return start, goal

    def _log(self, ctx: StageContext, paths: dict[str, F64]) -> None:
        import rerun as rr

        colours = {"greedy": (220, 40, 40), "uncertainty": (150, 60, 200)}
        for name, path in paths.items():
            base = name.removeprefix("astar_")
            col = colours.get(base, (200, 200, 200))
            if name.startswith("astar_"):
                col = tuple(int(0.5 * c + 100) for c in col)  # type: ignore[assignment]
            xyz = np.column_stack([path, np.zeros(len(path))]).astype(np.float32)
            ctx.recording.log(f"world/plan/{name}", rr.LineStrips3D([xyz], colors=[col], radii=0.03), static=True)


def _prior_variance(field: MapField, pts: F64) -> F64:
    """Prior latent variance ``Phi^T Lambda Phi`` at points: the normaliser of the uncertainty panel."""
    from core import hilbert_map as hm

    if field.prior_diag is None:
        return np.full(len(pts), np.nan)
    return np.asarray(hm.prior_variance_at(field.basis, field.prior_diag, pts))


STAGE = PlanStage()
