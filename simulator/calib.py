"""The ``calib/`` folder of the extracted form: transforms and single-chip radar configuration files.

``transforms/base_to_*.txt`` hold two lines, ``tx ty tz`` and ``qx qy qz qw`` (base <- sensor), written as
the dataset's ``bag_to_config.py`` does from the bag's ``/tf`` (``base_to_lidar`` composes ``os1_sensor``
with the driver's fixed ``os1_sensor -> os1_lidar`` offset). The radar configuration files use the
documented ``key value`` layout; their values describe a plausible AWR1843 chirp (we do not simulate
ADC samples or heatmaps), consistent with the simulated range and Doppler resolution.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from simulator import rig

C = 299_792_458.0

WAVEFORM: tuple[tuple[str, float | int], ...] = (
    ("num_rx", 4),
    ("num_tx", 3),
    ("num_adc_samples_per_chirp", 128),
    ("num_chirps_per_frame", 128),
    ("adc_sample_frequency", 2500000.0),
    ("start_frequency", 77000000000.0),
    ("idle_time", 6.5e-05),
    ("adc_start_time", 6e-06),
    ("ramp_end_time", 6.2e-05),
    ("frequency_slope", 23437500000000.0),
)


def range_bin_width() -> float:
    w = dict(WAVEFORM)
    chirp_s = int(w["num_adc_samples_per_chirp"]) / float(w["adc_sample_frequency"])
    return C / (2 * float(w["frequency_slope"]) * chirp_s)


def _transform_text(t: list[float], q: list[float]) -> str:
    return f"{t[0]!s} {t[1]!s} {t[2]!s}\n{q[0]!s} {q[1]!s} {q[2]!s} {q[3]!s}\n"


def transform_lines(ext: rig.Extrinsic, offset: rig.Extrinsic | None = None) -> str:
    """``write_transform`` of the dataset's bag_to_config.py (naive offset composition, as there)."""
    t = np.array(ext.translation, dtype=np.float64)
    q = np.array(ext.quaternion, dtype=np.float64)
    if offset is not None:
        off_t, off_q = np.array(offset.translation), np.array(offset.quaternion)
        t = t + off_t
        w = q[3] * off_q[3] - np.dot(q[:3], off_q[:3])
        v = q[3] * off_q[:3] + off_q[3] * q[:3] + np.cross(q[:3], off_q[:3])
        q = np.array([v[0], v[1], v[2], w])
    return _transform_text([float(x) for x in t], [float(x) for x in q])


def write_calib(calib: Path) -> None:
    (calib / "transforms").mkdir(parents=True, exist_ok=True)
    (calib / "single_chip").mkdir(parents=True, exist_ok=True)
    tf = calib / "transforms"
    (tf / "base_to_single_chip.txt").write_text(transform_lines(rig.BASE_TO_RADAR))
    (tf / "base_to_imu.txt").write_text(transform_lines(rig.BASE_TO_IMU))
    (tf / "base_to_cascade.txt").write_text(transform_lines(rig.BASE_TO_CASCADE))
    (tf / "base_to_lidar.txt").write_text(transform_lines(rig.BASE_TO_LIDAR_SENSOR, rig.LIDAR_SENSOR_TO_LIDAR))
    (calib / "single_chip" / "waveform_cfg.txt").write_text("".join(f"{k} {v}\n" for k, v in WAVEFORM))
    az = np.arcsin(np.linspace(-1, 1, 64, endpoint=False) + 1 / 64)
    el = np.arcsin(np.linspace(-0.5, 0.5, 8, endpoint=False) + 1 / 16)
    heat = [
        "num_range_bins 96\n",
        "num_elevation_bins 8\n",
        "num_azimuth_bins 64\n",
        f"range_bin_width {range_bin_width()}\n",
        "azimuth_bins" + "".join(f" {v}" for v in az.tolist()) + "\n",
        "elevation_bins" + "".join(f" {v}" for v in el.tolist()) + "\n",
    ]
    (calib / "single_chip" / "heatmap_cfg.txt").write_text("".join(heat))
