"""Tune the twins' radar model on RMap's *train* scenes.

For each train scene named, a twin (:func:`simulator.twin.twin_world`, the scene's ``lidar`` map, its recorded
path) is simulated for its radar only and the radar OctoMap is built along the simulated ground truth the way
the voxel stage builds it for the twins (``voxel.occupancy.radar_prob_miss = 0.5``: every fan voxel holding a return is
occupied; :func:`radar_map`), then measured against the scene's real ``lidar_filtered`` map beside the
authors' real radar map: L/R, CD-l2, F@0.15, D-Dist p50 / p90 (:func:`core.map_metrics.map_metrics`).

A train scene has no paper duration: it is walked at :data:`WALK_SPEED` (the median 2D speed of RICH-SLAM's six
ColoRadar runs, path length over the paper's duration: 0.55, 1.05, 0.99, 1.10, 0.81, 1.10 m/s), optionally
only its first ``--max-seconds``.

The search space is a small grid (:data:`GRID`; ``--trials`` runs a subset by index, seed fixed); each trial's
numbers go to a CSV row. The twins' tuning (docs/twins_radar_trials.csv, README "ColoRadar twins") ran 16
of its 90 combinations in three rounds, each chosen after the previous one: clutter rate x SNR at the 200-point
cap; the cap at 50; the cap at 100 with clutter rate, clutter strength and SNR.
The pick (:func:`pick`): the trial with the smallest mean over the scenes of
``|log(L/R_sim / L/R_real)| + |log(CD-l2_sim / CD-l2_real)|`` (as sparse and as noisy as the real radar, in
ratio terms). The twins' own scenes (RICH-SLAM's ColoRadar 1-6) are refused, so they only check.

Usage: ``RMAP_ROOT=... python -m experiments.twins_tune_radar --out trials.csv arpg_lab_run2 aspen_run9 ...``
"""

from __future__ import annotations

import argparse
import csv
import itertools
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

#: median 2D walking speed of RICH-SLAM's six ColoRadar runs (m/s, see the module doc)
WALK_SPEED = 1.0
#: the candidate values per tuned RadarParams field (every combination is a trial; the first is the default)
GRID: dict[str, tuple[float, ...]] = {
    "clutter_rate": (3.0, 20.0, 50.0),
    "snr_ref_db": (84.5, 80.5, 76.5, 70.5, 64.5),
    "max_points": (200, 100, 50),
    "clutter_snr_scale_db": (2.0, 15.0),
}
METRICS = ("n_radar", "lr_ratio", "cd_l2", "fscore_0.15", "ddist_p50", "ddist_p90")
TWIN_SCENES = ("aspen_run0", "outdoors_run0", "edgar_classroom_run0", "ec_hallways_run0", "arpg_lab_run0",
               "edgar_classroom_run3")


def radar_map(sim: Any, resolution: float = 0.15, fov_deg: float = 45.0, max_range: float = 10.0) -> np.ndarray:
    """Occupied voxel centres (N, 3) of the radar map of ``sim`` (a :class:`simulator.simulate.Simulation`).

    The voxel stage with ``radar_prob_miss = 0.5`` (a miss changes nothing): every voxel holding a return inside
    the fan (|azimuth|, |elevation| <= ``fov_deg``, range <= ``max_range``) of some scan, the scan placed at the
    ground-truth pose of its stamp with the stated radar extrinsic (as ingest and the voxel stage do).
    """
    from simulator import rig
    from stages.voxel.voxel_map import coord_to_key, key_to_coord

    T_br = rig.BASE_TO_RADAR.matrix()
    keys: list[np.ndarray] = []
    tan = np.tan(np.radians(fov_deg))
    for k in range(sim.n_windows):
        for scan in sim.radar_scans(k):
            p = np.column_stack([scan.points[c].astype(np.float64) for c in ("x", "y", "z")])
            r = np.linalg.norm(p, axis=1)
            ok = ((p[:, 0] > 0) & (np.abs(p[:, 1]) <= tan * p[:, 0])
                  & (np.abs(p[:, 2]) <= tan * np.hypot(p[:, 0], p[:, 1])) & (r <= max_range))
            st = sim.traj.state(np.array([scan.t]))
            T_wb = np.eye(4)
            T_wb[:3, :3] = st.rotation.as_matrix()[0]
            T_wb[:3, 3] = st.position[0]
            T = T_wb @ T_br
            keys.append(coord_to_key(p[ok] @ T[:3, :3].T + T[:3, 3], resolution))
    if not keys:
        return np.zeros((0, 3))
    return np.asarray(key_to_coord(np.unique(np.concatenate(keys), axis=0), resolution), np.float64)


def score(sim_row: dict[str, float], real_row: dict[str, float]) -> float:
    """The pick's loss on one scene: ``|log(L/R ratio)| + |log(CD-l2 ratio)|`` of simulated over real."""
    return float(abs(np.log(sim_row["lr_ratio"] / real_row["lr_ratio"]))
                 + abs(np.log(sim_row["cd_l2"] / real_row["cd_l2"])))


def pick(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The trial (``trial`` key) with the smallest mean :func:`score` over its scenes (rows carry ``score``)."""
    by: dict[int, list[float]] = {}
    for r in rows:
        by.setdefault(int(r["trial"]), []).append(float(r["score"]))
    best = min(by, key=lambda t: (float(np.mean(by[t])), t))
    return {"trial": best, "mean_score": float(np.mean(by[best]))}


def trials(grid: dict[str, tuple[float, ...]]) -> list[dict[str, float]]:
    """Every combination of the grid's values, in a fixed order (trial 0: the first value of each)."""
    names = list(grid)
    return [dict(zip(names, vals, strict=True)) for vals in itertools.product(*(grid[n] for n in names))]


def read_trials(paths: list[Path]) -> list[dict[str, Any]]:
    """Rows of trial CSVs (several runs of this script), each renumbered by its values in the current
    :data:`GRID` (a column missing from an older CSV: that field's first grid value, the model default)."""
    index = {tuple(t.values()): i for i, t in enumerate(trials(GRID))}
    out: list[dict[str, Any]] = []
    for path in paths:
        with path.open(newline="") as fh:
            for r in csv.DictReader(fh):
                vals = tuple(float(r[k]) if k in r else GRID[k][0] for k in GRID)
                out.append({**r, **dict(zip(GRID, vals, strict=True)), "trial": index[vals],
                            "score": float(r["score"])})
    return out


def _metrics(radar: np.ndarray, lidar_f: np.ndarray) -> dict[str, float]:
    from core.map_metrics import lr_ratio, map_metrics

    m = map_metrics(radar, lidar_f)
    return {"n_radar": float(len(radar)), "lr_ratio": lr_ratio(lidar_f, radar), **m}


def train_scene(root: Path, scene: str, max_seconds: float) -> tuple[Any, float, float] | None:
    """A train scene's map set, the seconds its whole path takes at :data:`WALK_SPEED` and the seconds simulated
    (``max_seconds`` > 0 cuts it); None, with the error on stderr, for a scene outside RMap's train split."""
    from sources.mapset import read_map_set

    ms = read_map_set(root, scene)
    if ms.split != "train":
        print(f"error: {scene}: split '{ms.split}', not a train scene of RMap's split", file=sys.stderr)
        return None
    full = float(np.linalg.norm(np.diff(ms.trajectory[:, :2], axis=0), axis=1).sum()) / WALK_SPEED
    return ms, full, min(full, max_seconds) if max_seconds > 0 else full


def _pick_main(paths: list[Path]) -> int:
    """Print the best trial among those run on every scene of the CSVs."""
    rows = read_trials(paths)
    names = {r["scene"] for r in rows}
    done = [r for r in rows if {q["scene"] for q in rows if q["trial"] == r["trial"]} == names]
    best = pick(done)
    print(f"{len({r['trial'] for r in done})} trials on all of {sorted(names)}; best: trial {best['trial']} "
          f"{trials(GRID)[best['trial']]}, mean score {best['mean_score']:.3f}")
    return 0


def main(argv: list[str]) -> int:
    from simulator.simulate import Simulation
    from simulator.twin import TwinParams, twin_world

    ap = argparse.ArgumentParser(prog="python -m experiments.twins_tune_radar", description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="*")
    ap.add_argument("--pick", type=Path, nargs="+", default=[], help="only pick from these trial CSVs: the best "
                    "trial among those run on every scene of the CSVs")
    ap.add_argument("--out", type=Path, default=Path("twins_radar_trials.csv"))
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--max-seconds", type=float, default=0.0, help="simulate only the first seconds (0: all)")
    ap.add_argument("--trials", default="", help="comma-separated trial numbers to run (default: all)")
    a = ap.parse_args(argv)
    if a.pick:
        return _pick_main(a.pick)
    if not a.scenes:
        ap.error("name at least one train scene (or --pick CSV ...)")
    bad = [s for s in a.scenes if s in TWIN_SCENES]
    if bad:
        print(f"error: {', '.join(bad)}: a twin's own scene (ColoRadar 1-6); tune on RMap's train scenes only",
              file=sys.stderr)
        return 2
    root = Path(os.environ.get("RMAP_ROOT", ""))
    all_trials = trials(GRID)
    run = [int(t) for t in a.trials.split(",")] if a.trials else list(range(len(all_trials)))
    rows: list[dict[str, Any]] = []
    new = not a.out.exists()
    with a.out.open("a", newline="") as fh:
        w = csv.writer(fh)
        if new:
            w.writerow(["scene", "trial", *GRID, "duration_s", "seconds", "score",
                        *(f"sim_{m}" for m in METRICS), *(f"real_{m}" for m in METRICS)])
        scenes: list[tuple[str, Any, float, float, dict[str, float]]] = []
        for scene in a.scenes:
            loaded = train_scene(root, scene, a.max_seconds)
            if loaded is None:
                return 2
            ms, full, dur = loaded
            scenes.append((scene, ms, full, dur, _metrics(ms.radar, ms.lidar_filtered)))
        for t in run:
            for scene, ms, full, dur, real in scenes:
                t0 = time.perf_counter()
                pts = ms.lidar if ms.lidar is not None else ms.lidar_filtered
                world = twin_world(scene, pts, ms.trajectory, duration=full, params=TwinParams(radar=all_trials[t]))
                sim = Simulation(world, dur, a.seed, workers=1)
                simr = _metrics(radar_map(sim), ms.lidar_filtered)
                sc = score(simr, real)
                dt = time.perf_counter() - t0
                rows.append({"trial": t, "score": sc})
                w.writerow([scene, t, *all_trials[t].values(), round(dur, 1), round(dt, 1), round(sc, 4),
                            *(round(simr[m], 4) for m in METRICS), *(round(real[m], 4) for m in METRICS)])
                fh.flush()
                print(f"{scene} trial {t} {all_trials[t]}: L/R {simr['lr_ratio']:.2f} (real {real['lr_ratio']:.2f}) "
                      f"CD-l2 {simr['cd_l2']:.3f} ({real['cd_l2']:.3f}) F {simr['fscore_0.15']:.3f} "
                      f"({real['fscore_0.15']:.3f}) score {sc:.3f} [{dt:.0f} s]", flush=True)
    print(pick(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
