"""Radar-only workflow against the default one on the demo (target: within 1.3x of `make demo`).

Both run every stage from an empty run store on the same simulated log (simulated once into a temporary
data cache first, so neither pays for the simulation): ``pipeline run all --seq demo`` (what ``make demo``
runs) and ``pipeline run all --seq demo --workflow radar_only``. ``--quick``: a 15 s log of the demo world
instead of the registered 60 s sequence.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from benchmarks.common import Result
from benchmarks.common import run_pipeline as _cli


def run(quick: bool = False) -> list[Result]:
    with tempfile.TemporaryDirectory(prefix="bench_radar_only_") as tmp:
        t = Path(tmp)
        env = {**os.environ, "RADAR_PIPELINE_CACHE": str(t / "cache")}
        if quick:
            bag = t / "demo15.bag"
            _cli(["simulate", "--world", "demo", "--out", str(bag), "--duration", "15", "--seed", "0"], env)
            src = ["--source", str(bag), "--seq", "demo15", "--set", "slam.n_particles=50"]
        else:
            src = ["--seq", "demo"]
            _cli(["run", "ingest", *src, "--runs-dir", str(t / "warm")], env)  # simulate into the cache once
        default = _cli(["run", "all", *src, "--runs-dir", str(t / "default")], env)
        radar_only = _cli(["run", "all", *src, "--runs-dir", str(t / "radar_only"), "--workflow", "radar_only"], env)
    log = "15 s demo log" if quick else "the demo sequence (60 s)"
    return [
        Result("radar_only", "run all, default workflow (make demo)", default, "s", note=log),
        Result("radar_only", "run all --workflow radar_only", radar_only, "s", "default workflow, same run",
               radar_only / default, "<= 1.3", log),
    ]
