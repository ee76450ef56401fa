"""The filter stage's parameters, in groups: which points feed the ego-velocity, the estimator (REVE's defaults),
the point-uncertainty gate and the multi-frame tracking.

One object: the stage validates it from its layers and the algorithms read it (``p.ego_velocity`` is what
:func:`stages.filter.ego_velocity.estimate` takes).
"""

from __future__ import annotations

from pydantic import Field

from core.stage import ParamGroup, StageParams


class PointParams(ParamGroup):
    """The radar points used: range, intensity and the estimator's field of view; the static test."""

    min_range_m: float = Field(0.25, ge=0, description="points closer than this are dropped (REVE min_dist)")
    max_range_m: float = Field(100.0, gt=0, description="points farther than this are dropped (REVE max_dist)")
    min_intensity: float = Field(5.0, description="intensity gate, in the radar's intensity unit (REVE min_db, dB)")
    max_azimuth_deg: float = Field(56.5, gt=0, le=180, description="|azimuth| limit of points used for the "
                                   "ego-velocity (REVE)")
    max_elevation_deg: float = Field(45.0, gt=0, le=90, description="|elevation| limit of points used for the "
                                     "ego-velocity (ColoRadar tools' +-45 deg field of view; REVE's own sensor: 22.5)")
    static_threshold_mps: float = Field(0.15, gt=0, description="keep points with |d + r.v| below this (static "
                                        "world)")


class EgoVelocityParams(ParamGroup):
    """The Doppler ego-velocity estimator: RANSAC, then least squares (REVE, Doer & Trommer 2020)."""

    inlier_threshold: float = Field(0.15, gt=0, description="RANSAC Doppler inlier threshold, m/s (REVE)")
    outlier_probability: float = Field(0.4, gt=0, lt=1, description="assumed outlier fraction for the RANSAC count")
    success_probability: float = Field(0.9999, gt=0, lt=1, description="RANSAC success probability")
    max_iterations: int = Field(200, ge=1, le=100_000, description="cap on RANSAC hypotheses")
    min_points: int = Field(5, ge=3, le=100_000, description="fewest usable points for an ego-velocity estimate")
    zero_velocity_threshold: float = Field(0.05, ge=0, description="zero-velocity test threshold, m/s (REVE)")
    allowed_outlier_fraction: float = Field(0.3, ge=0, lt=1, description="outlier share tolerated by the "
                                            "zero-velocity test (REVE)")
    sigma_offset: float = Field(0.05, ge=0, description="added to the LSQ velocity std, m/s (REVE sigma_offset)")
    max_condition: float = Field(1000.0, gt=1, description="LSQ condition bound; above it v_z is fixed to 0")
    max_sigma_xy: float = Field(0.2, gt=0, description="largest LSQ std of v_x, v_y for a valid estimate, m/s (REVE)")
    max_sigma_z: float = Field(0.2, gt=0, description="largest LSQ std of v_z, m/s; above it v_z is fixed to 0")
    max_vz: float = Field(1.0, gt=0, description="largest plausible |v_z|, m/s (radar z up); 3D solutions beyond it "
                          "fall back to the planar model")
    doppler_sigma_floor: float = Field(0.05, ge=0, description="floor of the LSQ residual std, m/s (Doppler "
                                       "resolution ~0.04 m/s)")
    temporal_prior: bool = Field(True, description="offer the previous scan's velocity as a RANSAC hypothesis; it "
                                 "wins ties in the inlier count")


class UncertaintyParams(ParamGroup):
    """The point-uncertainty gate: each point's modelled position covariance."""

    range_sigma_m: float = Field(0.0625, ge=0, description="modelled range noise std (half a 0.125 m range bin)")
    azimuth_sigma_deg: float = Field(5.5, ge=0, description="modelled azimuth noise std (half the ~11 deg "
                                     "resolution)")
    elevation_sigma_deg: float = Field(22.5, ge=0, description="modelled elevation noise std (half the ~45 deg "
                                       "resolution)")
    max_sigma_m: float = Field(1.0, gt=0, description="largest position std of a kept point, m")
    horizontal: bool = Field(True, description="gate on the horizontal (base xy) block of the covariance")


class TrackingParams(ParamGroup):
    """Multi-frame tracking: a point is kept when it is matched in the previous scans."""

    frames: int = Field(2, ge=0, le=100, description="previous scans a point must be matched in (0 = no tracking)")
    gate_m: float = Field(0.3, ge=0, description="match radius for tracking, m")
    gate_sigma_scale: float = Field(1.0, ge=0, description="adds this many modelled point stds to the gate")
    use_z: bool = Field(False, description="match in 3D (default: horizontal x, y of the radar frame)")
    max_scan_gap_s: float = Field(0.5, gt=0, description="a larger gap between scans breaks every track")


class FilterParams(StageParams):
    """Parameters of the `filter` stage (REVE's defaults for the ego-velocity estimator)."""

    seed: int = Field(0, description="seed of the RANSAC sampling")
    gt_velocity_half_window_s: float = Field(0.05, gt=0, description="central difference half-window for "
                                             "ground-truth velocity")
    rerun_every: int = Field(1, ge=1, le=1_000_000, description="log every n-th scan's kept/rejected points to Rerun")
    points: PointParams = Field(default_factory=PointParams, description="points used")
    ego_velocity: EgoVelocityParams = Field(default_factory=EgoVelocityParams, description="ego-velocity estimator")
    uncertainty: UncertaintyParams = Field(default_factory=UncertaintyParams, description="point-uncertainty gate")
    tracking: TrackingParams = Field(default_factory=TrackingParams, description="multi-frame tracking")
