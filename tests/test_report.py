"""`pipeline report`: gathering several runs' evaluate metrics into one comparison."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.errors import UserError
from pipeline.report import build_tables, comparison_table, gather, resolve_sequences, to_markdown, write_outputs
from schemas import read_artifact, write_artifact

ROOT = Path(__file__).resolve().parents[1]


def write_metrics(runs: Path, seq: str, rows: list[tuple[str, str, str, float, int]]) -> Path:
    d = runs / seq / "evaluate"
    d.mkdir(parents=True, exist_ok=True)
    return write_artifact({
        "seq": [seq] * len(rows), "section": [r[0] for r in rows], "method": [r[1] for r in rows],
        "metric": [r[2] for r in rows], "value": np.array([r[3] for r in rows]),
        "features": np.array([r[4] for r in rows], np.int32)}, d / "metrics.parquet", "metrics")


def rows_for(k: float) -> list[tuple[str, str, str, float, int]]:
    return [
        ("trajectory", "odometry", "ate_pos_rmse_m", 2.0 * k, 0),
        ("trajectory", "odometry", "ate_yaw_rmse_deg", 9.0, 0),
        ("trajectory", "rich_slam", "ate_pos_rmse_m", 0.5 * k, 0),
        ("trajectory", "rich_slam", "ate_yaw_rmse_deg", 3.0, 0),
        ("trajectory", "groundtruth", "length_m", 40.0, 0), ("trajectory", "groundtruth", "duration_s", 60.0, 0),
        ("mapping", "hilbert_gp", "auc", 0.91, 256), ("mapping", "rff", "auc", 0.81, 256),
        ("mapping", "hilbert_gp@64", "auc", 0.88, 64), ("mapping", "rff@64", "auc", 0.77, 64),
        ("mapping", "grid", "auc", 0.7, 0),
        ("rmap", "radar_map", "cd_l1", 0.3, 0), ("rmap", "radar_map", "cd_l2", 0.2, 0),
        ("rmap", "radar_map", "fscore_0.15", 0.25, 0), ("rmap", "radar_map", "ddist_p50", 0.1, 0),
        ("rmap", "radar_map", "lr_ratio", 4.2, 0),
    ]


@pytest.fixture
def runs(tmp_path: Path) -> Path:
    r = tmp_path / "runs"
    write_metrics(r, "seq_a", rows_for(1.0))
    write_metrics(r, "seq_b", rows_for(2.0))
    (r / "seq_c").mkdir()  # a run without evaluation
    return r


def test_gather_and_tables(runs: Path) -> None:
    seqs = resolve_sequences("seq_*", runs)
    assert seqs == ["seq_a", "seq_b", "seq_c"]
    records, missing = gather(runs, seqs)
    assert missing == ["seq_c"] and {r["seq"] for r in records} == {"seq_a", "seq_b"}
    tables = {t[0].split(" (")[0].split(":")[0]: t for t in build_tables(records)}
    _, headers, rows = tables["Trajectories"]
    assert headers == ["method", "seq_a", "seq_b"]
    by = {r[0]: r for r in rows}
    assert by["odometry"][1:] == ["2.00 / 9.00", "4.00 / 9.00"]
    assert by["rich_slam"][1:] == ["0.50 / 3.00", "1.00 / 3.00"]
    assert by["length / duration"][1] == "40.0 m, 60 s"
    auc = next(t for t in build_tables(records) if t[0].startswith("Occupancy AUC per"))
    assert auc[1] == ["sequence", "method \\ features", "64"]
    assert ["seq_a", "hilbert_gp", "0.880"] in auc[2]
    md = to_markdown(records)
    assert "| rich_slam | 0.50 / 3.00 | 1.00 / 3.00 |" in md and "radar_map" in md
    assert comparison_table(runs, ["seq_a", "seq_b"]) is not None
    assert comparison_table(runs, ["seq_c"]) is None


def test_write_outputs_round_trip(runs: Path, tmp_path: Path) -> None:
    records, _ = gather(runs, ["seq_a", "seq_b"])
    md, pq = write_outputs(records, tmp_path / "cmp" / "table.md", "Comparison")
    back = read_artifact(pq, "metrics").to_pylist()
    assert len(back) == len(records) and md.read_text().startswith("# Comparison")


def test_uncertainty_figure_across_sequences(runs: Path, tmp_path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from pipeline.report import uncertainty_curves, write_figures

    for i, seq in enumerate(("seq_a", "seq_b")):
        d = runs / seq / "slam"
        d.mkdir(parents=True)
        t = np.arange(5, dtype=np.int64) * 2_000_000_000 + 10**12
        med = np.linspace(1.0, 0.1 * (i + 1), 5)
        pq.write_table(pa.table({"scan": np.arange(5, dtype=np.int32), "t_ns": t, "u_p25": med / 2, "u_p50": med,
                                 "u_p75": np.minimum(med * 1.5, 1.0)}), d / "map_stats.parquet")
    curves = uncertainty_curves(runs, ["seq_a", "seq_b", "seq_c"])
    assert set(curves) == {"seq_a", "seq_b"}
    assert np.allclose(curves["seq_b"][:, 0], [0, 2, 4, 6, 8]) and curves["seq_b"][-1, 2] == pytest.approx(0.2)
    records, _ = gather(runs, ["seq_a", "seq_b"])
    written = write_figures(runs, records, tmp_path / "cmp.md")
    assert [p.name for p in written] == ["cmp_auc.png", "cmp_uncertainty.png"]


def test_bad_names(runs: Path) -> None:
    with pytest.raises(UserError, match="no run folders match"):
        resolve_sequences("nothing_*", runs)


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "COLUMNS": "200"}, timeout=120)


def test_report_command(runs: Path, tmp_path: Path) -> None:
    r = cli("report", "--seqs", "seq_a,seq_b,seq_c", "--runs-dir", str(runs), "--out", str(tmp_path / "r.md"))
    assert r.returncode == 0, r.stderr
    assert "0.50 / 3.00" in r.stdout and "1.00 / 3.00" in r.stdout and "Table III" in r.stdout
    assert "seq_c: no evaluation" in r.stderr
    assert (tmp_path / "r.md").exists() and (tmp_path / "r.parquet").exists()
    assert (tmp_path / "r_auc.png").stat().st_size > 1000  # Fig. 6 across the sequences
    r = cli("report", "--seqs", "seq_c", "--runs-dir", str(runs))
    assert r.returncode == 2 and "pipeline run evaluate --seq seq_c" in r.stderr and "Traceback" not in r.stderr
    r = cli("report", "--runs-dir", str(runs))
    assert r.returncode == 2 and "--seqs is required" in r.stderr
