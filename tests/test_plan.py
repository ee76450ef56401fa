"""The plan stage: A* optimality against scipy's Dijkstra, field gradients against finite differences,
the refinement's constraints and cost, and the stage end to end on a synthetic Hilbert map."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from core.errors import UserError
from core.map_field import MapField, field_from_posterior, strategy_cost
from core.recording import entity_paths_in
from schemas import read_artifact
from stages.plan.astar import SQRT2, astar, edge_cost
from stages.plan.refine import PlanProblem, refine, resample_polyline
from stages.plan.stage import STAGE, PlanParams
from tests.test_evaluate_fixtures import make_context, write_synthetic_run


def _reference_cost(blocked: np.ndarray, cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> float:
    """Dijkstra (scipy.sparse.csgraph) on the same 8-connected graph, built edge by edge."""
    nx, ny = blocked.shape
    rows, cols, w = [], [], []
    for x in range(nx):
        for y in range(ny):
            if blocked[x, y]:
                continue
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    u, v = x + dx, y + dy
                    if (dx, dy) == (0, 0) or not (0 <= u < nx and 0 <= v < ny) or blocked[u, v]:
                        continue
                    if dx and dy and blocked[x + dx, y] and blocked[x, y + dy]:
                        continue  # no squeezing between two blocked cells
                    rows.append(x * ny + y)
                    cols.append(u * ny + v)
                    w.append(edge_cost(cost, (x, y), (u, v), SQRT2 if dx and dy else 1.0))
    g = coo_matrix((w, (rows, cols)), shape=(nx * ny, nx * ny)).tocsr()
    return float(dijkstra(g, indices=start[0] * ny + start[1])[goal[0] * ny + goal[1]])


@pytest.mark.parametrize("seed", range(12))
def test_astar_is_optimal_against_dijkstra(seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = tuple(rng.integers(4, 14, size=2))
    blocked = rng.uniform(size=shape) < 0.3
    cost = rng.uniform(0, 3, size=shape) if seed % 2 else np.zeros(shape)
    free = np.argwhere(~blocked)
    s, g = (tuple(int(v) for v in free[i]) for i in rng.choice(len(free), 2, replace=False))
    path, c = astar(blocked, s, g, cost)
    ref = _reference_cost(blocked, cost, s, g)
    if not np.isfinite(ref):
        assert path == [] and c == np.inf
        return
    assert c == pytest.approx(ref, rel=1e-12)
    # the returned path is connected, free, and costs what A* says
    assert path[0] == s and path[-1] == g and not any(blocked[p] for p in path)
    steps = np.abs(np.diff(np.asarray(path), axis=0))
    assert np.all(steps.max(1) == 1)
    total = sum(edge_cost(cost, a, b, SQRT2 if abs(a[0] - b[0]) and abs(a[1] - b[1]) else 1.0)
                for a, b in itertools.pairwise(path))
    assert total == pytest.approx(c, rel=1e-12)


def test_astar_refuses_blocked_ends_and_walls() -> None:
    blocked = np.zeros((5, 5), bool)
    blocked[2, :] = True
    assert astar(blocked, (0, 0), (4, 4)) == ([], float("inf"))
    assert astar(blocked, (2, 2), (4, 4)) == ([], float("inf"))
    path, c = astar(np.zeros((3, 3), bool), (0, 0), (2, 2))
    assert path == [(0, 0), (1, 1), (2, 2)] and c == pytest.approx(2 * SQRT2)


@pytest.fixture(scope="module")
def field(tmp_path_factory: pytest.TempPathFactory) -> MapField:
    runs = tmp_path_factory.mktemp("plan") / "runs"
    write_synthetic_run(runs, duration=5.0, with_maps=False)
    return field_from_posterior(read_artifact(runs / "synth" / "slam" / "map_posterior.parquet", "map_posterior"))


def test_field_gradients_match_finite_differences(field: MapField) -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform(field.lo + 1, field.hi - 1, (20, 2))
    v = field.values(p)
    h = 1e-6
    for d in range(2):
        e = np.zeros(2)
        e[d] = h
        vp, vm = field.values(p + e, False), field.values(p - e, False)
        assert np.allclose(v.dz[:, d], (vp.z - vm.z) / (2 * h), atol=1e-5)
        assert np.allclose(v.du[:, d], (vp.u - vm.u) / (2 * h), atol=1e-6)
        assert np.allclose(v.do[:, d], (vp.o - vm.o) / (2 * h), atol=1e-6)
        for s in ("greedy", "uncertainty"):
            _, dc = strategy_cost(v, s, 1e-3)
            cp, _ = strategy_cost(vp, s, 1e-3)
            cm, _ = strategy_cost(vm, s, 1e-3)
            assert np.allclose(dc[:, d], (cp - cm) / (2 * h), rtol=1e-4, atol=1e-4), s


@pytest.mark.parametrize("strategy", ["greedy", "uncertainty"])
def test_refinement_respects_constraints_and_lowers_the_cost(field: MapField, strategy: str) -> None:
    lo, hi = field.lo + 0.5, field.hi - 0.5
    prob = PlanProblem(field, strategy, alpha=1.0, beta=1.0, eps=1e-3, d_max=0.8, o_max=0.6,  # type: ignore[arg-type]
                       lo=lo, hi=hi)
    # a feasible but poor initial guess: through the free corridor south of the central block, zig-zagging
    xs = np.linspace(-5.5, 5.5, 25)
    ys = -3.2 + 0.3 * np.sin(np.arange(25) * 1.7)
    init = np.stack([xs, ys], 1)
    assert prob.feasible(init)
    res = refine(prob, init)
    assert res.accepted, res.message
    assert prob.feasible(res.path)
    v = prob.violations(res.path)
    assert v["step"] <= 1e-3 and v["occupancy"] <= 1e-4 and v["domain"] <= 1e-9
    assert res.cost <= res.initial_cost and res.cost == pytest.approx(prob.cost(res.path))
    assert np.array_equal(res.path[0], init[0]) and np.array_equal(res.path[-1], init[-1])


def test_refinement_keeps_the_guess_when_the_result_is_worse(field: MapField) -> None:
    prob = PlanProblem(field, "greedy", 1.0, 1.0, 1e-3, d_max=0.8, o_max=0.6, lo=field.lo, hi=field.hi)
    init = np.stack([np.linspace(-5.5, 5.5, 25), np.full(25, -3.2)], 1)
    res = refine(prob, init, max_iter=1)
    assert prob.feasible(res.path) and res.cost <= res.initial_cost + 1e-12


def test_resample_polyline_spacing() -> None:
    p = resample_polyline(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]]), 0.45)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert np.all(seg <= 0.45 + 1e-12) and np.allclose(p[[0, -1]], [[0, 0], [3, 4]])


def test_stage_writes_paths_figure_and_rerun(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=5.0, with_maps=False)
    p = PlanParams(start=[-5.6, 0.0], goal=[5.6, 0.0])
    out = tmp_path / "out"
    ctx = make_context(runs, "synth", "plan", p, ["slam"], out)
    STAGE.run(ctx)
    ctx.close()
    t = read_artifact(out / "paths.parquet", "paths").to_pylist()
    strategies = {r["strategy"] for r in t}
    assert strategies == {"greedy", "uncertainty", "astar_greedy", "astar_uncertainty"}
    field = field_from_posterior(read_artifact(runs / "synth" / "slam" / "map_posterior.parquet", "map_posterior"))
    for s in ("greedy", "uncertainty"):
        rows = sorted((r for r in t if r["strategy"] == s), key=lambda r: r["k"])
        xy = np.array([[r["x"], r["y"]] for r in rows])
        assert np.allclose(xy[0], p.start) and np.allclose(xy[-1], p.goal)
        assert np.linalg.norm(np.diff(xy, axis=0), axis=1).max() <= p.objective.d_max + 1e-3
        assert field.values(xy, False).o.max() <= p.objective.o_max + 1e-4
        # from the west to the east end of the loop, around the central block (|x| < 3.5, |y| < 1.5)
        dense = resample_polyline(xy, 0.05)
        assert not np.any((np.abs(dense[:, 0]) < 3.5) & (np.abs(dense[:, 1]) < 1.5))
    assert ctx.stats["greedy"]["cost"] <= ctx.stats["greedy"]["initial_cost"] + 1e-9
    assert (out / "plan.png").stat().st_size > 1000
    assert {"/world/plan/greedy", "/world/plan/uncertainty"} <= entity_paths_in(out / "plan.rrd")


def test_default_endpoints_and_bad_parameters(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=5.0, with_maps=False)
    ctx = make_context(runs, "synth", "plan", PlanParams(), ["slam"], tmp_path / "a")
    STAGE.run(ctx)
    ctx.close()
    assert len(ctx.stats["start"]) == 2 and ctx.stats["start"] != ctx.stats["goal"]
    with pytest.raises(UserError, match=r"plan\.start"):
        STAGE.run(make_context(runs, "synth", "plan", PlanParams(start=[500.0, 0.0], goal=[0.0, 3.0]), ["slam"],
                               tmp_path / "b"))
    with pytest.raises(ValueError, match="waypoint_spacing"):
        PlanParams.model_validate({"astar": {"waypoint_spacing": 2.0}, "objective": {"d_max": 1.0}})
