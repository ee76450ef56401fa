"""The evaluate stage's parameters, in groups: trajectories, the mapping AUC protocol (RICH-SLAM Fig. 6-7), the
HILBERT-GP and baseline maps it compares, the uncertainty figures and the RMap map metrics."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from core.stage import ParamGroup, StageParams

Section = Literal["trajectory", "mapping", "uncertainty", "rmap"]
MappingMethod = Literal["hilbert_gp", "rff", "sparse", "nystrom", "grid"]


class TrajectoryParams(ParamGroup):
    """Trajectory errors against ground truth."""

    n_align: int = Field(100, ge=2, le=10_000_000, description="the paper's protocol: SE(2) alignment on the first N "
                         "ground-truth-matched frames (the whole-trajectory alignment is reported beside it)")
    max_gt_gap_s: float = Field(0.5, gt=0, description="an estimate is matched only when the ground-truth samples "
                                "around its time are at most this far apart (s)")


class MappingParams(ParamGroup):
    """The AUC protocol: occupancy samples from the radar along ground truth, held-out scans."""

    auc_points: Literal["filtered", "raw"] = Field("filtered", description="radar points of the AUC protocol: the "
                                                   "filter stage's output or the raw detections")
    test_fraction: float = Field(0.2, gt=0, lt=1, description="share of scans held out for the AUC")
    split_block_scans: int = Field(10, ge=1, le=1_000_000, description="scans are held out in contiguous blocks of "
                                   "this size (blocks drawn at random with the seed)")
    free_per_metre: float = Field(0.5, gt=0, description="free samples per metre of beam: max(1, floor(d * this)) "
                                  "per beam, uniform in [0, d - 0.1] (Hilbert maps: 0.5)")
    max_range: float | None = Field(None, gt=0, description="drop beams longer than this (m); default: the slam "
                                    "stage's beams.max_range (5 m, Table II)")
    z_min: float | None = Field(None, description="keep radar points with base-frame z >= z_min (m); default: the "
                                "slam stage's gate if it has one")
    z_max: float | None = Field(None, description="keep radar points with base-frame z <= z_max (m); default: the "
                                "slam stage's gate if it has one")
    methods: list[MappingMethod] = Field(["hilbert_gp", "rff", "sparse", "nystrom", "grid"],
                                         description="mapping methods of the AUC comparison")
    feature_counts: list[int] = Field([64, 144, 256, 400], description="numbers of map features (Fig. 6); perfect "
                                      "squares for the tensor Hilbert basis")
    headline: bool = Field(True, description="also score every method at the slam stage's feature count M (the rows "
                           "without @) and write gt_map_grid.parquet / gt_map.png")
    domain_padding: float | None = Field(None, ge=0, description="Hilbert domain = ground-truth envelope padded by "
                                         "this (m); default: the slam stage's")
    grid_spacing: float = Field(0.25, ge=0.01, description="query spacing of the maps written and plotted (m)")


class GPParams(ParamGroup):
    """HILBERT-GP's hyperparameters in the comparison (default: the slam posterior's)."""

    lengthscale_m: float | None = Field(None, gt=0, description="length scale, m")
    signal_variance: float | None = Field(None, gt=0, description="signal variance")
    noise_variance: float | None = Field(None, gt=0, description="noise variance")


class BaselineParams(ParamGroup):
    """The SGD-trained Hilbert-map baselines (RFF, sparse, Nystrom) and the count-grid reference."""

    lengthscale_m: float = Field(1.0, gt=0, description="SE length scale of the RFF and Nystrom baselines and the "
                                 "minimum sparse-kernel support (m)")
    alpha: float = Field(1e-4, gt=0, description="L2 penalty of the SGD baselines (also sets the learning rate "
                         "1 / (alpha (t0 + t)))")
    epochs: int = Field(1, ge=1, le=10_000, description="passes over the training scans for the SGD baselines")
    sparse_support_factor: float = Field(2.0, gt=0, description="sparse-kernel support in inducing-grid spacings")
    grid_resolution: float = Field(0.5, ge=0.01, description="cell size of the count-grid reference (m)")


class UncertaintyParams(ParamGroup):
    """The map-uncertainty figures (Fig. 9-10)."""

    every: int = Field(10, ge=1, le=1_000_000, description="record the uncertainty quartiles every N scans")
    query_spacings: list[float] = Field([10.0, 2.0, 1.0, 0.25], description="grid spacings (m) at which the slam map "
                                        "posterior is queried for the resolution figure (Fig. 9)")


class EvaluateParams(StageParams):
    """Parameters of the `evaluate` stage."""

    sections: list[Section] = Field(["trajectory", "mapping", "uncertainty", "rmap"],
                                    description="what to evaluate: trajectory, mapping, uncertainty, rmap")
    seed: int = Field(0, description="seed of every random draw (split, free samples, random features)")
    fscore_threshold: float = Field(0.15, gt=0, description="RMap's F-score distance d (m): one voxel")
    blas_threads: int = Field(1, ge=0, le=256, description="BLAS threads while evaluating (0: leave the library's "
                              "default); the matrices are small, and a multi-threaded BLAS on a busy machine spins "
                              "more than it computes")
    trajectory: TrajectoryParams = Field(default_factory=TrajectoryParams, description="trajectory errors")
    mapping: MappingParams = Field(default_factory=MappingParams, description="the AUC protocol")
    gp: GPParams = Field(default_factory=GPParams, description="HILBERT-GP in the comparison")
    baselines: BaselineParams = Field(default_factory=BaselineParams, description="the SGD baselines")
    uncertainty: UncertaintyParams = Field(default_factory=UncertaintyParams, description="uncertainty figures")
