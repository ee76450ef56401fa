"""Executors: process pool and Ray give the same results; failures and killed workers stay contained."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from core.errors import UserError
from pipeline.executors import Executor, LocalExecutor, RunTask, make_executor, run_all
from pipeline.sequences import SequenceInfo
from schemas import read_artifact
from tests.toy_stages import NUMBERS, workflow_file

REGISTRY = "tests.toy_stages:registry"


def tasks(tmp_path: Path, runs: Path, points: list[dict]) -> list[RunTask]:
    wf = str(workflow_file(tmp_path))
    return [RunTask(SequenceInfo(name=f"seq{i}", kind="source", source=tmp_path), str(runs), ("all",), (),
                    overrides, wf, registry=REGISTRY) for i, overrides in enumerate(points)]


SWEEP = [{"make_numbers": {"scale": s}, "square": {"offset": o}} for s in (1.0, 2.0) for o in (0.0, 0.5)]


def squares(runs: Path, n: int) -> list[list[float]]:
    return [read_artifact(runs / f"seq{i}" / "square" / "squares.parquet", NUMBERS)["v"].to_pylist() for i in range(n)]


def test_inline_and_process_pool_agree(tmp_path: Path) -> None:
    a = run_all(tasks(tmp_path, tmp_path / "a", SWEEP), Executor())
    b = run_all(tasks(tmp_path, tmp_path / "b", SWEEP), LocalExecutor(2))
    assert all(r.ok for r in a + b), [r.error for r in a + b]
    assert [r.name for r in b] == [f"seq{i}" for i in range(4)]
    assert squares(tmp_path / "a", 4) == squares(tmp_path / "b", 4)
    assert squares(tmp_path / "a", 4)[3] == [(2.0 * i) ** 2 + 0.5 for i in range(5)]
    # the pool ran in other processes
    assert {r.worker for r in b} - {f"pid {os.getpid()}"}


def test_process_pool_shares_out_blas_threads(tmp_path: Path) -> None:
    import json

    res = run_all(tasks(tmp_path, tmp_path / "r", SWEEP[:2]), LocalExecutor(2, threads_per_worker=1))
    assert all(r.ok for r in res), [r.error for r in res]
    for i in range(2):
        stats = json.loads((tmp_path / "r" / f"seq{i}" / "make_numbers" / "manifest.json").read_text())["stats"]
        assert stats["blas_threads"] == 1
    assert LocalExecutor(2).threads == max(1, (os.cpu_count() or 1) // 2)


def test_ray_gives_identical_metrics(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    local = run_all(tasks(tmp_path, tmp_path / "local", SWEEP), LocalExecutor(2))
    ray_results = run_all(tasks(tmp_path, tmp_path / "ray", SWEEP), make_executor("ray", workers=2))
    assert all(r.ok for r in local + ray_results), [r.error for r in local + ray_results]
    assert squares(tmp_path / "local", 4) == squares(tmp_path / "ray", 4)


def test_failing_sequence_reports_and_others_finish(tmp_path: Path) -> None:
    points = [{}, {"square": {"fail_midway": True}}, {"make_numbers": {"count": 0}}, {"make_numbers": {"scale": 3.0}}]
    res = run_all(tasks(tmp_path, tmp_path / "runs", points), LocalExecutor(2))
    assert [r.ok for r in res] == [True, False, False, True]
    assert res[1].error_kind == "bug" and "boom midway" in (res[1].error or "")
    assert res[2].error_kind == "user" and "make_numbers.count=0" in (res[2].error or "")
    assert not (tmp_path / "runs" / "seq1" / "square").exists()
    assert not list((tmp_path / "runs" / "seq1").glob(".tmp-*"))


def test_killed_worker_leaves_previous_result(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    first = run_all(tasks(tmp_path, runs, [{}, {}]), LocalExecutor(2))
    assert all(r.ok for r in first)
    good = (runs / "seq0" / "square" / "squares.parquet").read_bytes()
    points = [{"square": {"offset": 1.0, "kill_midway": True}}, {"square": {"offset": 1.0}}]
    res = run_all(tasks(tmp_path, runs, points), LocalExecutor(2))
    assert not res[0].ok and res[0].error == "worker died (signal 9)"
    assert res[1].ok
    assert (runs / "seq0" / "square" / "squares.parquet").read_bytes() == good
    assert list((runs / "seq0").glob(".tmp-square-*"))  # the killed worker's partial output, not in place
    again = run_all(tasks(tmp_path, runs, [{}]), Executor())
    assert again[0].ok and {o.action for o in again[0].outcomes} == {"cached"}
    assert not list((runs / "seq0").glob(".tmp-*"))  # cleaned up under the lock


def test_concurrent_runs_of_one_sequence_are_refused(tmp_path: Path) -> None:
    wf = str(workflow_file(tmp_path))
    seq = SequenceInfo(name="same", kind="source", source=tmp_path)
    slow = {"make_numbers": {"sleep_s": 3.0}}
    ts = [RunTask(seq, str(tmp_path / "runs"), ("all",), (), slow, wf, registry=REGISTRY, label=f"t{i}")
          for i in range(2)]
    res = run_all(ts, LocalExecutor(2))
    assert sorted(r.ok for r in res) == [False, True]
    failed = next(r for r in res if not r.ok)
    assert failed.error_kind == "user" and "is being run by another process" in (failed.error or "")


def test_reuse_links_matching_results(tmp_path: Path) -> None:
    base = tmp_path / "base"
    run_all(tasks(tmp_path, base, [{}]), Executor())
    point = tasks(tmp_path, tmp_path / "point", [{"square": {"offset": 2.0}}])[0]
    from dataclasses import replace

    res = run_all([replace(point, reuse_from=(str(base),))], Executor())[0]
    assert {o.stage: o.action for o in res.outcomes} == {"make_numbers": "reused", "square": "ran"}
    a = base / "seq0" / "make_numbers" / "numbers.parquet"
    b = tmp_path / "point" / "seq0" / "make_numbers" / "numbers.parquet"
    assert os.path.samefile(a, b)


def test_unknown_executor() -> None:
    with pytest.raises(UserError, match="--executor rya: unknown executor; did you mean 'ray'"):
        make_executor("rya")


DRIVER = """
import sys
from pathlib import Path
from pipeline.executors import LocalExecutor, RunTask, run_all
from pipeline.sequences import SequenceInfo
tmp, runs = Path(sys.argv[1]), sys.argv[2]
ts = [RunTask(SequenceInfo(name=f"seq{i}", kind="source", source=tmp), runs, ("all",), (),
              {"make_numbers": {"count": 6, "sleep_s": 120.0}}, str(tmp / "toy.toml"),
              registry="tests.toy_stages:registry") for i in range(2)]
try:
    run_all(ts, LocalExecutor(2))
except KeyboardInterrupt:
    sys.exit(130)
sys.exit(0)
"""


def test_ctrl_c_stops_the_process_pool_and_keeps_previous_results(tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys
    import time

    runs = tmp_path / "runs"
    assert all(r.ok for r in run_all(tasks(tmp_path, runs, [{}, {}]), Executor()))
    before = [(runs / f"seq{i}" / "make_numbers" / "numbers.parquet").read_bytes() for i in range(2)]
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen([sys.executable, "-c", DRIVER, str(tmp_path), str(runs)], cwd=root,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        while len(list(runs.glob("seq*/.tmp-make_numbers-*"))) < 2:  # both workers are inside the stage
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert time.monotonic() - t0 < 30  # the workers were stopped, not waited for (they sleep 120 s)
    assert "Traceback" not in err
    for i in range(2):
        seq = runs / f"seq{i}"
        assert (seq / "make_numbers" / "numbers.parquet").read_bytes() == before[i]
        assert not [p.name for p in seq.iterdir() if p.name.startswith((".tmp-", ".old-"))]
