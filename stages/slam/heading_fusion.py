"""The filter's heading fused with the odometry's by a Kalman smoother that knows how each one errs.

The heading difference ``d_k = yaw_filter_k - yaw_odometry_k`` (unwrapped) is modelled as the sum of two
processes with different spectra:

- ``c``: the odometry's heading error (negated), which grows: a random walk with the odometry's own per-increment
  yaw variances (times ``increment_scale``) plus an integrated yaw-rate bias ``b`` whose random-walk density is
  ``bias_walk`` (rad/s/sqrt(s)) and initial std ``bias_sigma0`` (rad/s): what a drifting gyro does;
- ``w``: the filter's own heading error, which does not grow: a first-order Gauss-Markov process with stationary
  std ``filter_sigma`` (rad) and correlation time ``filter_tau`` (s): what a weight biased by the local
  geometry does (it pulls the heading off after a turn and holds it there, stages/slam/README.md stop 40).

The smoothed ``c`` corrects the odometry's heading; the position is the odometry's body-frame increments
composed along the corrected heading. Where the difference grows like a gyro drift the fused heading follows
the filter; where it wanders inside ``filter_sigma`` it stays with the odometry. States ``[c, b, w]``, exact
discretisation of the integrated random walk; a forward Kalman filter and a Rauch-Tung-Striebel pass. The
forward pass also gives the model's evidence ``log p(d | model)``; choosing the model per run by it was
measured and not adopted (stages/slam/README.md, stop 46). :func:`informed` widens ``filter_sigma`` on a run whose
filter weight holds little heading information (stop 47).
"""

from __future__ import annotations

import math
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
                             "from the prediction is a jump of the filter's own error, taken by it alone (0: off)")
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
    jumps: int  # scans where the filter's heading jumped past ``jump_gate`` (taken by its own error)
    log_evidence: float = 0.0  # log p(d | model): the sum of the forward pass's Gaussian innovation log densities


def fuse_heading(t_s: npt.ArrayLike, yaw_odometry: npt.ArrayLike, yaw_filter: npt.ArrayLike,
                 increment_var: npt.ArrayLike, model: HeadingFusion) -> FusedHeading:
    """Smoothed correction ``c`` of the odometry's heading (rad, per scan), its std and the filter's jumps.

    ``increment_var[k]``: the odometry's yaw variance of the increment from scan k-1 to k (index 0 unused). A
    difference further than ``jump_gate`` predicted sigmas from its prediction (the filter switched lineage or
    diverged within a scan, which neither error model does) is given to the filter's error alone: that scan adds
    the innovation's square to its variance before the update (a gated, adaptive process noise)."""
    t = np.asarray(t_s, np.float64)
    yo, yf = np.asarray(yaw_odometry, np.float64), np.asarray(yaw_filter, np.float64)
    var = np.asarray(increment_var, np.float64)
    n = len(t)
    if not (len(yo) == len(yf) == len(var) == n) or n == 0:
        raise ValueError(f"fuse_heading: {n} stamps, {len(yo)} odometry and {len(yf)} filter headings, {len(var)} "
                         "increment variances: one of each per scan")
    d = np.unwrap(yf - yo)
    d = d - d[0]  # both start at the same pose
    dts = np.r_[0.0, np.diff(t)]
    if np.any(dts < 0):
        raise ValueError("fuse_heading: the stamps go backwards")
    H = np.array([1.0, 0.0, 1.0])
    r = model.measurement_sigma ** 2
    xs_f = np.empty((n, 3))
    ps_f = np.empty((n, 3, 3))
    xs_p = np.empty((n, 3))
    ps_p = np.empty((n, 3, 3))
    fs = np.empty((n, 3, 3))
    x = np.zeros(3)
    p = np.diag([1e-12, model.bias_sigma0 ** 2 + 1e-18, 1e-12])
    qb = model.bias_walk ** 2
    jumps = 0
    log_evidence = 0.0
    for k in range(n):
        if k > 0:
            dt = dts[k]
            phi = np.exp(-dt / model.filter_tau)
            f = np.array([[1.0, -dt, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, phi]])
            q = np.zeros((3, 3))
            q[0, 0] = qb * dt ** 3 / 3 + model.increment_scale * var[k]
            q[0, 1] = q[1, 0] = -qb * dt ** 2 / 2
            q[1, 1] = qb * dt
            q[2, 2] = model.filter_sigma ** 2 * (1 - phi * phi)
            x = f @ x
            p = f @ p @ f.T + q
        else:
            f = np.eye(3)
        s = H @ p @ H + r
        nu = d[k] - H @ x
        if model.jump_gate > 0 and nu * nu > model.jump_gate ** 2 * s:
            # the filter's heading jumped (a lineage switch, a divergence): its own error takes the step
            p = p.copy()
            p[2, 2] += nu * nu
            s = H @ p @ H + r
            jumps += 1
        log_evidence -= 0.5 * (math.log(2.0 * math.pi * s) + nu * nu / s)
        fs[k], xs_p[k], ps_p[k] = f, x, p
        g = p @ H / s
        x = x + g * nu
        p = p - np.outer(g, H @ p)
        p = 0.5 * (p + p.T)
        xs_f[k], ps_f[k] = x, p
    xs = xs_f.copy()
    ps = ps_f.copy()
    for k in range(n - 2, -1, -1):
        a = ps_f[k] @ fs[k + 1].T @ np.linalg.inv(ps_p[k + 1])
        xs[k] = xs_f[k] + a @ (xs[k + 1] - xs_p[k + 1])
        ps[k] = ps_f[k] + a @ (ps[k + 1] - ps_p[k + 1]) @ a.T
    return FusedHeading(xs[:, 0], np.sqrt(np.maximum(ps[:, 0, 0], 0.0)), jumps, log_evidence)


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
