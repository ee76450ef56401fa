"""Parameter sweeps: ``workflows/sweep_*.toml`` with a ``[sweep]`` table of ``"stage.param" = [values]``.

``expand_sweep`` is a pure function from the ``[sweep]`` table to the list of parameter points (the
Cartesian product, first key slowest), each an override dict ``{stage: {param: value}}``. A key that names a
stage alone takes a list of tables, each one combination of that stage's parameters (``voxel =
[{trajectory = "groundtruth"}, {trajectory = "slam", slam_method = "rich_slam"}]``): combinations that a
product of per-parameter lists would repeat or get wrong. Every point
runs into its own run store ``runs/sweeps/<workflow>/<point>/<seq>/``; stages whose key is the same for
every point (usually everything upstream of the swept stage) run once in the main run store and are
hard-linked into the points. The points go through ``pipeline.executors`` (inline by default, a process
pool or Ray on request). Afterwards the ``evaluate`` metrics of all points are gathered into
``runs/sweeps/<workflow>/sweep_metrics.parquet`` and the workflow's figure is drawn
(``[workflow] figure = "auc_vs_features"`` for RICH-SLAM Fig. 6, ``"hyperparameter_grid"`` for Fig. 7).

Run one with ``pipeline sweep sweep_fig7 --seq demo`` (or ``python -m pipeline.sweep ...``).
"""

from __future__ import annotations

import itertools
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer
from typer.exceptions import TyperException

from core.errors import UserError
from core.stage import flatten_params
from pipeline.config import Overrides, Workflow, check_param_names, load_workflow, merge_overrides

SWEEPS_DIR = "sweeps"


@dataclass(frozen=True)
class SweepPoint:
    """One parameter point: a folder-safe name and its overrides."""

    name: str
    overrides: Overrides

    def values(self) -> dict[str, Any]:
        """``{"stage.param": value}``."""
        return {f"{s}.{k}": v for s, d in self.overrides.items() for k, v in d.items()}


def flatten_sweep(sweep: Mapping[str, Any], prefix: str = "") -> dict[str, list[Any]]:
    """``{"stage.param": values}`` from a ``[sweep]`` table written with quoted or dotted keys (a group's member:
    ``"stage.group.param"``)."""
    out: dict[str, list[Any]] = {}
    for key, value in sweep.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            out.update(flatten_sweep(value, name))
            continue
        if "." not in name and isinstance(value, list) and value and all(isinstance(v, Mapping) for v in value):
            # stage = [{param = value, ...}, ...]: listed combinations of one stage's parameters
            if any(not flatten_params(v) for v in value):
                raise UserError(f"[sweep] {name}: each entry must be a non-empty table of parameter = value")
            out[name] = [flatten_params(v) for v in value]  # a group's members as "group.param"
            continue
        if "." not in name:
            raise UserError(f"[sweep] {name}: expected 'stage.param' (or 'stage.group.param') = [values]")
        if not isinstance(value, list) or not value:
            raise UserError(f"[sweep] {name}: expected a non-empty list of values, got {value!r}")
        out[name] = list(value)
    return out


def expand_sweep(sweep: Mapping[str, Any]) -> list[Overrides]:
    """All points of the sweep (Cartesian product, first key varying slowest) as override dicts."""
    flat = flatten_sweep(sweep)
    keys = list(flat)
    points: list[Overrides] = []
    for combo in itertools.product(*(flat[k] for k in keys)):
        point: Overrides = {}
        for key, value in zip(keys, combo, strict=True):
            if "." not in key:  # a listed combination of the stage's parameters
                point.setdefault(key, {}).update(value)
                continue
            stage, param = key.split(".", 1)
            point.setdefault(stage, {})[param] = value
        points.append(point)
    return points


def _slug(value: Any) -> str:
    text = json.dumps(value, separators=(",", ":")) if not isinstance(value, str) else value
    return re.sub(r"[^A-Za-z0-9.+-]+", "_", text).strip("_") or "x"


def point_name(point: Overrides) -> str:
    """A readable folder name: ``gp_lengthscale_m=2,gp_signal_variance=16`` (stage prefixes kept when ambiguous)."""
    params = [(s, k) for s, d in point.items() for k in d]
    short = [k for _, k in params]
    parts = []
    for s, k in params:
        label = k if short.count(k) == 1 else f"{s}.{k}"
        parts.append(f"{label}={_slug(point[s][k])}")
    return ",".join(parts) or "base"


def sweep_points(sweep: Mapping[str, Any]) -> list[SweepPoint]:
    points = [SweepPoint(point_name(p), p) for p in expand_sweep(sweep)]
    names = [p.name for p in points]
    if len(set(names)) != len(names):
        raise UserError("[sweep]: two points get the same folder name; use distinct values")
    return points


def sweep_root(runs_dir: Path, workflow: str) -> Path:
    return Path(runs_dir) / SWEEPS_DIR / workflow


def workflow_meta(wf: Workflow) -> dict[str, Any]:
    """The ``[workflow]`` table of the file (figure settings live there)."""
    import tomllib

    if wf.path is None:
        return {}
    with wf.path.open("rb") as f:
        return dict(tomllib.load(f).get("workflow", {}))


@dataclass
class SweepRun:
    """What a sweep produced."""

    root: Path
    points: list[SweepPoint]
    results: list[Any]
    metrics: Path | None
    figures: list[Path]


def run_sweep(
    workflow: str, seqs: Sequence[Any], runs_dir: Path, overrides: Overrides | None = None,
    executor: Any = None, console: Any = None, registry: str = "pipeline.registry:load_stages",
    force: bool = False,
) -> SweepRun:
    """Run every point of ``workflow``'s sweep on ``seqs`` (``SequenceInfo``), gather metrics, draw the figure."""
    import importlib

    from rich.console import Console

    from pipeline.executors import Executor, RunTask, run_all
    from pipeline.runner import Runner

    console = console or Console(stderr=True)
    wf = load_workflow(workflow)
    if not wf.sweep:
        raise UserError(f"workflow '{wf.name}' has no [sweep] table ({wf.path})")
    module, _, func = registry.partition(":")
    stages = getattr(importlib.import_module(module), func)()
    points = sweep_points(wf.sweep)
    for key, values in flatten_sweep(wf.sweep).items():
        stage, _, param = key.partition(".")
        if stage not in stages:
            raise UserError(f"[sweep] {key}: unknown stage '{stage}'")
        names = {param: None} if param else {k: None for v in values for k in v}
        check_param_names(stage, names, stages, f"workflow {wf.path} [sweep]")
    base = overrides or {}
    root = sweep_root(runs_dir, wf.name)
    targets = tuple(wf.stages) or ("all",)
    # stages with one key across all points run once, in the main run store
    for info in seqs:
        runners = [Runner(info, root / p.name, stages, wf, merge_overrides(base, p.overrides), console)
                   for p in points]
        plan = runners[0].closure(runners[0].resolve_targets(targets)[0])
        shared = [s for s in plan if len({r.key(s) for r in runners}) == 1]
        if shared and len(shared) < len(plan):
            console.print(f"[bold]{info.name}[/]: shared stages {', '.join(shared)} in {runs_dir}")
            Runner(info, runs_dir, stages, wf, merge_overrides(base, points[0].overrides), console).run(shared)
    tasks = [RunTask(info, str(root / p.name), targets, targets if force else (), merge_overrides(base, p.overrides),
                     str(wf.path or wf.name), (str(runs_dir),), f"{p.name}/{info.name}", registry)
             for p in points for info in seqs]
    ex = executor or Executor()

    def done(res: Any) -> None:
        mark = "[green]ok[/]" if res.ok else f"[red]failed[/]: {(res.error or '').splitlines()[0]}"
        console.print(f"  {res.name}: {mark} ({res.seconds:.1f} s)")

    console.print(f"sweep {wf.name}: {len(points)} point(s) x {len(seqs)} sequence(s) on the {ex.name} executor")
    results = run_all(tasks, ex, done)
    gathered = swept_sequences(root, points, [s.name for s in seqs])
    if len(gathered) > len(seqs):
        console.print(f"gathering {len(gathered)} sequences (with those of earlier calls): {', '.join(gathered)}")
    table = gather_sweep(root, points, gathered)
    metrics = None
    figs: list[Path] = []
    if table is not None:
        from schemas import write_artifact

        metrics = write_artifact(table, root / "sweep_metrics.parquet", "metrics")
        figs = plot_sweep(wf, root, points, [s.name for s in seqs], table.to_pylist())
    return SweepRun(root, points, results, metrics, figs)


def swept_sequences(root: Path, points: Sequence[SweepPoint], current: Sequence[str],
                    stage: str = "evaluate") -> list[str]:
    """``current``, then every other sequence that an earlier call of the same sweep left results for (so the
    gathered table and figure cover every sequence swept so far, one call or many)."""
    seen = list(current)
    for p in points:
        d = root / p.name
        if not d.is_dir():
            continue
        for sub in sorted(d.iterdir()):
            if sub.name not in seen and (sub / stage / "metrics.parquet").exists():
                seen.append(sub.name)
    return seen


def gather_sweep(root: Path, points: Sequence[SweepPoint], seqs: Sequence[str], stage: str = "evaluate") -> Any:
    """One long table of every point's metrics, with ``point`` and ``params`` (JSON) columns; None when empty."""
    import pyarrow as pa

    from pipeline.results import gather

    cols: dict[str, list[Any]] = {k: [] for k in ("seq", "method", "metric", "value", "features", "section",
                                                  "point", "params")}
    for p in points:
        recs, _ = gather(root / p.name, seqs, stage)
        params = json.dumps(p.values(), sort_keys=True)
        for r in recs:
            for k in ("seq", "method", "metric", "value"):
                cols[k].append(r[k])
            cols["features"].append(int(r.get("features") or 0))
            cols["section"].append(str(r.get("section") or ""))
            cols["point"].append(p.name)
            cols["params"].append(params)
    if not cols["seq"]:
        return None
    return pa.table({
        "seq": pa.array(cols["seq"], pa.string()), "method": pa.array(cols["method"], pa.string()),
        "metric": pa.array(cols["metric"], pa.string()), "value": pa.array(cols["value"], pa.float64()),
        "features": pa.array(cols["features"], pa.int32()), "section": pa.array(cols["section"], pa.string()),
        "point": pa.array(cols["point"], pa.string()), "params": pa.array(cols["params"], pa.string()),
    })


# -- figures ----------------------------------------------------------------------------------------------------
def plot_sweep(wf: Workflow, root: Path, points: Sequence[SweepPoint], seqs: Sequence[str],
               records: Sequence[Mapping[str, Any]]) -> list[Path]:
    """The figure named by ``[workflow] figure`` (drawn by the evaluate stage's report); nothing when it names
    none."""
    from pipeline.registry import stage_report

    meta = workflow_meta(wf)
    kind = meta.get("figure")
    if kind is None:
        return []
    rep = stage_report()
    known = getattr(rep, "sweep_figure_kinds", ())
    if kind not in known:
        raise UserError(f"{wf.path}: [workflow] figure = {kind!r}; known: {', '.join(known)}")
    return rep.sweep_figures(str(kind), root, wf.name, wf.description, points, seqs, records, meta)


# -- command line ----------------------------------------------------------------------------------------------
def command(
    workflow: Annotated[str, typer.Argument(help="a sweep workflow in workflows/ (e.g. sweep_fig7) or a .toml")],
    seq: Annotated[list[str] | None, typer.Option(
        "--seq", "-s", help="sequence name, list (a,b) or glob; repeat it for more (default: demo)")] = None,
    set_: Annotated[list[str] | None, typer.Option("--set", help="extra STAGE.PARAM=VALUE for every point")] = None,
    runs_dir: Annotated[Path | None, typer.Option("--runs-dir", help="run store (default ./runs)")] = None,
    executor: Annotated[str | None, typer.Option("--executor", help="local (process pool) or ray; default: in "
                                                 "this process, one point after another")] = None,
    workers: Annotated[int | None, typer.Option("--workers", help="parallel points")] = None,
    force: Annotated[bool, typer.Option("--force", help="rerun the workflow's stages at every point")] = False,
) -> None:
    """Run every point of a sweep workflow, gather the metrics and draw the workflow's figure."""
    from rich.console import Console

    from core.paths import default_runs_dir
    from pipeline.config import parse_set
    from pipeline.executors import make_executor
    from pipeline.registry import load_stages
    from pipeline.sequences import expand_sequences, load_registry, seq_spec

    console = Console(stderr=True)
    overrides = parse_set(set_ or [], load_stages())
    seqs = expand_sequences(seq_spec(seq) or "demo", load_registry())
    ex = make_executor(executor, workers) if executor else None
    res = run_sweep(workflow, seqs, runs_dir or default_runs_dir(), overrides, ex, console, force=force)
    failed = [r for r in res.results if not r.ok]
    console.print(f"sweep folder: {res.root}")
    if res.metrics is not None:
        console.print(f"metrics: {res.metrics}")
    for f in res.figures:
        console.print(f"figure: {f}")
    if failed:
        raise typer.Exit(1 if any(r.error_kind == "bug" for r in failed) else 2)


def main() -> None:
    """``python -m pipeline.sweep WORKFLOW --seq SEQ`` with the CLI's exit codes (2 on a user error)."""
    import sys

    from rich.console import Console
    from rich.markup import escape

    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
    app.command()(command)
    try:
        app(standalone_mode=False)
    except UserError as exc:
        Console(stderr=True).print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True, highlight=False)
        sys.exit(2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        sys.exit(130)
    except TyperException as exc:  # usage errors (unknown option, missing argument)
        show = getattr(exc, "show", None)
        if callable(show):
            show()
        else:
            Console(stderr=True).print(f"[bold red]error:[/] {escape(str(exc))}")
        sys.exit(int(getattr(exc, "exit_code", 2) or 2))


if __name__ == "__main__":
    main()
