"""The filter's heading fused with the odometry's by a Kalman smoother that knows how each one errs.

The heading difference ``d_k = yaw_filter_k - yaw_odometry_k`` (unwrapped) is modelled as the sum of two
processes with different spectra, and a third that moves only where the filter's heading jumps:

- ``c``: the odometry's heading error (negated), which grows: a random walk with the odometry's own per-increment
  yaw variances (times ``increment_scale``) plus an integrated yaw-rate bias ``b`` whose random-walk density is
  ``bias_walk`` (rad/s/sqrt(s)) and initial std ``bias_sigma0`` (rad/s): what a drifting gyro does;
- ``w``: the filter's own heading error, which does not grow: a first-order Gauss-Markov process with stationary
  std ``filter_sigma`` (rad) and correlation time ``filter_tau`` (s): what a weight biased by the local
  geometry does (it pulls the heading off after a turn and holds it there, stages/slam/README.md stop 40);
- ``s``: the filter's persistent step: zero until a jump (a lineage switch, a divergence at a turn) is found by
  a gate, within one scan or summed over seconds; it then moves over a segment around the jump and stays where
  the jump took it, as a diverged filter does (``w`` reverts to zero, so without ``s`` the smoother read such a
  jump as the odometry's bias ramp; stages/slam/README.md stop 50).

The smoothed ``c`` corrects the odometry's heading; the position is the odometry's body-frame increments
composed along the corrected heading. Where the difference grows like a gyro drift the fused heading follows
the filter; where it wanders inside ``filter_sigma`` it stays with the odometry. States ``[c, b, w]`` (and ``s``
where a jump was found), exact discretisation of the integrated random walk; a forward Kalman filter that finds
the jumps, a second one with the step state's segments, and a Rauch-Tung-Striebel pass. The final
forward pass also gives the model's evidence ``log p(d | model)``; choosing the model per run by it was
measured and not adopted (stages/slam/README.md, stop 46). :func:`informed` widens ``filter_sigma`` on a run whose
filter weight holds little heading information (stop 47).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field

from stages.odometry.metrics import se2_increments
from stages.slam.se2 import compose, wrap_angle

F64 = npt.NDArray[np.floating[Any]]


class HeadingFusion(BaseModel):
    """The two error models of :mod:`heading_fusion` (SI units, radians). The defaults were chosen on the
    calibration runs at 200 particles (stages/slam/README.md, "The fused estimate"; ``bias_walk`` and
    ``filter_sigma`` re-fitted on twelve calibration runs at stop 49)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    increment_scale: float = Field(0.1, gt=0, description="factor on the odometry's per-increment yaw variances "
                                   "(their NEES says they over-cover yaw; chosen on the calibration runs, stop 46)")
    bias_sigma0: float = Field(0.003, ge=0, description="initial std of the odometry's unmodelled yaw-rate bias, rad/s")
    bias_walk: float = Field(1e-5, ge=0, description="random-walk density of that bias, rad/s/sqrt(s) (3e-4 "
                             "before stop 49)")
    filter_sigma: float = Field(math.radians(4.0), gt=0,
                                description="stationary std of the filter's heading error, rad (8 deg before stop 49)")
    filter_tau: float = Field(100.0, gt=0, description="correlation time of the filter's heading error, s")
    measurement_sigma: float = Field(1e-3, gt=0, description="white part of the filter's heading error, rad")
    jump_gate: float = Field(5.0, ge=0, description="a heading difference further than this many predicted sigmas "
                             "from the prediction, within one scan or summed over jump_window, is a jump of the "
                             "filter's own error, taken by its persistent step state (0: off)")
    jump_window: float = Field(10.0, ge=0, description="seconds over which the innovations are summed to find a "
                               "jump spread over a turn (stop 50; 0: the one-scan gate only)")
    jump_allowance: float = Field(2.0, gt=0, description="a found jump's segment lets the step state move by this "
                                  "many times the jump's size (one sigma; stop 50)")
    information_ref: float = Field(400.0, ge=0, description="yaw information of the filter's weight (rad^-2, per "
                                   "scan, the run's median) below which filter_sigma grows as 1/sqrt(information) "
                                   "(:func:`informed`; chosen on the calibration runs, stop 47; 0: off)")


def informed(model: HeadingFusion, information: npt.ArrayLike) -> HeadingFusion:
    """``model`` with the filter's heading-error std widened where its weight holds little heading:
    ``filter_sigma * max(1, sqrt(information_ref / median(information)))``, the median over the run's scans of the
    weight's yaw Fisher information (:func:`heading_information.yaw_information`). A Cramer-Rao-like scaling: the
    default model where the weight is as informative as the calibration runs that set it, a wider error (the
    fusion then keeps more of the odometry's heading) where it is not. ``information_ref = 0``: ``model``."""
    info = np.asarray(information, np.float64)
    if model.information_ref <= 0 or info.size == 0:
        return model
    # a weight without any heading information: the filter's heading is its proposal's walk (factor 100 caps it)
    median = max(float(np.median(info)), model.information_ref * 1e-4)
    factor = max(1.0, math.sqrt(model.information_ref / median))
    return model.model_copy(update={"filter_sigma": model.filter_sigma * factor})


class FusedHeading(NamedTuple):
    """:func:`fuse_heading`'s result."""

    correction: F64  # (n,) smoothed c: add to the odometry's heading (rad)
    std: F64  # (n,) its standard deviation (rad)
    jumps: int  # jumps of the filter's heading found by either gate (each one a segment of the step state s)
    log_evidence: float = 0.0  # log p(d | model): the sum of the final forward pass's innovation log densities
    step: F64 | None = None  # (n,) smoothed s, the filter's persistent step (rad; zeros where no jump was found)


class _Pass(NamedTuple):
    xs_f: F64
    ps_f: F64
    xs_p: F64
    ps_p: F64
    fs: F64
    jumps: list[tuple[int, int, float]]  # (detecting scan, first scan of the jump, the jump's square)
    log_evidence: float


def _forward(t: F64, d: F64, var: F64, model: HeadingFusion, step_q: F64 | None, detect: bool = False) -> _Pass:
    """One forward Kalman pass. ``detect``: the gates are on and only find the jumps (a found jump goes into the
    step state's variance, so the pass goes on past it). Otherwise no gates: states ``[c, b, w, s]`` with
    ``step_q[k]`` the step state's process noise at scan k, or ``[c, b, w]`` where ``step_q is None``."""
    n = len(t)
    dim = 4 if detect or step_q is not None else 3
    H = np.array([1.0, 0.0, 1.0, 1.0])[:dim]
    r = model.measurement_sigma ** 2
    dts = np.r_[0.0, np.diff(t)]
    xs_f, xs_p = np.empty((n, dim)), np.empty((n, dim))
    ps_f, ps_p, fs = np.empty((n, dim, dim)), np.empty((n, dim, dim)), np.empty((n, dim, dim))
    x = np.zeros(dim)
    # s starts at zero with (almost) no variance: the smoother's inverse needs a regular covariance
    p = np.diag([1e-12, model.bias_sigma0 ** 2 + 1e-18, 1e-12, 0.0 if detect else 1e-12][:dim])
    qb = model.bias_walk ** 2
    gate2 = model.jump_gate ** 2
    jumps: list[tuple[int, int, float]] = []
    window: deque[tuple[int, float, float]] = deque()  # (scan, innovation, its predicted variance)
    sum_nu = sum_s = 0.0
    log_evidence = 0.0
    for k in range(n):
        f = np.eye(dim)
        if k > 0:
            dt = dts[k]
            phi = math.exp(-dt / model.filter_tau)
            f[0, 1] = -dt
            f[2, 2] = phi
            q = np.zeros((dim, dim))
            q[0, 0] = qb * dt ** 3 / 3 + model.increment_scale * var[k]
            q[0, 1] = q[1, 0] = -qb * dt ** 2 / 2
            q[1, 1] = qb * dt
            q[2, 2] = model.filter_sigma ** 2 * (1 - phi * phi)
            x = f @ x
            p = f @ p @ f.T + q
        if step_q is not None and step_q[k] > 0:
            p[3, 3] += step_q[k]
        s = H @ p @ H + r
        nu = d[k] - H @ x
        if detect:
            if nu * nu > gate2 * s:  # a step within one scan
                jumps.append((k, k, nu * nu))
                p[3, 3] += nu * nu
                window.clear()
                sum_nu = sum_s = 0.0
            elif model.jump_window > 0:  # a jump spread over seconds: the window's innovations add up
                window.append((k, nu, s))
                sum_nu += nu
                sum_s += s
                while t[k] - t[window[0][0]] >= model.jump_window:
                    _, nu0, s0 = window.popleft()
                    sum_nu -= nu0
                    sum_s -= s0
                if len(window) > 1 and sum_nu * sum_nu > gate2 * sum_s:
                    jumps.append((k, window[0][0], sum_nu * sum_nu))
                    p[3, 3] += sum_nu * sum_nu
                    window.clear()
                    sum_nu = sum_s = 0.0
            s = H @ p @ H + r
        log_evidence -= 0.5 * (math.log(2.0 * math.pi * s) + nu * nu / s)
        fs[k], xs_p[k], ps_p[k] = f, x, p
        g = p @ H / s
        x = x + g * nu
        p = p - np.outer(g, H @ p)
        p = 0.5 * (p + p.T)
        xs_f[k], ps_f[k] = x, p
    return _Pass(xs_f, ps_f, xs_p, ps_p, fs, jumps, log_evidence)


def _smooth(fw: _Pass) -> tuple[F64, F64]:
    """Rauch-Tung-Striebel pass: the smoothed states and covariances."""
    xs, ps = fw.xs_f.copy(), fw.ps_f.copy()
    for k in range(len(xs) - 2, -1, -1):
        a = fw.ps_f[k] @ fw.fs[k + 1].T @ np.linalg.inv(fw.ps_p[k + 1])
        xs[k] = fw.xs_f[k] + a @ (xs[k + 1] - fw.xs_p[k + 1])
        ps[k] = fw.ps_f[k] + a @ (ps[k + 1] - fw.ps_p[k + 1]) @ a.T
    return xs, ps


def step_noise(t: F64, jumps: list[tuple[int, int, float]], allowance: float) -> F64:
    """The step state's process noise per scan: each jump found at scan ``j`` that began at scan ``i`` (a window's
    first scan; ``i = j`` for a one-scan jump) with square ``u2`` opens a segment ``[i, j + (j - i)]`` (a jump goes
    on about as long as it took to find) over which ``s`` random-walks with total variance ``allowance^2 u2``,
    spread evenly over the segment's seconds; a one-scan jump puts it all at its scan."""
    q = np.zeros(len(t))
    dts = np.r_[0.0, np.diff(t)]
    for j, i, u2 in jumps:
        total = allowance ** 2 * u2
        end = min(len(t) - 1, j + (j - i))
        span = t[end] - t[i]
        if j == i or span <= 0:
            q[j] += total
        else:
            q[i + 1:end + 1] += total * dts[i + 1:end + 1] / span
    return q


def fuse_heading(t_s: npt.ArrayLike, yaw_odometry: npt.ArrayLike, yaw_filter: npt.ArrayLike,
                 increment_var: npt.ArrayLike, model: HeadingFusion) -> FusedHeading:
    """Smoothed correction ``c`` of the odometry's heading (rad, per scan), its std and the filter's jumps.

    ``increment_var[k]``: the odometry's yaw variance of the increment from scan k-1 to k (index 0 unused).
    Two passes where the filter's heading jumps (a lineage switch, a divergence at a turn, which neither error
    model makes and which stays where it went): a first forward pass finds the jumps, a difference further than
    ``jump_gate`` predicted sigmas from its prediction within one scan, or summed over ``jump_window`` seconds;
    the final pass gives each jump to a persistent step state ``s`` of the filter's error (``d = c + w + s``)
    over a segment around it (:func:`step_noise`), then smooths. Without a jump: one pass on ``[c, b, w]``."""
    t = np.asarray(t_s, np.float64)
    yo, yf = np.asarray(yaw_odometry, np.float64), np.asarray(yaw_filter, np.float64)
    var = np.asarray(increment_var, np.float64)
    n = len(t)
    if not (len(yo) == len(yf) == len(var) == n) or n == 0:
        raise ValueError(f"fuse_heading: {n} stamps, {len(yo)} odometry and {len(yf)} filter headings, {len(var)} "
                         "increment variances: one of each per scan")
    if np.any(np.diff(t) < 0):
        raise ValueError("fuse_heading: the stamps go backwards")
    d = np.unwrap(yf - yo)
    d = d - d[0]  # both start at the same pose
    found = _forward(t, d, var, model, None, detect=True).jumps if model.jump_gate > 0 else []
    fw = _forward(t, d, var, model, step_noise(t, found, model.jump_allowance) if found else None)
    xs, ps = _smooth(fw)
    step = xs[:, 3] if xs.shape[1] == 4 else np.zeros(n)
    return FusedHeading(xs[:, 0], np.sqrt(np.maximum(ps[:, 0, 0], 0.0)), len(found), fw.log_evidence, step)


def recompose(odometry: npt.ArrayLike, correction: npt.ArrayLike) -> F64:
    """The odometry's body-frame increments composed along its heading plus ``correction`` (poses ``(n, 3)``)."""
    odo = np.asarray(odometry, np.float64)
    yaw = odo[:, 2] + np.asarray(correction, np.float64)
    body = se2_increments(odo)[1:, :2]
    out = np.empty_like(odo)
    out[0] = odo[0, 0], odo[0, 1], wrap_angle(yaw[0])
    steps = compose(np.c_[np.zeros((len(body), 2)), yaw[:-1]], np.c_[body, np.zeros(len(body))])[:, :2]
    out[1:, :2] = odo[0, :2] + np.cumsum(steps, axis=0)
    out[1:, 2] = wrap_angle(yaw[1:])
    return out
