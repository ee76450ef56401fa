"""Faults that must end in a one-line error (exit 2) or a clean recovery, with nothing lost: a full disk, clock
jumps and pauses, empty or NaN radar, a log without lidar, damaged artifacts, unbounded or mistyped parameters,
stale reports, an unwritable report path, and ``--source`` on every command that reads a run."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import Field, ValidationError

from core.errors import UserError
from core.stage import Stage, StageContext, StageParams
from pipeline.config import build_params, parse_set
from pipeline.registry import load_stages
from pipeline.runner import Runner, StagesFailed
from pipeline.sequences import SequenceInfo
from pipeline.store import RunStore
from simulator import log_faults, rig
from tests import toy_stages
from tests.toy_stages import MakeNumbers, Square

ROOT = Path(__file__).resolve().parents[1]
SEQ = SequenceInfo(name="toyseq", kind="source", source=Path("/nonexistent"))


# -- toy stages -----------------------------------------------------------------------------------------------
class BigParams(StageParams):
    points: int = Field(10, ge=1, le=10_000_000, description="points logged to the recording")


class BigRecording(Stage):
    """Writes a tiny Parquet file and a recording as large as asked (to fill a disk with the .rrd)."""

    name = "big"
    Params = BigParams
    outputs = ("numbers.parquet",)

    def run(self, ctx: StageContext) -> None:
        from schemas import write_artifact

        write_artifact({"i": np.arange(3, dtype=np.int32), "v": np.zeros(3)}, ctx.output("numbers.parquet"),
                       toy_stages.NUMBERS)
        rng = np.random.default_rng(0)
        n = ctx.params.points
        for k in range(0, n, 20_000):
            m = min(20_000, n - k)
            ctx.recording.points_over_time("world/radar/raw", [k], None, rng.random((m, 3)), [m])


class Huge(BigRecording):
    name = "huge"

    def memory_estimate(self, seq: Any, params: Any, input_dirs: Any) -> tuple[int, str]:
        return 1 << 60, "huge.points=10 x a petabyte each"


def registry() -> dict[str, Stage]:
    reg = toy_stages.registry()
    reg.update({"big": BigRecording(), "huge": Huge()})
    return reg


def make_runner(runs: Path, overrides: dict[str, dict[str, Any]] | None = None) -> Runner:
    wf = toy_stages.workflow()
    return Runner(SEQ, runs, registry(), wf, overrides or {})


def _lock_is_free(runs: Path) -> bool:
    with RunStore(runs, SEQ.name).lock():
        return True


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    """A 1 MB tmpfs (root only; skipped where mounting is not allowed)."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root); the ENOSPC tests below cover the same paths")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


# -- 1. a full disk -------------------------------------------------------------------------------------------
def test_a_full_disk_while_writing_the_recording_is_one_line_and_keeps_the_previous_result(tiny_disk: Path) -> None:
    runs = tiny_disk / "runs"
    make_runner(runs, {"big": {"points": 10}}).run(["big"])
    before = (runs / SEQ.name / "big" / "manifest.json").read_text()
    with pytest.raises(StagesFailed) as info:
        make_runner(runs, {"big": {"points": 400_000}}).run(["big"])  # ~5 MB of points into 1 MB
    assert info.value.user_error
    message = str(info.value.first)
    assert "the disk is full under" in message and "nothing was lost" in message and "\n" not in message
    assert (runs / SEQ.name / "big" / "manifest.json").read_text() == before
    assert RunStore(runs, SEQ.name).damage("big", checksums=True) is None
    assert not list((runs / SEQ.name).glob(".tmp-*"))
    assert _lock_is_free(runs)


def test_enospc_from_the_recording_or_a_parquet_writer_is_a_user_error(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import pyarrow.parquet as pq

    make_runner(tmp_path).run(["make_numbers"])
    before = (tmp_path / SEQ.name / "make_numbers" / "manifest.json").read_text()

    def full(*args: Any, **kwargs: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    # the recording is written with Path.write_bytes when the stage closes it; Parquet by pyarrow
    for target, attr in ((Path, "write_bytes"), (pq, "write_table")):
        with monkeypatch.context() as m:
            m.setattr(target, attr, full)
            with pytest.raises(StagesFailed) as info:
                make_runner(tmp_path, {"make_numbers": {"count": 7}}).run(["make_numbers"])
        assert info.value.user_error and "the disk is full" in str(info.value.first)
        assert (tmp_path / SEQ.name / "make_numbers" / "manifest.json").read_text() == before
        assert _lock_is_free(tmp_path)


# -- 4, 5. parameters -----------------------------------------------------------------------------------------
def test_size_parameters_are_bounded_and_a_bool_is_not_a_number() -> None:
    reg = load_stages()
    with pytest.raises(UserError, match=r"slam.n_particles=10000000: Input should be less than or equal to"):
        build_params(reg["slam"], [("--set", parse_set(["slam.n_particles=10000000"], reg)["slam"])])
    with pytest.raises(UserError, match=r"--set: slam.n_particles=true: a bool where a number is expected"):
        build_params(reg["slam"], [("--set", parse_set(["slam.n_particles=true"], reg)["slam"])])
    with pytest.raises(ValidationError, match="a bool where a number is expected"):
        reg["slam"].Params.model_validate({"n_particles": True})
    assert build_params(reg["slam"], [("--set", {"n_particles": 7})]).n_particles == 7  # type: ignore[attr-defined]
    # every int parameter of every stage has an upper bound, every float resolution a floor
    for stage in reg.values():
        for name, f in stage.Params.model_fields.items():
            if f.annotation in (int, int | None) and name != "seed":
                assert any(hasattr(m, "le") or hasattr(m, "lt") for m in f.metadata), f"{stage.name}.{name}"


def test_a_run_whose_memory_estimate_exceeds_the_machine_is_refused_before_it_starts(tmp_path: Path) -> None:
    with pytest.raises(StagesFailed) as info:
        make_runner(tmp_path).run(["huge"])
    message = str(info.value.first)
    assert info.value.user_error and "would need about" in message and "huge.points" in message
    assert not (tmp_path / SEQ.name / "huge").exists()


def test_slam_estimates_its_particle_maps() -> None:
    slam = load_stages()["slam"]
    p = slam.Params.model_validate({"n_particles": 100_000, "methods": ["rich_slam"], "method": "rich_slam"})
    need, what = slam.memory_estimate(SEQ, p, {}) or (0, "")
    assert need == 2 * 100_000 * (256 * 256 + 512) * 8 and "slam.n_particles=100000" in what
    small = slam.memory_estimate(SEQ, slam.Params(), {})
    assert small is not None and small[0] < 1 << 30


# -- 6. damaged artifacts -------------------------------------------------------------------------------------
@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_a_damaged_cached_result_is_reported_and_rerun(tmp_path: Path, damage: str) -> None:
    make_runner(tmp_path).run(["all"])
    path = tmp_path / SEQ.name / "make_numbers" / "numbers.parquet"
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    else:
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(data)
    runner = make_runner(tmp_path)
    status = {s.stage: s for s in runner.status()}
    if damage == "truncate":
        assert status["make_numbers"].state == "damaged" and "bytes, the manifest recorded" in status[
            "make_numbers"].reason
    out = {o.stage: o.action for o in make_runner(tmp_path).run(["all"])}
    assert out["make_numbers"] == "ran"
    assert RunStore(tmp_path, SEQ.name).damage("make_numbers", checksums=True) is None
    assert MakeNumbers.calls == 1 and Square.calls == 0  # the rebuilt result has the same key: square is current


# -- 3. stale report rows ---------------------------------------------------------------------------------------
def test_stale_rows_name_the_upstream_results_rerun_since(tmp_path: Path) -> None:
    from pipeline.report import stale_rows

    make_runner(tmp_path).run(["all"])
    assert stale_rows(tmp_path, [SEQ.name], stage="square") == {}
    make_runner(tmp_path, {"make_numbers": {"scale": 3.0}}).run(["make_numbers"])
    why = stale_rows(tmp_path, [SEQ.name], stage="square")[SEQ.name]
    assert "computed from 'make_numbers' result(s) rerun since" in why


# -- 10. report --out where nothing can be written ----------------------------------------------------------------
def cli(*args: str, cwd: Path = ROOT, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "COLUMNS": "250"}
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=timeout)


def _fake_evaluation(runs: Path, seq: str) -> None:
    """An evaluate result as the stage writes it (one metric row), with a manifest naming its slam input."""
    from schemas import write_artifact

    for stage, inputs in (("slam", {}), ("evaluate", {"slam": "k-slam"})):
        d = runs / seq / stage
        d.mkdir(parents=True)
        if stage == "evaluate":
            write_artifact({"seq": [seq], "method": ["odometry"], "metric": ["yaw_rmse_deg"], "value": np.array([1.0]),
                            "features": np.array([0], np.int32), "section": ["whole"]},
                           d / "metrics.parquet", "metrics")
        (d / "manifest.json").write_text(json.dumps({"complete": True, "key": f"k-{stage}", "inputs": inputs,
                                                     "artifacts": {}}))


def test_report_out_that_cannot_be_written_is_exit_2_and_stale_rows_are_said(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    _fake_evaluation(runs, "toyseq")
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    r = cli("report", "--seqs", "toyseq", "--runs-dir", str(runs), "--out", str(blocker / "report.md"))
    assert r.returncode == 2 and "--out" in r.stderr and "cannot write there" in r.stderr, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    # the slam result is replaced: the report says the evaluate row is stale, in the terminal and the file
    (runs / "toyseq" / "slam" / "manifest.json").write_text(json.dumps(
        {"complete": True, "key": "k-slam-2", "inputs": {}, "artifacts": {},
         "timings": {"finished_at": "2026-01-01T00:00:00+00:00"}}))
    r = cli("report", "--seqs", "toyseq", "--runs-dir", str(runs), "--out", str(tmp_path / "rep" / "r.md"))
    assert r.returncode == 0, r.stderr[-2000:]
    assert "stale" in r.stderr and "'slam' result(s) rerun since" in r.stderr
    assert "toyseq**: computed from 'slam'" in (tmp_path / "rep" / "r.md").read_text()


# -- 2, 7, 8, 9. logs -----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def short_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from simulator import simulate_to

    out = tmp_path_factory.mktemp("bags") / "short.bag"
    return simulate_to("demo", out, duration=6.0, seed=1)


@pytest.mark.parametrize("fault", ["radar_jump", "pause_all"])
def test_a_clock_jump_or_pause_is_an_error_with_its_times(short_bag: Path, tmp_path: Path, fault: str) -> None:
    bad = tmp_path / f"{fault}.bag"
    if fault == "radar_jump":
        log_faults.clock_jump(short_bag, bad, after_s=3.0, jump_s=7200.0, topics=[rig.RADAR_TOPIC])
    else:
        log_faults.pause_all(short_bag, bad, after_s=3.0, pause_s=7200.0)
    r = cli("run", "all", "--source", str(bad), "--runs-dir", str(tmp_path / "runs"))
    assert r.returncode == 2, r.stderr[-3000:]
    line = r.stderr.strip().splitlines()[-1]
    assert "no radar points for 7200" in line and "from 3.0 s" in line and "ingest.clock.max_gap_s" in line, line
    assert not (tmp_path / "runs" / fault / "ingest").exists()  # nothing half-written, nothing downstream


@pytest.mark.parametrize("fill", ["empty", "nan"])
def test_radar_scans_all_empty_or_nan_name_the_topic(short_bag: Path, tmp_path: Path, fill: str) -> None:
    bad = log_faults.radar_points(short_bag, tmp_path / f"{fill}.bag", fill)
    r = cli("run", "all", "--source", str(bad), "--runs-dir", str(tmp_path / "runs"))
    assert r.returncode == 2, r.stderr[-3000:]
    line = r.stderr.strip().splitlines()[-1]
    assert f"radar topic '{rig.RADAR_TOPIC}'" in line and "empty or hold only NaN" in line, line
    assert "Traceback" not in r.stderr


def test_a_radar_imu_coloradar_bag_runs_with_the_default_profile_and_source_works_everywhere(
        short_bag: Path, tmp_path: Path) -> None:
    bag = log_faults.drop_topics(short_bag, tmp_path / "radar_imu.bag", [rig.TF_STATIC_TOPIC, rig.IMU_TOPIC,
                                                                         rig.RADAR_TOPIC])
    runs = str(tmp_path / "runs")
    r = cli("run", "odometry", "--source", str(bag), "--runs-dir", runs)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "no lidar topic" in r.stderr
    r = cli("status", "--source", str(bag), "--runs-dir", runs)
    assert r.returncode == 0 and "radar_imu" in r.stdout, r.stderr[-2000:]
    rows = {ln.split()[1]: ln for ln in r.stdout.splitlines() if ln.startswith("│")}
    assert all("done" in rows[s] for s in ("ingest", "filter", "odometry")), r.stdout
    r = cli("view", "--source", str(bag), "--runs-dir", runs)
    assert r.returncode == 0 and "odometry.rrd" in r.stdout, r.stderr[-2000:]
    r = cli("export", "--source", str(bag), "--runs-dir", runs, "--format", "tum", "--out", str(tmp_path / "tum"))
    assert r.returncode == 0 and (tmp_path / "tum" / "odometry.tum").exists(), r.stderr[-2000:]
    r = cli("report", "--source", str(bag), "--runs-dir", runs)
    assert r.returncode == 2 and "no evaluation results for radar_imu" in r.stderr, r.stderr[-2000:]
