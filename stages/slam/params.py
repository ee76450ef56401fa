"""The slam stage's parameters, in groups: the Hilbert-GP map, the beams, the pose graph, the grid baseline.

One object: the stage validates it from its layers and the algorithms read it (``p.map.n_basis``,
``p.graph.loop_radius``). What the paper fixes and no user needs to change (GMapping's motion model of eq. 21,
the resampler, the discretised endpoint-tolerance disc, the grid's inverse sensor model, the output grids) is a
constant beside the algorithm that uses it.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from core.stage import ParamGroup, StageParams
from stages.slam.method_names import METHODS, PAPER_ENDPOINT_TOLERANCE, Method


class MapParams(ParamGroup):
    """The particles' Hilbert-space reduced-rank GP occupancy map (Sec. III, Table II)."""

    lengthscale_m: float = Field(2.0, gt=0, le=1000, description="SE length scale l in metres (Table II: 20 in the "
                                 "paper's 0.1 m map units)")
    signal_variance: float = Field(16.0, gt=0, description="sigma_f^2 (Table II: 16 ColoRadar, 0.7 ARS548)")
    noise_variance: float = Field(0.36, gt=0, description="sigma_n^2 (Table II: 0.36 ColoRadar, 0.1 ARS548)")
    n_basis: int = Field(256, ge=4, le=4096, description="basis functions M (a perfect square: the tensor basis of "
                         "eq. 7)")
    endpoint_tolerance: float = Field(PAPER_ENDPOINT_TOLERANCE, ge=0, description="endpoint tolerance radius r_e "
                                      "(m, eq. 29; the paper: 0.25); rich_slam_no_et always 0")
    dtype: Literal["float64", "float32"] = Field("float64", description="precision of the particle maps")

    @field_validator("n_basis")
    @classmethod
    def _square(cls, n: int) -> int:
        if round(n**0.5) ** 2 != n:
            raise ValueError(f"{n} is not a perfect square (the tensor basis of eq. 7 needs one)")
        return n


class BeamParams(ParamGroup):
    """Radar points to beams (Sec. IV-B, Fig. 3a): the filters' measurements."""

    max_range: float = Field(5.0, gt=0, description="beams longer than this are dropped (m, Table II)")
    ray_step: float = Field(1.0, ge=0.01, description="free-sample spacing along a beam (m, Table II)")
    z_min: float | None = Field(None, description="keep points with base-frame z >= z_min (m); None: no gate")
    z_max: float | None = Field(None, description="keep points with base-frame z <= z_max (m); None: no gate")

    @model_validator(mode="after")
    def _gate(self) -> BeamParams:
        if self.z_min is not None and self.z_max is not None and self.z_min > self.z_max:
            raise ValueError(f"z_min {self.z_min} > z_max {self.z_max}")
        return self


class GraphParams(ParamGroup):
    """radar_graph, the keyframe pose graph (:mod:`stages.slam.pose_graph`); chosen on the calibration runs."""

    max_range: float = Field(10.0, gt=0, description="endpoints up to this range (m) enter the keyframe clouds "
                             "(longer than the filters' beams: more structure)")
    keyframe_distance: float = Field(1.0, gt=0, description="a keyframe every this many metres of odometry travel")
    keyframe_angle: float = Field(15.0, gt=0, description="or every this many degrees turned")
    local_keyframes: int = Field(10, ge=1, le=1000, description="keyframes in the query cloud of a loop closure; "
                                 "the reference is the earlier pass within local_keyframes / 2 * "
                                 "keyframe_distance + max_range of the candidate")
    bias_sigma0: float = Field(0.01, gt=0, le=1, description="prior std of the yaw-rate bias the odometry leaves, "
                               "rad/s (each keyframe carries one)")
    bias_walk: float = Field(1e-4, gt=0, le=1, description="random walk of that bias, rad/s/sqrt(s)")
    loop_radius: float = Field(3.0, gt=0, description="keyframes this close on the odometry are loop candidates, "
                               "and the verification's translation search (m)")
    loop_min_travel: float = Field(15.0, gt=0, description="path length between the two keyframes of a loop "
                                   "candidate (m)")
    loop_search_yaw: float = Field(20.0, gt=0, le=180, description="the loop verification's yaw search (+- deg)")
    loop_min_inliers: float = Field(0.7, gt=0, le=1, description="share of the query's points within 0.3 m of the "
                                    "reference for a closure to be proposed (chosen on the calibration runs)")
    loop_rounds: int = Field(3, ge=1, le=10, description="rounds of loop proposals: each after the first "
                             "proposes from the poses the round before optimised (chosen on the calibration runs)")
    match_sigma: float = Field(0.15, gt=0, description="the registration's likelihood-field std (m)")
    match_temperature: float = Field(30.0, gt=0, description="divides the summed point log-likelihood in the "
                                     "registration covariance (points are not independent; chosen for a NEES near 3 "
                                     "on the calibration runs)")


class GridParams(ParamGroup):
    """fastslam_grid, the paper's FastSLAM-Radar baseline (occupancy grids and a likelihood field)."""

    resolution: float = Field(0.1, ge=0.01, description="cell size (m)")


class SlamParams(StageParams):
    """Parameters of the `slam` stage (defaults: RICH-SLAM Table II and Sec. IV, ColoRadar profile; radar_graph's
    chosen on the calibration runs)."""

    method: Method = Field("radar_graph", description="method whose trajectory is trajectory.parquet; the map "
                           "outputs are built along it (a Hilbert method's best particle's own map)")
    methods: list[Method] = Field(list(METHODS), description="methods run and written as "
                                  "trajectory_<method>.parquet (the main method always runs)")
    n_particles: int = Field(200, ge=1, le=100_000, description="particles N_p of the filters (Sec. V-A2)")
    seed: int = Field(0, description="seed of the particle filters' random generator")
    workers: int = Field(2, ge=0, le=256, description="worker processes sharing the particle maps, one BLAS thread "
                         "each; 0 = in process (numpy backend)")
    backend: Literal["numpy", "torch"] = Field(
        "numpy", description="array backend of the RICH-SLAM particle maps and filter loop: numpy (CPU, worker "
        "processes) or torch (batched tensors on slam.device; needs the learn extra)")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="device of the torch backend: cuda, cpu, or auto (cuda when torch sees one, else cpu)")
    map: MapParams = Field(default_factory=MapParams, description="the Hilbert-GP map")
    beams: BeamParams = Field(default_factory=BeamParams, description="the filters' beams")
    graph: GraphParams = Field(default_factory=GraphParams, description="radar_graph")
    grid: GridParams = Field(default_factory=GridParams, description="fastslam_grid")

    @model_validator(mode="after")
    def _check(self) -> SlamParams:
        if self.backend == "numpy" and self.device == "cuda":
            raise ValueError("device = cuda needs backend = torch (the numpy backend runs on the cpu)")
        return self
