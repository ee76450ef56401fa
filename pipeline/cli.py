"""The ``pipeline`` command line (typer + rich). Exit codes: 0 success, 2 user error, 1 bug."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from typer.exceptions import TyperException

from core.errors import UserError
from core.paths import default_runs_dir
from pipeline.config import describe_params, load_workflow, parse_set
from pipeline.profile_cli import app as profile_app
from pipeline.registry import STAGE_NAMES, load_stages
from pipeline.runner import Runner, StageOutcome, StagesFailed
from pipeline.sequences import SequenceInfo, expand_sequences, load_registry, seq_spec, source_sequence
from pipeline.store import RunStore
from pipeline.sweep import command as sweep_command
from pipeline.tables import Column, print_listing
from schemas.io import SchemaError

if TYPE_CHECKING:
    from collections.abc import Mapping

    from core.stage import Stage
    from pipeline.executors import TaskResult

app = typer.Typer(
    name="pipeline",
    help="Radar SLAM (RICH-SLAM) and radar mapping (RMap) as cached stages over ColoRadar-format logs.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)
out = Console()

SeqOpt = Annotated[list[str] | None, typer.Option(
    "--seq", "-s", help="sequence name, list (a,b) or glob ('coloradar_*'); repeat it for more")]
OneSeqOpt = Annotated[list[str] | None, typer.Option("--seq", "-s", help="one sequence name")]
SetOpt = Annotated[list[str] | None, typer.Option("--set", help="override a parameter: STAGE.PARAM=VALUE")]
RunsOpt = Annotated[Path | None, typer.Option("--runs-dir", help="run store (default ./runs or $RADAR_PIPELINE_RUNS)")]
WorkflowOpt = Annotated[str, typer.Option("--workflow", "-w", help="workflow in workflows/ (or a .toml path)")]
SourceOpt = Annotated[Path | None, typer.Option(
    "--source", help="a bag, MCAP or extracted folder (as given to `pipeline run --source`)")]
DatasetOpt = Annotated[str, typer.Option("--dataset", help="dataset profile for --source")]


def _sequences(seq: str | None, source: Path | None, dataset: str) -> list[SequenceInfo]:
    if source is not None:
        return [source_sequence(source, seq, dataset)]
    if not seq:
        raise UserError("--seq is required (see `pipeline sequences`), or pass --source PATH")
    return expand_sequences(seq, load_registry())


def seq_name(values: list[str] | None, source: Path | None, dataset: str, command: str) -> str:
    """The one sequence a command reads: ``--seq``, or the name ``pipeline run --source`` gave the log."""
    if source is not None:
        return source_sequence(source, one_seq(values, command) if values else None, dataset).name
    if not values:
        raise UserError(f"pipeline {command}: --seq is required (see `pipeline sequences`), or pass --source PATH")
    return one_seq(values, command)


def one_seq(values: list[str], command: str) -> str:
    """The one sequence a command works on: a repeated ``--seq`` is a user error, not the last one silently."""
    if len(values) != 1:
        raise UserError(f"pipeline {command} works on one sequence; --seq was given {len(values)} times "
                        f"({', '.join(values)}): run it once per sequence")
    return values[0]


def _runs_dir(runs_dir: Path | None, write: bool = False) -> Path:
    """The run store, checked: a file, or (``write``) a folder that cannot be written, is a user error."""
    runs = runs_dir or default_runs_dir()
    name = "--runs-dir" if runs_dir is not None else (
        "$RADAR_PIPELINE_RUNS" if os.environ.get("RADAR_PIPELINE_RUNS") else "the run store")
    if runs.exists() and not runs.is_dir():
        raise UserError(f"{name} {runs}: is a file, not a folder; name a folder (it is created if missing)")
    if write:
        try:
            runs.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=runs):
                pass
        except OSError as exc:
            raise UserError(f"{name} {runs}: cannot write there ({exc.strerror or exc}); "
                            f"name a folder you can write to") from None
    return runs


def _print_outcomes(seq: str, outcomes: list[StageOutcome]) -> None:
    table = Table(title=f"{seq}: stages", title_justify="left")
    table.add_column("stage")
    table.add_column("result")
    table.add_column("seconds", justify="right")
    table.add_column("note")
    styles = {"ran": "green", "cached": "dim", "skipped": "yellow", "failed": "red"}
    for o in outcomes:
        table.add_row(o.stage, f"[{styles.get(o.action, '')}]{o.action}[/]", f"{o.seconds:.1f}", escape(o.reason))
    console.print(table)


@app.command()
def run(
    stages: Annotated[list[str], typer.Argument(help=f"stages to bring up to date ({', '.join(STAGE_NAMES)}), or "
                                                "'all' (the workflow's stages)")],
    seq: Annotated[list[str] | None, typer.Option(
        "--seq", "-s", help="sequence name, list (a,b) or glob; repeat it for more")] = None,
    set_: SetOpt = None,
    force: Annotated[bool, typer.Option("--force", help="rerun the named stages even when cached")] = False,
    runs_dir: RunsOpt = None,
    source: Annotated[Path | None, typer.Option("--source", help="a bag, MCAP or extracted folder to run on")] = None,
    dataset: Annotated[str, typer.Option("--dataset", help="dataset profile for --source")] = "coloradar",
    workflow: WorkflowOpt = "default",
    executor: Annotated[str | None, typer.Option(
        "--executor", help="local (process pool, default for several sequences) or ray")] = None,
    workers: Annotated[int | None, typer.Option("--workers", help="parallel sequences (default: CPU count)")] = None,
    ray_address: Annotated[str | None, typer.Option(
        "--ray-address", help="Ray cluster address (default: start a local instance)")] = None,
) -> None:
    """Run stages (and any missing or stale upstream stages); cached stages are skipped."""
    registry = load_stages()
    overrides = parse_set(set_ or [], registry)
    wf = load_workflow(workflow)
    seqs = _sequences(seq_spec(seq), source, dataset)
    runs = _runs_dir(runs_dir, write=True)
    forced = tuple(stages) if force else ()
    if len(seqs) == 1 and executor is None:
        runner = Runner(seqs[0], runs, registry, wf, overrides, console)
        try:
            outcomes = runner.run(stages, force=forced)
        except StagesFailed as exc:
            _print_outcomes(seqs[0].name, exc.outcomes)
            if exc.user_error:
                raise UserError(str(exc)) from None
            raise exc.first from exc
        _print_outcomes(seqs[0].name, outcomes)
        return
    from pipeline.executors import RunTask, make_executor, run_all

    tasks = [RunTask(s, str(runs), tuple(stages), forced, overrides, str(wf.path or wf.name)) for s in seqs]
    ex = make_executor(executor or "local", workers, ray_address)
    console.print(f"running {len(tasks)} sequence(s) on the {ex.name} executor")

    def on_done(res: TaskResult) -> None:
        mark = "[green]ok[/]" if res.ok else "[red]failed[/]"
        why = "" if res.ok else f": {escape(_first_line(res))}"
        console.print(f"  {escape(res.name)}: {mark} in {res.seconds:.1f} s{why}")

    results = run_all(tasks, ex, on_done)
    _print_results(results, runs)
    for line in not_installed_warnings(results, registry):
        console.print(f"[yellow]warning[/]: {escape(line)}", soft_wrap=True, highlight=False)
    if any(r.error_kind == "bug" for r in results):
        raise typer.Exit(1)
    if any(not r.ok for r in results):
        raise typer.Exit(2)


def not_installed_warnings(results: list[TaskResult], registry: Mapping[str, Stage]) -> list[str]:
    """One line per stage that did not run in some sequences because it is not installed (the per-sequence
    skip rows and warnings stay inside the workers), with the reason and the install command."""
    by_stage: dict[str, tuple[str, list[str]]] = {}
    for r in results:
        for o in r.outcomes:
            if o.action == "skipped" and o.stage in registry and registry[o.stage].unavailable_reason():
                by_stage.setdefault(o.stage, (o.reason, []))[1].append(r.name)
    out = []
    for stage, (reason, names) in by_stage.items():
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        out.append(f"'{stage}' did not run for {len(names)} sequence(s) ({shown}), and the stages that use it went "
                   f"without it: {reason}")
    return out


def _first_line(res: TaskResult) -> str:
    return (res.error or "").splitlines()[0] if res.error else ""


def _print_results(results: list[TaskResult], runs: Path) -> None:
    table = Table(title="sequences", title_justify="left")
    for col in ("sequence", "result", "ran", "cached/reused", "seconds", "error"):
        table.add_column(col)
    for r in results:
        ran = sum(o.action == "ran" for o in r.outcomes)
        cached = sum(o.action in ("cached", "reused") for o in r.outcomes)
        table.add_row(r.name, "[green]ok[/]" if r.ok else "[red]failed[/]", str(ran), str(cached),
                      f"{r.seconds:.1f}", _first_line(r))
    console.print(table)
    for r in results:
        if r.error_kind == "bug":
            console.print(f"[red]{escape(r.name)}[/]: {escape(str(r.error))}")
    gather = _comparison_table()
    if gather is not None:
        cmp = gather(runs, [r.seq for r in results if r.ok])
        if cmp is not None:
            out.print(cmp)


def _comparison_table() -> Any:
    """``pipeline.report.comparison_table`` when the evaluation reports are available."""
    import importlib

    try:
        return getattr(importlib.import_module("pipeline.report"), "comparison_table", None)
    except ImportError:
        return None


@app.command()
def status(
    seq: SeqOpt = None,
    set_: SetOpt = None,
    runs_dir: RunsOpt = None,
    workflow: WorkflowOpt = "default",
    source: SourceOpt = None,
    dataset: DatasetOpt = "coloradar",
) -> None:
    """Per stage: done / stale (why) / missing / unavailable, with timings."""
    registry = load_stages()
    overrides = parse_set(set_ or [], registry)
    wf = load_workflow(workflow)
    for info in _sequences(seq_spec(seq), source, dataset):
        runner = Runner(info, _runs_dir(runs_dir), registry, wf, overrides, console)
        table = Table(title=f"{info.name} ({runner.store.seq_dir})", title_justify="left")
        for col in ("stage", "state", "seconds", "finished", "why"):
            table.add_column(col, justify="right" if col == "seconds" else "left")
        colors = {"done": "green", "stale": "yellow", "damaged": "red", "missing": "red", "unavailable": "dim"}
        for st in runner.status():
            table.add_row(st.stage, f"[{colors[st.state]}]{st.state}[/]",
                          f"{st.seconds:.1f}" if st.seconds is not None else "",
                          st.finished_at or "", st.reason)
        out.print(table)


@app.command()
def sequences(
    split: Annotated[str | None, typer.Option("--split", help="only the map sequences of this RMap split "
                                              "(test: the Table III scenes, train)")] = None,
    present: Annotated[bool, typer.Option("--present", help="only sequences whose data is present")] = False,
    names: Annotated[bool, typer.Option("--names", help="print the names only, comma-separated (for --seq)")]
    = False,
) -> None:
    """Registered sequences, where their data is expected, and whether it is present."""
    rows = []
    chosen = [info for info in load_registry().values()
              if (split is None or info.split == split) and (not present or info.locate())]
    if split is not None and not chosen:
        raise UserError(f"--split {split}: no registered sequence has that split; map sequences have test or "
                        f"train (set RMAP_ROOT to the map set)")
    if names:
        print(",".join(info.name for info in chosen), flush=True)
        return
    for info in chosen:
        found = info.locate()
        where = info.where()
        if info.kind == "simulated":
            state = "[green]yes[/]" if found else "[dim]generated on first use[/]"
        else:
            state = "[green]yes[/]" if found else "[red]no[/]"
        rows.append([escape(info.name), escape(info.kind), escape(where), state,
                     escape(info.description or (info.run or ""))])
    columns = [Column("name", keep=True), Column("kind"), Column("data", keep=True), Column("present"),
               Column("description")]
    print_listing(out, "sequences (data/sequences.toml)", columns, rows)


@app.command()
def params(stage: Annotated[str | None, typer.Argument(help="a stage name (default: all)")] = None,
           workflow: WorkflowOpt = "default",
           seqs: Annotated[list[str] | None, typer.Option(
               "--seq", "-s", help="show the values this sequence runs with, and the layer that set each")] = None,
           set_: SetOpt = None,
           full: Annotated[bool, typer.Option("--full", help="whole descriptions (default: their first clause)")]
           = False) -> None:
    """List stage parameters, their types, defaults and the workflow's values (with --seq: the effective ones)."""
    registry = load_stages()
    wf = load_workflow(workflow)
    names = [stage] if stage else list(registry)
    for name in names:
        if name not in registry:
            from pipeline.config import did_you_mean

            raise UserError(f"unknown stage '{name}'{did_you_mean(name, registry)}")
    if seqs:
        from pipeline.config import effective_params
        from pipeline.sequences import get_sequence

        if len(seqs) != 1 or "," in seqs[0]:
            raise UserError("params --seq takes one sequence name")
        info = get_sequence(seqs[0])
        runner = Runner(info, default_runs_dir(), registry, wf, parse_set(set_ or [], registry), console=console)
        for name in names:
            rows = [[escape(f"{name}.{pname}"), escape(repr(value)), escape(layer),
                     escape(desc if full else brief(desc))]
                    for pname, value, layer, desc in effective_params(registry[name], runner.param_layers(name))]
            columns = [Column("parameter", keep=True), Column("value"), Column("set by"), Column("description")]
            print_listing(out, f"{name} on {info.name}: {registry[name].description}", columns, rows)
        return
    for name in names:
        rows = []
        for pname, typ, default, desc in describe_params(registry[name]):
            wval = wf.params.get(name, {}).get(pname, "")
            rows.append([escape(f"{name}.{pname}"), escape(typ), escape(repr(default)),
                         escape(repr(wval)) if wval != "" else "", escape(desc if full else brief(desc))])
        columns = [Column("parameter", keep=True), Column("type"), Column("default"),
                   Column(f"workflow {wf.name}"), Column("description")]
        print_listing(out, f"{name}: {registry[name].description}", columns, rows)


def brief(text: str) -> str:
    """A description's first clause (up to ``; ``)."""
    return text.split("; ", 1)[0]


@app.command()
def view(
    stages: Annotated[list[str] | None, typer.Argument(help="stages to open (default: all present)")] = None,
    seqs: OneSeqOpt = None,
    runs_dir: RunsOpt = None,
    source: SourceOpt = None,
    dataset: DatasetOpt = "coloradar",
) -> None:
    """Open the run's .rrd files in the Rerun viewer (prints the command when headless)."""
    seq = seq_name(seqs, source, dataset, "view")
    store = RunStore(_runs_dir(runs_dir), seq)
    present = [p.name for p in sorted(store.seq_dir.glob("*")) if p.is_dir() and not p.name.startswith(".")]
    order = {name: i for i, name in enumerate(STAGE_NAMES)}
    names = stages or sorted(present, key=lambda n: order.get(n, len(order)))  # pipeline order
    files = [store.stage_dir(s) / f"{s}.rrd" for s in names]
    files = [f for f in files if f.exists()]
    if not files:
        raise UserError(f"no .rrd recordings for '{seq}' in {store.seq_dir}; run `pipeline run all --seq {seq}` first")
    cmd = [sys.executable, "-m", "rerun", *map(str, files)]
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) or sys.platform == "win32":
        console.print("headless: open the recordings with")
        print(shlex.join(["rerun", *map(str, files)]), flush=True)  # one line, never wrapped: it is pasted
        return
    subprocess.Popen(cmd)


@app.command()
def export(
    fmt: Annotated[str, typer.Option("--format", "-f", help="tum | ply | mcap")],
    seqs: OneSeqOpt = None,
    out_dir: Annotated[Path | None, typer.Option("--out", help="output folder (default runs/<seq>/export)")] = None,
    runs_dir: RunsOpt = None,
    groundtruth_stamps: Annotated[str, typer.Option(
        "--groundtruth-stamps", help="tum: ground truth interpolated at the estimates' stamps (estimates: evo "
        "pairs every pose exactly) or at its own samples (own)")] = "estimates",
    source: SourceOpt = None,
    dataset: DatasetOpt = "coloradar",
) -> None:
    """Export trajectories (TUM, evo-compatible), maps (PLY) or results (MCAP with Foxglove schemas)."""
    from pipeline.export import export as do_export

    store = RunStore(_runs_dir(runs_dir), seq_name(seqs, source, dataset, "export"))

    def note(message: str) -> None:
        console.print(f"[yellow]note[/] {escape(message)}", soft_wrap=True, highlight=False)

    written = do_export(store, fmt, out_dir or store.seq_dir / "export", note, groundtruth_stamps)
    for p in written:
        print(p, flush=True)


@app.command()
def simulate(
    world: Annotated[str, typer.Option("--world", help="a world in data/worlds/, a registered twin sequence "
                                       "(coloradar_3_twin) or <scene>_twin for a scene under $RMAP_ROOT")],
    out_path: Annotated[Path, typer.Option("--out", help="output .bag file or folder")],
    duration: Annotated[float | None, typer.Option("--duration", help="seconds (default: 60; a twin: its whole "
                                                   "recorded path)")] = None,
    seed: Annotated[int, typer.Option("--seed")] = 0,
    fmt: Annotated[str, typer.Option("--format", help="bag | folder")] = "bag",
) -> None:
    """Write a ColoRadar-format log (ROS1 bag or extracted folder) simulated in a built-in world or a twin."""
    try:
        from simulator import simulate_to
    except ImportError as exc:
        raise UserError("the simulator is not available in this installation") from exc
    from sources import simulated

    spec = load_registry().get(world)
    if spec is not None and spec.kind != "simulated":
        spec = None
    scene = simulated.twin_scene_of(world, spec.scene if spec is not None else None)
    if scene is not None:
        target: Any = simulated.twin_world_for(world, scene, spec.twin if spec is not None else None)
    elif spec is not None and spec.world and simulated.world_file_missing(world):
        target = spec.world  # a registered sequence's name (sim_hallway_loop -> its world, hallway_loop)
    else:
        target = world
    path = simulate_to(world=target, out=out_path, duration=duration, seed=seed, fmt=fmt, console=console)
    out.print(str(path))


@app.command()
def report(
    seqs_: Annotated[list[str] | None, typer.Option(
        "--seqs", "--seq", "-s", help="sequences to compare: a,b,... or globs ('sim_*') over the run folders; repeat "
        "it for more")] = None,
    runs_dir: RunsOpt = None,
    out_file: Annotated[Path | None, typer.Option("--out", help="also write the tables as markdown (and the "
                                                  "combined metrics as .parquet beside it)")] = None,
    sweep: Annotated[str | None, typer.Option("--sweep", help="gather a sweep's points (runs/sweeps/NAME) "
                                              "instead; run sweeps with `pipeline sweep NAME --seq SEQ`")] = None,
    source: SourceOpt = None,
    dataset: DatasetOpt = "coloradar",
) -> None:
    """Gather the evaluate results of several runs (or of a sweep) into one comparison table."""
    seqs = seq_spec(seqs_)
    if source is not None:  # --seq names the --source run, as for `pipeline run`
        seqs = seq_name(seqs_, source, dataset, "report")
    from pipeline import report as rep

    runs = runs_dir or default_runs_dir()
    if sweep is not None:
        records, title = rep.sweep_records(runs, sweep, seqs), f"Sweep {sweep}"
        missing: list[str] = []
    else:
        if not seqs:
            raise UserError("--seqs is required (e.g. --seqs demo,sim_hallway_loop), or pass --sweep NAME")
        records, missing = rep.report_sequences(runs, seqs)
        title = "Comparison"
    for t in rep.build_tables(records, runs_dir=runs) if sweep is None else rep.sweep_tables(records):
        out.print(rep.rich_table(*t))
    for m in missing:
        console.print(f"[yellow]note[/] {m}: no evaluation in {runs}; run `pipeline run evaluate --seq {m}`")
    stale = rep.stale_rows(runs, sorted({str(r["seq"]) for r in records})) if sweep is None else {}
    for seq, why in stale.items():
        console.print(f"[yellow]stale[/] {escape(seq)}: {escape(why)}; refresh with "
                      f"`pipeline run evaluate --seq {seq}`", soft_wrap=True, highlight=False)
    if out_file is not None:
        command = rep.command_line(sys.argv[1:])
        try:
            if sweep is None:
                written = rep.write_outputs(records, out_file, title, runs_dir=runs, stale=stale, command=command)
                written += rep.write_figures(runs, records, out_file)
            else:
                written = rep.write_sweep_markdown(records, out_file, title, command=command)
        except OSError as exc:
            raise UserError(f"--out {out_file}: cannot write there ({exc.strerror or exc}); name a file in a "
                            f"folder you can write to") from None
        for p in written:
            out.print(str(p))


@app.command()
def train(
    model: Annotated[str, typer.Option("--model", help="uppointr (the paper's patch network, on --seqs or --maps) "
                                       "or voxel (the voxel U-Net, on --maps)")] = "uppointr",
    seqs_: Annotated[list[str] | None, typer.Option("--seqs", "-s", help="sequences for the patch pairs: a,b,... "
                                                    "or globs (or --maps); repeat it for more")] = None,
    test_seqs_: Annotated[list[str] | None, typer.Option(
        "--test-seqs", help="held-out sequences (not trained on; their patch CD is logged per epoch); 'none' for no "
        "held-out set; default: RMap's split of --seqs by run index; repeat it for more")] = None,
    size: Annotated[str, typer.Option("--size", help="model size: small (CPU) or paper")] = "small",
    epochs: Annotated[int, typer.Option("--epochs", help="uppointr: epochs (paper: 100)")] = 100,
    batch_size: Annotated[int | None, typer.Option("--batch-size", help="patches per step (uppointr; paper: 16) or "
                                                   "crops per step (voxel: 2)")] = None,
    lr: Annotated[float | None, typer.Option("--lr", help="AdamW initial learning rate (uppointr; paper: 1e-5; "
                                             "voxel: 1e-3)")] = None,
    weight_decay: Annotated[float, typer.Option("--weight-decay", help="AdamW weight decay (paper: 5e-5)")] = 5e-5,
    lr_decay: Annotated[float, typer.Option("--lr-decay", help="lr factor every --decay-every epochs")] = 0.9,
    decay_every: Annotated[int, typer.Option("--decay-every", help="epochs between lr decays (paper: 20)")] = 20,
    loss: Annotated[str, typer.Option("--loss", help="Chamfer variant per level: l2 (eq. 1) or l1")] = "l2",
    augment: Annotated[bool, typer.Option("--augment/--no-augment", help="random yaw and mirror")] = True,
    crop: Annotated[bool, typer.Option("--crop-target/--no-crop-target", help="cut lidar targets to the ball "
                                       "their radar patch spans (for maps with L/R well below 4)")] = True,
    seed: Annotated[int, typer.Option("--seed", help="seed of weights, batches, resampling, augmentation")] = 0,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda or auto (cuda when present)")] = "auto",
    threads: Annotated[int | None, typer.Option("--threads", help="torch CPU threads")] = None,
    time_limit: Annotated[float | None, typer.Option("--time-limit", help="uppointr: stop after the epoch that "
                                                     "passes this many seconds; voxel: the training budget and the "
                                                     "cosine schedule's length (default 3600)")] = None,
    out_path: Annotated[Path | None, typer.Option("--out", help="checkpoint (.safetensors or .pt); default "
                                                  "<runs>/models/rmap_<size>.safetensors (rmap_voxel for voxel)")
                        ] = None,
    half: Annotated[bool, typer.Option("--half", help="store the weights as float16")] = False,
    cached_only: Annotated[bool, typer.Option("--cached-only", help="train on the finished patches runs as they "
                                              "are, without bringing them up to date")] = False,
    set_: SetOpt = None,
    train_set: Annotated[list[str] | None, typer.Option("--train-set", help="override for the training sequences "
                                                        "only, e.g. patches.a=16 (the paper's a_train)")] = None,
    maps: Annotated[Path | None, typer.Option("--maps", help="train on a published map set (index.json + "
                                              "<scene>/{radar,lidar_filtered}.parquet): its train scenes, "
                                              "validation scenes picked from them")] = None,
    a_train: Annotated[float, typer.Option("--a-train", help="--maps: patch seed multiplier a for training")] = 16.0,
    a_val: Annotated[float, typer.Option("--a-val", help="--maps: a for the validation scenes (a_test)")] = 4.0,
    val_scenes: Annotated[str | None, typer.Option("--val-scenes", help="--maps: validation train scenes "
                                                   "(default: one per environment)")] = None,
    patches_per_epoch: Annotated[int | None, typer.Option("--patches-per-epoch", help="a seeded random subset "
                                                          "of the training patches per epoch")] = None,
    init: Annotated[str | None, typer.Option("--init", help="start from this checkpoint's weights "
                                             "(fine-tuning)")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="continue the run saved in --state")] = False,
    state: Annotated[Path | None, typer.Option("--state", help="resumable training state, written every epoch "
                                               "(default <out>.state.pt)")] = None,
    option: Annotated[list[str] | None, typer.Option("--option", "-o", help="voxel: a training setting KEY=VALUE "
                                                     "(jitter, coverage_weight, widths, crop_xy, val_every, workers, "
                                                     "...); repeat it for more")] = None,
    runs_dir: RunsOpt = None,
    workflow: WorkflowOpt = "default",
) -> None:
    """Train a completion network (RMap Sec. III-D): UpPoinTr on the patches of --seqs or a map set (--maps), or
    the voxel U-Net on a map set's train scenes; writes a checkpoint, its curve and history as it goes
    (resumable with --resume)."""
    if model not in ("uppointr", "voxel"):
        raise UserError(f"--model {model}: choose uppointr or voxel")
    if model == "voxel":
        _train_voxel(maps, out_path, runs_dir, option or [], time_limit=time_limit, seed=seed,
                     batch_size=batch_size, lr=lr, device=device, threads=threads, resume=resume, init=init)
        return
    if option:
        raise UserError("--option sets the voxel model's training; for uppointr use the named options")
    from pipeline.train import TrainRequest, run_training

    seqs, test_seqs = seq_spec(seqs_), seq_spec(test_seqs_)

    registry = load_stages()
    runs = _runs_dir(runs_dir, write=True)
    req = TrainRequest(
        seqs=seqs, test_seqs=test_seqs, runs_dir=runs, registry=registry, workflow=load_workflow(workflow),
        overrides=parse_set(set_ or [], registry), train_overrides=parse_set(train_set or [], registry),
        out=out_path or runs / "models" / f"rmap_{size}.safetensors",
        train_kwargs=dict(size=size, epochs=epochs, batch_size=batch_size or 16, lr=lr or 1e-5,
                          weight_decay=weight_decay,
                          lr_decay=lr_decay, decay_every=decay_every, loss=loss, augment=augment, seed=seed,
                          crop_target=crop, patches_per_epoch=patches_per_epoch, init=init,
                          device=device, time_limit_s=time_limit),
        threads=threads, half=half, cached_only=cached_only, maps=maps, a_train=a_train, a_val=a_val,
        val_scenes=val_scenes, resume=resume, state=state,
    )
    summary = run_training(req, console)
    for key in ("checkpoint", "curve", "history"):
        out.print(summary[key])


def _train_voxel(maps: Path | None, out_path: Path | None, runs_dir: Path | None, options: list[str],
                 **given: Any) -> None:
    from pipeline.train import VoxelTrainRequest, parse_options, run_voxel_training

    if maps is None:
        raise UserError("pipeline train --model voxel: give --maps (a map set: index.json + "
                        "<scene>/{radar,lidar_filtered}.parquet, e.g. ../shared/data/coloradar_maps)")
    config = parse_options(options)
    for key in ("time_limit", "seed", "batch_size", "lr"):
        if given[key] is not None and key not in config:
            config[key] = given[key]
    out_file = out_path or _runs_dir(runs_dir, write=True) / "models" / "rmap_voxel.safetensors"
    init = Path(given["init"]) if given["init"] else None
    req = VoxelTrainRequest(maps=maps, out=out_file, config=config, device=given["device"],
                            threads=given["threads"], resume=given["resume"], init=init)
    summary = run_voxel_training(req, console)
    out.print(json.dumps(summary))


app.command("sweep")(sweep_command)
app.add_typer(profile_app, name="profile")


INTERRUPTED = 130  #: exit code after Ctrl-C (128 + SIGINT), as shells report it


def _interrupted() -> None:
    console.print("[red]interrupted[/]: finished stages are kept; a stage that was running left its previous "
                  "result", soft_wrap=True)
    sys.exit(INTERRUPTED)


def main() -> None:
    """Console entry point with the exit-code contract (0 ok, 2 user error, 1 bug, 130 interrupted)."""
    try:
        # without standalone mode typer turns Ctrl-C (KeyboardInterrupt) into a returned Exit code 130, and
        # an explicit ``raise typer.Exit(n)`` into a returned n: both must become the process's exit status
        code = app(standalone_mode=False)
    except (UserError, SchemaError) as exc:
        console.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True, highlight=False)
        sys.exit(2)
    except typer.Abort:
        console.print("[red]aborted[/]")
        sys.exit(INTERRUPTED)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except TyperException as exc:  # usage errors (unknown command or option, bad value)
        show = getattr(exc, "show", None)
        if callable(show):
            show()
        else:
            console.print(f"[bold red]error:[/] {escape(str(exc))}")
        sys.exit(int(getattr(exc, "exit_code", 2) or 2))
    except KeyboardInterrupt:
        _interrupted()
    except OSError as exc:
        from pipeline.resources import is_disk_full

        if not is_disk_full(exc):
            raise
        where = f" writing {exc.filename}" if getattr(exc, "filename", None) else ""
        console.print(f"[bold red]error:[/] the disk is full{escape(where)} ({escape(exc.strerror or str(exc))}); free "
                      f"space or write elsewhere (--runs-dir, --out)", soft_wrap=True, highlight=False)
        sys.exit(2)
    if code == INTERRUPTED:
        _interrupted()
    if isinstance(code, int) and not isinstance(code, bool) and code != 0:
        sys.exit(code)


if __name__ == "__main__":
    main()
