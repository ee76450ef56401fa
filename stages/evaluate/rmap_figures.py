"""RMap's qualitative figure (Fig. 3): top views of the input radar, completed and lidar maps of a few scenes.

matplotlib with the Agg backend; one row per scene, one column per map, coloured by height, the same
extent in a row. ``z_max`` drops the ceiling as the paper does (Fig. 3 cuts at 0.8 m).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from stages.evaluate.figures import _plt

F64 = npt.NDArray[np.float64]
COLUMNS = (("radar_map", "input radar map"), ("completed_map", "completed map"), ("lidar_map", "lidar map"))


def plot_top_views(path: Path, scenes: Mapping[str, Mapping[str, F64]], title: str = "",
                   columns: Sequence[tuple[str, str]] = COLUMNS, z_max: float | None = None,
                   max_points: int = 60000, seed: int = 0) -> Path:
    """Write a grid of top views: ``scenes[scene][method]`` is an (N, 3) map; a missing map leaves its panel empty.

    Points above ``z_max`` (m) are dropped; at most ``max_points`` per panel (a seeded subsample).
    The image is written to a temporary name and renamed into place.
    """
    if not scenes:
        raise ValueError("plot_top_views needs at least one scene")
    plt = _plt()
    rng = np.random.default_rng(seed)
    n_r, n_c = len(scenes), len(columns)
    fig, axes = plt.subplots(n_r, n_c, figsize=(4.6 * n_c, 4.2 * n_r), squeeze=False, constrained_layout=True)
    for row, (scene, maps) in zip(axes, scenes.items(), strict=True):
        clouds = {m: _visible(np.asarray(maps[m], np.float64).reshape(-1, 3), z_max) for m, _ in columns if m in maps}
        filled = [c for c in clouds.values() if len(c)]
        both = np.concatenate(filled) if filled else np.zeros((0, 3))
        z_lo, z_hi = (np.percentile(both[:, 2], [2, 98]) if len(both) else (0.0, 1.0))
        for ax, (method, label) in zip(row, columns, strict=True):
            pts = clouds.get(method)
            n = 0 if pts is None else len(pts)
            if pts is not None and n:
                if n > max_points:
                    pts = pts[rng.choice(n, max_points, replace=False)]
                ax.scatter(pts[:, 0], pts[:, 1], c=pts[:, 2], s=0.2, cmap="viridis", vmin=z_lo, vmax=z_hi,
                           rasterized=True)
            if len(both):
                ax.set_xlim(both[:, 0].min(), both[:, 0].max())
                ax.set_ylim(both[:, 1].min(), both[:, 1].max())
            ax.set_aspect("equal")
            shown = f"{n} points" + ("" if z_max is None else f" at z <= {z_max:g} m")
            ax.set_title(f"{scene}: {label} ({shown})" if pts is not None else f"{scene}: {label} (not run)",
                         fontsize=9)
            ax.set_xlabel("x [m]")
            ax.set_ylabel("y [m]")
    if title:
        fig.suptitle(title)
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)
    return path


def _visible(points: F64, z_max: float | None) -> F64:
    return points if z_max is None else points[points[:, 2] <= z_max]
