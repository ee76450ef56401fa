"""What each real-radar effect of the drifting twins does to the radar map, on RMap *train* scenes.

For each train scene named, the radar-only twin of :mod:`experiments.twins_tune_radar`
(walked at its ``WALK_SPEED``, seed 7, the map built as the voxel stage builds the twins') with the twins'
tuned radar (``TWIN_RADAR``), then with each effect of ``data/twins/drift.toml``'s ``[radar]`` alone, then all
of them (the drifting twins' radar): L/R, CD-l1, CD-l2, F@0.15 against the real ``lidar_filtered`` map, beside
the authors' real radar map. The six twins' own scenes are refused (they only check).

Usage: ``RMAP_ROOT=... python -m experiments.twins_radar_effects aspen_run9 [--max-seconds 40]``; prints Markdown.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from experiments.twins_tune_radar import TWIN_SCENES, _metrics, radar_map, train_scene

COLUMNS = ("n_radar", "lr_ratio", "cd_l1", "cd_l2", "fscore_0.15")


def variants(drift_radar: dict[str, float]) -> dict[str, dict[str, float]]:
    """The radar settings compared: the tuned twins' radar, each effect alone, all (the drifting twins')."""
    from simulator.params import REALISM_FIELDS
    from simulator.twin import TWIN_RADAR

    base = dict(TWIN_RADAR) | {k: v for k, v in drift_radar.items() if k not in REALISM_FIELDS}
    out = {"tuned twin radar (TWIN_RADAR)": base}
    loss = {"multipath_ghost_loss_db": drift_radar.get("multipath_ghost_loss_db", 12.0)}
    for k in ("multipath_ghost_share", "doppler_outlier_share", "elevation_noise_deg"):
        if drift_radar.get(k):
            out[f"+ {k} = {drift_radar[k]:g}"] = base | {k: drift_radar[k]} | loss
    out["all (the drifting twins' radar)"] = dict(drift_radar)
    return out


def main(argv: list[str]) -> int:
    from simulator.simulate import Simulation
    from simulator.twin import TwinParams, twin_world, variant_params

    ap = argparse.ArgumentParser(prog="python -m experiments.twins_radar_effects", description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--variant", default="drift", help="twin variant whose [radar] effects are compared")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--max-seconds", type=float, default=0.0, help="simulate only the first seconds (0: all)")
    a = ap.parse_args(argv)
    bad = [s for s in a.scenes if s in TWIN_SCENES]
    if bad:
        print(f"error: {', '.join(bad)}: a twin's own scene (ColoRadar 1-6); use RMap's train scenes",
              file=sys.stderr)
        return 2
    root = Path(os.environ.get("RMAP_ROOT", ""))
    lines = ["| scene | radar | " + " | ".join(COLUMNS) + " | seconds |", "|" + "---|" * (len(COLUMNS) + 3)]
    for scene in a.scenes:
        loaded = train_scene(root, scene, a.max_seconds)
        if loaded is None:
            return 2
        ms, full, dur = loaded
        real = _metrics(ms.radar, ms.lidar_filtered)
        lines.append(f"| {scene} | real radar (authors) | " + " | ".join(
            f"{real[c]:.0f}" if c == "n_radar" else f"{real[c]:.3f}" for c in COLUMNS) + " | |")
        pts = ms.lidar if ms.lidar is not None else ms.lidar_filtered
        for label, radar in variants(variant_params(a.variant).radar).items():
            t0 = time.perf_counter()
            world = twin_world(scene, pts, ms.trajectory, duration=full, params=TwinParams(radar=radar))
            r = _metrics(radar_map(Simulation(world, dur, a.seed, workers=1)), ms.lidar_filtered)
            lines.append(f"| {scene} | {label} | " + " | ".join(
                f"{r[c]:.0f}" if c == "n_radar" else f"{r[c]:.3f}" for c in COLUMNS)
                + f" | {time.perf_counter() - t0:.0f} |")
            print(lines[-1], file=sys.stderr, flush=True)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
