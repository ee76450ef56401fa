"""Single-chip radar detections (TI AWR1843 with the mmWave SDK processing chain, as the ColoRadar rig's).

Scene: the world's persistent scatterers (:mod:`simulator.scatterers`), each visible one (a ray cast from
the radar finds nothing in front of it) with mean SNR ``snr_ref - L log10(r) + RCS - antenna pattern``
(``L`` = 40 dB per decade, the radar equation for point scatterers), plus multipath ghosts: a strong
scatterer seen via a vertical wall or box face (the mirror image behind it, when the reflection point is
on the face and both legs are unobstructed), weaker by ``ghost_loss_db`` and two bounces off the mirror
(its material's ``specular``, an amplitude reflection coefficient: ``40 log10(specular)`` dB).
Per scan every return gets a Swerling-1 complex amplitude (exponential power, uniform phase).

Processing, as the TI mmWave SDK's out-of-box demo does it (evidence in data/datasets/coloradar.md, "radar
model": SDK 3.x AoA DPU ``aoaprochwa.c`` / ``aoaprochwa_internal.h``, SDK 1.x/2.x demo ``post_processing.c``
``MmwDemo_peakGrouping`` / ``MmwDemo_XYZestimation``, the SDK user guide's ``cfarCfg`` / ``multiObjBeamForming``
and the out-of-box configuration ``cfarCfg -1 0 2 8 4 3 0 15 1``, ``cfarCfg -1 1 0 4 2 3 1 15 1``,
``multiObjBeamForming -1 1 0.5``, zero range bias):

1. range-Doppler detection matrix: each return lands at ``r / dr`` and ``doppler / dv`` (Doppler
   ``-u . v``, negative when approaching) and spreads over +-2 bins with the Hann-window kernel
   ``sinc(x) / (1 - x^2)``; cells hold the power averaged over the 12 virtual channels plus thermal noise
   (unit power per channel, the 12-channel average of exponentials);
2. CFAR on the dB values: cell averaging in Doppler (cyclic, window 4, guard 2) and smallest-of cell
   averaging in range (window 8, guard 4), both ``cfar_threshold_db`` (15 dB) above the noise estimate;
   then peak grouping (a cell is kept only if none of its 8 range/Doppler neighbours is stronger) and the
   CFAR range limits;
3. per detected cell, the 12-channel snapshot (all returns in the cell, with their kernel weights, plus
   channel noise): 64-point zero-padded FFT over the 8 azimuth channels, the peak bin ``k`` gives
   ``Wx = 2 k / 64`` (no interpolation), a second peak is reported when it exceeds ``multi_peak_ratio`` of
   the first (multiObjBeamForming); elevation ``Wz = angle(P1 P2* exp(j 2 pi Wx)) / pi`` from the azimuth
   peak ``P1`` and the 4 elevated channels' FFT ``P2`` at the same bin (a phase comparison: continuous,
   exact for a lone strong scatterer, biased when returns at different heights share the cell, noisy at
   low SNR);
4. ``R = range bin * dr`` (no sub-bin interpolation, zero range bias), ``x = R Wx``, ``z = R Wz``,
   ``y = sqrt(R^2 - x^2 - z^2)`` (TI frame; the driver maps to x forward, y left), Doppler = signed
   Doppler bin * dv, intensity = the cell's SNR in dB.

Clutter false alarms (sidelobes, interference: not modelled physically) are a Poisson number of points on
the same grids with random Doppler and an SNR of the CFAR threshold plus an exponential of mean
``clutter_snr_scale_db``. The driver's field-of-view filter and the strongest-``max_points``
cap come last. Three effects of the real radar that voxel worlds (no mirror faces) otherwise lack, all off by
default (every existing log is unchanged; the drifting ColoRadar twins turn them on): statistical multipath
ghosts (:func:`multipath_ghosts`, ``multipath_ghost_share``), Doppler outliers (:func:`doppler_outliers`,
``doppler_outlier_share``) and an extra elevation error (``elevation_noise_deg``, added to each detected
cell's elevation angle before the position is formed); they come before clutter, the field-of-view filter
and the cap. Each point's label and noise-free position come from the return that dominates its cell
at the reported azimuth (``cell_scatterers`` counts the returns within 10 dB of the strongest in the cell).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from simulator.params import RadarParams
from simulator.raycast import cast
from simulator.scatterers import KIND_SURFACE, Scatterers
from simulator.world import Scene

LABEL_SURFACE, LABEL_CLUTTER, LABEL_GHOST = 0, 1, 2
N_AZ, N_EL, EL_OFFSET, N_CH = 8, 4, 2, 12  # virtual channels: 8 azimuth, 4 elevated (above azimuth 2..5)
KERNEL_HALF = 2  # Hann window main lobe: +-2 bins
CULL_SNR_DB = -10.0  # returns this far below the noise floor neither detect nor raise the CFAR noise
OCCLUSION_TOL = 0.02  # m (plus 0.2 % of the range): a return is hidden by a surface this much in front

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
    cell_scatterers: np.ndarray  # int16 (N,), returns within 10 dB of the strongest in the point's cell


def hann_kernel(x: np.ndarray) -> np.ndarray:
    """Amplitude response of a Hann-windowed FFT ``x`` bins from a tone (1 at 0, 0.5 at +-1, 0 at +-2)."""
    x = np.asarray(x, dtype=np.float64)
    near = np.abs(np.abs(x) - 1.0) < 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.sinc(x) / (1.0 - x * x)
    return np.where(near, 0.5, out)


def _to_radar(points: np.ndarray, origin: np.ndarray, yaw: float) -> np.ndarray:
    """World points (K, 3) into the level radar frame (x boresight, y left, z up)."""
    d = points - origin
    c, s = np.cos(yaw), np.sin(yaw)
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])


def _visible(scene: Scene, origin: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Whether each target point (K, 3) is seen from ``origin`` (nothing hit before it)."""
    return _visible_from(scene, np.broadcast_to(origin, targets.shape), targets, nudge=0.0)


def _visible_from(scene: Scene, starts: np.ndarray, targets: np.ndarray, nudge: float = 1e-3) -> np.ndarray:
    """Whether the straight legs ``starts -> targets`` (K, 3) are unobstructed.

    Each leg starts ``nudge`` metres along itself, so that a start on a surface does not hit that surface.
    """
    d = targets - starts
    dxy = np.hypot(d[:, 0], d[:, 1])
    ok = dxy > 1e-6
    out = np.zeros(len(targets), bool)
    if not ok.any():
        return out
    h = d[ok, :2] / dxy[ok, None]
    r = np.linalg.norm(d[ok], axis=1)
    o = starts[ok] + nudge * d[ok] / r[:, None] if nudge else starts[ok]
    with np.errstate(invalid="ignore"):  # level rays: 0 slope * inf distance in the caster's height test
        hits = cast(scene, o, h, (d[ok, 2] / dxy[ok])[:, None], float(r.max()) + 1)
    slack = float(getattr(scene, "occlusion_slack", 0.0))  # voxel worlds: the depth of a surface voxel
    out[ok] = hits.range[:, 0] >= r - nudge - OCCLUSION_TOL - 2e-3 * r - slack
    return out


def _ghosts(scene: Scene, origin: np.ndarray, src: np.ndarray,
            max_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mirror images of ``src`` (M, 3) behind vertical faces: (image positions, source index, mirror loss dB)."""
    empty = (np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0))
    if not len(src) or not len(scene.seg_a):
        return empty
    a, b = scene.seg_a, scene.seg_b
    e = b - a
    length = np.linalg.norm(e, axis=1)
    n = np.column_stack([-e[:, 1], e[:, 0]]) / length[:, None]
    d_o = ((origin[:2] - a) * n).sum(1)  # (S,)
    d_s = ((src[:, None, :2] - a[None]) * n[None]).sum(-1)  # (M, S)
    same = (d_o[None] * d_s > 0) & (np.abs(d_o)[None] > 0.05) & (np.abs(d_s) > 0.05)
    si, gi = np.nonzero(same)
    if not len(si):
        return empty
    img = src[si].copy()
    img[:, :2] -= 2 * d_s[si, gi][:, None] * n[gi]
    t = d_o[gi] / (d_o[gi] + d_s[si, gi])
    x = origin + t[:, None] * (img - origin)
    u = ((x[:, :2] - a[gi]) * e[gi]).sum(1) / length[gi] ** 2
    rng_img = np.linalg.norm(img - origin, axis=1)
    ok = ((u >= 0) & (u <= 1) & (x[:, 2] >= scene.seg_z[gi, 0]) & (x[:, 2] <= scene.seg_z[gi, 1])
          & (rng_img <= max_range) & (scene.specular[scene.seg_mat[gi]] > 0))
    si, gi, img, x = si[ok], gi[ok], img[ok], x[ok]
    if not len(si):
        return empty
    vis = _visible(scene, origin, x) & _visible_from(scene, x, src[si])
    si, gi, img = si[vis], gi[vis], img[vis]
    loss = -40 * np.log10(scene.specular[scene.seg_mat[gi]])  # two bounces, amplitude reflectivity
    return img, si, loss


def cfar_detect(det_db: np.ndarray, p: RadarParams) -> np.ndarray:
    """Cells detected by Doppler CA-CFAR (cyclic) and range CASO-CFAR, then peak-grouped (boolean grid)."""
    nr, nd = det_db.shape
    thr = p.cfar_threshold_db
    # Doppler direction: cell averaging, cyclic
    gd, wd = p.cfar_doppler_guard, p.cfar_doppler_window
    acc = np.zeros_like(det_db)
    for o in range(gd + 1, gd + wd + 1):
        acc += np.roll(det_db, o, axis=1) + np.roll(det_db, -o, axis=1)
    dopp_ok = det_db > acc / (2 * wd) + thr
    # range direction: smallest-of cell averaging, one-sided at the ends
    gr, wr = p.cfar_range_guard, p.cfar_range_window
    cs = np.vstack([np.zeros((1, nd)), np.cumsum(det_db, axis=0)])
    i = np.arange(nr)
    lo0, lo1 = i - gr - wr, i - gr  # left window [lo0, lo1)
    hi0, hi1 = i + gr + 1, i + gr + wr + 1  # right window [hi0, hi1)
    has_l, has_r = lo0 >= 0, hi1 <= nr
    left = (cs[np.clip(lo1, 0, nr)] - cs[np.clip(lo0, 0, nr)]) / wr
    right = (cs[np.clip(hi1, 0, nr)] - cs[np.clip(hi0, 0, nr)]) / wr
    noise = np.where((has_l & has_r)[:, None], np.minimum(left, right), np.where(has_l[:, None], left, right))
    det = dopp_ok & (det_db > noise + thr)
    if p.peak_grouping:
        pad = np.vstack([np.full((1, nd), -np.inf), det_db, np.full((1, nd), -np.inf)])
        for dr in (-1, 0, 1):
            rows = pad[1 + dr: 1 + dr + nr]
            for dd in (-1, 0, 1):
                if dr or dd:
                    det &= det_db >= np.roll(rows, dd, axis=1)
    return det


def angle_of_arrival(snap: np.ndarray, n_bins: int = 64,
                     multi_peak_ratio: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """AoA of detected cells from their 12-channel snapshots (n, 12): 8 azimuth channels then 4 elevated ones.

    Returns (cell index, azimuth bin, ``Wx``, ``Wz``) per reported peak: ``Wx = 2 k / n_bins`` from the peak of
    the zero-padded azimuth FFT (a second peak outside the first's main lobe when its power exceeds
    ``multi_peak_ratio`` of the first), ``Wz = angle(P1 P2* exp(j 2 pi Wx)) / pi`` (aoaprochwa's formula).
    """
    n_det = len(snap)
    spec = np.fft.fft(snap[:, :N_AZ], n=n_bins, axis=1)
    mag = np.abs(spec) ** 2
    k1 = np.argmax(mag, axis=1) if n_det else np.zeros(0, np.int64)
    peaks_cell, peaks_bin = [np.arange(n_det)], [k1]
    if multi_peak_ratio > 0 and n_det:
        dist = np.abs((np.arange(n_bins)[None, :] - k1[:, None] + n_bins // 2) % n_bins - n_bins // 2)
        local = (mag >= np.roll(mag, 1, axis=1)) & (mag >= np.roll(mag, -1, axis=1))
        m2 = np.where((dist > n_bins // N_AZ) & local, mag, -1.0)
        k2 = np.argmax(m2, axis=1)
        rows = np.arange(n_det)
        two = m2[rows, k2] > multi_peak_ratio * mag[rows, k1]
        peaks_cell.append(np.nonzero(two)[0])
        peaks_bin.append(k2[two])
    pc, pb = np.concatenate(peaks_cell), np.concatenate(peaks_bin)
    ks = np.where(pb >= n_bins // 2, pb - n_bins, pb)
    wx = 2.0 * ks / n_bins
    p1 = spec[pc, pb]
    p2 = (snap[pc, N_AZ:] * np.exp(-2j * np.pi * np.arange(N_EL)[None, :] * pb[:, None] / n_bins)).sum(1)
    wz = np.angle(p1 * np.conj(p2) * np.exp(2j * np.pi * wx)) / np.pi
    return pc, pb, wx, wz


def steering(u: np.ndarray) -> np.ndarray:
    """12-channel array response (K, 12) to unit directions ``u`` (K, 3) in the radar frame (TI virtual array:
    8 azimuth channels half a wavelength apart, 4 channels half a wavelength above azimuth channels 2..5)."""
    ch = np.arange(N_AZ)
    return np.concatenate([np.exp(1j * np.pi * ch[None, :] * u[:, 1:2]),
                           np.exp(1j * np.pi * ((np.arange(N_EL)[None, :] + EL_OFFSET) * u[:, 1:2] - u[:, 2:3]))],
                          axis=1)


@dataclass(frozen=True)
class Detections:
    """A scan's detected points before clutter, the field-of-view filter and the cap (radar frame)."""

    xyz: np.ndarray  # (n, 3) reported position
    r: np.ndarray  # (n,) reported range (a range bin)
    dop: np.ndarray  # (n,) reported Doppler (a Doppler bin), m/s
    snr: np.ndarray  # (n,) dB
    label: np.ndarray  # int8 (n,)
    xyz_true: np.ndarray  # (n, 3)
    n_cell: np.ndarray  # int16 (n,)

    def concat(self, other: Detections) -> Detections:
        return Detections(*(np.concatenate([a, b]).astype(a.dtype, copy=False)
                            for a, b in zip(_arrays(self), _arrays(other), strict=True)))


def _arrays(d: Detections) -> tuple[np.ndarray, ...]:
    return d.xyz, d.r, d.dop, d.snr, d.label, d.xyz_true, d.n_cell


def _doppler_bin(dop: np.ndarray, dv: float, n_d: int) -> np.ndarray:
    """Doppler ``dop`` (m/s) as the radar reports it: the nearest bin, wrapped into [-n_d/2, n_d/2) bins."""
    b = np.round(dop / dv).astype(np.int64)
    return np.asarray(((b + n_d // 2) % n_d - n_d // 2) * dv)


def multipath_ghosts(det: Detections, v_radar: np.ndarray, p: RadarParams, n_d: int,
                     rng: np.random.Generator) -> Detections:
    """Multipath ghosts for worlds without mirror faces (voxel maps): a Poisson number, with mean
    ``multipath_ghost_share`` times the detected scene points, of first-order mirror images.

    Each ghost takes a source point ``s`` and a mirror point ``q`` (both drawn uniformly among the detected
    scene points) and reflects ``s`` in the vertical plane through ``q`` facing the radar (normal: ``q``'s
    horizontal direction): the radar -> wall -> target path of a wall the radar sees. Only a source on the
    radar's side of the plane (more than 5 cm) makes a ghost. The image is a virtual static target: its
    range and Doppler (``-u . v``) are those of the image, on the range and Doppler bins; its SNR is the
    source's less ``multipath_ghost_loss_db``. Label :data:`LABEL_GHOST`, noise-free position the image.
    """
    scene = np.nonzero(det.label != LABEL_CLUTTER)[0]
    n_g = int(rng.poisson(p.multipath_ghost_share * len(scene))) if len(scene) >= 2 else 0
    s = scene[rng.integers(0, len(scene), n_g)] if n_g else np.zeros(0, np.int64)
    m = scene[rng.integers(0, len(scene), n_g)] if n_g else np.zeros(0, np.int64)
    q = det.xyz[m]
    qh = np.hypot(q[:, 0], q[:, 1])
    nrm = np.zeros((len(m), 3))
    nrm[:, :2] = q[:, :2] / np.maximum(qh, 1e-9)[:, None]
    dist = ((det.xyz[s] - q) * nrm).sum(1)  # < 0: the source is on the radar's side of the wall
    ok = (dist < -0.05) & (qh > 0.3)
    s, nrm, dist = s[ok], nrm[ok], dist[ok]
    img = det.xyz[s] - 2 * dist[:, None] * nrm
    img_true = det.xyz_true[s] - 2 * ((det.xyz_true[s] - det.xyz[m[ok]]) * nrm).sum(1)[:, None] * nrm
    r = np.linalg.norm(img, axis=1)
    u = img / np.maximum(r, 1e-9)[:, None]
    r_bin = np.round(r / p.range_resolution) * p.range_resolution
    return Detections(xyz=u * r_bin[:, None], r=r_bin, dop=_doppler_bin(-(u @ v_radar), p.doppler_resolution, n_d),
                      snr=det.snr[s] - p.multipath_ghost_loss_db, label=np.full(len(s), LABEL_GHOST, np.int8),
                      xyz_true=img_true, n_cell=np.zeros(len(s), np.int16))


def doppler_outliers(det: Detections, p: RadarParams, n_d: int, rng: np.random.Generator) -> Detections:
    """``doppler_outlier_share`` of the scene points (not clutter) with a Doppler drawn uniformly over the bins."""
    scene = np.nonzero(det.label != LABEL_CLUTTER)[0]
    hit = scene[rng.random(len(scene)) < p.doppler_outlier_share]
    dop = det.dop.copy()
    dop[hit] = rng.integers(-(n_d // 2), n_d // 2, len(hit)) * p.doppler_resolution
    return replace(det, dop=dop)


def simulate_scan(scene: Scene, scat: Scatterers, p: RadarParams, index: int, t: float, origin: np.ndarray,
                  yaw: float, velocity: np.ndarray, rng: np.random.Generator) -> RadarScan:
    """One radar scan. ``origin`` and ``velocity`` (world) of the radar, ``yaw`` of its boresight (level mount)."""
    deg = np.pi / 180
    dr, dv = p.range_resolution, p.doppler_resolution
    n_d = max(8, round(2 * p.doppler_max / dv))
    reach = p.max_range + (p.cfar_range_window + p.cfar_range_guard + KERNEL_HALF + 1) * dr
    n_r = int(np.ceil(reach / dr)) + KERNEL_HALF + 1
    c, s = np.cos(yaw), np.sin(yaw)
    v_radar = np.array([c * velocity[0] + s * velocity[1], -s * velocity[0] + c * velocity[1], velocity[2]])

    # --- returns: visible scatterers and their ghosts ----------------------------------------------------
    ret = scat.returns(origin, reach)
    xyz = _to_radar(ret.pos, origin, yaw)
    r = np.linalg.norm(xyz, axis=1)
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    el = np.arcsin(np.clip(xyz[:, 2] / np.maximum(r, 1e-9), -1, 1))
    pattern = 3.0 * ((az / (p.beam_azimuth_3db_deg * deg)) ** 2 + (el / (p.beam_elevation_3db_deg * deg)) ** 2)
    snr = p.snr_ref_db + ret.rcs_db - p.range_loss_db_per_decade * np.log10(np.maximum(r, 1e-3)) - pattern
    cand = np.nonzero((np.abs(az) < np.pi / 2) & (snr > CULL_SNR_DB) & (r > 0.05))[0]
    cand = cand[_visible(scene, origin, ret.pos[cand])]
    pos_w, snr_c, kind = ret.pos[cand], snr[cand], ret.kind[cand]
    strong = np.nonzero(kind != KIND_SURFACE)[0]
    img, gsrc, gloss = _ghosts(scene, origin, pos_w[strong], reach)
    g_xyz = _to_radar(img, origin, yaw)
    g_r = np.linalg.norm(g_xyz, axis=1)
    g_az = np.arctan2(g_xyz[:, 1], g_xyz[:, 0])
    g_el = np.arcsin(np.clip(g_xyz[:, 2] / np.maximum(g_r, 1e-9), -1, 1))
    g_pattern = 3.0 * ((g_az / (p.beam_azimuth_3db_deg * deg)) ** 2 + (g_el / (p.beam_elevation_3db_deg * deg)) ** 2)
    g_snr = (p.snr_ref_db + ret.rcs_db[cand][strong][gsrc] - p.range_loss_db_per_decade * np.log10(g_r)
             - g_pattern - p.ghost_loss_db - gloss)
    gk = (np.abs(g_az) < np.pi / 2) & (g_snr > CULL_SNR_DB)
    true_xyz = np.concatenate([xyz[cand], g_xyz[gk]])
    snr_all = np.concatenate([snr_c, g_snr[gk]])
    label = np.concatenate([np.full(len(cand), LABEL_SURFACE, np.int8), np.full(int(gk.sum()), LABEL_GHOST, np.int8)])
    k = len(true_xyz)
    rr = np.linalg.norm(true_xyz, axis=1)
    u = true_xyz / np.maximum(rr, 1e-9)[:, None]
    dop = -(u @ v_radar)
    amp = np.sqrt(10 ** (snr_all / 10)) * (rng.standard_normal(k) + 1j * rng.standard_normal(k)) / np.sqrt(2)

    # --- range-Doppler detection matrix ---------------------------------------------------------------
    fr, fd = rr / dr, dop / dv
    ir, idp = np.round(fr).astype(np.int64), np.round(fd).astype(np.int64)
    off = np.arange(-KERNEL_HALF, KERNEL_HALF + 1)
    wr = hann_kernel(off[None, :] - (fr - ir)[:, None])  # (K, 5)
    wd = hann_kernel(off[None, :] - (fd - idp)[:, None])
    cell_r = ir[:, None, None] + off[None, :, None]  # (K, 5, 1)
    cell_d = np.mod(idp[:, None, None] + off[None, None, :], n_d)  # (K, 1, 5)
    w = wr[:, :, None] * wd[:, None, :]  # (K, 5, 5) amplitude weights
    in_grid = np.broadcast_to((cell_r >= 0) & (cell_r < n_r), w.shape)
    cr, cd = np.broadcast_to(cell_r, w.shape), np.broadcast_to(cell_d, w.shape)
    flat = (cr * n_d + cd)[in_grid]
    kk = np.broadcast_to(np.arange(k)[:, None, None], w.shape)[in_grid]
    wk = w[in_grid]
    power = rng.gamma(N_CH, 1.0 / N_CH, n_r * n_d)
    power += np.bincount(flat, weights=np.abs(amp[kk] * wk) ** 2, minlength=n_r * n_d)
    det_db = 10 * np.log10(power.reshape(n_r, n_d))
    det = cfar_detect(det_db, p)
    bins_r = np.arange(n_r) * dr
    det &= ((bins_r >= p.min_range) & (bins_r <= p.max_range))[:, None]
    cells = np.flatnonzero(det.ravel())
    n_det = len(cells)

    # --- angle of arrival per detected cell -----------------------------------------------------------
    cell_id = np.full(n_r * n_d, -1, np.int64)
    cell_id[cells] = np.arange(n_det)
    pid = cell_id[flat]
    sel = pid >= 0
    pid, pk, pw = pid[sel], kk[sel], wk[sel]
    steer = steering(u)
    snap = (rng.standard_normal((n_det, N_CH)) + 1j * rng.standard_normal((n_det, N_CH))) / np.sqrt(2)
    contrib = (amp[pk] * pw)[:, None] * steer[pk]
    np.add.at(snap, pid, contrib)
    pc, _, wx, wz = angle_of_arrival(snap, p.n_azimuth_bins, p.multi_peak_ratio)
    if p.elevation_noise_deg > 0:  # elevation spread beyond the phase noise (off by default: no draw)
        el_m = np.arcsin(np.clip(wz, -1, 1)) + rng.normal(0.0, np.radians(p.elevation_noise_deg), len(wz))
        wz = np.sin(np.clip(el_m, -np.pi / 2, np.pi / 2))
    rng_m = (cells[pc] // n_d) * dr
    dbin = cells[pc] % n_d
    dop_m = np.where(dbin >= n_d // 2, dbin - n_d, dbin) * dv
    x_lat, z_m = rng_m * wx, rng_m * wz
    fwd2 = rng_m**2 - x_lat**2 - z_m**2
    snr_m = det_db.ravel()[cells[pc]]

    # --- which return each point comes from -----------------------------------------------------------
    src = np.full(len(pc), -1, np.int64)
    n_in = np.zeros(len(pc), np.int16)
    if len(pid):
        order = np.argsort(pid, kind="stable")
        pid_s, pk_s, pw_s = pid[order], pk[order], pw[order]
        starts = np.searchsorted(pid_s, np.arange(n_det + 1))
        cell_of = np.repeat(np.arange(n_det), np.diff(starts))
        strength = np.abs(amp[pk_s] * pw_s)
        best = np.zeros(n_det)
        np.maximum.at(best, cell_of, strength)
        n_cell = np.bincount(cell_of, weights=strength**2 >= 0.1 * best[cell_of] ** 2, minlength=n_det)
        n_in = n_cell[pc].astype(np.int16)
        for j in range(len(pc)):  # few hundred peaks per scan at most
            a, b = starts[pc[j]], starts[pc[j] + 1]
            if b > a:
                dd = u[pk_s[a:b], 1] - wx[j]
                beam = np.abs(np.sinc(N_AZ * dd / 2) / np.maximum(np.abs(np.sinc(dd / 2)), 1e-9))
                src[j] = pk_s[a + int(np.argmax(strength[a:b] * beam))]
    keep = fwd2 > 0
    lab = np.where(src >= 0, label[np.maximum(src, 0)], LABEL_CLUTTER).astype(np.int8)
    pts_xyz = np.column_stack([np.sqrt(np.maximum(fwd2, 0)), x_lat, z_m])
    t_xyz = np.where((src >= 0)[:, None], true_xyz[np.maximum(src, 0)], pts_xyz)

    # --- clutter false alarms on the same grids -------------------------------------------------------
    nc = int(rng.poisson(p.clutter_rate))
    c_r = rng.integers(int(np.ceil(max(p.min_range, 0.5) / dr)), int(p.max_range / dr) + 1, nc) * dr
    nb = p.n_azimuth_bins
    kmax = int(np.sin(p.fov_azimuth_deg * deg) * nb / 2)
    c_wx = 2.0 * rng.integers(-kmax, kmax + 1, nc) / nb
    c_wz = rng.uniform(-np.sin(p.fov_elevation_deg * deg), np.sin(p.fov_elevation_deg * deg), nc)
    c_dop = rng.integers(-(n_d // 2), n_d // 2, nc) * dv
    c_snr = p.cfar_threshold_db + rng.exponential(p.clutter_snr_scale_db, nc)
    c_f2 = c_r**2 * (1 - c_wx**2 - c_wz**2)
    c_xyz = np.column_stack([np.sqrt(np.maximum(c_f2, 0)), c_r * c_wx, c_r * c_wz])

    dets = Detections(xyz=pts_xyz[keep], r=rng_m[keep], dop=dop_m[keep], snr=snr_m[keep], label=lab[keep],
                     xyz_true=t_xyz[keep], n_cell=n_in[keep])
    if p.multipath_ghost_share > 0:
        dets = dets.concat(multipath_ghosts(dets, v_radar, p, n_d, rng))
    if p.doppler_outlier_share > 0:
        dets = doppler_outliers(dets, p, n_d, rng)

    xyz_all = np.concatenate([dets.xyz, c_xyz])
    r_all = np.concatenate([dets.r, c_r])
    dop_all = np.concatenate([dets.dop, c_dop])
    snr_out = np.concatenate([dets.snr, c_snr])
    labels = np.concatenate([dets.label, np.full(nc, LABEL_CLUTTER, np.int8)])
    true_all = np.concatenate([dets.xyz_true, c_xyz])
    n_cell_all = np.concatenate([dets.n_cell, np.zeros(nc, np.int16)])

    # the driver's field-of-view filter, then the strongest max_points, in range order
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = ((xyz_all[:, 0] > 0) & (np.abs(xyz_all[:, 1] / xyz_all[:, 0]) < np.tan(p.fov_azimuth_deg * deg))
              & (xyz_all[:, 2] ** 2 / (xyz_all[:, 0] ** 2 + xyz_all[:, 1] ** 2)
                 < np.tan(p.fov_elevation_deg * deg) ** 2)
              & (r_all >= p.min_range) & (r_all <= p.max_range))
    idx = np.nonzero(ok)[0]
    if len(idx) > p.max_points:
        idx = idx[np.argsort(-snr_out[idx], kind="stable")[: p.max_points]]
    idx = idx[np.lexsort((np.arctan2(xyz_all[idx, 1], xyz_all[idx, 0]), r_all[idx]))]
    pts = np.zeros(len(idx), dtype=RADAR_DTYPE)
    pts["x"], pts["y"], pts["z"] = xyz_all[idx, 0], xyz_all[idx, 1], xyz_all[idx, 2]
    pts["intensity"] = snr_out[idx]
    pts["range"] = r_all[idx]
    pts["doppler"] = dop_all[idx]
    return RadarScan(index=index, t=t, points=pts, labels=labels[idx], xyz_true=true_all[idx].astype(np.float32),
                     cell_scatterers=n_cell_all[idx])
