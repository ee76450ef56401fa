"""The smooth ground-truth trajectory that drives every sensor.

The path is a C2 periodic cubic spline through the world's waypoints, re-parametrised by arc length
``s``. The rig moves along it with speed ``v(t) = v0 * ramp(t) * (1 + m sin(2 pi t / T))`` (quintic
ramp from rest), so position, velocity and acceleration are analytic:
``p = q(s)``, ``dp/dt = q'(s) v``, ``d2p/dt2 = q''(s) v^2 + q'(s) dv/dt``.
The base stays level (no roll or pitch); its height varies slowly as ``h + A sin(2 pi t / Tz)``.
The base frame (ColoRadar ``imu_viz_link``) has +y forward, +x to the right, +z up, so the base yaw is
the path heading minus 90 degrees and the radar (boresight along base +y) looks where the rig goes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator
from scipy.integrate import cumulative_simpson
from scipy.interpolate import CubicHermiteSpline, CubicSpline
from scipy.spatial.transform import Rotation

#: base yaw = path heading + YAW_OFFSET (the rig's forward axis is base +y)
YAW_OFFSET = -np.pi / 2


class TrajectorySpec(BaseModel):
    """A smooth closed loop through the waypoints, driven with a smooth speed profile (a world's
    ``[trajectory]`` table)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    waypoints: list[tuple[float, float]] = Field(description="closed loop of [x, y] waypoints, visited in order")
    height: float = Field(1.1, description="mean height of the base frame above the floor, metres")
    height_amplitude: float = Field(0.04, ge=0.0, le=0.3, description="amplitude of the slow height change, metres")
    height_period: float = Field(9.0, gt=0.5, description="period of the height change, seconds")
    speed: float = Field(1.0, gt=0.05, le=3.0, description="mean speed along the path, m/s")
    speed_variation: float = Field(0.2, ge=0.0, lt=0.9, description="relative amplitude of the speed modulation")
    speed_period: float = Field(13.0, gt=0.5, description="period of the speed modulation, seconds")
    start_ramp: float = Field(2.0, ge=0.0, description="seconds to accelerate smoothly from rest")
    start_offset: float = Field(0.0, ge=0.0, description="arc length along the loop where the run starts, metres")
    reverse: bool = Field(False, description="drive the loop in the reverse waypoint order")

    @field_validator("waypoints")
    @classmethod
    def _enough(cls, v: list[tuple[float, float]]) -> list[tuple[float, float]]:
        if len(v) < 3:
            raise ValueError("a trajectory loop needs at least three waypoints")
        return v


class LoopPath:
    """A closed planar curve through waypoints, parametrised by arc length (metres)."""

    def __init__(self, spec: TrajectorySpec, sample_step: float = 0.05) -> None:
        pts = np.asarray(spec.waypoints, dtype=np.float64)
        if spec.reverse:
            pts = pts[::-1]
        closed = np.vstack([pts, pts[:1]])
        u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
        chord = CubicSpline(u, closed, bc_type="periodic")
        # arc length of the chord-parametrised spline, then a re-sampled spline in arc length
        uu = np.linspace(0.0, u[-1], 20 * len(u) + int(u[-1] / 0.005) + 1)
        speed = np.linalg.norm(chord(uu, 1), axis=1)
        s_of_u = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(uu))])
        self.length = float(s_of_u[-1])
        n = max(16, round(self.length / sample_step))
        s_grid = np.linspace(0.0, self.length, n + 1)
        q = chord(np.interp(s_grid, s_of_u, uu))
        q[-1] = q[0]
        self._q = CubicSpline(s_grid, q, bc_type="periodic")

    def position(self, s: np.ndarray) -> np.ndarray:
        return np.asarray(self._q(np.mod(s, self.length)))

    def derivative(self, s: np.ndarray, order: int) -> np.ndarray:
        return np.asarray(self._q(np.mod(s, self.length), order))


@dataclass(frozen=True)
class TrajectoryState:
    """Ground truth of the base frame at times ``t`` (seconds from the start of the run)."""

    t: np.ndarray  # (N,)
    position: np.ndarray  # (N, 3) world
    velocity: np.ndarray  # (N, 3) world
    acceleration: np.ndarray  # (N, 3) world
    yaw: np.ndarray  # (N,) base yaw
    yaw_rate: np.ndarray  # (N,)
    yaw_acc: np.ndarray  # (N,)

    @property
    def rotation(self) -> Rotation:
        """world <- base."""
        return Rotation.from_quat(self.quaternion)

    @property
    def quaternion(self) -> np.ndarray:
        """world <- base as (x, y, z, w), w >= 0."""
        h = 0.5 * self.yaw
        q = np.stack([np.zeros_like(h), np.zeros_like(h), np.sin(h), np.cos(h)], axis=1)
        return q * np.where(q[:, 3:] < 0, -1.0, 1.0)

    @property
    def omega_world(self) -> np.ndarray:
        """Angular velocity (world frame, equal to the body frame for a level base)."""
        z = np.zeros_like(self.yaw_rate)
        return np.stack([z, z, self.yaw_rate], axis=1)

    def sensor(self, t_bs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration (world) of a point fixed at ``t_bs`` in the base frame."""
        r = self.rotation.apply(np.asarray(t_bs, dtype=np.float64))  # (N, 3)
        w = self.omega_world
        alpha = np.stack([np.zeros_like(self.yaw_acc), np.zeros_like(self.yaw_acc), self.yaw_acc], axis=1)
        wxr = np.cross(w, r)
        return (self.position + r, self.velocity + wxr,
                self.acceleration + np.cross(alpha, r) + np.cross(w, wxr))


class Trajectory:
    """Time-parametrised motion along a :class:`LoopPath` (pure functions of time)."""

    def __init__(self, spec: TrajectorySpec, duration: float, floor: float = 0.0) -> None:
        self.spec = spec
        self.duration = float(duration)
        self.path = LoopPath(spec)
        self.floor = floor
        # s(t) = s0 + integral of v: Simpson on a 1 ms grid, Hermite interpolation with the exact v
        n = max(8, int(np.ceil((self.duration + 1.0) / 1e-3)))
        tg = np.linspace(0.0, self.duration + 1.0, n + 1)
        vg = self._speed(tg)
        sg = spec.start_offset + cumulative_simpson(vg, x=tg, initial=0.0)
        self._s = CubicHermiteSpline(tg, sg, vg)

    # speed profile v(t) and its derivative -------------------------------------------------------
    def _ramp(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tr = self.spec.start_ramp
        if tr <= 0:
            return np.ones_like(t), np.zeros_like(t)
        x = np.clip(t / tr, 0.0, 1.0)
        r = x**3 * (10 - 15 * x + 6 * x**2)
        dr = np.where((t > 0) & (t < tr), 30 * x**2 * (1 - x) ** 2 / tr, 0.0)
        return r, dr

    def _speed(self, t: np.ndarray) -> np.ndarray:
        sp = self.spec
        r, _ = self._ramp(t)
        return sp.speed * r * (1 + sp.speed_variation * np.sin(2 * np.pi * t / sp.speed_period))

    def _speed_dot(self, t: np.ndarray) -> np.ndarray:
        sp = self.spec
        r, dr = self._ramp(t)
        w = 2 * np.pi / sp.speed_period
        return sp.speed * (dr * (1 + sp.speed_variation * np.sin(w * t)) + r * sp.speed_variation * w * np.cos(w * t))

    # state ----------------------------------------------------------------------------------------------
    def state(self, t: np.ndarray) -> TrajectoryState:
        """Analytic pose, velocity, acceleration and yaw derivatives at times ``t`` (seconds)."""
        t = np.asarray(t, dtype=np.float64)
        sp = self.spec
        s = self._s(t)
        v = self._speed(t)
        vd = self._speed_dot(t)
        q1 = self.path.derivative(s, 1)
        q2 = self.path.derivative(s, 2)
        q3 = self.path.derivative(s, 3)
        xy = self.path.position(s)
        wz = 2 * np.pi / sp.height_period
        z = self.floor + sp.height + sp.height_amplitude * np.sin(wz * t)
        zd = sp.height_amplitude * wz * np.cos(wz * t)
        zdd = -sp.height_amplitude * wz**2 * np.sin(wz * t)
        pos = np.column_stack([xy, z])
        vel = np.column_stack([q1 * v[:, None], zd])
        acc = np.column_stack([q2 * (v**2)[:, None] + q1 * vd[:, None], zdd])
        n2 = (q1**2).sum(1)
        cr = q1[:, 0] * q2[:, 1] - q1[:, 1] * q2[:, 0]
        dpsi_ds = cr / n2
        d2psi_ds2 = ((q1[:, 0] * q3[:, 1] - q1[:, 1] * q3[:, 0]) * n2 - cr * 2 * (q1 * q2).sum(1)) / n2**2
        yaw = np.arctan2(q1[:, 1], q1[:, 0]) + YAW_OFFSET
        yaw = np.arctan2(np.sin(yaw), np.cos(yaw))
        return TrajectoryState(
            t=t, position=pos, velocity=vel, acceleration=acc, yaw=yaw,
            yaw_rate=dpsi_ds * v, yaw_acc=d2psi_ds2 * v**2 + dpsi_ds * vd,
        )
