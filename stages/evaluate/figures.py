"""The evaluation figures (matplotlib, Agg): RICH-SLAM Fig. 6, 7-style maps, 10, 11 and an RMap top view."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

METHOD_COLOURS = {
    "odometry": "tab:orange", "fastslam_grid": "tab:green", "rich_slam": "tab:red",
    "rich_slam_no_et": "tab:purple", "rich_slam_mean_only": "tab:pink", "radar_graph": "tab:blue",
    "hilbert_gp": "tab:red", "rff": "tab:blue", "sparse": "tab:green",
    "nystrom": "tab:orange", "grid": "tab:gray",
}
METHOD_LABELS = {
    "odometry": "odometry", "fastslam_grid": "FastSLAM (grid)", "rich_slam": "RICH-SLAM",
    "rich_slam_no_et": "RICH-SLAM w/o ET", "rich_slam_mean_only": "RICH-SLAM mean only",
    "radar_graph": "radar pose graph",
    "hilbert_gp": "HILBERT-GP (Kalman)", "rff": "RFF (SGD)",
    "sparse": "SPARSE (SGD)", "nystrom": "NYSTRÖM (SGD)", "grid": "count grid",
}


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def colour(method: str) -> str:
    """A method's colour; a row of one of its estimates (``"rich_slam, fused"``) takes the method's."""
    return METHOD_COLOURS.get(method, METHOD_COLOURS.get(method.split(", ")[0], "black"))


def label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def plot_trajectories(path: Path, gt_xy: F64, estimates: Mapping[str, F64], title: str = "") -> Path:
    """Fig. 11: aligned trajectories over ground truth; circles at the start, squares at the end."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 6), constrained_layout=True)
    ax.plot(gt_xy[:, 0], gt_xy[:, 1], "-", color="black", lw=2.0, label="ground truth")
    ax.plot(*gt_xy[0], "o", color="black", ms=8, mfc="none")
    ax.plot(*gt_xy[-1], "s", color="black", ms=8, mfc="none")
    for name, xy in estimates.items():
        c = colour(name)
        ax.plot(xy[:, 0], xy[:, 1], "-", color=c, lw=1.2, label=label(name))
        ax.plot(*xy[0], "o", color=c, ms=7, mfc="none")
        ax.plot(*xy[-1], "s", color=c, ms=7, mfc="none")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title or "trajectories after SE(2) alignment on the first matched frames")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_auc_vs_features(path: Path, rows: Sequence[tuple[str, int, float, float]], title: str = "",
                         reference: Mapping[str, float] | None = None) -> Path:
    """Fig. 6: AUC against the number of map features; rows are (method, features, mean, std).

    ``reference`` draws horizontal lines for feature-free methods (the count grid).
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.2), constrained_layout=True)
    methods = list(dict.fromkeys(r[0] for r in rows))
    for m in methods:
        sel = sorted((r for r in rows if r[0] == m), key=lambda r: r[1])
        x = np.array([r[1] for r in sel], float)
        y = np.array([r[2] for r in sel])
        s = np.array([r[3] for r in sel])
        ax.plot(x, y, "o-", color=colour(m), label=label(m))
        if np.any(s > 0):
            ax.fill_between(x, y - s, y + s, color=colour(m), alpha=0.15)
    for m, v in (reference or {}).items():
        ax.axhline(v, color=colour(m), ls=":", label=label(m))
    ax.set_xlabel("number of map features")
    ax.set_ylabel("AUC (held-out scans)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title or "occupancy AUC vs map features")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_map_pair(path: Path, gx: F64, gy: F64, occupancy: F64, norm_u: F64, title: str,
                  trajectory: F64 | None = None, endpoints: F64 | None = None) -> Path:
    """A Hilbert-GP map: occupancy (eq. 28) and normalised predictive uncertainty (eq. 33 / prior)."""
    plt = _plt()
    extent = (gx[0], gx[-1], gy[0], gy[-1])
    aspect = (gy[-1] - gy[0]) / max(gx[-1] - gx[0], 1e-9)
    fig, axes = plt.subplots(1, 2, figsize=(12, max(3.5, 5.5 * aspect) + 0.6), constrained_layout=True)
    for ax, img, cmap, lab in ((axes[0], occupancy, "viridis", "occupancy probability"),
                               (axes[1], norm_u, "magma", "normalised predictive uncertainty")):
        im = ax.imshow(img.T, origin="lower", extent=extent, cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.8, label=lab)
        if trajectory is not None:
            ax.plot(trajectory[:, 0], trajectory[:, 1], "-", color="tab:red", lw=1.0)
        if endpoints is not None and ax is axes[0]:
            ax.plot(endpoints[:, 0], endpoints[:, 1], ".", color="white", ms=1.0, alpha=0.5)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_uncertainty(path: Path, curves: Mapping[str, F64], title: str = "") -> Path:
    """Fig. 10 (right): median normalised predictive uncertainty over time with the 25-75 % band.

    ``curves`` maps a label to rows (t_s, p25, p50, p75).
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.0), constrained_layout=True)
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, rows) in enumerate(curves.items()):
        if len(rows) == 0:
            continue
        c = cycle[i % len(cycle)]
        ax.plot(rows[:, 0], rows[:, 2], "-", color=c, label=name)
        ax.fill_between(rows[:, 0], rows[:, 1], rows[:, 3], color=c, alpha=0.2)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("normalised predictive uncertainty")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title or "predictive uncertainty over the mapped area")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_maps_top(path: Path, clouds: Mapping[str, F64], title: str = "", max_points: int = 60000,
                  seed: int = 0) -> Path:
    """Top views of 3D maps (radar, lidar, completed) side by side, coloured by height."""
    plt = _plt()
    n = len(clouds)
    fig, axes = plt.subplots(1, n, figsize=(5.2 * n, 5), constrained_layout=True, squeeze=False)
    rng = np.random.default_rng(seed)
    allp = np.concatenate([c for c in clouds.values() if len(c)]) if any(len(c) for c in clouds.values()) else None
    for ax, (name, pts) in zip(axes[0], clouds.items(), strict=True):
        if len(pts) > max_points:
            pts = pts[rng.choice(len(pts), max_points, replace=False)]
        if len(pts):
            ax.scatter(pts[:, 0], pts[:, 1], c=pts[:, 2], s=0.3, cmap="viridis")
        if allp is not None:
            ax.set_xlim(allp[:, 0].min(), allp[:, 0].max())
            ax.set_ylim(allp[:, 1].min(), allp[:, 1].max())
        ax.set_aspect("equal")
        ax.set_title(f"{name} ({len(clouds[name])} points)")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_query_resolutions(path: Path, panels: Sequence[tuple[float, F64, F64, F64]], title: str = "") -> Path:
    """Fig. 9: one occupancy field (eq. 28) evaluated on grids of decreasing spacing, one panel each."""
    plt = _plt()
    n = len(panels)
    _, gx0, gy0, _ = panels[0]
    aspect = (gy0[-1] - gy0[0] + 1e-9) / max(gx0[-1] - gx0[0], 1e-9)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, max(3.0, 4.0 * aspect) + 0.8), squeeze=False,
                             constrained_layout=True)
    im = None
    for ax, (spacing, gx, gy, occ) in zip(axes[0], panels, strict=True):
        h = spacing / 2
        im = ax.imshow(occ.T, origin="lower", extent=(gx[0] - h, gx[-1] + h, gy[0] - h, gy[-1] + h),
                       cmap="viridis", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(f"{spacing:g} m grid ({len(gx)} x {len(gy)})", fontsize=9)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.7, label="occupancy probability")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_table3(path: Path, results: Mapping[str, Mapping[str, Sequence[tuple[float, float]]]],
                title: str = "", per_row: int = 5,
                paper: Mapping[str, Mapping[str, tuple[float, float]]] | None = None) -> Path:
    """RICH-SLAM Table III over seeds: one panel per sequence, a bar per method at its mean yaw RMSE
    with one dot per seed, and the mean position RMSE written on the bar; a row of one of a method's estimates
    (``"rich_slam, fused"``) is hatched in the method's colour.

    ``results[sequence][method]`` are the seeds' ``(position RMSE m, yaw RMSE deg)``; ``paper[sequence][method]``
    (optional) the published ``(position, yaw)`` of that method's counterpart, drawn as a black bar mark.
    """
    plt = _plt()
    seqs = list(results)
    rows = max(1, -(-len(seqs) // per_row))
    cols = min(per_row, max(1, len(seqs)))
    fig, axes = plt.subplots(rows, cols, figsize=(3.1 * cols, 3.4 * rows), squeeze=False, constrained_layout=True)
    for ax in axes.ravel()[len(seqs):]:
        ax.set_visible(False)
    order = list(METHOD_LABELS)  # one method order in every panel (unknown methods last), estimates after it

    def rank(m: str) -> tuple[int, str]:
        method = m.split(", ")[0]
        return (order.index(method) if method in order else len(order), m)

    for ax, seq in zip(axes.ravel(), seqs, strict=False):
        methods = sorted(results[seq], key=rank)
        marks = (paper or {}).get(seq, {})
        labelled = False
        for i, m in enumerate(methods):
            v = np.asarray(results[seq][m], dtype=np.float64).reshape(-1, 2)
            ax.bar(i, v[:, 1].mean(), color=colour(m), alpha=0.55, width=0.75,
                   hatch="///" if ", " in m else None, edgecolor="white" if ", " in m else None)  # an estimate
            ax.plot(np.full(len(v), float(i)), v[:, 1], "o", color=colour(m), ms=3.5, mec="black", mew=0.4)
            ax.text(i, 0.0, f"{v[:, 0].mean():.2f} m", ha="center", va="bottom", fontsize=6.5, rotation=90)
            pub = marks.get(m)
            if pub is not None:
                ax.plot([i - 0.38, i + 0.38], [pub[1], pub[1]], color="black", lw=1.6,
                        label=None if labelled else "paper")
                labelled = True
        ax.set_xticks(range(len(methods)), [METHOD_LABELS.get(m, m) for m in methods], rotation=40,
                      ha="right", fontsize=7)
        ax.set_title(seq, fontsize=9)
        ax.set_ylabel("yaw RMSE [deg]", fontsize=8)
        ax.grid(axis="y", alpha=0.3)
        if labelled:
            ax.legend(fontsize=6.5, loc="best")
    fig.suptitle(title or "Table III: yaw RMSE (bar: mean over seeds, dots: seeds; text: position RMSE"
                 + ("; black line: the paper's value" if paper else "") + ")",
                 fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
