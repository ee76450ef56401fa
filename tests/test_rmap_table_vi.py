"""Table VI over several run stores (one per a_test): ``experiments.rmap_table_vi``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core import map_metrics as mm
from experiments.rmap_table_vi import main
from schemas import write_artifact


def _store(root: Path, a: float, n_patches: int, shift: float) -> None:
    """One evaluated map sequence (arpg_lab_run0) whose completed map is off by ``shift``."""
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 4, size=(200, 3))
    seq = root / "rmap_arpg_lab_run0"
    for stage in ("patches", "complete", "evaluate"):
        (seq / stage).mkdir(parents=True)
    recs = [("radar_map", k, v) for k, v in mm.map_metrics(gt[::3] + 0.05, gt).items()]
    recs += [("completed_map", k, v) for k, v in mm.map_metrics(gt[::2] + shift, gt).items()]
    write_artifact({"seq": [seq.name] * len(recs), "method": [r[0] for r in recs], "metric": [r[1] for r in recs],
                    "value": np.array([r[2] for r in recs])}, seq / "evaluate" / "metrics.parquet", "metrics")
    (seq / "patches" / "manifest.json").write_text(json.dumps({"params": {"a": a}, "stats": {"n_seeds": n_patches}}))
    (seq / "complete" / "manifest.json").write_text(json.dumps(
        {"stats": {"n_patches": n_patches, "model_seconds": 0.5 * n_patches, "device": "cpu"}}))


def test_table_vi_rows_come_from_each_store(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _store(tmp_path / "a1", 1.0, 3, 0.20)
    _store(tmp_path / "a4", 4.0, 12, 0.01)
    out = tmp_path / "t6.md"
    assert main([str(tmp_path / "a1"), str(tmp_path / "a4"), "--out", str(out)]) == 0
    rows = {tuple(c.strip() for c in line.split("|")[1:3]): line for line in out.read_text().splitlines()
            if line.startswith("| ")}
    ours1, ours4 = rows[("1", "ours")], rows[("4", "ours")]
    assert "| 3 |" in ours1 and "| 12 |" in ours4  # total patches of each store
    cd1 = float(ours1.split("|")[5])  # CD-l2 column
    cd4 = float(ours4.split("|")[5])
    assert cd1 > cd4  # the store with the worse completed map has the larger CD-l2
    assert "– | – | – |" in rows[("2", "ours")]  # no store at a = 2
    assert capsys.readouterr().out.count("| ours |") == 4  # a = 1, 2, 4, 8


def test_a_store_without_map_sequences_is_a_one_line_error(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().out
    assert "no evaluated map sequences" in err and len(err.strip().splitlines()) == 1
