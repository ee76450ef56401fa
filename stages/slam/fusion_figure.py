"""Figure: where the fused estimate takes its heading from (stages/slam/heading_fusion.py), against the truth.

One panel per kept filter trajectory (``table3 --keep``): the heading errors of the odometry, of the filter's
smoothed trajectory and of the fused estimate, each relative to its first scan, the filter's persistent step
``s`` found by the fusion's jump gates, and where its segments begin. Usage::

    python -m stages.slam.fusion_figure RUN KEPT.npz [RUN KEPT.npz ...] --rows ROWS.jsonl --out F.png

``--rows``: a Table III results file with the fused rows of these trajectories; each panel's fusion model takes
the filter-error std its row records (``fusion_filter_sigma_deg``, the information-scaled one) and the row's
configuration; without a row, the configured defaults (``--set``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.slam.heading_fusion import FusedHeading, HeadingFusion, fuse_heading
from stages.slam.stage import SlamParams
from stages.slam.table3 import read_odometry_motion, slam_overrides

F64 = npt.NDArray[np.floating[Any]]


def heading_errors(t_ns: npt.NDArray[np.int64], yaw: F64, truth_t_ns: npt.NDArray[np.int64], truth_yaw: F64) -> F64:
    """Unwrapped heading error at the scan stamps (truth interpolated), relative to the first scan (rad)."""
    truth = np.interp(t_ns.astype(np.float64), truth_t_ns.astype(np.float64), np.unwrap(truth_yaw))
    err = np.unwrap(yaw) - truth
    return err - err[0]


def panel_model(row: dict[str, Any] | None, overrides: dict[str, Any]) -> HeadingFusion:
    """The fusion model of a fused row (its configuration and its information-scaled filter-error std)."""
    config = {k: v for k, v in json.loads(row["config"]).items() if k != "estimate"} if row else {}
    model = SlamParams(**{**config, **overrides}).config().fusion
    if row and row.get("fusion_filter_sigma_deg") is not None:
        model = model.model_copy(update={"filter_sigma": math.radians(row["fusion_filter_sigma_deg"])})
    return model


def read_rows_file(paths: list[Path]) -> dict[tuple[str, str, int], dict[str, Any]]:
    """The rows of Table III results files by (sequence, method, seed); a later row replaces an earlier one."""
    rows: dict[tuple[str, str, int], dict[str, Any]] = {}
    for f in paths:
        for line in f.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                rows[(r["seq"], r["method"], int(r["seed"]))] = r
    return rows


def draw(out: Path, panels: list[dict[str, Any]]) -> None:
    """Draw the panels (``title``, ``t`` s, errors deg ``odometry``/``filter``/``fused``, ``step`` deg,
    ``jumps``: the scans where a step segment begins) one above the other into a PNG (written to a temporary
    name, then renamed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(panels), 1, figsize=(9.0, 3.1 * len(panels)), squeeze=False)
    for ax, p in zip(axes[:, 0], panels, strict=True):
        ax.axhline(0.0, color="0.75", lw=0.8)
        ax.plot(p["t"], p["odometry"], color="tab:gray", lw=1.2, label="odometry")
        ax.plot(p["t"], p["filter"], color="tab:orange", lw=1.0, label="filter (smoothed)")
        ax.plot(p["t"], p["fused"], color="tab:blue", lw=1.6, label="fused")
        if np.any(p["step"] != 0):
            ax.plot(p["t"], p["step"], color="tab:red", lw=1.0, ls="--", label="the filter's step s (the fusion's)")
        for k in p["jumps"]:
            ax.axvline(p["t"][k], color="tab:red", lw=0.6, alpha=0.5)
        ax.set_title(p["title"], fontsize=9)
        ax.set_ylabel("heading error (deg)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    axes[-1, 0].set_xlabel("time (s)")
    save_png(fig, out, 110)


def save_png(fig: Any, out: Path, dpi: int) -> None:
    """Lay out and write a matplotlib figure to ``out`` through a temporary name (nothing half-written), then
    close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + ".tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    tmp.replace(out)


def build_panel(run_dir: Path, kept_path: Path, rows: dict[tuple[str, str, int], dict[str, Any]],
                overrides: dict[str, Any]) -> dict[str, Any]:
    """One panel's curves: the kept smoothed trajectory fused again with its row's model."""
    kept = np.load(kept_path)
    label, seed = str(kept["label"]).split(",")[0], int(kept["seed"])
    _, t_ns, odo, motion = read_odometry_motion(run_dir)
    if not np.array_equal(t_ns, kept["t_ns"]):
        raise ValueError(f"{kept_path}: its scan stamps are not those of {run_dir}/odometry")
    row = rows.get((run_dir.name, f"{label}, fused", seed))
    model = panel_model(row, overrides)
    t = np.cumsum(motion.dt)
    fused: FusedHeading = fuse_heading(t, odo[:, 2], kept["pose"][:, 2], motion.cov[:, 2, 2], model)
    truth = (kept["truth_t_ns"], kept["truth_yaw"])
    errors = {k: np.degrees(heading_errors(t_ns, yaw, *truth)) for k, yaw in (
        ("odometry", odo[:, 2]), ("filter", kept["pose"][:, 2]), ("fused", odo[:, 2] + fused.correction))}
    rmse = {k: float(np.sqrt(np.mean(errors[k] ** 2))) for k in ("odometry", "fused")}
    step = np.zeros(len(t)) if fused.step is None else fused.step
    moving = np.r_[False, np.abs(np.diff(step)) > 1e-6]  # where s moves: the found jumps' segments
    starts = np.flatnonzero(moving & ~np.r_[False, moving[:-1]])
    return {
        "title": f"{run_dir.name}: {label} seed {seed}, filter-error std {math.degrees(model.filter_sigma):.1f} deg, "
                 f"{fused.jumps} jump(s) found\nheading error RMS from the first scan (no alignment): odometry "
                 f"{rmse['odometry']:.2f} deg, fused {rmse['fused']:.2f} deg",
        "t": t,
        **errors,
        "step": np.degrees(step),
        "jumps": [int(k) for k in starts],
    }


def figure_main(name: str, doc: str, build: Callable[..., dict[str, Any]],
                draw_panels: Callable[[Path, list[dict[str, Any]]], None], argv: list[str] | None) -> int:
    """The command line of a figure over kept trajectories (this module's and :mod:`consistency_figure`'s):
    ``RUN KEPT.npz`` pairs, ``--rows``, ``--set``, ``--out``; a bad input is a one-line error (exit 2)."""
    ap = argparse.ArgumentParser(prog=f"python -m stages.slam.{name}", description=doc.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="RUN KEPT.npz pairs: a run folder and a kept smoothed trajectory")
    ap.add_argument("--rows", type=Path, nargs="*", default=[], help="Table III results files with their fused rows")
    ap.add_argument("--set", action="append", default=[], metavar="PARAM=JSON",
                    help="a slam parameter (fusion_*), as table3 takes it")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    if len(a.pairs) % 2:
        print(f"{name}: give RUN KEPT.npz pairs (an odd number of paths was given)", file=sys.stderr)
        return 2
    try:
        overrides = slam_overrides(a.set)
        rows = read_rows_file(a.rows)
        panels = [build(Path(run), Path(kept), rows, overrides)
                  for run, kept in zip(a.pairs[::2], a.pairs[1::2], strict=True)]
    except (OSError, ValueError, KeyError) as e:
        print(f"{name}: {e}", file=sys.stderr)
        return 2
    draw_panels(a.out, panels)
    print(f"wrote {a.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return figure_main("fusion_figure", __doc__ or "", build_panel, draw, argv)


if __name__ == "__main__":
    raise SystemExit(main())
