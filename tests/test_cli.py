"""The command line: exit codes and one-line errors."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from pipeline.config import describe_params
from pipeline.registry import load_stages
from pipeline.sequences import SequenceInfo, load_registry

ROOT = Path(__file__).resolve().parents[1]


def cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "COLUMNS": "200", **(env or {})}, timeout=120)


def test_user_errors_exit_2_with_one_line() -> None:
    r = cli("status", "--seq", "dmeo")
    assert r.returncode == 2
    assert "unknown sequence 'dmeo'; did you mean 'demo'?" in r.stderr
    assert "Traceback" not in r.stderr
    r = cli("run", "slam", "--seq", "demo", "--set", "slma.n_particles=5")
    assert r.returncode == 2 and "did you mean 'slam'?" in r.stderr
    r = cli("run", "slam")
    assert r.returncode == 2 and "--seq is required" in r.stderr
    r = cli("run", "all", "--source", "/does/not/exist.bag")
    assert r.returncode == 2 and "--source /does/not/exist.bag: no such file or folder" in r.stderr


def test_usage_error_exits_2_and_help_exits_0() -> None:
    assert cli("frobnicate").returncode == 2
    assert cli("--help").returncode == 0
    assert cli("run", "--help").returncode == 0


def test_sequences_and_status_list_everything(tmp_path: Path) -> None:
    r = cli("sequences")
    assert r.returncode == 0
    for name in ("demo", "coloradar_4"):
        assert name in r.stdout
    r = cli("status", "--seq", "demo", "--runs-dir", str(tmp_path))
    assert r.returncode == 0
    for stage in ("ingest", "filter", "odometry", "slam", "voxel", "patches", "complete", "evaluate", "plan"):
        assert stage in r.stdout


def test_coloradar_without_data_is_a_clear_error(tmp_path: Path) -> None:
    r = cli("run", "ingest", "--seq", "coloradar_4", "--runs-dir", str(tmp_path),
            env={"COLORADAR_ROOT": str(tmp_path)})
    assert r.returncode == 2 and "Traceback" not in r.stderr
    # until ingest lands the stage refuses; afterwards the message names what it looked for
    assert "coloradar_4" in r.stderr or "not implemented yet" in r.stderr


def test_view_headless_prints_the_command(tmp_path: Path) -> None:
    d = tmp_path / "s" / "ingest"
    d.mkdir(parents=True)
    (d / "ingest.rrd").write_bytes(b"")
    r = cli("view", "--seq", "s", "--runs-dir", str(tmp_path), env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    assert r.returncode == 0 and "rerun " in r.stdout and "ingest.rrd" in r.stdout
    r = cli("view", "--seq", "nothing", "--runs-dir", str(tmp_path))
    assert r.returncode == 2 and "no .rrd recordings" in r.stderr


@dataclass
class Ran:
    returncode: int
    stdout: str
    stderr: str


@pytest.fixture
def main(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> Callable[..., Ran]:
    """``pipeline ARGS`` through the console entry point in this process (no interpreter start-up per call)."""
    from pipeline import cli as cli_module

    def call(*args: str, env: dict[str, str] | None = None, columns: int = 200) -> Ran:
        for key, value in (env or {}).items():
            monkeypatch.setenv(key, value)
        monkeypatch.setattr(sys, "argv", ["pipeline", *args])
        for con in (cli_module.out, cli_module.console):
            monkeypatch.setattr(con, "_width", columns)
        capsys.readouterr()
        code: object = 0
        try:
            cli_module.main()
        except SystemExit as exc:
            code = exc.code
        cap = capsys.readouterr()
        return Ran(code if isinstance(code, int) else 1, cap.out, cap.err)

    return call


def _tokens(text: str) -> set[str]:
    """Whole words of a listing or table (split at spaces and table borders)."""
    return set(re.split(r"[\s│┃┏┓┗┛┡┩━─┳╇]+", text))


def _data_column(info: SequenceInfo) -> list[str]:
    """The words of the data column (``where()`` may name two alternatives: ``A or B``)."""
    return info.where().split()


@pytest.mark.parametrize("columns", [80, 200])
def test_sequences_never_cut_names_or_paths(tmp_path: Path, main: Callable[..., Ran], columns: int) -> None:
    root = tmp_path / ("a_long_folder_name_for_the_coloradar_data_" * 2)
    root.mkdir()
    r = main("sequences", env={"COLORADAR_ROOT": str(root)}, columns=columns)
    assert r.returncode == 0, r.stderr
    words = _tokens(r.stdout)
    for info in load_registry().values():
        assert info.name in words
        for part in _data_column(info):
            assert part in words, part
    assert "…" not in r.stdout


@pytest.mark.parametrize("columns", [80, 200])
def test_params_never_cut_parameter_names(main: Callable[..., Ran], columns: int) -> None:
    r = main("params", columns=columns)
    assert r.returncode == 0, r.stderr
    words = _tokens(r.stdout)
    for stage in load_stages().values():
        for name, *_ in describe_params(stage):
            assert f"{stage.name}.{name}" in words
    assert "…" not in r.stdout


def test_view_prints_one_pasteable_line(tmp_path: Path, main: Callable[..., Ran]) -> None:
    runs = tmp_path / ("runs_in_a_deliberately_long_folder_name_" * 2)
    files = []
    for stage in ("ingest", "filter", "odometry"):
        d = runs / "s" / stage
        d.mkdir(parents=True)
        files.append(d / f"{stage}.rrd")
        files[-1].write_bytes(b"")
    r = main("view", "--seq", "s", "--runs-dir", str(runs), env={"DISPLAY": "", "WAYLAND_DISPLAY": ""}, columns=80)
    assert r.returncode == 0, r.stderr
    (line,) = r.stdout.splitlines()
    assert shlex.split(line) == ["rerun", *map(str, files)]  # in pipeline order


def test_bad_runs_dir_is_a_one_line_user_error(tmp_path: Path, main: Callable[..., Ran]) -> None:
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    for args in (["run", "ingest", "--seq", "demo"], ["status", "--seq", "demo"], ["view", "--seq", "demo"],
                 ["export", "--seq", "demo", "--format", "tum"]):
        r = main(*args, "--runs-dir", str(afile), columns=80)
        assert r.returncode == 2, (args, r.stderr)
        assert f"--runs-dir {afile}: is a file, not a folder" in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = main("run", "ingest", "--seq", "demo", "--runs-dir", str(afile / "runs"))
    assert r.returncode == 2 and f"--runs-dir {afile / 'runs'}: cannot write there (Not a directory)" in r.stderr
    r = main("run", "ingest", "--seq", "demo", env={"RADAR_PIPELINE_RUNS": str(afile)})
    assert r.returncode == 2 and f"$RADAR_PIPELINE_RUNS {afile}: is a file" in r.stderr
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o555)
        r = main("run", "ingest", "--seq", "demo", "--runs-dir", str(ro))
        assert r.returncode == 2 and "cannot write there (Permission denied)" in r.stderr
    # the same through a real process: exit status 2, one line, no traceback
    r2 = cli("run", "ingest", "--seq", "demo", "--runs-dir", str(afile))
    assert r2.returncode == 2 and r2.stderr.strip().splitlines() == [
        f"error: --runs-dir {afile}: is a file, not a folder; name a folder (it is created if missing)"]


def test_failed_sequences_of_a_multi_sequence_run_set_the_exit_code(tmp_path: Path, main: Callable[..., Ran]) -> None:
    # typer hands `raise typer.Exit(2)` back as a return value without standalone mode; it must not become 0
    r = main("run", "ingest", "--seq", "coloradar_1,coloradar_2", "--workers", "1", "--runs-dir", str(tmp_path),
             env={"COLORADAR_ROOT": str(tmp_path)})
    assert r.returncode == 2, r.stderr
    assert "coloradar_1: failed" in r.stderr and "coloradar_2: failed" in r.stderr


def test_a_repeated_seq_adds_sequences_and_a_one_sequence_command_refuses_it(tmp_path: Path) -> None:
    """``--seq a --seq b`` means both (it once ran only b, silently); view and export take one and say so."""
    r = cli("status", "--seq", "demo", "--seq", "demo_drift,sim_hallway_loop", "--runs-dir", str(tmp_path))
    assert r.returncode == 0
    titles = re.findall(r"^([a-z_]+)\b(?! +│)", r.stdout + r.stderr, re.MULTILINE)  # a table title (may wrap)
    assert titles == ["demo", "demo_drift", "sim_hallway_loop"]
    r = cli("run", "slam", "--seq", "demo", "--seq", "dmeo", "--runs-dir", str(tmp_path))
    assert r.returncode == 2 and "unknown sequence 'dmeo'" in r.stderr  # the first is not run alone
    assert not (tmp_path / "demo").exists()
    for args in (["view"], ["export", "--format", "tum"]):
        r = cli(*args, "--seq", "demo", "--seq", "demo_drift", "--runs-dir", str(tmp_path))
        assert r.returncode == 2 and r.stderr.count("\n") == 1
        assert f"pipeline {args[0]} works on one sequence; --seq was given 2 times (demo, demo_drift)" in r.stderr
    r = cli("report", "--seqs", "demo", "--seqs", "demo_drift", "--runs-dir", str(tmp_path))
    assert r.returncode == 2 and "no evaluation results for demo, demo_drift in" in r.stderr
