"""The odometry stage's parameters, in groups: the IMU's noise, the start, the standstill, the velocity update,
the recovery, the height (mount and level prior), the increment covariance, and the log's own odometry.

One object: the stage validates it from its layers and :func:`stages.odometry.ekf_rio.run_ekf` reads it.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from core.stage import ParamGroup, StageParams


class ImuParams(ParamGroup):
    """The filter's IMU process noise (error-state propagation)."""

    gravity: float = Field(9.80665, gt=0, description="gravity magnitude, m/s^2")
    accel_noise_density: float = Field(
        0.2, gt=0, description="accelerometer process noise, m/s^2/sqrt(Hz): MEMS white noise is ~0.002, the rest "
                               "covers unmodelled vibration (heel strikes, engines) and misalignment")
    gyro_noise_density: float = Field(0.002, gt=0, description="gyro white noise, rad/s/sqrt(Hz)")
    accel_bias_walk: float = Field(1e-3, ge=0, description="accelerometer bias random walk, m/s^2/sqrt(s)")
    gyro_bias_walk: float = Field(1e-4, ge=0, description="gyro bias random walk, rad/s/sqrt(s)")


class InitParams(ParamGroup):
    """The initial state and its uncertainty."""

    sigma_v0: float = Field(0.2, gt=0, description="initial velocity std, m/s")
    sigma_attitude0_deg: float = Field(2.0, gt=0, description="initial roll/pitch std, degrees")
    sigma_gyro_bias0: float = Field(0.005, gt=0, description="initial gyro bias std, rad/s (MEMS turn-on bias)")
    sigma_accel_bias0: float = Field(0.1, gt=0, description="initial accelerometer bias std, m/s^2")
    window_s: float = Field(0.2, gt=0, description="IMU window (each side of the first scan) for gravity")
    motion_compensation: bool = Field(
        True, description="remove the kinematic acceleration (from the first ego-velocities) before gravity alignment")


class StandstillParams(ParamGroup):
    """Starting from an initial standstill (attitude, biases and noise floors from it)."""

    enabled: bool = Field(True, description="start from an initial standstill when there is one")
    min_s: float = Field(1.0, gt=0, description="shortest initial standstill used, s")
    accel_std: float = Field(0.3, gt=0, description="largest specific-force std per axis in a 0.2 s window, m/s^2")
    gyro_std: float = Field(0.03, gt=0, description="largest rate std per axis, rad/s")
    max_speed: float = Field(0.15, gt=0, description="largest radar speed, m/s")
    accel_change: float = Field(0.15, gt=0, description="largest change of the mean specific force from the first "
                                "window, m/s^2")
    gyro_change: float = Field(0.01, gt=0, description="largest change of the mean rate from the first window, rad/s")


class VelocityParams(ParamGroup):
    """The Doppler ego-velocity update and the zero-rate update."""

    use_estimator_covariance: bool = Field(True, description="use the ego-velocity LSQ covariance as R")
    cov_scale: float = Field(1.0, gt=0, description="scales the ego-velocity covariance")
    sigma_mps: float = Field(0.1, gt=0, description="fixed ego-velocity std when not using the estimator's")
    gate_probability: float = Field(0.999, gt=0, lt=1, description="chi-square gate of the velocity update")
    zero_rate_update: bool = Field(True, description="zero angular-rate update on zero-velocity scans")
    zero_rate_sigma: float = Field(0.002, gt=0, description="std of the zero angular-rate pseudo-measurement, rad/s")
    zero_rate_min_scans: int = Field(5, ge=1, le=100_000,
                                     description="consecutive zero-velocity scans before a zero-rate update")


class RecoveryParams(ParamGroup):
    """Recovery of a filter that is off: covariances raised after a streak of rejected updates."""

    after: int = Field(3, ge=1, le=100_000, description="velocity updates rejected in a row before the covariance "
                       "is inflated and the update retried")
    consistent: bool = Field(True, description="recover only when the rejected velocity innovations agree with one "
                             "another (the filter is off); scattered ones are the radar's outliers and are only "
                             "rejected")
    sigma_v: float = Field(0.5, gt=0, description="velocity std after a recovery, m/s")
    sigma_attitude_deg: float = Field(5.0, gt=0, description="attitude std after a recovery, degrees")
    sigma_accel_bias: float = Field(0.3, gt=0, description="accelerometer bias std after a recovery, m/s^2")


class HeightParams(ParamGroup):
    """The radar's mount as a filter state and a level prior (off by default; on in the radar-only workflow)."""

    mount_sigma0_deg: float = Field(
        0.0, ge=0, le=20, description="estimate the radar mount's rotation error with this prior std per axis, degrees "
                                      "(a pitched radar reads forward speed as climb); 0: trust the stated extrinsic")
    level_velocity_sigma: float = Field(
        0.0, ge=0, description="a zero vertical-velocity pseudo-measurement at every scan with this std, m/s (the "
                               "platform moves on level floors on average); 0: none")
    level_schmidt: bool = Field(
        True, description="the level pseudo-measurement moves only the height, the vertical velocity and the mount "
                          "(a Schmidt update: attitude and biases keep their means); false: a full update")


class CovarianceParams(ParamGroup):
    """The increment covariance written (a suboptimal-filter covariance analysis, Gelb 1974 ch. 7)."""

    accel_noise_density: float | None = Field(
        2.0e-3, gt=0, description="the accelerometer white noise it assumes, m/s^2/sqrt(Hz) (datasheet, low-cost MEMS: "
                                  "BMI088 ~190 ug/sqrt(Hz)); null: the filter's imu.accel_noise_density")
    gyro_noise_density: float | None = Field(
        2.5e-4, gt=0, description="the gyro white noise it assumes, rad/s/sqrt(Hz) (datasheet, BMI088 0.014 "
                                  "deg/s/sqrt(Hz)); null: the filter's imu.gyro_noise_density")
    velocity_scale: float = Field(
        0.125, gt=0, description="factor on the ego-velocity covariance it assumes (chosen on calibration runs only)")
    scale: float = Field(1.0, gt=0, description="factor on the increment covariance written (the NEES check: chosen "
                         "on calibration runs only)")


class BagParams(ParamGroup):
    """source = bag: the increment covariance given to the log's own odometry."""

    std_xy: float = Field(0.005, gt=0, description="increment std on x and y per scan, m")
    rel_trans: float = Field(0.05, ge=0, description="increment std on x and y per metre, m/m")
    std_yaw: float = Field(0.001, gt=0, description="increment yaw std per scan, rad")
    rot_per_trans: float = Field(0.03, ge=0, description="increment yaw std per metre, rad/m")


class OdometryParams(StageParams):
    """Parameters of the `odometry` stage (EKF-RIO, Doer & Trommer 2020)."""

    source: Literal["ekf", "bag"] = Field("ekf", description="'ekf': EKF-RIO; 'bag': the log's odometry topic")
    anchor: Literal["groundtruth", "origin"] = Field(
        "groundtruth", description="start at the ground-truth pose of the first scan, or at (0, 0, 0)")
    reject_warn_share: float = Field(0.1, ge=0, le=1, description="warn when more than this share of velocity "
                                                                  "updates is rejected by the gate")
    imu: ImuParams = Field(default_factory=ImuParams, description="IMU process noise")
    init: InitParams = Field(default_factory=InitParams, description="initial state")
    standstill: StandstillParams = Field(default_factory=StandstillParams, description="initial standstill")
    velocity: VelocityParams = Field(default_factory=VelocityParams, description="velocity update")
    recovery: RecoveryParams = Field(default_factory=RecoveryParams, description="recovery")
    height: HeightParams = Field(default_factory=HeightParams, description="mount and level prior")
    covariance: CovarianceParams = Field(default_factory=CovarianceParams, description="increment covariance")
    bag: BagParams = Field(default_factory=BagParams, description="source = bag")
