"""EKF radar-inertial odometry (EKF-RIO, Doer & Trommer 2020): IMU propagation, Doppler ego-velocity updates.

Error-state EKF in the IMU frame. Nominal state: position p and velocity v of the IMU in the world
frame, attitude R = world <- imu, gyro bias b_g and accelerometer bias b_a; error state
``dx = [dp, dv, dtheta, db_g, db_a]`` (15) with the right perturbation ``R = R_hat Exp(dtheta)``.

Propagation (zero-order hold of each IMU sample, world gravity g = (0, 0, -|g|)):
``p += v dt + 1/2 (R a + g) dt^2``, ``v += (R a + g) dt``, ``R <- R Exp(w dt)`` with ``a = a_m - b_a``,
``w = w_m - b_g``; ``F`` has ``dv' = -R [a]x dtheta - R db_a`` and ``dtheta' = -[w]x dtheta - db_g``.

Measurement (radar velocity in the radar frame; extrinsic imu <- radar = (R_ir, t_ir)):
``v_r = R_ir^T (R^T v + w x t_ir)`` with ``H_v = R_ir^T R^T``, ``H_theta = R_ir^T [R^T v]x``,
``H_bg = R_ir^T [t_ir]x``; a chi-square gate rejects outliers.

Mounting error (``mount_sigma0 > 0``): the error state gains the radar mount's rotation error ``dphi`` (3,
radar frame, ``R_ir = R_ir_hat Exp(dphi)``, a constant with prior std ``mount_sigma0``), so
``v_r = Exp(-dphi) R_ir_hat^T u ~ R_ir_hat^T u + [R_ir_hat^T u]x dphi`` with ``u = R^T v + w x t_ir``:
``H_phi = [R_ir_hat^T u]x``. A radar pitched against its stated mount reads part of the forward speed as
climb. At constant speed that is a real climb to the filter (the mount alone is unobservable: only speed
changes show it to the IMU's vertical channel, which handheld process noise drowns). The level prior
(``level_velocity_sigma > 0``, a zero vertical-velocity pseudo-measurement at every scan; by default a Schmidt
update of p_z, v_z and the mount only) makes the pitch observable: a climb proportional to the speed, which
the prior denies, is then the mount's.

Scans the estimator marks as zero velocity for at least ``zero_rate_min_scans`` scans in a row also give a
zero-angular-rate update (``w_m - b_g = 0``), which makes the gyro bias observable whenever the platform stands
still.

Real MEMS IMUs (handheld or vehicle): when the log starts with a standstill (IMU specific force and rate
steady, radar speed near zero, at least ``standstill_min_s``), the filter starts from it: attitude from the
mean specific force over the whole standstill, gyro bias = the mean rate, accelerometer bias along gravity
= ``|f| - g``, velocity zero, and the process noise densities raised to what the standstill shows
(``max(configured, std / sqrt(rate))``); its scans also give zero-rate updates. Recovery: after
``recover_after`` velocity updates in a row rejected by the gate, the velocity, attitude and accelerometer
bias covariances are inflated (``recover_sigma_*``) and the update is tried again, so the filter follows
the radar again instead of diverging silently; a non-finite state is re-initialised from the radar. Only when
the rejected innovations agree with one another (``recover_consistent``, :func:`innovations_agree`): a filter
that is off sees the same innovation scan after scan, while a radar whose estimates are outliers (a standstill
with a handful of static returns among clutter that forms its own Doppler consensus) scatters them, and
inflating the attitude there only injects the outliers into the heading.

Increment covariance: a clone of the error state at each scan (the pose written there, never corrected
later) and, with ``actual_*`` noise set, a second covariance propagated with the actual noise and updated with
the filter's own gain in Joseph form, ``(I - K H) P (I - K H)^T + K R K^T`` (the error covariance of a
suboptimal filter): the estimate keeps the filter's noise, the covariance is that of its actual error.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from stages.odometry.params import OdometryParams

F64 = npt.NDArray[np.float64]


def skew(v: F64) -> F64:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(w: F64) -> F64:
    """Rodrigues' formula for a rotation vector."""
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th ** 2 * K @ K


#: the standstill detector's window (s)
STANDSTILL_WINDOW_S = 0.2


@dataclass
class EkfResult:
    """World <- imu poses at the scan times and per-scan diagnostics."""

    T_world_imu: F64
    velocity: F64
    gyro_bias: F64
    accel_bias: F64
    updated: npt.NDArray[np.bool_]
    rejected: npt.NDArray[np.bool_]
    initialized: npt.NDArray[np.bool_]
    #: sqrt of the covariance diagonal per scan (15: p, v, theta, b_g, b_a)
    sigma: F64 = field(default_factory=lambda: np.zeros((0, 15)))
    #: scans where the covariance was inflated after repeated rejections (or the state re-initialised)
    recovered: npt.NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    #: joint covariance of the pose errors (dp, dtheta) at scan s and at scan s-1, ``(S, 12, 12)``, the current
    #: pose first (stochastic cloning, :meth:`EkfRio.clone`; with ``actual_*`` noise set, the covariance analysis of
    #: this filter under that noise); zero up to the filter's first scan
    pose_pair_cov: F64 = field(default_factory=lambda: np.zeros((0, 12, 12)))
    stats: dict[str, Any] = field(default_factory=dict)
    #: the estimated mount rotation error per scan (rotation vector, radar frame, rad; zero without the state)
    mount_error: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    #: its std per scan (rad)
    mount_sigma: F64 = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass(frozen=True)
class Standstill:
    """The initial standstill found in the IMU: its time span and what it shows."""

    t0_ns: int
    t1_ns: int
    gyro_mean: F64
    accel_mean: F64
    gyro_noise_density: float
    accel_noise_density: float
    samples: int

    def as_dict(self) -> dict[str, Any]:
        return {"start_ns": self.t0_ns, "seconds": round((self.t1_ns - self.t0_ns) * 1e-9, 3), "samples": self.samples,
                "gyro_bias": [round(float(v), 6) for v in self.gyro_mean],
                "gyro_noise_density": round(self.gyro_noise_density, 6),
                "accel_noise_density": round(self.accel_noise_density, 5)}


def radar_moving(vel: F64, cov: F64, valid: npt.NDArray[np.bool_], max_speed: float) -> npt.NDArray[np.bool_]:
    """Scans whose ego-velocity is clearly not zero: faster than ``max_speed`` and outside the 99.9 %
    ellipsoid of their own covariance (an elevation-poor radar reads tenths of m/s in z when still)."""
    v = np.nan_to_num(np.asarray(vel, dtype=np.float64))
    c = np.nan_to_num(np.asarray(cov, dtype=np.float64)) + np.eye(3) * 1e-6
    d2 = np.einsum("si,si->s", v, np.linalg.solve(c, v[:, :, None])[:, :, 0])
    return valid & (np.linalg.norm(v, axis=1) > max_speed) & (d2 > chi2.ppf(0.999, df=3))


def find_standstill(imu_t: npt.NDArray[np.int64], acc: F64, gyro: F64, t0: int, scan_t: npt.NDArray[np.int64],
                    moving: npt.NDArray[np.bool_], cfg: OdometryParams) -> Standstill | None:
    """The standstill starting at ``t0``: consecutive IMU windows of ``standstill_window_s`` whose specific
    force and rate vary less than ``standstill_accel_std`` / ``standstill_gyro_std`` (per axis) and whose
    means stay within ``standstill_accel_change`` / ``standstill_gyro_change`` of the first window's (a slow
    start shows in the means first), cut at the first radar scan that is ``moving``, less one window of
    margin; None when shorter than ``standstill_min_s``."""
    win = round(STANDSTILL_WINDOW_S * 1e9)
    fast = scan_t[(scan_t >= t0) & moving]
    t_stop = int(fast[0]) if len(fast) else int(imu_t[-1])
    i0 = int(np.searchsorted(imu_t, t0))
    end = int(t0)
    first: tuple[F64, F64] | None = None
    while end + win <= t_stop:
        lo, hi = np.searchsorted(imu_t, [end, end + win])
        if hi - lo < 4:
            break
        a, g = acc[lo:hi], gyro[lo:hi]
        if a.std(axis=0).max() > cfg.standstill.accel_std or g.std(axis=0).max() > cfg.standstill.gyro_std:
            break
        means = (a.mean(axis=0), g.mean(axis=0))
        first = first or means
        if np.abs(means[0] - first[0]).max() > cfg.standstill.accel_change or \
                np.abs(means[1] - first[1]).max() > cfg.standstill.gyro_change:
            break
        end += win
    end -= win
    if end - t0 < cfg.standstill.min_s * 1e9:
        return None
    i1 = int(np.searchsorted(imu_t, end))
    a, g = acc[i0:i1], gyro[i0:i1]
    rate = (i1 - i0 - 1) / max((imu_t[i1 - 1] - imu_t[i0]) * 1e-9, 1e-9)
    return Standstill(int(t0), int(end), g.mean(axis=0), a.mean(axis=0),
                      float(g.std(axis=0).mean() / np.sqrt(rate)), float(a.std(axis=0).mean() / np.sqrt(rate)), i1 - i0)


class EkfRio:
    """The filter state and its two operations."""

    def __init__(self, cfg: OdometryParams, R0: F64, v0: F64) -> None:
        self.cfg = cfg
        #: error-state size: 15, or 18 with the mount rotation error
        self.n = 18 if np.radians(cfg.height.mount_sigma0_deg) > 0 else 15
        #: the mount rotation correction (radar frame): R_ir = R_ir_stated Exp(mount)
        self.mount = np.zeros(3)
        self.p = np.zeros(3)
        self.v = np.asarray(v0, dtype=np.float64).copy()
        self.R = np.asarray(R0, dtype=np.float64).copy()
        self.bg = np.zeros(3)
        self.ba = np.zeros(3)
        self.g = np.array([0.0, 0.0, -cfg.imu.gravity])
        ini = cfg.init
        s = np.r_[np.zeros(3), np.full(3, ini.sigma_v0), np.full(2, np.radians(ini.sigma_attitude0_deg)), 1e-6,
                  np.full(3, cfg.init.sigma_gyro_bias0), np.full(3, cfg.init.sigma_accel_bias0),
                  np.full(self.n - 15, np.radians(cfg.height.mount_sigma0_deg))]
        self.P = np.diag(s ** 2)
        q = np.r_[np.full(3, cfg.imu.accel_noise_density ** 2), np.full(3, cfg.imu.gyro_noise_density ** 2),
                  np.full(3, cfg.imu.gyro_bias_walk ** 2), np.full(3, cfg.imu.accel_bias_walk ** 2)]
        self._qc = q  # continuous-time noise densities of [v, theta, bg, ba]
        #: stochastic clone of the error state at the last scan: cross covariance cov(dx_now, dx_clone) and
        #: the clone's own covariance (Roumeliotis & Burdick 2002)
        self.C = self.P.copy()
        self.Pc = self.P.copy()
        #: the actual error covariance under the ``actual_*`` noise (same gains), with its clone; None: P itself
        cv = cfg.covariance
        self._separate = (cv.accel_noise_density is not None or cv.gyro_noise_density is not None
                          or cfg.covariance.velocity_scale != 1.0)
        self._qt = q.copy()
        if cfg.covariance.accel_noise_density is not None:
            self._qt[0:3] = cfg.covariance.accel_noise_density ** 2
        if cfg.covariance.gyro_noise_density is not None:
            self._qt[3:6] = cfg.covariance.gyro_noise_density ** 2
        self.Pt, self.Ct, self.Pct = self.P.copy(), self.P.copy(), self.P.copy()
        #: the last update's innovation and its covariance (before the gate)
        self.last_innovation: tuple[F64, F64] = (np.zeros(0), np.zeros((0, 0)))

    def clone(self) -> None:
        """Clone the error state (at a scan): the next :meth:`pose_pair_cov` is of the increment from here."""
        self.C = self.P.copy()
        self.Pc = self.P.copy()
        self.Ct = self.Pt.copy()
        self.Pct = self.Pt.copy()

    def pose_pair_cov(self) -> F64:
        """Joint covariance of the pose errors ``(dp, dtheta)`` now and at the clone, ``(12, 12)`` (the actual
        error covariance when ``actual_*`` noise is set)."""
        P, C, Pc = (self.Pt, self.Ct, self.Pct) if self._separate else (self.P, self.C, self.Pc)
        i = np.r_[0:3, 6:9]
        out = np.empty((12, 12))
        out[:6, :6] = P[np.ix_(i, i)]
        out[:6, 6:] = C[np.ix_(i, i)]
        out[6:, :6] = out[:6, 6:].T
        out[6:, 6:] = Pc[np.ix_(i, i)]
        return 0.5 * (out + out.T)

    def set_gyro_bias_variance(self, var: float) -> None:
        """The gyro-bias block of the covariance (filter and actual), cross terms dropped."""
        for M in (self.P, self.Pt):
            M[9:12, :] = 0.0
            M[:, 9:12] = 0.0
            M[9:12, 9:12] = np.eye(3) * var

    def set_noise(self, accel_noise_density: float, gyro_noise_density: float) -> None:
        """Raise the noise densities to what a standstill showed (filter and actual: at least these)."""
        self._qc[0:3] = accel_noise_density ** 2
        self._qc[3:6] = gyro_noise_density ** 2
        self._qt[0:3] = np.maximum(self._qt[0:3], accel_noise_density ** 2 if self.cfg.covariance.accel_noise_density
                                   is None else self._qt[0:3])
        self._qt[3:6] = np.maximum(self._qt[3:6], gyro_noise_density ** 2 if self.cfg.covariance.gyro_noise_density
                                   is None else self._qt[3:6])

    def raise_actual_noise(self, accel_noise_density: float, gyro_noise_density: float) -> None:
        """The actual noise at least what a standstill measured (its std over sqrt(rate))."""
        self._qt[0:3] = np.maximum(self._qt[0:3], accel_noise_density ** 2)
        self._qt[3:6] = np.maximum(self._qt[3:6], gyro_noise_density ** 2)

    def inflate(self, sigma_v: float, sigma_attitude: float, sigma_accel_bias: float) -> None:
        """Recovery: velocity, attitude and accelerometer-bias variances at least these (cross terms dropped)."""
        for M in (self.P, self.Pt):
            for sl, s in ((slice(3, 6), sigma_v), (slice(6, 9), sigma_attitude), (slice(12, 15), sigma_accel_bias)):
                d = np.maximum(np.diag(M)[sl], s * s)
                M[sl, :] = 0.0
                M[:, sl] = 0.0
                M[sl, sl] = np.diag(d)

    def finite(self) -> bool:
        return bool(np.isfinite(self.p).all() and np.isfinite(self.v).all() and np.isfinite(self.R).all()
                    and np.isfinite(self.P).all())

    def propagate(self, acc: F64, gyro: F64, dt: float) -> None:
        if dt <= 0:
            return
        a = acc - self.ba
        w = gyro - self.bg
        R = self.R
        acc_w = R @ a + self.g
        self.p = self.p + self.v * dt + 0.5 * acc_w * dt * dt
        self.v = self.v + acc_w * dt
        self.R = R @ so3_exp(w * dt)
        F = np.eye(self.n)
        F[0:3, 3:6] = np.eye(3) * dt
        F[3:6, 6:9] = -R @ skew(a) * dt
        F[3:6, 12:15] = -R * dt
        F[6:9, 6:9] = so3_exp(-w * dt)
        F[6:9, 9:12] = -np.eye(3) * dt
        P = F @ self.P @ F.T
        self.C = F @ self.C  # the clone is static: only the current half of the cross covariance moves
        idx = np.arange(3, 15)
        P[idx, idx] += self._qc * dt
        self.P = 0.5 * (P + P.T)
        if self._separate:
            Pt = F @ self.Pt @ F.T
            Pt[idx, idx] += self._qt * dt
            self.Pt = 0.5 * (Pt + Pt.T)
            self.Ct = F @ self.Ct

    def _correct(self, y: F64, H: F64, Rm: F64, scale_actual: bool = False,
                 only: npt.NDArray[np.intp] | None = None) -> bool:
        S = H @ self.P @ H.T + Rm
        self.last_innovation = (y, S)
        try:
            Sinv_y = np.linalg.solve(S, y)
        except np.linalg.LinAlgError:
            return False
        d2 = float(y @ Sinv_y)
        if d2 > chi2.ppf(self.cfg.velocity.gate_probability, df=len(y)):
            return False
        K = np.linalg.solve(S, H @ self.P).T  # P H^T S^-1 (S symmetric)
        if only is not None:  # a Schmidt (consider) update: the other states keep their means; Joseph stays exact
            keep = np.zeros(self.n, bool)
            keep[only] = True
            K[~keep] = 0.0
        dx = K @ y
        IKH = np.eye(self.n) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ Rm @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        # the clone is the pose written at the last scan, never corrected afterwards: its error stays the
        # filtered one (Pc fixed) and only the cross covariance moves, cov(dx+, dc) = (I - K H) C. (Reducing Pc
        # by (H C)^T S^-1 (H C) would describe a clone whose mean is corrected too, i.e. a smoothed previous pose.)
        self.C = IKH @ self.C
        if self._separate:  # the same gain on the actual error: Joseph form with the actual measurement noise
            Rt = Rm * self.cfg.covariance.velocity_scale if scale_actual else Rm
            self.Pt = IKH @ self.Pt @ IKH.T + K @ Rt @ K.T
            self.Pt = 0.5 * (self.Pt + self.Pt.T)
            self.Ct = IKH @ self.Ct
        self.p += dx[0:3]
        self.v += dx[3:6]
        self.R = self.R @ so3_exp(dx[6:9])
        self.bg += dx[9:12]
        self.ba += dx[12:15]
        if self.n > 15:
            self.mount = Rotation.from_matrix(so3_exp(self.mount) @ so3_exp(dx[15:18])).as_rotvec()
        return True

    def update_velocity(self, v_radar: F64, cov: F64, rows: npt.NDArray[np.intp], gyro: F64, R_ir: F64, t_ir: F64
                        ) -> bool:
        """Radar ego-velocity update on the measurement rows ``rows`` (indices into x, y, z)."""
        w = gyro - self.bg
        v_body = self.R.T @ self.v
        if self.n > 15:
            R_ir = R_ir @ so3_exp(self.mount)
        h = R_ir.T @ (v_body + np.cross(w, t_ir))
        H = np.zeros((3, self.n))
        H[:, 3:6] = R_ir.T @ self.R.T
        H[:, 6:9] = R_ir.T @ skew(v_body)
        H[:, 9:12] = R_ir.T @ skew(t_ir)
        if self.n > 15:
            H[:, 15:18] = skew(h)
        r = np.asarray(rows, dtype=int)
        return self._correct((v_radar - h)[r], H[r], cov[np.ix_(r, r)], scale_actual=True)

    def update_level(self, sigma: float) -> bool:
        """Zero vertical velocity (world z), std ``sigma``."""
        H = np.zeros((1, self.n))
        H[0, 5] = 1.0
        only = np.r_[2, 5, 15:self.n] if self.cfg.height.level_schmidt else None
        return self._correct(np.array([-self.v[2]]), H, np.array([[sigma * sigma]]), only=only)

    def update_zero_rate(self, gyro_mean: F64, sigma: float) -> bool:
        H = np.zeros((3, self.n))
        H[:, 9:12] = np.eye(3)
        return self._correct(gyro_mean - self.bg, H, np.eye(3) * sigma ** 2)


def innovations_agree(rejected: list[tuple[npt.NDArray[np.intp], F64, F64]], probability: float) -> bool:
    """Whether consecutive rejected velocity innovations ``(rows, y, S)`` agree with one another: the difference
    of each pair, on the rows both have, inside the chi-square gate of ``probability`` on the sum of their
    covariances. A filter that is off gives the same innovation scan after scan (recover); a radar
    whose estimates are outliers (few static returns, clutter that forms a consensus) gives scattered ones."""
    for (ra, ya, Sa), (rb, yb, Sb) in itertools.pairwise(rejected):
        common = np.intersect1d(ra, rb)
        ia, ib = np.searchsorted(ra, common), np.searchsorted(rb, common)
        d = ya[ia] - yb[ib]
        C = Sa[np.ix_(ia, ia)] + Sb[np.ix_(ib, ib)]
        try:
            d2 = float(d @ np.linalg.solve(C, d))
        except np.linalg.LinAlgError:
            return False
        if d2 > chi2.ppf(probability, df=len(common)):
            return False
    return True


def gravity_aligned(acc_mean: F64) -> F64:
    """world <- imu with zero yaw whose z axis is the measured 'up' (the specific force at rest)."""
    up = acc_mean / np.linalg.norm(acc_mean)
    # rotation taking `up` (imu frame) to world z; then remove its yaw
    rot, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up])
    R = rot.as_matrix()
    yaw = np.arctan2(R[1, 0], R[0, 0])
    c, s = np.cos(-yaw), np.sin(-yaw)
    return np.asarray(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R)


def run_ekf(imu_t: npt.NDArray[np.int64], acc: F64, gyro: F64, scan_t: npt.NDArray[np.int64], vel: F64, cov: F64,
            dims: npt.NDArray[np.integer], valid: npt.NDArray[np.bool_], imu_from_radar: F64, cfg: OdometryParams
            ) -> EkfResult:
    """Run the filter over a whole sequence; poses (world <- imu) at every scan time.

    The filter starts at the first scan with a valid ego-velocity that has IMU data before it; earlier
    scans repeat the initial pose (``initialized`` false). Attitude starts gravity-aligned from the mean
    specific force over ``init_window_s`` (yaw 0) less the kinematic acceleration ``dv/dt + w x v`` seen by
    the first two ego-velocities (so a start in motion does not tilt the initial attitude), velocity from
    that scan's ego-velocity. With a standstill at the start (:func:`find_standstill`) the filter starts
    from it instead (see the module docstring).
    """
    S = len(scan_t)
    out = EkfResult(np.tile(np.eye(4), (S, 1, 1)), np.zeros((S, 3)), np.zeros((S, 3)), np.zeros((S, 3)),
                    np.zeros(S, bool), np.zeros(S, bool), np.zeros(S, bool), np.zeros((S, 15)), np.zeros(S, bool),
                    np.zeros((S, 12, 12)), mount_error=np.zeros((S, 3)), mount_sigma=np.zeros((S, 3)))
    R_ir, t_ir = imu_from_radar[:3, :3], imu_from_radar[:3, 3]
    if S == 0 or len(imu_t) < 2:
        return out
    starts = np.flatnonzero(valid & (scan_t >= imu_t[0]) & (scan_t <= imu_t[-1]))
    if len(starts) == 0:
        return out
    s0 = int(starts[0])
    t0 = scan_t[s0]
    win = (imu_t >= t0 - round(cfg.init.window_s * 1e9)) & (imu_t <= t0 + round(cfg.init.window_s * 1e9))
    if not win.any():
        win = np.argsort(np.abs(imu_t - t0))[:10]
    k = int(np.searchsorted(imu_t, t0, side="right") - 1)
    w0 = gyro[win].mean(axis=0)
    v_imu = R_ir @ vel[s0] - np.cross(w0, t_ir)
    f0 = acc[win].mean(axis=0)
    nxt = starts[1] if len(starts) > 1 else None
    if cfg.init.motion_compensation and nxt is not None and (scan_t[nxt] - t0) < 1e9:
        # specific force = kinematic acceleration - gravity: remove d(v_body)/dt + w x v_body first
        v1 = R_ir @ vel[nxt] - np.cross(w0, t_ir)
        dv = (v1 - v_imu) / ((scan_t[nxt] - t0) * 1e-9)
        if np.all(np.isfinite(dv)):
            f0 = f0 - dv - np.cross(w0, v_imu)
    still = None
    if cfg.standstill.enabled:
        moving = radar_moving(vel, cov * cfg.velocity.cov_scale, valid, cfg.standstill.max_speed)
        still = find_standstill(imu_t, acc, gyro, int(t0), scan_t, moving, cfg)
    if still is not None:
        R0 = gravity_aligned(still.accel_mean)
        ekf = EkfRio(cfg, R0, np.zeros(3))
        ekf.bg = still.gyro_mean.copy()
        f = still.accel_mean
        ekf.ba = (np.linalg.norm(f) - cfg.imu.gravity) * f / np.linalg.norm(f)
        ekf.set_noise(max(cfg.imu.accel_noise_density, still.accel_noise_density),
                      max(cfg.imu.gyro_noise_density, still.gyro_noise_density))
        # the bias is the mean of `samples` rates: its std is the rate noise std over sqrt(samples)
        rate = still.samples / max((still.t1_ns - still.t0_ns) * 1e-9, 1e-9)
        g_sd = still.gyro_noise_density * np.sqrt(rate / max(still.samples, 1))
        ekf.set_gyro_bias_variance(max(float(g_sd), 1e-4) ** 2)
        ekf.raise_actual_noise(still.accel_noise_density, still.gyro_noise_density)
    else:
        R0 = gravity_aligned(f0)
        ekf = EkfRio(cfg, R0, R0 @ v_imu)
    chi_rows = {3: np.arange(3), 2: np.arange(2), 0: np.arange(3)}
    n_upd = n_rej = n_zaru = n_recover = n_reinit = n_level_rej = n_scattered = 0
    in_row = 0
    recover_t: list[int] = []
    #: the innovations (rows, y, S) of the rejected velocity updates in the current streak (the last recover_after)
    rejected_nu: list[tuple[npt.NDArray[np.intp], F64, F64]] = []
    # standstill runs: a zero-rate update needs this many consecutive zero-velocity scans (a slow creep can pass
    # the Doppler zero-velocity test while the platform still turns); scans of the initial standstill count too
    zero = valid & (np.asarray(dims) == 0)
    if still is not None:
        zero |= (scan_t >= still.t0_ns) & (scan_t <= still.t1_ns)
    run_len = np.zeros(S, np.int64)
    for i in range(S):
        run_len[i] = (run_len[i - 1] + 1 if i else 1) if zero[i] else 0
    tc = int(t0)
    N = len(imu_t)
    for s in range(S):
        if s < s0:
            continue
        target = int(scan_t[s])
        g_sum = np.zeros(3)
        g_dt = 0.0
        while tc < target:
            t_next = min(int(imu_t[k + 1]) if k + 1 < N else target, target)
            if t_next <= tc:
                k += 1
                continue
            dt = (t_next - tc) * 1e-9
            ekf.propagate(acc[k], gyro[k], dt)
            g_sum += gyro[k] * dt
            g_dt += dt
            tc = t_next
            if k + 1 < N and tc >= imu_t[k + 1]:
                k += 1
        if s > s0 and valid[s]:
            vp = cfg.velocity
            c = cov[s] * vp.cov_scale if vp.use_estimator_covariance else np.eye(3) * vp.sigma_mps ** 2
            c = np.where(np.isfinite(c), c, 0.0)
            rows = chi_rows.get(int(dims[s]), np.arange(3))
            w_k = gyro[min(k, N - 1)]
            if not ekf.finite():  # re-initialise from the radar: velocity, level attitude kept in yaw
                yaw = float(np.arctan2(out.T_world_imu[s - 1, 1, 0], out.T_world_imu[s - 1, 0, 0]))
                p_last = out.T_world_imu[s - 1, :3, 3].copy()
                c_, s_ = np.cos(yaw), np.sin(yaw)
                R_re = np.array([[c_, -s_, 0.0], [s_, c_, 0.0], [0.0, 0.0, 1.0]])
                ekf = EkfRio(cfg, R_re, R_re @ (R_ir @ vel[s]))
                ekf.p = p_last
                n = ekf.n
                ekf.Pc, ekf.C = ekf.P.copy(), np.zeros((n, n))  # the clone's error: independent of the new state
                ekf.Pct, ekf.Ct = ekf.Pt.copy(), np.zeros((n, n))
                n_reinit += 1
                out.recovered[s] = True
            ok = ekf.update_velocity(vel[s], c, rows, w_k, R_ir, t_ir)
            if not ok:
                in_row += 1
                rejected_nu.append((rows, *ekf.last_innovation))
                del rejected_nu[:-cfg.recovery.after]
                if in_row >= cfg.recovery.after and cfg.recovery.consistent and not innovations_agree(
                        rejected_nu, cfg.velocity.gate_probability):
                    n_scattered += 1  # the radar's outliers: kept rejected, no inflation
                elif in_row >= cfg.recovery.after:
                    rc = cfg.recovery
                    ekf.inflate(rc.sigma_v, np.radians(rc.sigma_attitude_deg), rc.sigma_accel_bias)
                    n_recover += 1
                    recover_t.append(int(scan_t[s]))
                    out.recovered[s] = True
                    ok = ekf.update_velocity(vel[s], c, rows, w_k, R_ir, t_ir)
            if ok:
                n_upd += 1
                in_row = 0
                rejected_nu.clear()
                out.updated[s] = True
            else:
                n_rej += 1
                out.rejected[s] = True
            if cfg.height.level_velocity_sigma > 0:  # the gate rejects it where the platform really climbs: counted
                n_level_rej += int(not ekf.update_level(cfg.height.level_velocity_sigma))
            if cfg.velocity.zero_rate_update and run_len[s] >= cfg.velocity.zero_rate_min_scans and g_dt > 0:
                n_zaru += int(ekf.update_zero_rate(g_sum / g_dt, cfg.velocity.zero_rate_sigma))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = ekf.R, ekf.p
        out.T_world_imu[s] = T
        out.velocity[s] = ekf.v
        out.gyro_bias[s] = ekf.bg
        out.accel_bias[s] = ekf.ba
        sd = np.sqrt(np.diag(ekf.P))
        out.sigma[s] = sd[:15]
        if ekf.n > 15:
            out.mount_error[s], out.mount_sigma[s] = ekf.mount, sd[15:18]
        if s > s0:
            out.pose_pair_cov[s] = ekf.pose_pair_cov()
        ekf.clone()
        out.initialized[s] = True
    out.T_world_imu[:s0] = out.T_world_imu[s0]
    out.stats = {"start_scan": s0, "velocity_updates": n_upd, "velocity_rejected": n_rej, "zero_rate_updates": n_zaru,
                 "recoveries": n_recover, "reinitialisations": n_reinit, "recovery_t_ns": recover_t,
                 "recoveries_declined": n_scattered,
                 "level_rejected": n_level_rej,
                 "standstill": still.as_dict() if still is not None else None}
    return out


def increment_covariance(T_world_imu: F64, pose_pair_cov: F64, base_from_imu: F64, eps: float = 1e-6) -> F64:
    """Covariance ``(S, 3, 3)`` of the body-frame SE(2) increment ``(dx, dy, dyaw)`` of the base from scan s-1
    to scan s (as :func:`stages.slam.rbpf.odometry_increments` forms it from the world <- base poses).

    First order: ``J Sigma J^T`` with ``Sigma`` the joint pose-error covariance of the two scans
    (``pose_pair_cov``: right perturbations ``R Exp(dtheta)`` and ``p + dp`` of world <- imu) and J by central
    differences. Row 0 is zero. A rigid SE(2) motion of the whole trajectory (the anchor) leaves it unchanged.
    """
    T = np.asarray(T_world_imu, dtype=np.float64)
    S = len(T)
    out = np.zeros((S, 3, 3))
    if S < 2:
        return out
    imu_from_base = np.linalg.inv(base_from_imu)

    def inc(Tc: F64, Tp: F64) -> F64:
        a, b = Tp @ imu_from_base, Tc @ imu_from_base
        yaw_a, yaw_b = np.arctan2(a[..., 1, 0], a[..., 0, 0]), np.arctan2(b[..., 1, 0], b[..., 0, 0])
        d = b[..., :2, 3] - a[..., :2, 3]
        c, s_ = np.cos(yaw_a), np.sin(yaw_a)
        dyaw = np.angle(np.exp(1j * (yaw_b - yaw_a)))
        return np.stack([c * d[..., 0] + s_ * d[..., 1], -s_ * d[..., 0] + c * d[..., 1], dyaw], axis=-1)

    def perturb(Tm: F64, k: int, h: float) -> F64:
        Tq = Tm.copy()
        if k < 3:
            Tq[:, k, 3] += h
        else:
            w = np.zeros(3)
            w[k - 3] = h
            Tq[:, :3, :3] = Tq[:, :3, :3] @ so3_exp(w)
        return Tq

    cur, prev = T[1:], T[:-1]
    J = np.zeros((S - 1, 3, 12))
    for k in range(12):
        if k < 6:
            d = inc(perturb(cur, k, eps), prev) - inc(perturb(cur, k, -eps), prev)
        else:
            d = inc(cur, perturb(prev, k - 6, eps)) - inc(cur, perturb(prev, k - 6, -eps))
        d[:, 2] = np.angle(np.exp(1j * d[:, 2]))
        J[:, :, k] = d / (2 * eps)
    out[1:] = J @ np.asarray(pose_pair_cov, dtype=np.float64)[1:] @ np.swapaxes(J, 1, 2)
    return np.asarray(0.5 * (out + np.swapaxes(out, 1, 2)))
