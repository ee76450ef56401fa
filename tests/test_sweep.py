"""Sweeps: the pure expansion of a [sweep] table, and the sequential runner on a toy two-stage registry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import Field

from core.errors import UserError
from core.stage import Stage, StageContext, StageParams
from pipeline.config import load_workflow
from pipeline.report import sweep_records, sweep_tables
from pipeline.sequences import SequenceInfo
from pipeline.sweep import expand_sweep, flatten_sweep, point_name, run_sweep, sweep_points
from schemas import read_artifact, write_artifact
from tests.toy_stages import NUMBERS

ROOT = Path(__file__).resolve().parents[1]


# -- expansion (pure) --------------------------------------------------------------------------------------------
def test_expand_is_the_cartesian_product_first_key_slowest() -> None:
    sweep = {"evaluate.gp_lengthscale_m": [2, 20], "evaluate.gp_signal_variance": [1, 16, 64]}
    pts = expand_sweep(sweep)
    assert len(pts) == 6
    assert pts[0] == {"evaluate": {"gp_lengthscale_m": 2, "gp_signal_variance": 1}}
    assert pts[2] == {"evaluate": {"gp_lengthscale_m": 2, "gp_signal_variance": 64}}
    assert pts[3] == {"evaluate": {"gp_lengthscale_m": 20, "gp_signal_variance": 1}}
    assert point_name(pts[4]) == "gp_lengthscale_m=20,gp_signal_variance=16"


def test_dotted_and_quoted_keys_and_list_values() -> None:
    import tomllib

    doc = tomllib.loads('[sweep]\nslam.n_particles = [10, 20]\n"evaluate.feature_counts" = [[16], [64, 144]]\n')
    flat = flatten_sweep(doc["sweep"])
    assert flat == {"slam.n_particles": [10, 20], "evaluate.feature_counts": [[16], [64, 144]]}
    pts = sweep_points(doc["sweep"])
    assert [p.name for p in pts] == ["n_particles=10,feature_counts=16", "n_particles=10,feature_counts=64_144",
                                     "n_particles=20,feature_counts=16", "n_particles=20,feature_counts=64_144"]
    assert pts[1].overrides == {"slam": {"n_particles": 10}, "evaluate": {"feature_counts": [64, 144]}}
    # the same parameter name in two stages keeps the stage in the folder name
    assert point_name({"a": {"seed": 1}, "b": {"seed": 2}}) == "a.seed=1,b.seed=2"


def test_listed_combinations_of_one_stage() -> None:
    import tomllib

    doc = tomllib.loads('[sweep]\nvoxel = [{maps = "build"}, '
                        '{trajectory.source = "slam", trajectory.slam_method = "g"}]\n'
                        '"evaluate.seed" = [0, 1]\n')
    pts = sweep_points(doc["sweep"])
    assert [p.name for p in pts] == ["maps=build,seed=0", "maps=build,seed=1",
                                     "trajectory.source=slam,trajectory.slam_method=g,seed=0",
                                     "trajectory.source=slam,trajectory.slam_method=g,seed=1"]
    assert pts[2].overrides == {"voxel": {"trajectory.source": "slam", "trajectory.slam_method": "g"},
                                "evaluate": {"seed": 0}}
    assert pts[2].values() == {"voxel.trajectory.source": "slam", "voxel.trajectory.slam_method": "g",
                               "evaluate.seed": 0}
    with pytest.raises(UserError, match="non-empty table"):
        expand_sweep({"voxel": [{}]})


def test_bad_sweep_tables() -> None:
    with pytest.raises(UserError, match="non-empty list"):
        expand_sweep({"slam.n_particles": 5})
    with pytest.raises(UserError, match=r"stage\.param"):
        expand_sweep({"n_particles": [1, 2]})


def test_shipped_sweep_workflows_expand_against_the_real_stages() -> None:
    from pipeline.config import build_params, check_param_names
    from pipeline.registry import load_stages

    stages = load_stages()
    for name, n in (("sweep_fig6", 21), ("sweep_fig7", 9), ("sweep_radar_only", 7), ("sweep_table3", 3)):
        wf = load_workflow(name)
        assert wf.stages == ["evaluate"] and len(sweep_points(wf.sweep)) == n
        for p in sweep_points(wf.sweep):
            for stage, values in p.overrides.items():
                check_param_names(stage, values, stages, name)
                build_params(stages[stage], [(name, wf.params.get(stage, {})), ("sweep point", values)])


# -- the runner on a toy registry ---------------------------------------------------------------------------------
class SourceParams(StageParams):
    scale: float = Field(1.0, description="multiplier")


class Source(Stage):
    name = "source"
    Params = SourceParams
    outputs = ("numbers.parquet",)

    def run(self, ctx: StageContext) -> None:
        i = np.arange(4, dtype=np.int32)
        write_artifact({"i": i, "v": i * ctx.params.scale}, ctx.output("numbers.parquet"), NUMBERS)


class ToyEvalParams(StageParams):
    feature_counts: list[int] = Field([16], description="counts")
    seed: int = Field(0, description="seed")


class ToyEvaluate(Stage):
    """Writes metrics like the evaluate stage: AUC rows per feature count, depending on seed and count."""

    name = "evaluate"
    inputs = ("source",)
    Params = ToyEvalParams
    outputs = ("metrics.parquet",)

    def run(self, ctx: StageContext) -> None:
        v = read_artifact(ctx.input("source", "numbers.parquet"), NUMBERS)["v"].to_numpy().sum()
        rows = [(f"{m}@{n}", 0.5 + n / 1000 + 0.01 * ctx.params.seed + (0.1 if m == "hilbert_gp" else 0) + 0 * v, n)
                for n in ctx.params.feature_counts for m in ("hilbert_gp", "rff")]
        rows.append(("hilbert_gp", 0.9, 256))
        write_artifact({"seq": [ctx.seq.name] * len(rows), "method": [r[0] for r in rows],
                        "metric": ["auc"] * len(rows), "value": np.array([r[1] for r in rows]),
                        "features": np.array([r[2] for r in rows], np.int32)},
                       ctx.output("metrics.parquet"), "metrics")


def toy_registry() -> dict[str, Stage]:
    return {"source": Source(), "evaluate": ToyEvaluate()}


def test_sweep_runs_points_shares_upstream_and_gathers(tmp_path: Path) -> None:
    wf = tmp_path / "sweep_toy.toml"
    wf.write_text('[workflow]\nstages = ["evaluate"]\nfigure = "auc_vs_features"\n'
                  '[source]\nscale = 2.0\n'
                  '[sweep]\n"evaluate.feature_counts" = [[16], [64]]\n"evaluate.seed" = [0, 1]\n')
    runs = tmp_path / "runs"
    seq = SequenceInfo(name="toyseq", kind="source", source=Path("/nonexistent"))
    res = run_sweep(str(wf), [seq], runs, registry="tests.test_sweep:toy_registry")
    assert all(r.ok for r in res.results), [r.error for r in res.results]
    assert len(res.points) == 4 and res.root == runs / "sweeps" / "sweep_toy"
    # the upstream stage ran once in the main store and was linked into every point
    assert (runs / "toyseq" / "source" / "manifest.json").exists()
    for r in res.results:
        actions = {o.stage: o.action for o in r.outcomes}
        assert actions == {"source": "reused", "evaluate": "ran"}
    for p in res.points:
        assert (res.root / p.name / "toyseq" / "evaluate" / "metrics.parquet").exists()
    assert res.metrics is not None
    table = read_artifact(res.metrics, "metrics").to_pylist()
    assert len(table) == 4 * 3 and {r["point"] for r in table} == {p.name for p in res.points}
    assert all(r["params"].startswith('{"evaluate.feature_counts"') for r in table)
    assert [f.name for f in res.figures] == ["sweep_toy.png"] and res.figures[0].stat().st_size > 1000
    # gathered by `pipeline report --sweep`
    recs = sweep_records(runs, "sweep_toy")
    from pipeline.report import write_sweep_markdown

    (md,) = write_sweep_markdown(recs, tmp_path / "sweep.md", "Sweep sweep_toy")
    text = md.read_text()
    assert "## AUC per sweep point" in text and "| toyseq | feature_counts=16,seed=0 |" in text
    tabs = {t[0]: t for t in sweep_tables(recs)}
    agg = tabs["toyseq: AUC per number of map features, mean ± std over 2 point(s)"]
    assert agg[1] == ["method", "16", "64"]
    assert agg[2][0] == ["hilbert_gp", "0.621±0.005", "0.669±0.005"]
    # a second run is cached everywhere
    again = run_sweep(str(wf), [seq], runs, registry="tests.test_sweep:toy_registry")
    assert all(o.action == "cached" for r in again.results for o in r.outcomes)
    # another sequence swept in a later call: the gathered table holds both
    other = SequenceInfo(name="toyseq2", kind="source", source=Path("/nonexistent"))
    res2 = run_sweep(str(wf), [other], runs, registry="tests.test_sweep:toy_registry")
    assert res2.metrics is not None
    assert {r["seq"] for r in read_artifact(res2.metrics, "metrics").to_pylist()} == {"toyseq", "toyseq2"}


def test_sweep_rejects_unknown_parameters(tmp_path: Path) -> None:
    wf = tmp_path / "bad.toml"
    wf.write_text('[workflow]\nstages = ["evaluate"]\n[sweep]\n"evaluate.sede" = [0, 1]\n')
    seq = SequenceInfo(name="toyseq", kind="source", source=Path("/nonexistent"))
    with pytest.raises(UserError, match=r"did you mean 'evaluate\.seed'"):
        run_sweep(str(wf), [seq], tmp_path / "runs", registry="tests.test_sweep:toy_registry")


def test_sweep_command_line_exit_codes() -> None:
    import os
    import subprocess
    import sys

    entry = ["-m", "pipeline.sweep"]

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, *entry, *args], capture_output=True, text=True,
                              cwd=ROOT, env={**os.environ, "COLUMNS": "200"}, timeout=120)

    assert run("--help").returncode == 0
    entry = ["-m", "pipeline", "sweep"]  # the same command under `pipeline sweep`
    h = run("--help")
    assert h.returncode == 0 and "sweep workflow" in h.stdout
    r = run("default", "--seq", "demo")
    assert r.returncode == 2 and "has no [sweep] table" in r.stderr and "Traceback" not in r.stderr
    r = run("sweep_fig7", "--seq", "dmeo")
    assert r.returncode == 2 and "did you mean 'demo'" in r.stderr
    assert run("--bogus").returncode == 2
    entry = ["-m", "pipeline.sweep"]
    r = run("sweep_fig7", "--seq", "dmeo")
    assert r.returncode == 2 and "did you mean 'demo'" in r.stderr
