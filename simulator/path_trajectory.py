"""A trajectory from a recorded position-only path (the ColoRadar twins' ground truth).

The RMap authors' trajectory files (``<scene>_all.txt`` / ``trajectory.parquet``) hold the lidar ground
truth of a run as x, y, z positions, about 15 Hz, with no time stamps and no orientation. The motion is
rebuilt as follows (every step an assumption, stated here):

- **time**: uniform over the samples, ``t_k = k * duration / (N - 1)``, ``duration`` the run's length from
  the paper (RICH-SLAM Table III's sequences: see :data:`simulator.twin.PAPER_DURATIONS_S`);
- **position**: the samples smoothed with a Gaussian of ``smoothing_s`` seconds (the ground truth carries
  centimetre jitter that would give the IMU model huge accelerations), then a quintic interpolating
  spline through them: velocity, acceleration and jerk are continuous and bounded; the height is the
  recorded one (smoothed the same way);
- **heading**: the direction of the smoothed path's horizontal tangent (the rig faced its direction of
  travel: an assumption, the files have no orientation), held through stops (speed below
  ``min_speed``), unwrapped, smoothed with ``heading_smoothing_s`` and splined: yaw rate and yaw
  acceleration are the spline's derivatives. The base stays level (no roll or pitch), as in the built-in
  worlds. Base yaw = heading + :data:`simulator.trajectory.YAW_OFFSET` (the rig's forward axis is base +y).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.interpolate import make_interp_spline
from scipy.ndimage import gaussian_filter1d

from simulator.trajectory import YAW_OFFSET, TrajectoryState


class PathParams(BaseModel):
    """How a position-only path becomes a smooth trajectory."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    smoothing_s: float = Field(0.4, ge=0, description="std of the Gaussian smoothing of the positions, seconds")
    heading_smoothing_s: float = Field(0.5, ge=0, description="std of the Gaussian smoothing of the heading, s")
    min_speed: float = Field(0.15, gt=0, description="below this horizontal speed the heading is held, m/s")


class PathTrajectory:
    """Pose, velocity and acceleration along recorded positions (pure functions of time, see the module doc)."""

    def __init__(self, positions: np.ndarray, duration: float, params: PathParams | None = None) -> None:
        p = params or PathParams()
        pos = np.asarray(positions, np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3 or len(pos) < 6:
            raise ValueError("a recorded path needs at least 6 (x, y, z) samples")
        if not np.isfinite(pos).all():
            raise ValueError("a recorded path holds non-finite positions")
        if not duration > 0:
            raise ValueError("the path's duration must be positive")
        self.duration = float(duration)
        n = len(pos)
        self.t_samples = np.linspace(0.0, self.duration, n)
        dt = self.duration / (n - 1)
        smooth = gaussian_filter1d(pos, p.smoothing_s / dt, axis=0, mode="nearest") if p.smoothing_s > 0 else pos
        self._pos = make_interp_spline(self.t_samples, smooth, k=5)
        # heading on a fine grid from the tangent, held through stops
        tg = np.linspace(0.0, self.duration, max(2 * n, int(self.duration * 50) + 1))
        v = self._pos(tg, 1)
        speed = np.hypot(v[:, 0], v[:, 1])
        moving = speed >= p.min_speed
        if not moving.any():
            moving = speed >= speed.max() * 0.5 if speed.max() > 0 else np.ones(len(tg), bool)
        head = np.arctan2(v[:, 1], v[:, 0])
        idx = np.where(moving, np.arange(len(tg)), -1)
        idx = np.maximum.accumulate(idx)
        first = int(np.argmax(moving))
        idx[idx < 0] = first
        head = np.unwrap(head[idx])
        dtg = tg[1] - tg[0]
        if p.heading_smoothing_s > 0:
            head = gaussian_filter1d(head, p.heading_smoothing_s / dtg, mode="nearest")
        self._head = make_interp_spline(tg, head, k=5)

    def state(self, t: np.ndarray) -> TrajectoryState:
        """The base frame's ground truth at times ``t`` (seconds from the start of the run)."""
        t = np.asarray(t, dtype=np.float64)
        yaw = self._head(t) + YAW_OFFSET
        return TrajectoryState(
            t=t, position=np.asarray(self._pos(t)), velocity=np.asarray(self._pos(t, 1)),
            acceleration=np.asarray(self._pos(t, 2)), yaw=np.arctan2(np.sin(yaw), np.cos(yaw)),
            yaw_rate=np.asarray(self._head(t, 1)), yaw_acc=np.asarray(self._head(t, 2)),
        )
