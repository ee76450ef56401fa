"""Figure: how the fused estimate's scale is chosen (stages/slam/map_consistency.py), against the truth.

One panel per kept filter trajectory (``table3 --keep``): over the scales ``alpha`` of the fusion's heading
correction that the fused estimate searches, the criterion of the scale along each recomposed trajectory (what
chooses, relative to the odometry's, ``alpha = 0``) and the trajectory's whole-trajectory yaw RMSE against
the ground truth (what it should have chosen); the chosen scale and the error's minimum marked. Usage::

    python -m stages.slam.consistency_figure RUN KEPT.npz [RUN KEPT.npz ...] --rows ROWS.jsonl --out F.png

``--rows`` and ``--set`` as in :mod:`fusion_figure` (each panel's fusion model is its fused row's).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stages.slam.fusion_figure import figure_main, panel_model, save_png
from stages.slam.heading_fusion import fuse_heading, recompose
from stages.slam.map_consistency import consistent_scale, stacked_endpoints
from stages.slam.stage import SlamParams
from stages.slam.table3 import error_fields, load_inputs


def build_panel(run_dir: Path, kept_path: Path, rows: dict[tuple[str, str, int], dict[str, Any]],
                overrides: dict[str, Any]) -> dict[str, Any]:
    """One panel: the scores and the yaw RMSE over the searched scales of one kept smoothed trajectory."""
    kept = np.load(kept_path)
    label, seed = str(kept["label"]).split(",")[0], int(kept["seed"])
    row = rows.get((run_dir.name, f"{label}, fused", seed))
    params = SlamParams(**overrides)
    t_ns, odo, scans, truth, motion = load_inputs(run_dir, params)
    if not np.array_equal(t_ns, kept["t_ns"]):
        raise ValueError(f"{kept_path}: its scan stamps are not those of {run_dir}/odometry")
    model = panel_model(row, overrides)
    consistency = params.config().consistency
    if consistency.alpha_max <= 0:
        raise ValueError("slam.fusion_alpha_max is 0: no scale is searched; set it above 0")
    t = np.cumsum(motion.dt)
    correction = fuse_heading(t, odo[:, 2], kept["pose"][:, 2], motion.cov[:, 2, 2], model).correction
    points, scan = stacked_endpoints(scans)
    choice = consistent_scale(odo, correction, points, scan, t, consistency)
    yaw = np.array([error_fields(t_ns, np.asarray(recompose(odo, a * correction), np.float64),
                                 truth)["yaw_rmse_whole_deg"] for a in choice.alphas])
    return {"title": f"{run_dir.name}: {label} seed {seed}", "alphas": choice.alphas,
            "scores": choice.scores / choice.scores[0] if choice.scores[0] > 0 else choice.scores,
            "yaw": yaw, "alpha": choice.alpha}


def draw(out: Path, panels: list[dict[str, Any]], columns: int = 3) -> None:
    """Panels in a grid (relative score on the left axis, yaw RMSE on the right), written to a temporary name,
    then renamed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_rows = -(-len(panels) // columns)
    fig, axes = plt.subplots(n_rows, columns, figsize=(4.2 * columns, 2.9 * n_rows), squeeze=False)
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    for ax, p in zip(axes.flat, panels, strict=False):
        ax.plot(p["alphas"], p["scores"], color="tab:blue", marker="o", ms=3, lw=1.2)
        ax.axvline(p["alpha"], color="tab:blue", lw=0.8, ls="--")
        ax.set_ylabel("criterion / odometry's (lower: more consistent)", color="tab:blue", fontsize=8)
        ax.set_xlabel("scale alpha of the fused correction (0: odometry, 1: fused)", fontsize=8)
        right = ax.twinx()
        right.plot(p["alphas"], p["yaw"], color="tab:red", marker="s", ms=3, lw=1.2)
        best = int(np.argmin(p["yaw"]))
        right.plot([p["alphas"][best]], [p["yaw"][best]], color="tab:red", marker="*", ms=11, ls="none")
        right.set_ylabel("yaw RMSE, deg (truth)", color="tab:red", fontsize=8)
        chosen = int(np.argmin(np.abs(p["alphas"] - p["alpha"])))
        ax.set_title(f"{p['title']}\nchosen alpha {p['alpha']:.3g}: {p['yaw'][chosen]:.2f} deg (odometry "
                     f"{p['yaw'][0]:.2f}, best {p['yaw'][best]:.2f})", fontsize=8)
        ax.grid(alpha=0.3)
    save_png(fig, out, 100)


def main(argv: list[str] | None = None) -> int:
    return figure_main("consistency_figure", __doc__ or "", build_panel, draw, argv)


if __name__ == "__main__":
    raise SystemExit(main())
