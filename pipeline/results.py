"""Reading the metric records of finished runs (``runs/<seq>/<stage>/metrics.parquet``)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from pipeline.store import RunStore

METRICS_FILE = "metrics.parquet"


def metrics_path(runs_dir: Path, seq: str, stage: str = "evaluate") -> Path:
    return RunStore(Path(runs_dir), seq).stage_dir(stage) / METRICS_FILE


def read_records(path: Path) -> list[dict[str, Any]]:
    """Records of one ``metrics.parquet`` (validated)."""
    from schemas import read_artifact

    return read_artifact(path, "metrics").to_pylist()


def gather(runs_dir: Path, seqs: Iterable[str], stage: str = "evaluate") -> tuple[list[dict[str, Any]], list[str]]:
    """All metric records of the sequences that have them, and the names of those that do not."""
    records: list[dict[str, Any]] = []
    missing: list[str] = []
    for seq in seqs:
        path = metrics_path(runs_dir, seq, stage)
        if not path.exists():
            missing.append(seq)
            continue
        recs = read_records(path)
        for r in recs:
            r["seq"] = seq  # the run folder names the sequence (a --source run may carry another name)
        records += recs
    return records, missing
