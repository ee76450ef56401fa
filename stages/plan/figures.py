"""Fig. 12: planned paths over the occupancy and the normalised uncertainty of the Hilbert map (matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
COLOURS = {"greedy": "tab:red", "uncertainty": "tab:purple"}
LABELS = {"greedy": "greedy (c = z)", "uncertainty": "uncertainty-aware (c = z / (sqrt(u) + eps))"}


def plot_plan(path: Path, gx: F64, gy: F64, occupancy: F64, norm_uncertainty: F64, paths: dict[str, F64],
              start: F64, goal: F64, title: str = "") -> Path:
    """Two panels (occupancy, normalised uncertainty), each with every path; A* guesses dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    extent = (gx[0], gx[-1], gy[0], gy[-1])
    u = norm_uncertainty
    u_label = "normalised predictive uncertainty u / u_prior"
    if not np.all(np.isfinite(u)):
        u = u / max(float(np.nanmax(u)), 1e-300)
        u_label = "predictive uncertainty u / max u"
    aspect = (gy[-1] - gy[0]) / max(gx[-1] - gx[0], 1e-9)
    fig, axes = plt.subplots(1, 2, figsize=(12, max(3.5, 5.5 * aspect) + 0.6), constrained_layout=True)
    for ax, img, cmap, label, vmax in ((axes[0], occupancy, "viridis", "occupancy probability (eq. 28)", 1.0),
                                       (axes[1], u, "magma", u_label, None)):
        im = ax.imshow(img.T, origin="lower", extent=extent, cmap=cmap, vmin=0.0, vmax=vmax, interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.8, label=label)
        for name, p in paths.items():
            base = name.removeprefix("astar_")
            dashed = name.startswith("astar_")
            ax.plot(p[:, 0], p[:, 1], "--" if dashed else "-", color=COLOURS.get(base, "white"),
                    lw=1.0 if dashed else 2.0, alpha=0.7 if dashed else 1.0,
                    label=("A* " + base) if dashed else LABELS.get(base, base))
        ax.plot(*start, "o", ms=9, mfc="white", mec="black", label="start")
        ax.plot(*goal, "s", ms=9, mfc="white", mec="black", label="goal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal")
    axes[0].legend(loc="best", fontsize=7)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
