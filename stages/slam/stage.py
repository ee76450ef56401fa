"""`slam` stage: RICH-SLAM (RBPF with Hilbert-GP occupancy maps) and the baselines it is compared against.

Inputs: ``ingest/calibration.json`` (``base_from_radar``), ``filter/radar_filtered.parquet`` (radar
frame), ``odometry/odometry.parquet`` (world <- base at the radar scan times). Radar points go to the
base frame, are projected to the plane (optional height gate) and sampled along beams from the radar
origin (Fig. 3a). Every method in ``methods`` runs over the same samples and writes
``trajectory_<method>.parquet``; ``trajectory.parquet`` is ``method``'s. The map outputs (posterior,
grid, per-scan uncertainty statistics) come from ``method``: its best particle's final map for the
Hilbert methods, else a Hilbert map built along its trajectory. Units: see README.md.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import Field, ValidationError, model_validator

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams

if TYPE_CHECKING:
    from pipeline.sequences import SequenceInfo

from schemas.artifacts import ODOMETRY_COV_COLS, ODOMETRY_COV_IDX
from schemas.io import read_artifact, write_artifact
from stages.slam import hilbert_map as hm
from stages.slam.backend import resolve_device
from stages.slam.beam_sampling import BeamSamples, radar_to_body_2d, sample_beams, to_world
from stages.slam.divergence import heading_deviation
from stages.slam.grid_map import GridModel
from stages.slam.heading_fusion import HeadingFusion
from stages.slam.map_consistency import MapConsistency
from stages.slam.methods import (
    GRAPH_METHODS,
    HILBERT_METHODS,
    METHODS,
    PAPER_METHODS,
    REFINED_METHODS,
    Estimate,
    Method,
    MethodResult,
    OdometryMotion,
    SlamConfig,
    domain_from_trajectory,
    run_method,
)
from stages.slam.pose_graph import GraphModel, GraphResult, optimise_graph
from stages.slam.pose_refinement import PoseRefinement
from stages.slam.rbpf import MotionNoise, WideMode, YawBias
from stages.slam.registration import MatcherModel
from stages.slam.submaps import SubmapModel

F64 = npt.NDArray[np.floating[Any]]


class SlamParams(StageParams):
    """Parameters of the `slam` stage (defaults: RICH-SLAM Table II, ColoRadar profile)."""

    method: Method = Field("rich_slam", description="method whose trajectory is trajectory.parquet and whose "
                           "map is written (odometry, fastslam_grid, rich_slam, rich_slam_no_et, rich_slam_mean_only)")
    methods: list[Method] = Field(list(METHODS), description="methods run and written as "
                                  "trajectory_<method>.parquet (the main method always runs; rich_slam_paper is the "
                                  "paper's configuration, the reference row)")
    n_particles: int = Field(200, ge=1, le=100_000, description="particles N_p (Sec. V-A2)")
    seed: int = Field(0, description="seed of the particle filter's random generator")
    # -- Hilbert-GP map (Table II)
    lengthscale: float = Field(20.0, gt=0, description="SE length scale l in map units (Table II: 20)")
    length_unit_m: float = Field(0.1, gt=0, le=100, description="metres per map unit: l in metres = lengthscale * this "
                                 "(README: decimetres reproduce the paper's maps; 1.0 = literal metres)")
    signal_variance: float = Field(16.0, gt=0, description="sigma_f^2 (Table II: 16 ColoRadar, 0.7 ARS548)")
    noise_variance: float = Field(0.36, gt=0, description="sigma_n^2 (Table II: 0.36 ColoRadar, 0.1 ARS548)")
    endpoint_noise_variance: float | None = Field(
        None, gt=0, description="sigma_n^2 of the endpoints' +1 labels in the map update (free samples keep "
        "noise_variance); unset: one value, the paper (issue 17 lever; measured in stages/slam/README.md)")
    n_basis: int = Field(256, ge=1, le=4096, description="basis functions M (a perfect square for the tensor basis)")
    basis_kind: Literal["tensor", "circular"] = Field("tensor", description="'tensor': eq. 7; 'circular': the M "
                                                      "smallest eigenvalues (Solin and Sarkka's code)")
    domain_padding: float = Field(10.0, ge=0, description="Hilbert domain = odometry envelope padded by this (m)")
    map: Literal["global", "submaps", "hybrid"] = Field(
        "global", description="the Hilbert filters' particle maps: one global map over the odometry's envelope (the "
        "paper), local submaps that move with the robot (stages/slam/submaps.py), or both, each scan weighed half "
        "against each (hybrid); rich_slam_paper and rich_slam_refined: always global")
    submap_half_width: float = Field(9.0, gt=0, description="submaps: half width of each square submap (m); must "
                                     "exceed max_range + endpoint_tolerance + 0.5")
    submap_n_basis: int = Field(256, ge=1, le=4096,
                                description="submaps: basis functions per submap (a perfect square for "
                                "the tensor basis)")
    submap_lengthscale: float = Field(10.0, gt=0, description="submaps: SE length scale in map units (10 dm = 1 m)")
    submap_keep_closed: bool = Field(False, description="submaps: keep closed submaps (each particle's mean map) "
                                     "and weigh a scan against the oldest submap whose window holds the robot, so a "
                                     "place seen again is weighed against its first visit (loop closure)")
    map_update: Literal["kalman", "laplace"] = Field("kalman", description="map update: Kalman (eq. 15-19) or "
                                                     "recursive Laplace (Appendix)")
    laplace_iterations: int = Field(20, ge=1, le=1000, description="Newton iterations of the Laplace update at most")
    map_form: Literal["auto", "information", "covariance"] = Field(
        "auto", description="particle map storage: covariance (eq. 15-19 literally; cheaper for sparse scans), "
        "information matrix with its Cholesky factor (same posterior; cheaper for dense scans), or auto (by a "
        "cost model at the sequence's samples per scan)")
    dtype: Literal["float64", "float32"] = Field("float64", description="precision of the particle maps")
    workers: int = Field(2, ge=0, le=256,
                         description="worker processes sharing the particle maps (information form), one "
                         "BLAS thread each; 0 = in process (numpy backend)")
    backend: Literal["numpy", "torch"] = Field(
        "numpy", description="array backend of the RICH-SLAM particle maps and filter loop: numpy (CPU, worker "
        "processes) or torch (batched tensors on slam.device; needs the learn extra)")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="device of the torch backend: cuda, cpu, or auto (cuda when torch sees one, else cpu; "
        "the fallback is logged); numpy runs on the cpu")
    torch_threads: int = Field(1, ge=0, le=256, description="CPU threads of the torch backend on the cpu (0 = torch's "
                               "default, one per core; one thread is far faster on a shared machine, README)")
    # -- measurements (Sec. IV-B, Fig. 3a)
    max_range: float = Field(5.0, gt=0, description="beams longer than this are dropped (m, Table II)")
    min_range: float = Field(0.0, ge=0, description="beams shorter than this are dropped (m)")
    ray_step: float = Field(1.0, ge=0.01, description="free-sample spacing along a beam (m, Table II)")
    free_clearance: float = Field(0.0, ge=0, description="no free sample closer than this to the endpoint (m)")
    z_min: float | None = Field(None, description="keep points with base-frame z >= z_min (m); None: no gate")
    z_max: float | None = Field(None, description="keep points with base-frame z <= z_max (m); None: no gate")
    # -- weights (Sec. IV-D2)
    endpoint_tolerance: float = Field(
        0.0, ge=0, description="endpoint tolerance radius r_e (m, eq. 29; the paper: 0.25); 0 = off, chosen on the "
        "calibration runs (stop 39, stages/slam/README.md); rich_slam_paper always takes the paper's 0.25 and "
        "rich_slam_no_et always 0")
    et_ring_points: int = Field(8, ge=1, le=64, description="points on each ring of the discretised r_e disc")
    et_rings: int = Field(1, ge=1, le=16, description="rings of the discretised r_e disc")
    et_variance: Literal["exact", "taylor"] = Field(
        "taylor", description="variance at the tolerance points: with Phi linearised about the endpoint (the mean "
        "stays exact; log weights within 0.003 of the exact ones on the demo, README), or exact Phi^T cov Phi (slower)")
    likelihood_exponent: float = Field(
        0.5, gt=0, description="exponent on the scan likelihood of the Hilbert filters (1: the paper, eq. 22; 0.5 "
        "tempers the weight for beams that are not independent, chosen on the calibration runs, stages/slam/README.md;"
        " rich_slam_paper: always 1)")
    informed_exponent_information: float | None = Field(
        None, gt=0, description="the Hilbert filters (not rich_slam_paper nor rich_slam_refined): run with "
        "informed_likelihood_exponent where the weight's median yaw "
        "information along the odometry (rad^-2, at likelihood_exponent; computed before the filter) is at least "
        "this; None: off (stages/slam/README.md, stop 49)")
    informed_likelihood_exponent: float = Field(
        1.0, gt=0, description="the exponent on the scan likelihood where informed_exponent_information switches")
    grid_likelihood_exponent: float = Field(1.0, gt=0, description="fastslam_grid: exponent on its scan likelihood "
                                            "(1 was better on the calibration runs)")
    grid_share: float = Field(0.0, ge=0, lt=1, description="share of each scan's log-likelihood that rich_slam takes "
                              "from a FastSLAM occupancy grid each particle carries beside its Hilbert map (the "
                              "detail M basis functions cannot hold on a large domain); 0: the paper's Hilbert "
                              "weight alone (rich_slam_paper always)")
    map_delay: int = Field(0, ge=0, le=100_000,
                           description="rich_slam: weigh each scan against the particle's map without its "
                           "last map_delay scans, which agree with the particle's heading right or wrong "
                           "(stages/slam/delayed_maps.py); 0: the paper's map of every earlier scan")
    outlier: float = Field(0.0, ge=0, lt=1, description="probability that a radar sample is not explained by the "
                           "map (clutter, multipath): it then scores 1/2 whatever the map says, so no sample can "
                           "outweigh the scan (the grid's z_rand); 0: the paper's eq. 28 (rich_slam_paper always)")
    common_support: float | None = Field(
        None, gt=0, le=1, description="score each scan only on the samples every particle's map has seen: predictive "
        "variance below this fraction of signal_variance for every particle (stages/slam/README.md; unset: every "
        "sample, the paper; rich_slam_paper: always unset). Needs workers = 0 and backend = numpy")
    free_weight: float = Field(1.0, ge=0, description="weight of the free samples' log terms against the endpoints' "
                               "in every Hilbert method's weight (1: the paper, eq. 23)")
    # -- pose refinement (rich_slam_refined, stages/slam/pose_refinement.py)
    refine_iterations: int = Field(3, ge=1, le=100,
                                   description="rich_slam_refined: Gauss-Newton steps per scan on each "
                                   "particle's pose against its own map before weighting")
    refine_max_step_xy: float = Field(0.25, gt=0, description="rich_slam_refined: largest x, y step per iteration (m)")
    refine_max_step_yaw: float = Field(0.05, gt=0, description="rich_slam_refined: largest yaw step per iteration "
                                       "(rad)")
    refine_objective: Literal["gaussian", "logistic"] = Field(
        "logistic", description="rich_slam_refined: scan term matched: the map's own Gaussian regression of the "
        "+-1 labels (least squares on y - m / sigma_n) or eq. 28's mean-only logistic term")
    refine_covariance_scale: float = Field(1.0, gt=0, description="rich_slam_refined: the proposal is N(refined "
                                           "pose, this * inverse Gauss-Newton Hessian)")
    refine_free_weight: float | None = Field(
        None, ge=0, description="rich_slam_refined: weight of the free samples' terms against the endpoints' in the "
        "refinement objective only (unset: free_weight, the weights' own)")
    # -- particles (Sec. IV-D1, D3)
    motion_std_xy: float = Field(0.002, ge=0, description="process noise std on x and y per scan (m, eq. 21)")
    motion_std_yaw: float = Field(0.0005, ge=0, description="process noise std on yaw per scan (rad, eq. 21)")
    motion_rel_trans: float = Field(0.05, ge=0, description="extra xy std per metre of odometry translation")
    motion_rel_rot: float = Field(0.005, ge=0, description="extra yaw std per radian of odometry rotation")
    motion_rot_per_trans: float = Field(0.03, ge=0, description="extra yaw std per metre of odometry translation "
                                        "(rad/m; GMapping's str)")
    motion_trans_per_rot: float = Field(0.06, ge=0, description="extra xy std per radian of odometry rotation "
                                        "(m/rad; GMapping's srt)")
    proposal: Literal["odometry_covariance", "gmapping"] = Field(
        "odometry_covariance", description="the filters' proposal noise: the odometry's own per-scan increment "
        "covariance (odometry.parquet cov_*; the default, chosen on the four calibration runs, stages/slam/README.md) "
        "or GMapping's fitted form (motion_*); rich_slam_paper: always gmapping")
    proposal_scale: float = Field(1.0, gt=0, description="factor on the odometry's increment covariance in the "
                                  "odometry_covariance proposal (1: the covariance as the odometry writes it)")
    yaw_bias: bool = Field(False, description="each particle carries a yaw-rate bias that corrects its odometry "
                           "heading increment (not rich_slam_paper); off by default: worse on the calibration runs "
                           "whose odometry is good (stages/slam/README.md)")
    yaw_bias_sigma0: float = Field(0.005, gt=0, description="yaw-rate bias prior std, rad/s (the odometry's gyro "
                                   "bias prior, odometry.sigma_gyro_bias0)")
    yaw_bias_walk: float = Field(3.9e-6, ge=0, description="yaw-rate bias random walk, rad/s/sqrt(s) (3DM-GX5 "
                                 "in-run bias instability 8 deg/h over a 100 s correlation time)")
    yaw_bias_share: float = Field(1.0, gt=0, le=1, description="share of the particles that carry the yaw-rate bias; "
                                  "the others keep none, so the weights choose between a drifting and a good "
                                  "odometry (1: all)")
    proposal_wide_share: float = Field(0.0, ge=0, lt=1, description="with the odometry_covariance proposal: the "
                                       "stationary share of the particles drawn with GMapping's wide fitted noise "
                                       "(motion_*) instead, resampled with their mode, for an odometry that drifts "
                                       "more than its covariance says (0: off; worse on the calibration runs, "
                                       "stages/slam/README.md stop 54)")
    proposal_wide_switch: float = Field(0.01, ge=0, le=1, description="per-scan probability that a particle's "
                                        "mode (wide or the odometry's) is drawn afresh from proposal_wide_share")
    resampling: Literal["systematic", "stratified", "multinomial"] = Field(
        "systematic", description="resampler (systematic = low variance)")
    resample_threshold: float = Field(0.5, gt=0, le=1, description="resample when N_eff < this * N_p (eq. 31)")
    resample_keep_mean: bool = Field(False, description="resampling keeps the particles' weighted mean pose "
                                     "(removes resampling's Monte Carlo drift of the mean; not rich_slam_paper; "
                                     "stages/slam/README.md)")
    estimate: Estimate = Field(
        "fused", description="trajectory: the largest-weight particle at each scan (Algorithm 1), the "
        "final best particle's history, the weighted mean pose at each scan (x, y arithmetic, yaw circular), or "
        "the smoothed mean (the final particles' ancestors with the final weights: uses the later scans too; "
        "stages/slam/README.md), or that smoothed heading fused with the odometry's by the fusion_* error models "
        "(the odometry's increments composed along it); rich_slam_paper: always the first")
    fusion_bias_sigma0: float = Field(0.003, ge=0, description="estimate = fused: initial std of the odometry's "
                                      "unmodelled yaw-rate bias, rad/s")
    fusion_bias_walk: float = Field(1e-5, ge=0, description="estimate = fused: random-walk density of that bias, "
                                    "rad/s/sqrt(s) (re-fitted on twelve calibration runs at stop 49; 3e-4 before)")
    fusion_filter_sigma: float = Field(4.0, gt=0, description="estimate = fused: stationary std of the filter's "
                                       "heading error, deg (stop 49; 8 before)")
    fusion_filter_tau: float = Field(100.0, gt=0, description="estimate = fused: correlation time of the filter's "
                                     "heading error, s")
    fusion_increment_scale: float = Field(0.1, gt=0, description="estimate = fused: factor on the odometry's "
                                          "per-increment yaw variances in the fusion's model of its error (below 1: "
                                          "they over-cover yaw; stages/slam/README.md stop 46)")
    fusion_information_ref: float = Field(400.0, ge=0, description="estimate = fused: the yaw information of the "
                                          "filter's scan weight (rad^-2 per scan, the run's median along the "
                                          "odometry) below which fusion_filter_sigma grows as 1/sqrt(information): "
                                          "the fusion keeps more of the odometry's heading where the weight holds "
                                          "little (stages/slam/README.md, stop 47; 0: off)")
    fusion_jump_gate: float = Field(5.0, ge=0, description="estimate = fused: a heading step of the filter past "
                                    "this many predicted sigmas, within one scan or summed over "
                                    "fusion_jump_window, is a jump of its own error, which stays (0: off)")
    fusion_jump_window: float = Field(10.0, ge=0, description="estimate = fused: seconds over which a jump of the "
                                      "filter's heading spread over a turn is summed (stop 50; 0: one-scan gate "
                                      "only)")
    fusion_alpha_max: float = Field(1.5, ge=0, description="estimate = fused: the fusion's heading correction is "
                                    "applied times the scale in 0 (the odometry), 0.125, ..., this that makes the "
                                    "radar scans' endpoints most consistent with each other along the trajectory "
                                    "(stages/slam/map_consistency.py; chosen on the calibration runs at stop 51; "
                                    "0: off, the correction as the fusion gives it)")
    fusion_alpha_criterion: Literal["capped", "matched", "common"] = Field(
        "capped", description="estimate = fused: what the scale minimises: 'capped', the whole capped score (stop "
        "51), which also falls when more endpoints merely overlap, 'matched', the mean square distance of the "
        "endpoints that have a counterpart (stop 52: better on the calibration runs, worse on the evaluated ones), "
        "or 'common', that of the endpoints matched at every scale searched (stop 53)")
    fusion_alpha_guard: float = Field(0.0, ge=0, description="estimate = fused: the chosen scale stands only if "
                                      "its criterion beats the odometry's by more than this many standard errors "
                                      "over 10 s blocks of the run, else the odometry stays (stop 55; 0: off)")
    # -- radar_graph: keyframe pose graph (stages/slam/pose_graph.py; settings chosen on the calibration runs)
    graph_max_range: float = Field(10.0, gt=0, description="radar_graph: endpoints up to this range (m) enter the "
                                   "keyframe clouds (longer than max_range, the Hilbert map's: more structure)")
    graph_keyframe_distance: float = Field(1.0, gt=0, description="radar_graph: a keyframe every this many metres "
                                           "of odometry travel")
    graph_keyframe_angle: float = Field(15.0, gt=0, description="radar_graph: or every this many degrees turned")
    graph_local_keyframes: int = Field(10, ge=1, le=1000, description="radar_graph: keyframes in a local map "
                                       "(registration and loop verification)")
    graph_registration: bool = Field(False, description="radar_graph: a factor from each keyframe registered "
                                     "against the keyframes before it (off: measured biased on the calibration "
                                     "runs, stages/slam/README.md)")
    graph_yaw_rate_sigma: float = Field(0.03, ge=0, description="radar_graph: rad/s of gyro bias the odometry's "
                                        "covariance does not hold, added to each odometry factor's yaw variance")
    graph_loop_radius: float = Field(3.0, gt=0, description="radar_graph: keyframes this close on the odometry "
                                     "are loop candidates, and the verification's translation search (m)")
    graph_loop_min_travel: float = Field(15.0, gt=0, description="radar_graph: path length between the two "
                                         "keyframes of a loop candidate (m)")
    graph_loop_search_yaw: float = Field(20.0, gt=0, le=180, description="radar_graph: the loop verification's "
                                         "yaw search (+- deg)")
    graph_loop_min_inliers: float = Field(0.6, gt=0, le=1, description="radar_graph: share of a cloud's points "
                                          "within 0.3 m of the other for a closure to be proposed")
    graph_robust: Literal["gnc", "none"] = Field("gnc", description="radar_graph: graduated non-convexity (GTSAM, "
                                                 "truncated quadratic) on the loop closures, or plain least squares")
    graph_match_sigma: float = Field(0.15, gt=0, description="radar_graph: the likelihood field's std (m)")
    graph_match_temperature: float = Field(30.0, gt=0, description="radar_graph: divides the summed point "
                                           "log-likelihood in the registration covariance (points are not "
                                           "independent; chosen for a NEES near 3 on the calibration runs)")
    # -- FastSLAM grid baseline
    grid_resolution: float = Field(0.1, ge=0.01, description="fastslam_grid cell size (m)")
    grid_l_occ: float = Field(0.85, gt=0, description="fastslam_grid log-odds added at an endpoint cell")
    grid_l_free: float = Field(-0.4, lt=0, description="fastslam_grid log-odds added along a beam")
    grid_l_clamp: float = Field(4.0, gt=0, description="fastslam_grid log-odds clamp (+-)")
    grid_sigma_hit: float = Field(0.2, gt=0, description="likelihood-field std of the endpoint distance (m)")
    grid_max_dist: float = Field(0.5, gt=0, description="likelihood-field search radius / distance cap (m)")
    grid_z_hit: float = Field(0.9, gt=0, description="likelihood-field hit weight")
    grid_z_rand: float = Field(0.1, gt=0, description="likelihood-field random weight (keeps logs finite)")
    # -- outputs
    deviation_warn_sigmas: float = Field(
        3.0, gt=0, description="warn when a filter's heading leaves the odometry's by more than this many sigma of "
        "the odometry's accumulated heading uncertainty (stages/slam/divergence.py); the value is in the manifest "
        "either way")
    grid_spacing: float = Field(0.25, ge=0.01, description="spacing of the query grid of map_grid.parquet (m)")
    stats_every: int = Field(5, ge=1, le=1_000_000,
                             description="map_stats.parquet: uncertainty quartiles every N scans")
    stats_spacing: float = Field(1.0, ge=0.01, description="map_stats.parquet: spacing of the cells summarised (m)")
    n_map_snapshots: int = Field(8, ge=0, le=1000, description="occupancy / uncertainty images logged to Rerun")
    image_spacing: float = Field(0.25, ge=0.01, description="pixel size of the Rerun map images (m)")

    @model_validator(mode="after")
    def _check(self) -> SlamParams:
        sizes = {"n_basis": self.n_basis, **({"submap_n_basis": self.submap_n_basis} if self.map != "global" else {})}
        for name, M in sizes.items():
            if self.basis_kind == "tensor" and round(M**0.5) ** 2 != M:
                raise ValueError(f"{name} = {M} is not a perfect square (the tensor basis of eq. 7 needs one; or set "
                                 "basis_kind = 'circular')")
        if self.map != "global":
            try:
                self.submap_model()
            except ValueError as exc:
                raise ValueError(f"slam.submap_half_width = {self.submap_half_width}: {exc}") from None
            hil = [m for m in dict.fromkeys([self.method, *self.methods]) if m in HILBERT_METHODS
                   and m not in (*PAPER_METHODS, *REFINED_METHODS)]
            if self.backend == "torch" and hil:
                raise ValueError(f"map = {self.map} runs on the numpy backend only ({', '.join(hil)}): set "
                                 "slam.backend = numpy or slam.map = global")
        if self.z_min is not None and self.z_max is not None and self.z_min > self.z_max:
            raise ValueError(f"z_min {self.z_min} > z_max {self.z_max}")
        if self.backend == "torch" and self.map_update != "kalman":
            raise ValueError("backend = torch implements the Kalman map update only; use backend = numpy for "
                             "map_update = laplace")
        refined = [m for m in dict.fromkeys([self.method, *self.methods]) if m in REFINED_METHODS]
        if self.backend == "torch" and refined:
            raise ValueError(f"{', '.join(refined)} (pose refinement) runs on the numpy backend only: set "
                             "slam.backend = numpy or leave it out of slam.methods")
        if self.backend == "torch" and self.endpoint_noise_variance is not None:
            raise ValueError("endpoint_noise_variance (per-label map noise) runs on the numpy backend only: set "
                             "slam.backend = numpy or leave endpoint_noise_variance unset")
        if self.backend == "numpy" and self.device == "cuda":
            raise ValueError("device = cuda needs backend = torch (the numpy backend runs on the cpu)")
        for name in ("map_delay", "grid_share"):  # options built on the in-process global map
            value = getattr(self, name)
            if value > 0 and (self.backend != "numpy" or self.map != "global"):
                raise ValueError(f"slam.{name} = {value} runs on the numpy backend with the global map: set "
                                 f"slam.backend = numpy and slam.map = global, or {name} = 0")
        if self.common_support is not None and (self.workers > 0 or self.backend != "numpy"):
            raise ValueError("common_support compares every particle's samples in one process: set slam.workers = 0 "
                             "and slam.backend = numpy, or leave common_support unset")
        try:
            self.consistency_model()
        except ValidationError as exc:
            raise ValueError(f"slam.fusion_alpha_guard = {self.fusion_alpha_guard:g} with slam.fusion_alpha_criterion "
                             f"= {self.fusion_alpha_criterion}: {exc.errors()[0]['ctx']['error']}") from None
        return self

    def consistency_model(self) -> MapConsistency:
        """The fused estimate's search of the correction's scale (``fusion_alpha_*``)."""
        return MapConsistency(alpha_max=self.fusion_alpha_max, criterion=self.fusion_alpha_criterion,
                              guard=self.fusion_alpha_guard)

    def submap_model(self) -> SubmapModel:
        """The submaps' geometry (their samples reach max_range plus the endpoint tolerance)."""
        return SubmapModel(self.submap_half_width, self.submap_n_basis, self.max_range + self.endpoint_tolerance,
                           keep_closed=self.submap_keep_closed)

    def graph_model(self) -> GraphModel:
        """radar_graph's parameter object (:class:`pose_graph.GraphModel`)."""
        return GraphModel(
            keyframe_distance=self.graph_keyframe_distance, keyframe_angle_deg=self.graph_keyframe_angle,
            local_keyframes=self.graph_local_keyframes, registration=self.graph_registration,
            yaw_rate_sigma=self.graph_yaw_rate_sigma, loop_radius=self.graph_loop_radius,
            loop_min_travel=self.graph_loop_min_travel, loop_search_yaw_deg=self.graph_loop_search_yaw,
            loop_min_inliers=self.graph_loop_min_inliers, robust=self.graph_robust,
            matcher=MatcherModel(sigma=self.graph_match_sigma, temperature=self.graph_match_temperature))

    def config(self) -> SlamConfig:
        return SlamConfig(
            submaps=self.submap_model() if self.map != "global" else None,
            submap_share=0.5 if self.map == "hybrid" else 1.0,
            submap_lengthscale_m=self.submap_lengthscale * self.length_unit_m,
            n_particles=self.n_particles, lengthscale_m=self.lengthscale * self.length_unit_m,
            signal_variance=self.signal_variance, noise_variance=self.noise_variance, n_basis=self.n_basis,
            basis_kind=self.basis_kind, endpoint_tolerance=self.endpoint_tolerance,
            et_ring_points=self.et_ring_points, et_rings=self.et_rings, et_variance=self.et_variance,
            likelihood_exponent=self.likelihood_exponent, grid_likelihood_exponent=self.grid_likelihood_exponent,
            informed_exponent_information=self.informed_exponent_information,
            informed_likelihood_exponent=self.informed_likelihood_exponent,
            noise=MotionNoise(self.motion_std_xy, self.motion_std_yaw, self.motion_rel_trans, self.motion_rel_rot,
                              self.motion_rot_per_trans, self.motion_trans_per_rot),
            proposal=self.proposal, proposal_scale=self.proposal_scale,
            yaw_bias=YawBias(self.yaw_bias_sigma0, self.yaw_bias_walk, self.yaw_bias_share) if self.yaw_bias else None,
            wide=WideMode(self.proposal_wide_share, self.proposal_wide_switch) if self.proposal_wide_share else None,
            resampling=self.resampling, resample_threshold=self.resample_threshold,
            resample_keep_mean=self.resample_keep_mean, map_update=self.map_update,
            laplace_iterations=self.laplace_iterations, map_form=self.map_form, dtype=self.dtype,
            workers=self.workers, backend=self.backend, device=self.device, torch_threads=self.torch_threads,
            grid=GridModel(self.grid_l_occ, self.grid_l_free, -self.grid_l_clamp, self.grid_l_clamp, 0.0,
                           self.grid_sigma_hit, self.grid_max_dist, self.grid_z_hit, self.grid_z_rand),
            grid_resolution=self.grid_resolution, estimate=self.estimate,
            refinement=PoseRefinement(
                iterations=self.refine_iterations, max_step_xy=self.refine_max_step_xy,
                max_step_yaw=self.refine_max_step_yaw, covariance_scale=self.refine_covariance_scale,
                objective=self.refine_objective,
                free_weight=self.free_weight if self.refine_free_weight is None else self.refine_free_weight,
                noise_variance=self.noise_variance,
                endpoint_noise_variance=self.endpoint_noise_variance),
            free_weight=self.free_weight, endpoint_noise_variance=self.endpoint_noise_variance,
            outlier=self.outlier, grid_share=self.grid_share, map_delay=self.map_delay,
            support_variance=None if self.common_support is None else self.common_support * self.signal_variance,
            fusion=HeadingFusion(bias_sigma0=self.fusion_bias_sigma0, bias_walk=self.fusion_bias_walk,
                                 filter_sigma=math.radians(self.fusion_filter_sigma),
                                 filter_tau=self.fusion_filter_tau, jump_gate=self.fusion_jump_gate,
                                 jump_window=self.fusion_jump_window,
                                 increment_scale=self.fusion_increment_scale,
                                 information_ref=self.fusion_information_ref),
            consistency=self.consistency_model(),
        )


class SlamStage(Stage):
    name = "slam"
    description = "RICH-SLAM: RBPF with Hilbert-GP occupancy maps, and baselines"
    inputs = ("ingest", "filter", "odometry")
    Params = SlamParams
    version = "3"
    outputs = ("trajectory.parquet", "map_posterior.parquet", "map_grid.parquet", "map_stats.parquet")

    def memory_estimate(self, seq: SequenceInfo, params: StageParams,
                        input_dirs: Mapping[str, Path]) -> tuple[int, str] | None:
        """The particle maps of the largest method, twice over (resampling copies them): N_p x M^2 for a Hilbert
        filter, N_p x cells for the grid filter over the odometry's envelope."""
        p = cast(SlamParams, params)
        methods = set(p.methods) | {p.method}
        item = 4 if p.dtype == "float32" else 8
        out: list[tuple[int, str]] = []
        if methods & set(HILBERT_METHODS):
            M = p.n_basis
            out.append((2 * p.n_particles * (M * M + 2 * M) * item,
                        f"slam.n_particles={p.n_particles} Hilbert maps of slam.n_basis={M}^2 {p.dtype}"))
        if "fastslam_grid" in methods and "odometry" in input_dirs:
            try:
                t = pq.read_table(input_dirs["odometry"] / "odometry.parquet", columns=["x", "y"])
                xy = np.column_stack([t["x"].to_numpy(), t["y"].to_numpy()])
            except (OSError, KeyError, pa.ArrowInvalid):
                xy = np.zeros((0, 2))
            if len(xy) and np.all(np.isfinite(xy)):
                half, _ = domain_from_trajectory(xy, p.domain_padding)
                cells = float(np.prod(np.ceil(2 * half / p.grid_resolution)))
                out.append((int(2 * p.n_particles * cells * 4),
                            f"slam.n_particles={p.n_particles} grids of {cells:.3g} cells at "
                            f"slam.grid_resolution={p.grid_resolution} m"))
        return max(out) if out else None

    def run(self, ctx: StageContext) -> None:
        p: SlamParams = ctx.params
        cfg = p.config()
        base_from_radar = read_calibration(ctx)
        scans, t_ns, odo, inc_cov = read_odometry(ctx)
        motion = OdometryMotion(inc_cov, np.r_[0.0, np.diff(t_ns) * 1e-9])
        point_scan, xyz = read_radar(ctx)
        samples = beam_samples_by_scan(point_scan, xyz, scans, base_from_radar, p)
        ctx.stats["radar_points_used"] = int(sum(len(o.endpoints) for o in samples))
        half, centre = domain_from_trajectory(odo[:, :2], p.domain_padding)
        basis = hm.make_basis(half, centre, p.n_basis, p.basis_kind)
        device, note = resolve_device(p.backend, p.device)
        if note:
            ctx.console.print(f"[yellow]slam: {note}[/]")
        ctx.stats.update({"backend": p.backend, "device": device, **({"device_note": note} if note else {})})
        n_samples = np.array([s.n for s in samples])
        ctx.stats.update({
            "scans": len(scans), "scans_with_samples": int(np.sum(n_samples > 0)),
            "samples_per_scan_mean": float(n_samples.mean()) if len(n_samples) else 0.0,
            "samples_per_scan_max": int(n_samples.max()) if len(n_samples) else 0,
            "beams_per_scan_mean": float(np.mean([len(s.endpoints) for s in samples])) if samples else 0.0,
            "domain": {"L1": float(half[0]), "L2": float(half[1]), "cx": float(centre[0]), "cy": float(centre[1])},
            "lengthscale_m": cfg.lengthscale_m,
        })
        methods = [p.method, *[m for m in dict.fromkeys(p.methods) if m != p.method]]
        tracker = MapTracker(basis, cfg, p, samples, scans, t_ns, ctx)
        results: dict[str, MethodResult] = {}
        graphs: dict[str, GraphResult] = {}
        with ctx.progress(len(methods) * len(scans), "methods") as advance:
            for m in methods:
                local = cfg.for_method(m).submaps is not None  # no global map to track: replayed below
                obs = tracker.observe if (m == p.method and m in HILBERT_METHODS and not local) else None
                if m in GRAPH_METHODS:
                    endpoints = graph_endpoints_by_scan(point_scan, xyz, scans, base_from_radar, p)
                    res, graph = run_graph(ctx, p, odo, inc_cov, t_ns, endpoints)
                    graphs[m] = graph
                    advance(len(scans))
                else:
                    res = run_method(m, odo, samples, basis, cfg, p.seed, observer=obs, on_step=advance,
                                     motion=motion)
                results[m] = res
                write_trajectory(ctx.output(f"trajectory_{m}.parquet"), scans, t_ns, res)
                # the fused estimate's scale of the fusion's correction (map_consistency): recorded and said
                scaled = (p.estimate == "fused" and p.fusion_alpha_max > 0 and m != "odometry"
                          and res.fusion_alpha is not None)
                ctx.stats.setdefault("methods", {})[m] = {
                    "seconds": round(res.seconds, 3),
                    "seconds_per_scan": round(res.seconds / max(len(scans), 1), 5),
                    "resamplings": res.resampled,
                    "n_eff_median": float(np.median(res.n_eff)) if len(res.n_eff) else None,
                    "map_form": res.form,
                    **({"yaw_bias_final_deg_s": round(float(np.degrees(res.yaw_bias[-1])), 5)}
                       if res.yaw_bias is not None and len(res.yaw_bias) else {}),
                    **({"wide_share_mean": round(float(np.mean(res.wide_share)), 4)}
                       if res.wide_share is not None and len(res.wide_share) else {}),
                    **({"device": res.device} if m in HILBERT_METHODS else {}),
                    **({"submaps_opened": res.submaps_opened} if res.submaps_opened else {}),
                    **({"submap_revisits": res.submap_revisits} if res.submap_revisits else {}),
                    **({"fusion_jumps": res.fusion_jumps} if p.estimate == "fused" and m != "odometry" else {}),
                    **({"fusion_alpha": res.fusion_alpha} if scaled else {}),
                    **({"fusion_alpha_evidence": res.fusion_alpha_evidence}
                       if scaled and res.fusion_alpha_evidence is not None else {}),
                    **({"fusion_filter_sigma_deg": round(res.fusion_filter_sigma_deg, 3)}
                       if p.estimate == "fused" and res.fusion_filter_sigma_deg is not None and m != "odometry"
                       else {}),
                    **({"heading_information": round(res.heading_information, 2)}
                       if res.heading_information is not None and m != "odometry" else {}),
                    **({"likelihood_exponent": res.likelihood_exponent} if res.likelihood_exponent is not None else {}),
                }
                ctx.console.print(f"[dim]slam: {m}: {res.seconds:.1f} s ({res.seconds / max(len(scans), 1):.3f} "
                                  f"s/scan), {res.resampled} resamplings[/]")
                if scaled:
                    ctx.console.print(f"slam: {m}: the fused estimate applies {res.fusion_alpha:g} x the fusion's "
                                      "heading correction (the scale that makes the scans most consistent; 0: the "
                                      "odometry itself, the filter's heading made them less consistent)"
                                      + (f"; the best scale's gain: {res.fusion_alpha_evidence:.2f} standard errors "
                                         f"(guard {p.fusion_alpha_guard:g})"
                                         if res.fusion_alpha_evidence is not None else ""))
                if m in GRAPH_METHODS:
                    g = graphs[m]
                    ctx.stats["methods"][m].update({
                        "keyframes": len(g.keyframes), "registration_factors": g.count("registration"),
                        "registrations_failed": g.registrations_failed, "loops_proposed": g.count("loop"),
                        "loops_accepted": g.count("loop", True), "loops_rejected": g.count("loop", False)})
                    ctx.console.print(f"slam: {m}: {len(g.keyframes)} keyframes, {g.count('registration')} "
                                      f"registration factors, loop closures {g.count('loop')} proposed / "
                                      f"{g.count('loop', True)} accepted / {g.count('loop', False)} rejected")
                    for w in g.warnings:
                        ctx.warn(f"{m}: {w}")
                    write_graph(ctx, g, scans, t_ns)
                elif m != "odometry":
                    # the filter's own heading: the fused estimate leans on the odometry and would hide a divergence
                    own = res.estimates.get("smoothed", res.poses) if p.estimate == "fused" else res.poses
                    dev = heading_deviation(odo, own, inc_cov)
                    ctx.stats["methods"][m]["heading_deviation_sigmas"] = round(dev.sigmas, 2)
                    if p.estimate == "fused" and res.fusion_jumps:
                        ctx.warn(f"{m}'s heading jumped {res.fusion_jumps} time(s) (past slam.fusion_jump_gate = "
                                 f"{p.fusion_jump_gate} sigma, within a scan or over slam.fusion_jump_window = "
                                 f"{p.fusion_jump_window} s): the fused estimate gave each jump to the filter's own "
                                 f"error and kept the odometry's heading there; compare trajectory_{m}.parquet with "
                                 "trajectory_odometry.parquet")
                    if dev.sigmas > p.deviation_warn_sigmas:
                        ctx.warn(f"{m}'s heading left the odometry's by {dev.degrees:.1f} deg at scan "
                                 f"{int(scans[dev.index])}, {dev.sigmas:.1f} sigma of the odometry's own accumulated "
                                 f"heading uncertainty ({dev.sigma_degrees:.2f} deg): it corrected a drift or it "
                                 f"diverged; compare trajectory_{m}.parquet with trajectory_odometry.parquet")
        main = results[p.method]
        write_trajectory(ctx.output("trajectory.parquet"), scans, t_ns, main)
        if main.theta is None or main.cov is None:
            theta, cov = tracker.replay(main.poses)
        else:
            theta, cov = main.theta, main.cov
        write_posterior(ctx.output("map_posterior.parquet"), basis, theta, cov, p, int(scans[-1]) if len(scans) else -1)
        grid = query_grid(basis, theta, cov, p.grid_spacing, cfg)
        write_artifact(grid, ctx.output("map_grid.parquet"), "map_grid", metadata={"grid_spacing": str(p.grid_spacing)})
        tracker.write(ctx.output("map_stats.parquet"))
        log_recording(ctx, scans, t_ns, results, p.method, tracker)
        for g in graphs.values():
            log_graph(ctx, g, scans, t_ns)


# -- reading -----------------------------------------------------------------------------------------------------


def read_calibration(ctx: StageContext) -> F64:
    path = ctx.input("ingest", "calibration.json")
    try:
        T = np.asarray(json.loads(path.read_text())["base_from_radar"], dtype=np.float64)
    except (KeyError, json.JSONDecodeError, ValueError, TypeError) as exc:
        raise UserError(f"{path}: no readable 'base_from_radar' 4x4 ({exc}); rerun "
                        f"`pipeline run ingest --seq {ctx.seq.name} --force`") from exc
    if T.shape != (4, 4):
        raise UserError(f"{path}: 'base_from_radar' has shape {T.shape}, expected 4x4")
    return T


def read_odometry(ctx: StageContext) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F64, F64]:
    """Scan ids, times, (x, y, yaw) and increment covariances ``(T, 3, 3)`` of the valid odometry rows, in
    scan order."""
    return read_odometry_file(ctx.input("odometry", "odometry.parquet"), ctx.seq.name)


def read_odometry_file(path: Path, seq: str) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F64, F64]:
    """:func:`read_odometry` of an ``odometry.parquet`` (``seq`` names the rerun command of the error).

    The covariance of a kept row's increment is the sum of those of the rows since the previous kept row
    (skipped rows' increments are added up; their errors taken as independent)."""
    t = read_artifact(path, "odometry")
    scans = t["scan"].to_numpy().astype(np.int64)
    keep = np.ones(len(scans), dtype=bool)
    if "valid" in t.column_names:
        keep = t["valid"].to_numpy(zero_copy_only=False).astype(bool)
    poses = np.stack([t[c].to_numpy().astype(np.float64) for c in ("x", "y", "yaw")], axis=1)
    keep &= np.all(np.isfinite(poses), axis=1)
    cov = np.zeros((len(scans), 3, 3))
    for c, (i, j) in zip(ODOMETRY_COV_COLS, ODOMETRY_COV_IDX, strict=True):
        cov[:, i, j] = cov[:, j, i] = np.nan_to_num(t[c].to_numpy().astype(np.float64))
    order0 = np.argsort(scans, kind="stable")
    csum = np.cumsum(cov[order0], axis=0)  # in scan order: a kept row takes the sum since the previous kept one
    kept_sorted = keep[order0]
    at = np.flatnonzero(kept_sorted)
    acc = csum[at] - np.concatenate([np.zeros((1, 3, 3)), csum[at[:-1]]])
    acc[:1] = 0.0
    order = np.argsort(scans[keep], kind="stable")
    scans, t_ns, poses = scans[keep][order], t["t_ns"].to_numpy()[keep][order], poses[keep][order]
    if len(scans) < 2:
        raise UserError(f"{path}: {len(scans)} valid odometry poses; the slam stage needs at least 2 "
                        f"(rerun `pipeline run odometry --seq {seq} --force`)")
    return scans, t_ns.astype(np.int64), poses, acc


def read_radar(ctx: StageContext) -> tuple[npt.NDArray[np.int64], F64]:
    """The filtered radar points' scan numbers and radar-frame x, y, z."""
    t = read_artifact(ctx.input("filter", "radar_filtered.parquet"), "radar_filtered", columns=["scan", "x", "y", "z"])
    xyz = np.stack([t[c].to_numpy().astype(np.float64) for c in ("x", "y", "z")], axis=1)
    return t["scan"].to_numpy().astype(np.int64), xyz


def points_by_scan(point_scan: npt.NDArray[np.int64], xyz: F64, scans: npt.NDArray[np.int64],
                   base_from_radar: F64, p: SlamParams) -> list[tuple[F64, F64]]:
    """Each scan of ``scans``: its radar-frame points ``xyz`` (tagged ``point_scan``) in the 2D base frame inside
    the height gate, and the radar origin there."""
    order = np.argsort(point_scan, kind="stable")
    s, xyz = point_scan[order], xyz[order]
    lo = np.searchsorted(s, scans, side="left")
    hi = np.searchsorted(s, scans, side="right")
    return [radar_to_body_2d(xyz[a:b], base_from_radar, p.z_min, p.z_max) for a, b in zip(lo, hi, strict=True)]


def beam_samples_by_scan(point_scan: npt.NDArray[np.int64], xyz: F64, scans: npt.NDArray[np.int64],
                         base_from_radar: F64, p: SlamParams) -> list[BeamSamples]:
    """Body-frame beam samples of every scan in ``scans`` from radar-frame points ``xyz`` tagged ``point_scan``."""
    return [sample_beams(pts, origin, p.ray_step, p.max_range, p.min_range, p.free_clearance)
            for pts, origin in points_by_scan(point_scan, xyz, scans, base_from_radar, p)]


def graph_endpoints_by_scan(point_scan: npt.NDArray[np.int64], xyz: F64, scans: npt.NDArray[np.int64],
                            base_from_radar: F64, p: SlamParams) -> list[F64]:
    """radar_graph's input: each scan's points in the 2D base frame within ``graph_max_range`` of the radar (and
    beyond ``min_range``, inside the height gate)."""
    out = []
    for pts, origin in points_by_scan(point_scan, xyz, scans, base_from_radar, p):
        r = np.hypot(*(pts - origin).T) if len(pts) else np.zeros(0)
        out.append(pts[(r <= p.graph_max_range) & (r >= p.min_range)])
    return out


# -- radar_graph ---------------------------------------------------------------------------------------------------


def run_graph(ctx: StageContext, p: SlamParams, odo: F64, inc_cov: F64, t_ns: npt.NDArray[np.int64],
              endpoints: list[F64]) -> tuple[MethodResult, GraphResult]:
    """radar_graph on the stage's inputs (a one-line error for a log too short or GTSAM missing)."""
    t0 = time.perf_counter()
    try:
        g = optimise_graph(odo, inc_cov, (t_ns - t_ns[0]) * 1e-9, endpoints, p.graph_model())
    except ImportError as exc:
        raise UserError(f"slam.methods includes radar_graph: {exc} (or leave radar_graph out of slam.methods and "
                        "set slam.method to another method)") from None
    except ValueError as exc:
        raise UserError(f"{ctx.input('odometry', 'odometry.parquet')}: {exc}; lower slam.graph_keyframe_distance "
                        "or leave radar_graph out of slam.methods") from None
    res = MethodResult("radar_graph", g.poses, np.ones(len(g.poses)), time.perf_counter() - t0)
    return res, g


def write_graph(ctx: StageContext, g: GraphResult, scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64]
                ) -> None:
    """``graph_keyframes.parquet`` (the optimised keyframe poses and marginal covariances) and
    ``graph_edges.parquet`` (every factor between keyframes: kind, keyframes, measurement, inlier share, whether
    the optimiser kept it)."""
    k = g.keyframes
    pq.write_table(pa.table({
        "keyframe": pa.array(np.arange(len(k)), pa.int32()), "scan": pa.array(scans[k], pa.int32()),
        "t_ns": pa.array(t_ns[k], pa.int64()), "x": g.keyframe_poses[:, 0], "y": g.keyframe_poses[:, 1],
        "yaw": g.keyframe_poses[:, 2], "cov_xx": g.keyframe_cov[:, 0, 0], "cov_yy": g.keyframe_cov[:, 1, 1],
        "cov_yawyaw": g.keyframe_cov[:, 2, 2], "cov_xy": g.keyframe_cov[:, 0, 1],
        "cov_xyaw": g.keyframe_cov[:, 0, 2], "cov_yyaw": g.keyframe_cov[:, 1, 2],
    }), ctx.output("graph_keyframes.parquet"))
    e = g.edges
    pq.write_table(pa.table({
        "kind": pa.array([x.kind for x in e], pa.string()), "from_keyframe": pa.array([x.i for x in e], pa.int32()),
        "to_keyframe": pa.array([x.j for x in e], pa.int32()),
        "dx": pa.array([float(x.z[0]) for x in e], pa.float64()), "dy": pa.array([float(x.z[1]) for x in e],
                                                                             pa.float64()),
        "dyaw": pa.array([float(x.z[2]) for x in e], pa.float64()),
        "sigma_yaw_deg": pa.array([float(np.degrees(np.sqrt(x.cov[2, 2]))) for x in e], pa.float64()),
        "inliers": pa.array([x.inliers for x in e], pa.float64()),
        "accepted": pa.array([x.accepted for x in e], pa.bool_()),
    }), ctx.output("graph_edges.parquet"))


def log_graph(ctx: StageContext, g: GraphResult, scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64]) -> None:
    """Keyframes and loop-closure edges (accepted green, rejected red) on the ``scan`` timeline, each edge from
    the scan of its later keyframe on."""
    import rerun as rr

    rec = ctx.recording
    P = g.keyframe_poses
    k = g.keyframes
    xyz = np.column_stack([P[:, :2], np.zeros(len(P))])
    rec.points_over_time("world/slam/graph/keyframes", scans[k], t_ns[k], xyz, np.ones(len(k), dtype=np.int64),
                         radii=0.08)
    for e in g.edges:
        if e.kind != "loop":
            continue
        seg = np.array([[P[e.i, 0], P[e.i, 1], 0.0], [P[e.j, 0], P[e.j, 1], 0.0]])
        rec.log(f"world/slam/graph/{'loops' if e.accepted else 'rejected_loops'}/{e.i}_{e.j}",
                rr.LineStrips3D([seg], colors=[(40, 200, 80) if e.accepted else (230, 40, 40)]),
                scan=int(scans[k[e.j]]), t_ns=int(t_ns[k[e.j]]))


# -- map statistics and snapshots (Fig. 10, Rerun images) -------------------------------------------------------------


class MapTracker:
    """Per-scan uncertainty quartiles of the best particle's map and a few map snapshots."""

    def __init__(self, basis: hm.HilbertBasis, cfg: SlamConfig, p: SlamParams, samples: list[BeamSamples],
                 scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64], ctx: StageContext) -> None:
        self.basis, self.cfg, self.p, self.samples = basis, cfg, p, samples
        self.scans, self.t_ns = scans, t_ns
        lo, hi = basis.centre - basis.half_widths, basis.centre + basis.half_widths
        gx = np.arange(lo[0] + p.stats_spacing / 2, hi[0], p.stats_spacing)
        gy = np.arange(lo[1] + p.stats_spacing / 2, hi[1], p.stats_spacing)
        self.cells = np.stack(np.meshgrid(gx, gy, indexing="xy"), -1).reshape(-1, 2)
        self.prior_diag = hm.prior_variances(basis, cfg.lengthscale_m, cfg.signal_variance)
        self.cell_prior = hm.prior_variance_at(basis, self.prior_diag, self.cells)
        self.observed = np.zeros(len(self.cells), dtype=bool)
        self.rows: list[tuple[int, int, float, float, float, int, float]] = []
        T = len(scans)
        k = min(p.n_map_snapshots, T)
        self.snapshot_at = set(np.unique(np.linspace(0, T - 1, k).round().astype(int)).tolist()) if k else set()
        self.snapshots: list[tuple[int, int, F64, F64]] = []
        self.image_axes = (np.arange(lo[0] + p.image_spacing / 2, hi[0], p.image_spacing),
                           np.arange(lo[1] + p.image_spacing / 2, hi[1], p.image_spacing))

    def observe(self, i: int, f: Any, best: int) -> None:
        """At scan ``i`` of a Hilbert method's filter (``RBPF`` or ``TorchRBPF``): the best particle's pose
        (recorded in the history just before) and, every ``stats_every`` scans, its map."""
        assert hasattr(f.maps, "map_of")
        pose = f.history.best_pose[-1]
        last = i == len(self.scans) - 1
        if i % self.p.stats_every == 0 or last or i in self.snapshot_at:
            theta, cov = f.maps.map_of(best)
            self._observe_map(i, pose, theta, cov)
        else:
            self._observe_map(i, pose, None, None)

    def _observe_map(self, i: int, pose: F64, theta: F64 | None, cov: F64 | None) -> None:
        near = np.sum((self.cells - pose[:2]) ** 2, axis=1) <= self.p.max_range**2
        self.observed |= near
        last = i == len(self.scans) - 1
        if theta is None or cov is None:
            return
        if i % self.p.stats_every == 0 or last:
            idx = np.flatnonzero(self.observed)
            _, var, _ = hm.query(self.basis, theta.astype(np.float64), cov.astype(np.float64), self.cells[idx])
            u = var / np.maximum(self.cell_prior[idx], 1e-300)
            q = np.quantile(u, [0.25, 0.5, 0.75]) if len(u) else np.full(3, np.nan)
            self.rows.append((int(self.scans[i]), int(self.t_ns[i]), float(q[0]), float(q[1]), float(q[2]), len(idx),
                              float(np.mean(u)) if len(u) else float("nan")))
        if i in self.snapshot_at:
            gx, gy = self.image_axes
            g = np.stack(np.meshgrid(gx, gy, indexing="xy"), -1).reshape(-1, 2)
            _, var, occ = hm.query(self.basis, theta.astype(np.float64), cov.astype(np.float64), g)
            u = var / np.maximum(hm.prior_variance_at(self.basis, self.prior_diag, g), 1e-300)
            self.snapshots.append((int(self.scans[i]), int(self.t_ns[i]), occ.reshape(len(gy), len(gx)),
                                   u.reshape(len(gy), len(gx))))

    def replay(self, poses: F64) -> tuple[F64, F64]:
        """Statistics for a method without its own Hilbert maps: a map built along its poses (returned)."""
        theta, cov = hm.prior(self.basis, self.cfg.lengthscale_m, self.cfg.signal_variance)
        for i, (pose, s) in enumerate(zip(poses, self.samples, strict=True)):
            if s.n:
                phi = hm.features(self.basis, to_world(pose, s.points))
                theta, cov = hm.kalman_update(theta, cov, phi, s.labels, hm.label_noise_variance(
                    s.labels, self.cfg.noise_variance, self.cfg.endpoint_noise_variance), inplace=True)
            self._observe_map(i, pose, theta, cov)
        return theta, cov

    def write(self, path: Any) -> None:
        cols: list[Any] = list(zip(*self.rows, strict=True)) if self.rows else [[] for _ in range(7)]
        table = pa.table({
            "scan": pa.array(cols[0], pa.int32()), "t_ns": pa.array(cols[1], pa.int64()),
            "u_p25": pa.array(cols[2], pa.float64()), "u_p50": pa.array(cols[3], pa.float64()),
            "u_p75": pa.array(cols[4], pa.float64()), "n_cells": pa.array(cols[5], pa.int32()),
            "u_mean": pa.array(cols[6], pa.float64()),
        }).replace_schema_metadata({"description": "normalised predictive variance u(p) / u_prior(p) (eq. 33) of "
                                    "the best particle's map over the cells within max_range of its path so far"})
        pq.write_table(table, path)


# -- writing -------------------------------------------------------------------------------------------------


def write_trajectory(path: Any, scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64], res: MethodResult) -> None:
    write_artifact({"scan": scans.astype(np.int32), "t_ns": t_ns, "x": res.poses[:, 0], "y": res.poses[:, 1],
                    "yaw": res.poses[:, 2], "n_eff": res.n_eff}, path, "trajectory", metadata={"method": res.method})


def write_posterior(path: Any, basis: hm.HilbertBasis, theta: F64, cov: F64, p: SlamParams, last_scan: int) -> None:
    M = basis.M
    write_artifact({
        "theta": pa.array([np.asarray(theta, np.float64).tolist()], pa.list_(pa.float64())),
        "cov": pa.array([np.asarray(cov, np.float64).reshape(-1).tolist()], pa.list_(pa.float64())),
        "L1": [float(basis.half_widths[0])], "L2": [float(basis.half_widths[1])],
        "cx": [float(basis.centre[0])], "cy": [float(basis.centre[1])], "M": [M],
        "lengthscale": [p.lengthscale], "signal_variance": [p.signal_variance], "noise_variance": [p.noise_variance],
        "length_unit_m": [p.length_unit_m], "lengthscale_m": [p.lengthscale * p.length_unit_m],
        "basis_kind": [basis.kind], "method": [p.method], "scan": [last_scan],
    }, path, "map_posterior")


def query_grid(basis: hm.HilbertBasis, theta: F64, cov: F64, spacing: float, cfg: SlamConfig) -> dict[str, F64]:
    """The posterior on a regular grid over the domain (any spacing: the map is continuous)."""
    lo, hi = basis.centre - basis.half_widths, basis.centre + basis.half_widths
    gx = np.arange(lo[0] + spacing / 2, hi[0], spacing)
    gy = np.arange(lo[1] + spacing / 2, hi[1], spacing)
    g = np.stack(np.meshgrid(gx, gy, indexing="xy"), -1).reshape(-1, 2)
    mean, var, occ = hm.query(basis, np.asarray(theta, np.float64), np.asarray(cov, np.float64), g)
    u0 = hm.prior_variance_at(basis, hm.prior_variances(basis, cfg.lengthscale_m, cfg.signal_variance), g)
    return {"x": g[:, 0], "y": g[:, 1], "occupancy": occ, "variance": var, "mean": mean, "prior_variance": u0}


def _colormap(values: F64, name: str, vmin: float, vmax: float) -> npt.NDArray[np.uint8]:
    from matplotlib import colormaps

    v = np.clip((np.nan_to_num(values, nan=vmin) - vmin) / (vmax - vmin), 0.0, 1.0)
    return (colormaps[name](v)[..., :3] * 255).astype(np.uint8)


def log_recording(ctx: StageContext, scans: npt.NDArray[np.int64], t_ns: npt.NDArray[np.int64],
                  results: dict[str, MethodResult], main: str, tracker: MapTracker) -> None:
    import rerun as rr

    rec = ctx.recording
    colors = {"odometry": (70, 130, 255), "radar_graph": (250, 250, 80), "fastslam_grid": (60, 200, 90),
              "rich_slam": (230, 50, 50),
              "rich_slam_no_et": (170, 80, 220), "rich_slam_mean_only": (240, 160, 40)}
    for m, res in results.items():
        xyz = np.column_stack([res.poses[:, :2], np.zeros(len(res.poses))])
        entity = "world/slam/trajectory" if m == main else f"world/slam/methods/{m}"
        rec.trajectory(entity, scans, t_ns, xyz, color=colors.get(m, (255, 255, 255)))
    res = results[main]
    if res.particles is not None and len(res.particles):
        T, Np = res.particles.shape[:2]
        pts = np.concatenate([res.particles[..., :2], np.zeros((T, Np, 1))], axis=-1).reshape(-1, 3)
        rec.points_over_time("world/slam/particles", scans, t_ns, pts, np.full(T, Np), radii=0.03)
        rec.scalars("metrics/slam/n_eff", scans, t_ns, res.n_eff)
    for scan, t, occ, u in tracker.snapshots:
        # image rows run from +y (top) down
        rec.log("world/slam/map/occupancy", rr.Image(_colormap(occ[::-1], "viridis", 0.0, 1.0)), scan=scan, t_ns=t)
        rec.log("world/slam/map/uncertainty", rr.Image(_colormap(u[::-1], "magma", 0.0, 1.0)), scan=scan, t_ns=t)


STAGE = SlamStage()
