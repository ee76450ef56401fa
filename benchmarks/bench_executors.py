"""Speed-up of the local executor with 2 workers over 1 on the four built-in sequences.

Ingest is brought up to date once in a warm store; each measured run then recomputes the stages
downstream of it (``filter``, ``odometry``, ``voxel``: about 30-40 s of work per sequence) in a fresh
store, reusing ingest through hard links, so both runs do the same work and only the parallelism
differs. With 2 workers each worker gets one BLAS thread (the cores shared out); 1 worker runs in
process with the library default.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from benchmarks.common import Result
from pipeline.executors import LocalExecutor, RunTask, run_all
from pipeline.sequences import load_registry

SEQUENCES = ("demo", "sim_hallway_loop", "sim_outdoor_open", "sim_cluttered_lab")
TARGETS = ("filter", "odometry", "voxel")


def run(quick: bool = False) -> list[Result]:
    registry = load_registry()
    seqs = [registry[s] for s in SEQUENCES]
    root = Path(tempfile.mkdtemp(prefix="bench-executors-"))
    warm = root / "warm"
    prep = run_all([RunTask(s, str(warm), ("ingest",)) for s in seqs], LocalExecutor(2))
    failed = [r for r in prep if not r.ok]
    if failed:
        return [Result("executors", "speed-up 2 workers / 1", float("nan"), "x",
                       note=f"ingest failed for {failed[0].name}: {failed[0].error}")]
    times = {}
    for workers in (1, 2):
        tasks = [RunTask(s, str(root / f"w{workers}"), TARGETS, reuse_from=(str(warm),)) for s in seqs]
        t0 = time.perf_counter()
        res = run_all(tasks, LocalExecutor(workers))
        times[workers] = time.perf_counter() - t0
        bad = [r for r in res if not r.ok]
        if bad:
            return [Result("executors", "speed-up 2 workers / 1", float("nan"), "x",
                           note=f"{bad[0].name} failed: {bad[0].error}")]
    return [
        Result("executors", f"{' + '.join(TARGETS)} on 4 sequences, 1 worker", times[1], "s"),
        Result("executors", f"{' + '.join(TARGETS)} on 4 sequences, 2 workers", times[2], "s"),
        Result("executors", "speed-up 2 workers / 1", times[1] / times[2], "x", reference="1 worker, same run",
               ratio=times[1] / times[2], target="close to 2 on 2 free cores",
               note=f"{os.cpu_count()} CPUs; spawned process per sequence"),
    ]
