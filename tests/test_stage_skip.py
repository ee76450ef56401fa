"""Stages that cannot run for a sequence are skipped with a one-line reason, with everything that needs them.

Toy stages exercise the runner's rules (static needs, data-dependent reasons, optional inputs, named targets,
status); one end-to-end run checks the case of a radar + IMU log (no lidar, no ground truth) runs
``run all`` to exit 0 and names what was skipped and why.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.errors import UserError
from core.stage import Stage, StageContext, StageParams, parquet_rows
from pipeline.config import Workflow
from pipeline.runner import Runner
from pipeline.sequences import SequenceInfo
from schemas import write_artifact
from tests.toy_stages import NUMBERS

ROOT = Path(__file__).resolve().parents[1]
LOG = SequenceInfo(name="toy_log", kind="source", source=Path("/nonexistent"))
MAPS = SequenceInfo(name="rmap_toy", kind="rmap", scene="toy", source=Path("/nonexistent"))


class Count(StageParams):
    n: int = 3


def _write(ctx: StageContext, n: int) -> None:
    i = np.arange(n, dtype=np.int32)
    write_artifact({"i": i, "v": i * 1.0}, ctx.output("numbers.parquet"), NUMBERS)


class Read(Stage):
    """Reads the log (needs it); writes ``n`` rows (0 = "the log had nothing")."""

    name = "read"
    needs = frozenset({"log"})
    Params = Count
    outputs = ("numbers.parquet",)

    def run(self, ctx: StageContext) -> None:
        _write(ctx, ctx.params.n)


class Build(Stage):
    """Needs ``read``'s rows: skipped on an empty input."""

    name = "build"
    inputs = ("read",)
    outputs = ("numbers.parquet",)

    def skip_reason_for_inputs(self, seq: SequenceInfo, params: StageParams,
                               input_dirs: Mapping[str, Path]) -> str | None:
        return "the log holds no rows" if parquet_rows(input_dirs["read"] / "numbers.parquet") == 0 else None

    def run(self, ctx: StageContext) -> None:
        _write(ctx, 2)


class After(Stage):
    name = "after"
    inputs = ("build",)
    outputs = ("numbers.parquet",)

    def run(self, ctx: StageContext) -> None:
        _write(ctx, 1)


class Report(Stage):
    """Runs on any source; reads ``build`` when it can (an optional input)."""

    name = "report"
    optional_inputs = ("build",)
    outputs = ("numbers.parquet",)

    def run(self, ctx: StageContext) -> None:
        ctx.stats["had_build"] = ctx.has_input("build")
        _write(ctx, 1)


def runner(tmp: Path, seq: SequenceInfo, **params: Any) -> Runner:
    reg = {s.name: s for s in (Read(), Build(), After(), Report())}
    wf = Workflow("toy", list(reg), {})
    return Runner(seq, tmp, reg, wf, {k: dict(v) for k, v in params.items()})


def result(outcomes: list[Any]) -> dict[str, tuple[str, str]]:
    return {o.stage: (o.action, o.reason) for o in outcomes}


def test_static_skip_by_source_kind_and_downstream(tmp_path: Path) -> None:
    r = runner(tmp_path, MAPS)
    out = result(r.run(["all"]))
    assert out["read"] == ("skipped", "'rmap_toy' is a published map set, it has no log")
    assert out["build"] == ("skipped", "needs 'read', skipped: 'rmap_toy' is a published map set, it has no log")
    assert out["after"][0] == "skipped" and "needs 'read'" in out["after"][1]
    assert out["report"][0] == "ran"  # its optional input is left out
    import json

    manifest = json.loads((tmp_path / "rmap_toy" / "report" / "manifest.json").read_text())
    assert manifest["stats"]["had_build"] is False and "build" not in manifest["inputs"]
    st = {s.stage: s for s in r.status()}
    assert st["build"].state == "unavailable" and st["build"].reason.startswith("needs 'read'")
    assert st["report"].state == "done"
    # a named stage that cannot run is a user error, not a silent skip
    with pytest.raises(UserError, match=r"stage 'after' cannot run for sequence 'rmap_toy': needs 'read'"):
        runner(tmp_path, MAPS).run(["after"])


def test_data_dependent_skip_after_inputs_finish(tmp_path: Path) -> None:
    out = result(runner(tmp_path, LOG, read={"n": 0}).run(["all"]))
    assert out["read"][0] == "ran"
    assert out["build"] == ("skipped", "the log holds no rows")
    assert out["after"] == ("skipped", "needs 'build', skipped: the log holds no rows")
    assert out["report"][0] == "ran"
    # rows arrive: build runs, report's key now includes build, so report reruns
    out = result(runner(tmp_path, LOG, read={"n": 4}).run(["all"]))
    assert [out[s][0] for s in ("read", "build", "after", "report")] == ["ran", "ran", "ran", "ran"]
    out = result(runner(tmp_path, LOG, read={"n": 4}).run(["all"]))
    assert {a for a, _ in out.values()} == {"cached"}
    with pytest.raises(UserError, match="stage 'after' cannot run for sequence 'toy_log': needs 'build'"):
        runner(tmp_path, LOG, read={"n": 0}).run(["after"])


def _drop_topics(src: Path, dst: Path, keep: tuple[str, ...]) -> None:
    from rosbags.rosbag1 import Reader, Writer

    with Reader(src) as r, Writer(dst) as w:
        conns = [c for c in r.connections if c.topic in keep]
        out = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest) for c in conns}
        for c, t, raw in r.messages(connections=conns):
            w.write(out[c.id], t, raw)


def test_radar_imu_only_log_runs_all_to_exit_0(tmp_path: Path) -> None:
    """A log with radar and IMU only; stages needing lidar or ground truth are skipped."""
    env = {**os.environ, "COLUMNS": "250"}

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                              env=env, timeout=600)

    r = cli("simulate", "--world", "demo", "--out", str(tmp_path / "full.bag"), "--duration", "2")
    assert r.returncode == 0, r.stderr
    _drop_topics(tmp_path / "full.bag", tmp_path / "radar_imu.bag", ("/tf_static", "/gx5/imu/data",
                                                                      "/mmWaveDataHdl/RScan"))
    r = cli("run", "all", "--source", str(tmp_path / "radar_imu.bag"), "--dataset", "generic", "--runs-dir",
            str(tmp_path / "runs"), "--set", "slam.n_particles=4", "--set", 'slam.methods=["rich_slam"]')
    assert r.returncode == 0, r.stderr[-3000:]
    lines = {ln.split()[0]: ln for ln in r.stderr.splitlines() if " skipped: " in ln and ln[:1].isalpha()}
    assert set(lines) == {"voxel", "patches", "complete", "evaluate"}, r.stderr[-3000:]
    assert "the log has no ground truth" in lines["voxel"]
    assert all("needs 'voxel', skipped: the log has no ground truth" in lines[s] for s in ("patches", "complete"))
    done = {p.name for p in (tmp_path / "runs" / "radar_imu").iterdir() if not p.name.startswith(".")}
    assert {"ingest", "filter", "odometry", "slam", "plan"} <= done and not done & set(lines)


class NeedsExtra(Build):
    """``build`` as a stage whose extra is not installed (as ``complete`` without torch)."""

    requires = ("a_module_that_does_not_exist_xyz",)
    requires_extra = "learn"


def extra_runner(tmp: Path, seq: SequenceInfo, console: Any = None) -> Runner:
    reg = {s.name: s for s in (Read(), NeedsExtra(), After(), Report())}
    return Runner(seq, tmp, reg, Workflow("toy", list(reg), {}), {}, console)


def test_named_stage_needing_an_uninstalled_optional_input_is_refused(tmp_path: Path) -> None:
    """`run report` would leave out `build` (its extra is missing) and say nothing: a user error instead,
    naming the stage, the reason and the install command, before anything runs."""
    with pytest.raises(UserError) as info:
        extra_runner(tmp_path, LOG).run(["report"])
    msg = str(info.value)
    assert msg == ("stage 'report' needs 'build' for sequence 'toy_log', and 'build' cannot run: needs "
                   "a_module_that_does_not_exist_xyz, not installed (the 'learn' extra: pip install -e '.[learn]', "
                   "or make demo); `pipeline run all` goes on without it")
    assert not (tmp_path / "toy_log").exists()  # nothing ran, nothing written
    # where the stage would not run for the sequence anyway, the missing extra does not matter
    out = result(extra_runner(tmp_path, MAPS).run(["report"]))
    assert out == {"report": ("ran", "missing")}


def test_run_all_goes_without_an_uninstalled_stage_and_says_so(tmp_path: Path) -> None:
    import io

    from rich.console import Console

    buf = io.StringIO()
    out = result(extra_runner(tmp_path, LOG, Console(file=buf, width=300)).run(["all"]))
    assert out["build"] == ("skipped", "needs a_module_that_does_not_exist_xyz, not installed (the 'learn' extra: "
                                       "pip install -e '.[learn]', or make demo)")
    assert out["after"] == ("skipped", "input 'build' unavailable")
    assert out["read"][0] == "ran" and out["report"] == ("ran", "missing; without 'build' (not installed)")
    text = buf.getvalue()
    assert "warning: 'report' of toy_log went without 'build', which cannot run: needs " \
           "a_module_that_does_not_exist_xyz, not installed (the 'learn' extra: pip install -e '.[learn]'" in text
    # cached on the next run: still said
    buf = io.StringIO()
    out = result(extra_runner(tmp_path, LOG, Console(file=buf, width=300)).run(["all"]))
    assert out["report"] == ("cached", "without 'build' (not installed)") and "went without 'build'" in buf.getvalue()


def test_several_sequences_warn_once_per_uninstalled_stage(tmp_path: Path) -> None:
    """With several sequences the workers' consoles are quiet: the driver names the uninstalled stage once."""
    from pipeline.cli import not_installed_warnings
    from pipeline.executors import TaskResult

    reg = {s.name: s for s in (Read(), NeedsExtra(), After(), Report())}
    results = []
    for i in range(5):
        seq = SequenceInfo(name=f"toy_log{i}", kind="source", source=Path("/nonexistent"))
        wf = Workflow("toy", list(reg), {})
        outcomes = Runner(seq, tmp_path, reg, wf, {}, None).run(["all"])
        results.append(TaskResult(seq.name, seq.name, str(tmp_path), True, outcomes))
    (line,) = not_installed_warnings(results, reg)
    assert line == ("'build' did not run for 5 sequence(s) (toy_log0, toy_log1, toy_log2 and 2 more), and the stages "
                    "that use it went without it: needs a_module_that_does_not_exist_xyz, not installed (the 'learn' "
                    "extra: pip install -e '.[learn]', or make demo)")
    assert not_installed_warnings(results, {s.name: s for s in (Read(), Build(), After(), Report())}) == []
