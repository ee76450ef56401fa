"""The command line: exit codes and one-line errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, **(env or {}), "COLUMNS": "200"}, timeout=120)


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
