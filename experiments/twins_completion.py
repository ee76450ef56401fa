"""Does completion improve the simulated twins' radar maps?

For each twin run folder (``voxel/`` with ``radar_map``, ``lidar_map`` and ``map_trajectory``, and
``complete/completed_map`` of the default UpPoinTr completion; e.g. the ``trajectory=groundtruth`` point of
``pipeline sweep sweep_radar_only``): the radar map, the UpPoinTr map, and the voxel model alone and united with
the band-filtered radar map (as ``complete.model = voxel`` runs it), each scored against the lidar map with the
evaluate stage's ``map_metrics`` at 0.15 m.

Usage: ``python -m experiments.twins_completion RUNS/sweeps/sweep_radar_only/trajectory=groundtruth
[--checkpoint data/models/rmap_voxel.safetensors] [--out rows.json]``; prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

MAPS = ("radar", "uppointr", "voxel alone", "voxel+radar")
FIELDS = ("cd_l1", "cd_l2", "fscore_0.15", "precision_0.15", "recall_0.15")


def _points(path: Path) -> np.ndarray:
    import pyarrow.parquet as pq

    if not path.exists():
        raise SystemExit(f"{path}: missing; run the voxel and complete stages on this sequence first")
    t = pq.read_table(path)
    return np.column_stack([t[c].to_numpy() for c in "xyz"]).astype(np.float64)


def score_twin(run: Path, model: Any, meta: Any) -> dict[str, dict[str, float]]:
    """Every map of one twin against its lidar map."""
    from core.map_metrics import map_metrics
    from stages.complete.voxel_grid import key_centres, lattice_keys, trajectory_band
    from stages.complete.voxel_net import completed_keys, predict_tiles

    radar, lidar = _points(run / "voxel" / "radar_map.parquet"), _points(run / "voxel" / "lidar_map.parquet")
    traj = _points(run / "voxel" / "map_trajectory.parquet")
    res = meta.resolution
    keys = lattice_keys(trajectory_band(radar, traj, meta.band), res, f"{run} radar map")
    pred = predict_tiles(model, keys, traj, res, meta.band)
    maps = {"radar": radar, "uppointr": _points(run / "complete" / "completed_map.parquet"),
            "voxel alone": key_centres(completed_keys(pred, meta.threshold), res),
            "voxel+radar": key_centres(completed_keys(pred, meta.threshold, keys), res)}
    out = {}
    for name, pts in maps.items():
        m = map_metrics(pts, lidar, 0.15)
        out[name] = {k: float(m[k]) for k in FIELDS} | {"n": float(len(pts))}
    return out


def table(rows: dict[str, dict[str, dict[str, float]]]) -> str:
    lines = ["| twin | " + " | ".join(MAPS) + " |", "|---" * (len(MAPS) + 1) + "|"]
    for twin, r in rows.items():
        lines.append(f"| {twin} | " + " | ".join(f"{r[m]['cd_l2']:.3f} / {r[m]['fscore_0.15']:.3f}" for m in MAPS)
                     + " |")
    mean = {m: {k: float(np.mean([r[m][k] for r in rows.values()])) for k in ("cd_l2", "fscore_0.15")} for m in MAPS}
    lines.append("| mean | " + " | ".join(f"{mean[m]['cd_l2']:.3f} / {mean[m]['fscore_0.15']:.3f}" for m in MAPS)
                 + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("point", type=Path, help="a folder of twin run folders (coloradar_N_twin)")
    ap.add_argument("--checkpoint", type=Path, default=Path("data/models/rmap_voxel.safetensors"))
    ap.add_argument("--out", type=Path, help="write the rows as JSON here")
    a = ap.parse_args(argv)
    from stages.complete.voxel_checkpoint import load_voxel_checkpoint

    model, meta = load_voxel_checkpoint(a.checkpoint)
    twins = sorted(p for p in a.point.glob("coloradar_*_twin") if p.is_dir())
    if not twins:
        raise SystemExit(f"{a.point}: no coloradar_N_twin run folders")
    rows = {t.name: score_twin(t, model, meta) for t in twins}
    print(table(rows))
    if a.out:
        a.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
