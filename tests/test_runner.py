"""The stage runner: caching, staleness, atomicity, recovery, the lock, overrides."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from core.errors import LockHeldError, UserError
from pipeline.runner import Runner, StagesFailed
from pipeline.sequences import SequenceInfo
from pipeline.store import RunStore
from schemas import read_artifact
from tests import toy_stages
from tests.toy_stages import NUMBERS, MakeNumbers, Square

SEQ = SequenceInfo(name="toyseq", kind="source", source=Path("/nonexistent"))


def make_runner(runs: Path, overrides: dict | None = None, **wf: dict) -> Runner:
    return Runner(SEQ, runs, toy_stages.registry(), toy_stages.workflow(**wf), overrides or {})


def actions(outcomes: list) -> dict[str, str]:
    return {o.stage: o.action for o in outcomes}


def test_second_run_is_cached(tmp_path: Path) -> None:
    first = make_runner(tmp_path).run(["all"])
    assert actions(first) == {"make_numbers": "ran", "square": "ran"}
    assert MakeNumbers.calls == 1 and Square.calls == 1
    runner = make_runner(tmp_path)
    second = runner.run(["all"])
    assert actions(second) == {"make_numbers": "cached", "square": "cached"}
    assert MakeNumbers.calls == 0 and Square.calls == 0  # registry() reset the counters
    manifest = json.loads((tmp_path / "toyseq" / "square" / "manifest.json").read_text())
    assert manifest["complete"] and manifest["key"] == runner.key("square")
    assert manifest["inputs"] == {"make_numbers": runner.key("make_numbers")}
    assert manifest["stats"]["n"] == 5
    assert "squares.parquet" in manifest["artifacts"]


def test_named_stage_runs_missing_upstream_first(tmp_path: Path) -> None:
    out = make_runner(tmp_path).run(["square"])
    assert [o.stage for o in out] == ["make_numbers", "square"]
    assert actions(out) == {"make_numbers": "ran", "square": "ran"}


def test_changed_parameter_reruns_stage_and_downstream_only(tmp_path: Path) -> None:
    make_runner(tmp_path).run(["all"])
    # downstream parameter: only `square` reruns
    out = make_runner(tmp_path, {"square": {"offset": 1.0}}).run(["all"])
    assert actions(out) == {"make_numbers": "cached", "square": "ran"}
    # upstream parameter: both rerun
    runner = make_runner(tmp_path, {"make_numbers": {"scale": 2.0}, "square": {"offset": 1.0}})
    status = {s.stage: s for s in runner.status()}
    assert status["make_numbers"].state == "stale" and "scale 1.0->2.0" in status["make_numbers"].reason
    assert status["square"].state == "stale" and "input 'make_numbers' changed" in status["square"].reason
    out = runner.run(["all"])
    assert actions(out) == {"make_numbers": "ran", "square": "ran"}
    values = read_artifact(tmp_path / "toyseq" / "square" / "squares.parquet", NUMBERS)["v"].to_pylist()
    assert values == [(2.0 * i) ** 2 + 1.0 for i in range(5)]


def test_workflow_params_and_force(tmp_path: Path) -> None:
    make_runner(tmp_path, make_numbers={"count": 3}).run(["all"])
    t = read_artifact(tmp_path / "toyseq" / "make_numbers" / "numbers.parquet", NUMBERS)
    assert t.num_rows == 3
    out = make_runner(tmp_path, make_numbers={"count": 3}).run(["square"], force=["square"])
    assert actions(out) == {"make_numbers": "cached", "square": "ran"}


def test_failing_stage_keeps_previous_result_and_leaves_no_temp(tmp_path: Path) -> None:
    make_runner(tmp_path).run(["all"])
    stage_dir = tmp_path / "toyseq" / "square"
    before = {p.name: p.read_bytes() for p in stage_dir.iterdir()}
    with pytest.raises(StagesFailed, match="stage 'square' failed: boom midway") as err:
        make_runner(tmp_path, {"square": {"fail_midway": True}}).run(["all"])
    assert {o.stage: o.action for o in err.value.outcomes} == {"make_numbers": "cached", "square": "failed"}
    assert not err.value.user_error
    with pytest.raises(RuntimeError, match="boom midway"):
        make_runner(tmp_path, {"square": {"fail_midway": True}}).run(["all"], keep_going=False)
    after = {p.name: p.read_bytes() for p in stage_dir.iterdir()}
    assert after == before
    assert not list((tmp_path / "toyseq").glob(".tmp-*"))
    # the previous result is still valid for the old parameters
    assert actions(make_runner(tmp_path).run(["all"])) == {"make_numbers": "cached", "square": "cached"}


def test_interrupted_commit_is_repaired(tmp_path: Path) -> None:
    make_runner(tmp_path).run(["all"])
    seq_dir = tmp_path / "toyseq"
    # simulate a crash between the two renames of a commit, plus a leftover temp folder
    (seq_dir / "square").rename(seq_dir / ".old-square-deadbeef")
    (seq_dir / ".tmp-square-12345678").mkdir()
    out = make_runner(tmp_path).run(["all"])
    assert actions(out) == {"make_numbers": "cached", "square": "cached"}
    assert not list(seq_dir.glob(".old-*")) and not list(seq_dir.glob(".tmp-*"))


def test_lock_refuses_a_second_concurrent_run(tmp_path: Path) -> None:
    store = RunStore(tmp_path, "toyseq")
    store.seq_dir.mkdir(parents=True)
    script = textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        from pipeline.store import RunStore
        with RunStore(Path({str(tmp_path)!r}), "toyseq").lock():
            print("locked", flush=True)
            sys.stdin.readline()
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[1])
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "locked"
        with pytest.raises(LockHeldError, match=r"sequence 'toyseq' is being run by another process \(pid \d+"):
            make_runner(tmp_path).run(["all"])
    finally:
        assert proc.stdin is not None
        proc.stdin.write("\n")
        proc.stdin.flush()
        proc.wait(timeout=30)
    # released: runs now
    assert actions(make_runner(tmp_path).run(["all"]))["square"] == "ran"


def test_unknown_names_in_overrides_and_workflows(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"unknown parameter 'square.ofset'; did you mean 'square.offset'\?"):
        make_runner(tmp_path, {"square": {"ofset": 1.0}})
    with pytest.raises(UserError, match=r"workflow .*unknown stage 'sqare'; did you mean 'square'\?"):
        make_runner(tmp_path, sqare={"offset": 1.0})
    with pytest.raises(UserError, match=r"--set: make_numbers.count=0: Input should be greater than or equal to 1"):
        make_runner(tmp_path, {"make_numbers": {"count": 0}}).run(["all"])
    with pytest.raises(UserError, match=r"unknown stage 'sqaure'; did you mean 'square'\?"):
        make_runner(tmp_path).run(["sqaure"])


def test_unavailable_stage_is_skipped_in_all_and_refused_by_name(tmp_path: Path) -> None:
    reg = toy_stages.registry()

    class NeedsMissingModule(Square):
        requires = ("a_module_that_does_not_exist_xyz",)
        requires_extra = "learn"

    reg["square"] = NeedsMissingModule()
    runner = Runner(SEQ, tmp_path, reg, toy_stages.workflow())
    out = runner.run(["all"])
    assert actions(out) == {"square": "skipped", "make_numbers": "ran"}
    assert "needs a_module_that_does_not_exist_xyz, not installed (the 'learn' extra: pip install -e '.[learn]', " \
           "or make demo)" in out[0].reason
    with pytest.raises(UserError, match="stage 'square' cannot run: needs"):
        Runner(SEQ, tmp_path, reg, toy_stages.workflow()).run(["square"])
