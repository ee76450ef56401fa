"""Simulator: generation time and size of the built-in sequences, and the fan ray caster's speed-up.

- ``demo`` bag generation (60 s simulated; 10 s with ``--quick``), wall seconds; ratio = generation time /
  simulated time (the real-time factor; < 1 is faster than real time). Target: well under a minute.
- every registered simulated sequence (not with ``--quick``): generation seconds, size in MB, radar
  points per scan (median, p05, p95 in the note).
- lidar ray casting, rays/s: one Ouster-like sweep (256 columns x 16 beams) cast as fans (one 2D solve per
  column) against the reference of the same rays cast one by one (one group per ray) in the same run.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import Result, best_time

AREA = "simulator"


def _size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files) / 1e6


def _generate(world: str, duration: float, seed: int, fmt: str, tmp: Path) -> tuple[float, float, dict]:
    from simulator import sidecar_path, simulate_to

    t0 = time.perf_counter()
    out = simulate_to(world, tmp / world, duration=duration, seed=seed, fmt=fmt)
    seconds = time.perf_counter() - t0

    meta = json.loads((sidecar_path(out) / "meta.json").read_text())
    size = _size_mb(out)
    if out.is_dir():
        shutil.rmtree(out)
    else:
        out.unlink()
        shutil.rmtree(sidecar_path(out))
    return seconds, size, meta["stats"]


def _note(size: float, stats: dict) -> str:
    pps, lab = stats["points_per_scan"], stats["labels"]
    return (f"{size:.1f} MB; radar points/scan p05 {pps['p05']:g}, median {pps['median']:g}, p95 {pps['p95']:g}; "
            f"labels surface/clutter/ghost {lab['surface']}/{lab['clutter']}/{lab['ghost']}")


def _raycast(results: list[Result]) -> None:
    from simulator.lidar import beam_elevations, column_azimuths
    from simulator.params import LidarParams
    from simulator.raycast import cast
    from simulator.world import load_world

    w = load_world("cluttered_lab")
    p = LidarParams()
    az = column_azimuths(p)
    el = np.tan(beam_elevations(p))
    o = np.tile([0.0, -1.5, 1.1], (len(az), 1))
    h = np.column_stack([np.cos(az), np.sin(az)])
    n = len(az) * len(el)
    fan = best_time(lambda: cast(w.scene, o, h, el[None, :], 100.0), repeat=5)
    o1 = np.repeat(o, len(el), axis=0)
    h1 = np.repeat(h, len(el), axis=0)
    m1 = np.tile(el, len(az))[:, None]
    per_ray = best_time(lambda: cast(w.scene, o1, h1, m1, 100.0), repeat=5)
    a = cast(w.scene, o, h, el[None, :], 100.0).range.ravel()
    b = cast(w.scene, o1, h1, m1, 100.0).range
    assert np.allclose(a, b.ravel(), equal_nan=True)
    results.append(Result(AREA, "lidar sweep ray casting (fans)", n / fan, "rays/s", reference="one group per ray",
                          ratio=per_ray / fan, note=f"{n} rays, cluttered_lab, {fan * 1e3:.1f} ms per sweep"))


def run(quick: bool = False) -> list[Result]:
    from pipeline.sequences import load_registry

    results: list[Result] = []
    tmp = Path(tempfile.mkdtemp(prefix="bench-sim-"))
    try:
        duration = 10.0 if quick else 60.0
        seconds, size, stats = _generate("demo", duration, 0, "bag", tmp)
        results.append(Result(AREA, f"demo {duration:g} s bag generation", seconds, "s", reference="simulated time",
                              ratio=seconds / duration, target="well under 60 s for 60 s", note=_note(size, stats)))
        if not quick:
            for seq in load_registry().values():
                if seq.kind != "simulated" or seq.name == "demo" or seq.scene:  # twins: bench_twins.py
                    continue
                assert seq.world is not None
                seconds, size, stats = _generate(seq.world, seq.duration, seq.seed, seq.format, tmp)
                results.append(Result(
                    AREA, f"{seq.name} ({seq.world}, {seq.duration:g} s {seq.format})", seconds, "s",
                    reference="simulated time", ratio=seconds / seq.duration, note=_note(size, stats),
                ))
        _raycast(results)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return results
