"""RICH-SLAM's published localisation results as data.

Table III of "RICH-SLAM: Radar SLAM with Incremental and Continuous Hilbert Mapping".

Horizontal position RMSE [m] / yaw RMSE [deg] after the SE(2) alignment on the first 100 matched frames,
transcribed as printed. The ColoRadar columns CR 1-6 are the sequences that the twins ``coloradar_N_twin``
rebuild; Seq. 1-3 are the authors' own ARS548 recordings, which have no counterpart here.
Used by ``python -m experiments.slam_table3 --table ... --paper`` and checked against the paper's text by
``tests/test_rich_slam_paper.py``.
"""

from __future__ import annotations

#: Table III's methods in its row order
PAPER_METHODS: tuple[str, ...] = ("EKF-RIO", "OPT-RIO", "FastSLAM-Radar", "RICH-SLAM w/o ET", "RICH-SLAM")

#: Table III's columns in order
PAPER_SEQUENCES: tuple[str, ...] = ("Seq. 1", "Seq. 2", "Seq. 3", "CR 1", "CR 2", "CR 3", "CR 4", "CR 5", "CR 6")

_ROWS: dict[str, tuple[tuple[float, float], ...]] = {
    "EKF-RIO": ((1.01, 7.28), (2.17, 4.03), (4.70, 104.11), (3.26, 79.53), (1.60, 91.98), (3.72, 97.11),
                (0.89, 96.45), (2.76, 79.15), (3.26, 86.98)),
    "OPT-RIO": ((0.52, 1.97), (0.49, 1.28), (1.46, 14.73), (1.28, 7.69), (2.78, 25.41), (6.54, 15.36),
                (4.70, 16.90), (3.31, 26.34), (5.95, 9.00)),
    "FastSLAM-Radar": ((0.50, 2.28), (0.50, 1.45), (1.46, 14.87), (0.96, 13.51), (2.41, 24.69), (5.71, 13.04),
                       (4.91, 17.49), (2.97, 24.37), (6.64, 10.07)),
    "RICH-SLAM w/o ET": ((0.54, 3.03), (0.60, 2.70), (0.94, 7.31), (0.84, 7.07), (3.06, 24.43), (6.29, 12.21),
                         (4.04, 13.34), (2.61, 23.81), (2.12, 3.17)),
    "RICH-SLAM": ((0.54, 3.03), (0.60, 2.70), (0.94, 7.31), (0.86, 6.18), (2.68, 22.88), (4.72, 10.94),
                  (3.59, 12.61), (2.55, 23.23), (1.79, 3.06)),
}

#: ``TABLE_III[sequence][method] = (position RMSE m, yaw RMSE deg)``
TABLE_III: dict[str, dict[str, tuple[float, float]]] = {
    seq: {m: _ROWS[m][j] for m in PAPER_METHODS} for j, seq in enumerate(PAPER_SEQUENCES)
}

#: our methods and the paper's row each one reproduces (same proposal, same weighting)
COUNTERPART: dict[str, str] = {
    "fastslam_grid": "FastSLAM-Radar",
    "rich_slam": "RICH-SLAM",
    "rich_slam_no_et": "RICH-SLAM w/o ET",
}


def paper_sequence(seq: str) -> str | None:
    """Table III's column for one of our sequences: ``coloradar_3_twin`` (or ``coloradar_3``) -> ``CR 3``."""
    number = seq.removesuffix("_twin").removeprefix("coloradar_")
    if not number.isdigit() or not seq.startswith("coloradar_"):
        return None
    col = f"CR {int(number)}"
    return col if col in TABLE_III else None
