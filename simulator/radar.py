"""Single-chip radar detections: surface returns, clutter false alarms and multipath ghosts.

Per scan, ``n_rays`` random directions over a slightly enlarged field of view are cast into the world.
A hit is detected when its SNR, ``snr_ref - L_r log10(r) + material + q*10 log10(cos(inc)) - antenna
pattern + Swerling-1 fluctuation``, exceeds the CFAR threshold, so detection probability falls with
range and grazing angle. Specular returns from vertical surfaces may continue along the mirrored ray;
a second hit makes a ghost at range ``r1 + r2`` along the first ray (the mirror image behind the wall),
detected when the second surface seen over the whole path, less the mirror's reflection loss, clears the
threshold.
Reported points carry range noise and range-bin quantisation, several degrees of azimuth noise and more
in elevation, Doppler ``-u . v`` (``u`` the unit direction to the point, ``v`` the radar's velocity,
negative when approaching) plus noise, quantised and wrapped, and the SNR in dB as intensity.
The driver's angular field-of-view filter and the strongest-``max_points`` cap are applied last.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulator.params import RadarParams
from simulator.raycast import cast
from simulator.world import VERTICAL_KINDS, Scene

LABEL_SURFACE, LABEL_CLUTTER, LABEL_GHOST = 0, 1, 2

RADAR_DTYPE = np.dtype(
    {"names": ["x", "y", "z", "intensity", "range", "doppler"], "formats": ["<f4"] * 6,
     "offsets": [0, 4, 8, 16, 20, 24], "itemsize": 32}
)


@dataclass(frozen=True)
class RadarScan:
    index: int
    t: float  # seconds from the start of the run
    points: np.ndarray  # RADAR_DTYPE (N,)
    labels: np.ndarray  # int8 (N,)
    xyz_true: np.ndarray  # float32 (N, 3), noise-free position (ghosts: the mirror image) in the radar frame


def _quantise(x: np.ndarray, step: float) -> np.ndarray:
    return np.round(x / step) * step if step > 0 else x


def _wrap(v: np.ndarray, vmax: float) -> np.ndarray:
    return (v + vmax) % (2 * vmax) - vmax


def simulate_scan(scene: Scene, p: RadarParams, index: int, t: float, origin: np.ndarray, yaw: float,
                  velocity: np.ndarray, rng: np.random.Generator) -> RadarScan:
    """One radar scan. ``origin`` and ``velocity`` (world) of the radar, ``yaw`` of its boresight (level mount)."""
    deg = np.pi / 180
    az_lim = p.fov_azimuth_deg * deg + 3 * p.azimuth_noise_deg * deg
    el_lim = p.fov_elevation_deg * deg + 3 * p.elevation_noise_deg * deg
    az = rng.uniform(-az_lim, az_lim, p.n_rays)
    el = rng.uniform(-el_lim, el_lim, p.n_rays)
    heading = np.stack([np.cos(yaw + az), np.sin(yaw + az)], axis=1)
    origins = np.broadcast_to(origin, (p.n_rays, 3))
    hits = cast(scene, origins, heading, np.tan(el)[:, None], p.max_range)
    rng_ = hits.range[:, 0]
    hit = np.isfinite(rng_) & (rng_ >= p.min_range)
    mat = np.maximum(hits.material[:, 0], 0)
    cos_inc = np.maximum(hits.cos_incidence[:, 0], 1e-6)
    pattern = 3.0 * ((az / (p.beam_azimuth_3db_deg * deg)) ** 2 + (el / (p.beam_elevation_3db_deg * deg)) ** 2)
    with np.errstate(divide="ignore"):
        snr = (p.snr_ref_db + scene.radar_db[mat] - p.range_loss_db_per_decade * np.log10(np.maximum(rng_, 1e-3))
               + 10 * p.incidence_exponent * np.log10(cos_inc) - pattern
               + 10 * np.log10(rng.exponential(1.0, p.n_rays)))
    det = hit & (snr > p.threshold_db)

    # multipath ghosts from specular returns on vertical surfaces
    vertical = np.isin(hits.kind[:, 0], VERTICAL_KINDS)
    spawn = det & vertical & (rng.random(p.n_rays) < p.ghost_probability * scene.specular[mat] * cos_inc)
    gi = np.nonzero(spawn)[0]
    g_range = np.empty(0)
    g_snr = np.empty(0)
    if len(gi):
        n = hits.normal_xy[gi, 0]
        h = heading[gi]
        h2 = h - 2 * (h * n).sum(1, keepdims=True) * n
        h2 /= np.linalg.norm(h2, axis=1, keepdims=True)
        d3 = np.column_stack([h, np.tan(el[gi])]) / np.sqrt(1 + np.tan(el[gi]) ** 2)[:, None]
        p1 = origin + rng_[gi, None] * d3 + 1e-4 * np.column_stack([h2, np.zeros(len(gi))])
        second = cast(scene, p1, h2, np.tan(el[gi])[:, None], p.max_range)
        r2 = second.range[:, 0]
        total = rng_[gi] + r2
        mat2 = np.maximum(second.material[:, 0], 0)
        # the ghost is the second surface seen through the mirror: a direct return over the total path,
        # attenuated by the mirror's reflection loss
        with np.errstate(divide="ignore", invalid="ignore"):
            g_snr = (p.snr_ref_db + scene.radar_db[mat2] - p.range_loss_db_per_decade * np.log10(total)
                     + 10 * p.incidence_exponent * np.log10(np.maximum(second.cos_incidence[:, 0], 1e-6))
                     - pattern[gi] - p.ghost_loss_db + 10 * np.log10(scene.specular[mat[gi]])
                     + 10 * np.log10(rng.exponential(1.0, len(gi))))
        keep = np.isfinite(r2) & (total <= p.max_range) & (g_snr > p.threshold_db)
        gi, g_range, g_snr = gi[keep], total[keep], g_snr[keep]

    # true geometry (radar frame, spherical) of surface returns and ghosts
    si = np.nonzero(det)[0]
    r_true = np.concatenate([rng_[si], g_range])
    az_true = np.concatenate([az[si], az[gi]])
    el_true = np.concatenate([el[si], el[gi]])
    snr_all = np.concatenate([snr[si], g_snr])
    labels = np.concatenate([np.full(len(si), LABEL_SURFACE, np.int8), np.full(len(gi), LABEL_GHOST, np.int8)])
    u_true = np.column_stack([np.cos(el_true) * np.cos(az_true), np.cos(el_true) * np.sin(az_true), np.sin(el_true)])
    xyz_true = r_true[:, None] * u_true
    # Doppler of a static point (ghosts are static mirror images along the first ray): -u . v (radar frame)
    c, s = np.cos(yaw), np.sin(yaw)
    v_radar = np.array([c * velocity[0] + s * velocity[1], -s * velocity[0] + c * velocity[1], velocity[2]])
    dop_true = -(u_true @ v_radar)
    k = len(r_true)
    r_m = _quantise(np.maximum(r_true + rng.normal(0, p.range_noise, k), 0.0), p.range_resolution)
    az_m = az_true + rng.normal(0, p.azimuth_noise_deg * deg, k)
    el_m = el_true + rng.normal(0, p.elevation_noise_deg * deg, k)
    dop_m = dop_true + rng.normal(0, p.doppler_noise, k)

    # clutter false alarms: uniform in the field of view, random Doppler, SNR just above threshold
    nc = int(rng.poisson(p.clutter_rate))
    c_r = _quantise(rng.uniform(max(p.min_range, 0.5), p.max_range, nc), p.range_resolution)
    c_az = rng.uniform(-p.fov_azimuth_deg * deg, p.fov_azimuth_deg * deg, nc)
    c_el = rng.uniform(-p.fov_elevation_deg * deg, p.fov_elevation_deg * deg, nc)
    c_dop = rng.uniform(-p.doppler_max, p.doppler_max, nc)
    c_snr = p.threshold_db + rng.exponential(2.0, nc)
    c_xyz = c_r[:, None] * np.column_stack([np.cos(c_el) * np.cos(c_az), np.cos(c_el) * np.sin(c_az), np.sin(c_el)])

    r_all = np.concatenate([r_m, c_r])
    az_all = np.concatenate([az_m, c_az])
    el_all = np.concatenate([el_m, c_el])
    dop_all = _wrap(_quantise(np.concatenate([dop_m, c_dop]), p.doppler_resolution), p.doppler_max)
    snr_all = np.concatenate([snr_all, c_snr])
    labels = np.concatenate([labels, np.full(nc, LABEL_CLUTTER, np.int8)])
    xyz_true = np.concatenate([xyz_true, c_xyz])
    xyz = r_all[:, None] * np.column_stack(
        [np.cos(el_all) * np.cos(az_all), np.cos(el_all) * np.sin(az_all), np.sin(el_all)]
    )

    # the driver's field-of-view filter, then the strongest max_points, in range order
    with np.errstate(divide="ignore", invalid="ignore"):
        keep = ((xyz[:, 0] > 0) & (np.abs(xyz[:, 1] / xyz[:, 0]) < np.tan(p.fov_azimuth_deg * deg))
                & (xyz[:, 2] ** 2 / (xyz[:, 0] ** 2 + xyz[:, 1] ** 2) < np.tan(p.fov_elevation_deg * deg) ** 2)
                & (r_all >= p.min_range) & (r_all <= p.max_range))
    idx = np.nonzero(keep)[0]
    if len(idx) > p.max_points:
        idx = idx[np.argsort(-snr_all[idx], kind="stable")[: p.max_points]]
    idx = idx[np.lexsort((az_all[idx], r_all[idx]))]
    pts = np.zeros(len(idx), dtype=RADAR_DTYPE)
    pts["x"], pts["y"], pts["z"] = xyz[idx, 0], xyz[idx, 1], xyz[idx, 2]
    pts["intensity"] = snr_all[idx]
    pts["range"] = r_all[idx]
    pts["doppler"] = dop_all[idx]
    return RadarScan(index=index, t=t, points=pts, labels=labels[idx],
                     xyz_true=xyz_true[idx].astype(np.float32))
