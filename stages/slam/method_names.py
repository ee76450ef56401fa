"""The slam stage's method names and the paper's constants they carry (no imports of the stage's algorithms)."""

from __future__ import annotations

from typing import Literal

Method = Literal["odometry", "radar_graph", "fastslam_grid", "rich_slam", "rich_slam_no_et", "rich_slam_mean_only"]
METHODS: tuple[Method, ...] = ("odometry", "radar_graph", "fastslam_grid", "rich_slam", "rich_slam_no_et",
                               "rich_slam_mean_only")
#: RICH-SLAM (Sec. IV) and its Table III ablations: without endpoint tolerance, and the mean-only weight of H-SLAM
HILBERT_METHODS = ("rich_slam", "rich_slam_no_et", "rich_slam_mean_only")
#: methods that are not particle filters (:mod:`pose_graph`; the slam stage runs them on their own inputs)
GRAPH_METHODS = ("radar_graph",)
#: the paper's endpoint tolerance radius r_e (m, Sec. IV-D2: "we set r_e = 0.25 m")
PAPER_ENDPOINT_TOLERANCE = 0.25
