"""ColoRadar twins: simulation time per second of log in a real voxel map.

- ``coloradar_6_twin`` (edgar_classroom_run3, the largest twin: 275 s, 301 m, 326 k map voxels): the whole
  log written as a ColoRadar bag (20 s with ``--quick``), wall seconds per second of log; the world build
  (map read, carving, grid, clearance transform, scatterers) separately.
- voxel ray casting, rays/s: one lidar sweep (256 columns x 16 beams) from a pose of that path, fans through
  :func:`simulator.raycast.cast` (vectorised DDA with empty-space skipping).

The maps come from ``$RMAP_ROOT`` or, when unset, ``../shared/data/coloradar_maps`` beside the checkout;
without either the area reports nothing.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import Result, best_time

AREA = "twins"
SEQ = "coloradar_6_twin"


def _maps_root() -> Path | None:
    env = os.environ.get("RMAP_ROOT")
    if env:
        return Path(env)
    shared = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "coloradar_maps"
    return shared if shared.is_dir() else None


def run(quick: bool = False) -> list[Result]:
    from pipeline.sequences import load_registry
    from simulator import write_run
    from simulator.lidar import beam_elevations, column_azimuths
    from simulator.params import LidarParams, RadarParams
    from simulator.raycast import cast
    from simulator.simulate import Simulation
    from sources.simulated import twin_world_of

    root = _maps_root()
    if root is None:
        print("bench_twins: no maps (set RMAP_ROOT); skipped")
        return []
    os.environ.setdefault("RMAP_ROOT", str(root))
    seq = load_registry()[SEQ]
    duration = 20.0 if quick else seq.duration
    results: list[Result] = []
    t0 = time.perf_counter()
    world = twin_world_of(seq)
    Simulation(world, duration, seq.seed)  # scatterers are drawn here
    build = time.perf_counter() - t0
    scat = world.scatterers(RadarParams(), np.random.default_rng(0))
    results.append(Result(AREA, f"{SEQ} world build", build, "s",
                          note=f"{int(world.grid.occupied.sum())} voxels, grid {world.grid.shape}, "
                               f"{len(scat.pt_pos)} scatterers"))
    tmp = Path(tempfile.mkdtemp(prefix="bench-twins-"))
    try:
        t0 = time.perf_counter()
        stats = write_run(world, tmp / f"{SEQ}.bag", duration, seq.seed, "bag")
        seconds = time.perf_counter() - t0
        size = sum(p.stat().st_size for p in tmp.rglob("*") if p.is_file()) / 1e6
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    pps = stats["points_per_scan"]
    results.append(Result(AREA, f"{SEQ} simulation ({duration:g} s of log, bag)", seconds / duration,
                          "s per s of log", reference="real time", ratio=seconds / duration,
                          target="the 275 s log in minutes",
                          note=f"{seconds:.0f} s in all, {size:.0f} MB; radar points/scan median {pps['median']:g}"))
    p = LidarParams()
    az, el = column_azimuths(p), np.tan(beam_elevations(p))
    st = world.trajectory.state(np.array([duration / 2]))
    o = np.tile(st.position[0] + [0.0, 0.0, 0.1], (len(az), 1))
    h = np.column_stack([np.cos(az), np.sin(az)])
    sweep = best_time(lambda: cast(world.scene, o, h, el[None, :], p.max_range), repeat=5)
    n = len(az) * len(el)
    results.append(Result(AREA, "voxel lidar sweep ray casting", n / sweep, "rays/s",
                          note=f"{n} rays, {SEQ} map, {sweep * 1e3:.1f} ms per sweep"))
    return results
