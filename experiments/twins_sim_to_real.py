"""Sim-to-real check of the radar model on the ColoRadar twins.

For each twin named: its simulated radar OctoMap (the voxel stage's ``radar_map.parquet``, built along the
twin's ground truth, after ``pipeline run voxel --seq <twin>``) and the authors' real radar map of the same
scene, both measured against the same real ``lidar_filtered`` map: L/R (RMap Table I: lidar voxels over
radar voxels), D-Dist percentiles and CD-l1 / CD-l2 (RMap Table III's input row), F-score at 0.15 m.

Usage: ``RMAP_ROOT=... python -m experiments.twins_sim_to_real coloradar_1_twin [coloradar_5_twin ...]``
(the runs are read from ``$RADAR_PIPELINE_RUNS`` or ``runs/``). Prints a Markdown table.
``python -m experiments.twins_sim_to_real --figure twins.png``: the six twins' smoothed trajectories over
their maps (top view, the map coloured by height), one figure.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

COLUMNS = ("n_radar", "lr_ratio", "ddist_p50", "ddist_p75", "ddist_p90", "ddist_p95", "cd_l1", "cd_l2",
           "fscore_0.15")


def _row(radar: np.ndarray, lidar_f: np.ndarray) -> dict[str, float]:
    from core.map_metrics import lr_ratio, map_metrics

    m = map_metrics(radar, lidar_f)
    return {"n_radar": float(len(radar)), "lr_ratio": lr_ratio(lidar_f, radar), **m}


def figure(out: Path) -> Path:
    """The six twins' trajectories (as simulated: smoothed, with the heading every 10 s) over their maps.

    Each map is drawn from above as the number of occupied voxels per 0.15 m column (log grey scale, after
    the path carving of :func:`simulator.twin.twin_world`); the PNG is palette-quantised to stay small.
    """
    from PIL import Image

    from pipeline.sequences import load_registry
    from sources.simulated import twin_world_of
    from stages.evaluate.figures import _plt

    plt = _plt()
    reg = load_registry()
    fig, axes = plt.subplots(2, 3, figsize=(15, 9.5), constrained_layout=True)
    for ax, i in zip(axes.ravel(), range(1, 7), strict=True):
        seq = reg[f"coloradar_{i}_twin"]
        w = twin_world_of(seq)
        g = w.grid
        cells = np.argwhere(g.occupied)
        cols = np.zeros(g.shape[:2])
        np.add.at(cols, (cells[:, 0], cells[:, 1]), 1.0)
        x0, y0 = g.origin[0], g.origin[1]
        x1, y1 = x0 + g.shape[0] * g.resolution, y0 + g.shape[1] * g.resolution
        ax.imshow(np.log1p(cols).T, origin="lower", extent=(x0, x1, y0, y1), cmap="Greys", interpolation="nearest")
        st = w.trajectory.state(np.linspace(0, w.duration, 2000))
        ax.plot(st.position[:, 0], st.position[:, 1], "r-", lw=1.2)
        q = w.trajectory.state(np.arange(0, w.duration, 10.0))
        fwd = q.yaw + np.pi / 2  # the rig's forward axis (base +y)
        ax.quiver(q.position[:, 0], q.position[:, 1], np.cos(fwd), np.sin(fwd), color="r", scale=25, width=0.004)
        ax.plot(*st.position[0, :2], "bo", ms=6)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(f"coloradar_{i}_twin: {seq.scene} ({w.duration:g} s)")
    fig.suptitle("ColoRadar twins: recorded path as simulated (red; arrows: heading every 10 s; blue: start) "
                 "over the lidar voxel map (grey: occupied voxels per column)")
    tmp = out.with_name(out.name + ".tmp.png")
    fig.savefig(tmp, dpi=80)
    plt.close(fig)
    Image.open(tmp).convert("RGB").quantize(colors=64).save(out.with_name(out.name + ".q.png"), optimize=True)
    tmp.unlink()
    out.with_name(out.name + ".q.png").replace(out)
    return out


def main(argv: list[str]) -> int:
    import pyarrow.parquet as pq

    from pipeline.sequences import load_registry
    from sources.mapset import read_map_set
    from sources.simulated import twin_root

    if argv[:1] == ["--figure"]:
        print(figure(Path(argv[1] if len(argv) > 1 else "twins.png")))
        return 0
    runs = Path(os.environ.get("RADAR_PIPELINE_RUNS", "runs"))
    reg = load_registry()
    lines = ["| scene | map | " + " | ".join(COLUMNS) + " |", "|" + "---|" * (len(COLUMNS) + 2)]
    for name in argv or ["coloradar_1_twin"]:
        seq = reg[name]
        scene = str(seq.scene)
        maps = read_map_set(twin_root(name, scene), scene)
        table = pq.read_table(runs / name / "voxel" / "radar_map.parquet")
        sim = np.column_stack([table.column(c).to_numpy() for c in ("x", "y", "z")]).astype(np.float64)
        for label, radar in (("real radar (authors)", maps.radar), (f"simulated ({name})", sim)):
            r = _row(radar, maps.lidar_filtered)
            vals = " | ".join(f"{r[c]:.0f}" if c == "n_radar" else f"{r[c]:.3f}" for c in COLUMNS)
            lines.append(f"| {scene} | {label} | {vals} |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
