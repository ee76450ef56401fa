"""Sensor model parameters (defaults: TI AWR1843 single-chip radar, Ouster OS1-16, LORD 3DM-GX5 IMU).

A world file may override any of them in its ``[radar]``, ``[lidar]`` and ``[imu]`` tables.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from core.errors import UserError


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RadarParams(_Params):
    """Single-chip FMCW radar detections (what the TI driver publishes on /mmWaveDataHdl/RScan).

    Scene: persistent scatterers (``simulator.scatterers``). Processing: the TI mmWave SDK chain (range and
    Doppler FFT, CFAR in Doppler and range, peak grouping, 64-bin azimuth FFT, elevation by phase
    comparison); see ``simulator.radar`` and data/datasets/coloradar.md ("radar model") for the evidence.
    """

    fov_azimuth_deg: float = Field(60.0, gt=0, lt=90, description="half field of view in azimuth (driver filter)")
    fov_elevation_deg: float = Field(25.0, gt=0, lt=80, description="half field of view in elevation (driver filter)")
    min_range: float = Field(0.3, ge=0, description="closest reported detection, m")
    max_range: float = Field(12.0, gt=0, description="farthest reported detection (CFAR range limit), m")
    range_resolution: float = Field(0.125, gt=0, description="range bin width; reported range = bin index * width, m")
    doppler_resolution: float = Field(0.04, gt=0, description="Doppler bin width; reported Doppler = bin * width, m/s")
    doppler_max: float = Field(2.56, gt=0, description="unambiguous Doppler; faster radial speeds wrap, m/s")
    n_azimuth_bins: int = Field(64, ge=8, description="azimuth FFT size (zero-padded 8 virtual azimuth channels)")
    snr_ref_db: float = Field(84.5, description="per-channel SNR of a 1 m^2 point scatterer at 1 m on boresight, dB "
                                                "(link budget after range and Doppler FFT; coloradar.md)")
    range_loss_db_per_decade: float = Field(40.0, ge=0, description="SNR loss per decade of range (radar equation, "
                                                                    "point scatterers: 40)")
    beam_azimuth_3db_deg: float = Field(55.0, gt=0, description="azimuth angle where the antenna gain is -3 dB")
    beam_elevation_3db_deg: float = Field(22.0, gt=0, description="elevation angle where the antenna gain is -3 dB")
    cfar_threshold_db: float = Field(15.0, description="CFAR threshold over the noise estimate, dB (cfarCfg)")
    cfar_range_window: int = Field(8, ge=1, description="range CFAR (CASO) one-sided noise window, bins")
    cfar_range_guard: int = Field(4, ge=0, description="range CFAR one-sided guard, bins")
    cfar_doppler_window: int = Field(4, ge=1, description="Doppler CFAR (CA, cyclic) one-sided noise window, bins")
    cfar_doppler_guard: int = Field(2, ge=0, description="Doppler CFAR one-sided guard, bins")
    peak_grouping: bool = Field(
        False,
        description="keep a detected cell only if no range/Doppler neighbour is stronger (off, as in the TI ROS "
        "driver's 3D configuration; on gives 10-18 points per scan, below the tens to ~200 of ColoRadar's clouds)",
    )
    multi_peak_ratio: float = Field(0.5, ge=0, le=1, description="report a second azimuth peak of a cell when its "
                                                                 "power exceeds this share of the first (0: off)")
    max_points: int = Field(200, ge=1, description="most detections reported per scan (strongest kept)")
    clutter_rate: float = Field(3.0, ge=0, description="mean number of clutter false alarms per scan (Poisson)")
    clutter_snr_scale_db: float = Field(2.0, gt=0, description="clutter SNR = CFAR threshold + an exponential of "
                                                                "this mean, dB (larger: clutter survives the "
                                                                "max_points cap)")
    ghost_loss_db: float = Field(3.0, ge=0, description="extra loss of a double-bounce (mirror) path besides the "
                                                        "mirror's reflectivity, dB")
    scatterer_density: float = Field(4.0, gt=0, description="diffuse scatterers per m^2 on walls, boxes, floor and "
                                                             "ceiling")
    surface_sigma0_db: float = Field(-15.0, description="backscatter coefficient of a 0 dB material at normal "
                                                        "incidence, dB m^2/m^2")
    incidence_exponent: float = Field(2.0, ge=0, description="diffuse backscatter scales with cos(incidence)**exponent")
    dihedral_rcs_db: float = Field(10.0, description="RCS of a concave corner or wall/floor junction, dBsm")
    trihedral_rcs_db: float = Field(15.0, description="RCS of a concave room corner at the floor or ceiling, dBsm")
    edge_rcs_db: float = Field(-10.0, description="RCS of a convex edge (diffraction), dBsm")
    pillar_rcs_db: float = Field(5.0, description="RCS of a 0.1 m radius pillar (specular line), dBsm; "
                                                  "scales with the radius")
    tip_loss_db: float = Field(15.0, ge=0, description="loss of a line scatterer seen beyond its end (tip), dB")
    strong_rcs_spread_db: float = Field(3.0, ge=0, description="std of the once-drawn RCS of strong scatterers, dB")
    time_jitter: float = Field(0.001, ge=0, description="std of the scan period jitter, s")
    # --- real-radar effects the physical model lacks in voxel worlds (all off by default, so that
    # every existing log stays bit-identical; the drifting ColoRadar twins turn them on, simulator/twin.py) ---
    multipath_ghost_share: float = Field(0.0, ge=0, le=2, description="mean number of multipath ghosts per "
                                         "detected scene point (Poisson per scan): each is the mirror image "
                                         "of a detected point in the vertical plane through another detected "
                                         "point (a wall the radar sees), a virtual static target behind it")
    multipath_ghost_loss_db: float = Field(12.0, ge=0, description="SNR of a multipath ghost below its "
                                           "source point's, dB")
    doppler_outlier_share: float = Field(0.0, ge=0, le=1, description="share of reported scene points whose "
                                         "Doppler is replaced by a uniform draw over the Doppler bins (moving "
                                         "people, interference, cells whose Doppler belongs to another return)")
    elevation_noise_deg: float = Field(0.0, ge=0, le=30, description="std of an extra error of each scene "
                                       "point's elevation angle, deg (the 4-channel elevation estimate's "
                                       "spread beyond the model's phase noise)")


#: the RadarParams fields of the real-radar effects (all off by default)
REALISM_FIELDS = ("multipath_ghost_share", "multipath_ghost_loss_db", "doppler_outlier_share", "elevation_noise_deg")


def radar_dump(p: RadarParams) -> dict[str, Any]:
    """``p.model_dump()`` without :data:`REALISM_FIELDS` when the effects are off (a sidecar's ``meta.json``
    stays byte-identical to the one written before they existed)."""
    out = p.model_dump()
    if not (p.multipath_ghost_share or p.doppler_outlier_share or p.elevation_noise_deg):
        for k in REALISM_FIELDS:
            out.pop(k)
    return out


class LidarParams(_Params):
    """Spinning lidar like the Ouster OS1 (16 beams, reduced column count for speed and size)."""

    beams: int = Field(16, ge=1, le=128, description="number of beams (rings)")
    columns: int = Field(256, ge=8, le=2048, description="columns per revolution")
    vertical_fov_deg: float = Field(33.2, gt=0, lt=180, description="total vertical field of view, degrees")
    min_range: float = Field(0.5, ge=0, description="closest return, m")
    max_range: float = Field(100.0, gt=0, description="farthest return, m")
    range_noise: float = Field(0.01, ge=0, description="range noise std, m")
    dropout: float = Field(0.005, ge=0, le=1, description="probability that a valid return is missing")
    intensity_scale: float = Field(2000.0, gt=0, description="intensity = scale * reflectivity * cos / range^2")


class ImuParams(_Params):
    """MEMS IMU (3DM-GX5 class) with white noise and random-walk biases; accelerometer includes gravity."""

    gyro_noise_density: float = Field(1.5e-4, ge=0, description="gyro white noise, rad/s/sqrt(Hz)")
    accel_noise_density: float = Field(6.0e-4, ge=0, description="accelerometer white noise, m/s^2/sqrt(Hz)")
    gyro_bias_sigma: float = Field(2.0e-3, ge=0, description="std of the initial gyro bias, rad/s")
    accel_bias_sigma: float = Field(0.03, ge=0, description="std of the initial accelerometer bias, m/s^2")
    gyro_bias_walk: float = Field(2.0e-5, ge=0, description="gyro bias random walk, rad/s/sqrt(s)")
    accel_bias_walk: float = Field(3.0e-4, ge=0, description="accelerometer bias random walk, m/s^2/sqrt(s)")
    gravity: float = Field(9.80665, gt=0, description="gravity magnitude, m/s^2")


def make_params(model: type[_Params], overrides: dict[str, Any], where: str) -> Any:
    """Build a parameter model from a world file's table; errors name the file and the parameter."""
    try:
        return model(**overrides)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(x) for x in first["loc"])
        raise UserError(f"{where}: {loc}: {first['msg']}") from None
