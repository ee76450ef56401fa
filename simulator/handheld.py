"""A handheld radar + IMU rig (TI IWR6843 and an industrial MEMS IMU on a stick) carried at walking pace.

What makes it unlike the ColoRadar rig, and like handheld recordings from other public projects:

- frames and topics: the body (base) frame is the IMU frame ``imu_link`` (x forward, y left, z up); the
  radar publishes ``/ti_mmwave/radar_scan_pcl`` with fields ``x y z intensity velocity`` (the TI ROS
  driver's PointXYZIV layout, 32-byte points) and an empty ``frame_id``; there is no tf, no lidar and no
  ground-truth topic (the simulator keeps the truth in its sidecar only);
- the radar is mounted rotated: upside down (roll 180 deg about its boresight) and turned by
  ``radar_yaw_deg`` about the body z axis, so the log is wrong without the extrinsic;
- clocks: every radar header stamp is zero (the bag's record time is the only time), and the IMU's
  header stamps run on another clock ``imu_clock_offset_s`` away from the record time (days);
- motion (:class:`WalkingTrajectory`): a standstill, a smooth start, walking with step dynamics (vertical
  bob at the step frequency, torso yaw sway at half of it, speed surging per step), a smooth stop back at
  the start of the loop and a final standstill;
- heel-strike vibration (:func:`heel_strike`): a damped oscillation after every step in the IMU's
  specific force and angular rate; it integrates to zero velocity and rotation (sub-millimetre motion),
  so the radar and the ground truth do not see it;
- radar dropouts: scans published with width 0 during ``dropout_start_s`` .. ``+dropout_s``.

The sensor noise itself comes from ``[imu]`` (:class:`simulator.params.ImuParams`) and the deterministic
IMU errors from ``[errors]`` (:mod:`simulator.sensor_errors`) of the world file.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field, field_validator
from scipy.spatial.transform import Rotation

from simulator.params import _Params
from simulator.rig import Extrinsic
from simulator.trajectory import YAW_OFFSET, Trajectory, TrajectorySpec, TrajectoryState

IMU_FRAME = "imu_link"
RADAR_FRAME_NAME = "ti_mmwave"  # the radar's frame in the extrinsic; the messages' frame_id is empty

#: the TI ROS driver's PointXYZIV cloud (PCL pads xyz to 16 bytes)
TI_RADAR_DTYPE = np.dtype({"names": ["x", "y", "z", "intensity", "velocity"], "formats": ["<f4"] * 5,
                           "offsets": [0, 4, 8, 16, 20], "itemsize": 32})


class HandheldRig(_Params):
    """The ``[rig]`` table of a world with ``kind = "handheld"``."""

    kind: str = Field("handheld", description="'handheld' (the only other rig is the default ColoRadar one)")
    radar_topic: str = Field("/ti_mmwave/radar_scan_pcl", description="radar PointCloud2 topic")
    imu_topic: str = Field("/imu/data", description="sensor_msgs/Imu topic")
    radar_frame_id: str = Field("", description="header.frame_id of the radar messages (empty, as the real log)")
    imu_frame_id: str = Field(IMU_FRAME, description="header.frame_id of the IMU messages")
    radar_rate_hz: float = Field(10.0, gt=0, description="radar scan rate")
    imu_rate_hz: float = Field(400.0, gt=0, description="IMU sample rate")
    radar_translation: tuple[float, float, float] = Field((0.06, -0.02, 0.04), description="body <- radar, m")
    radar_yaw_deg: float = Field(-12.0, description="radar boresight yaw in the body frame, degrees")
    radar_roll_deg: float = Field(180.0, description="radar roll about its boresight: 0 or 180 (upside down)")
    radar_zero_stamps: bool = Field(True, description="radar header stamps are zero (record time only)")
    imu_clock_offset_s: float = Field(-337_000.25, description="IMU header stamp minus record time, s")
    radar_latency_s: tuple[float, float] = Field((0.025, 0.045), description="radar record-time latency range "
                                                           "(frame processing and UART), s")
    imu_latency_s: tuple[float, float] = Field((0.0005, 0.0015), description="IMU record-time latency range, s")
    standstill_start_s: float = Field(2.5, ge=0, description="standing still before walking, s")
    standstill_end_s: float = Field(2.0, ge=0, description="standing still after stopping, s")
    ramp_s: float = Field(1.5, gt=0, description="time to start or stop walking, s")
    laps: float = Field(1.0, gt=0, description="loops walked (1.0 ends where it started)")
    step_frequency_hz: float = Field(1.8, gt=0, description="steps per second")
    bob_amplitude_m: float = Field(0.025, ge=0, description="vertical bob amplitude at the step frequency, m")
    sway_yaw_deg: float = Field(3.0, ge=0, description="torso yaw sway amplitude at half the step frequency, deg")
    surge: float = Field(0.12, ge=0, lt=0.9, description="relative speed surge per step")
    vibration_accel: float = Field(5.0, ge=0, description="peak heel-strike specific force, m/s^2")
    vibration_gyro: float = Field(0.3, ge=0, description="peak heel-strike angular rate, rad/s")
    vibration_hz: float = Field(18.0, gt=0, description="ringing frequency of the heel strike")
    vibration_decay_s: float = Field(0.04, gt=0, description="decay time of the heel strike")
    dropout_start_s: float = Field(24.0, ge=0, description="start of a radar dropout (empty scans), s")
    dropout_s: float = Field(1.3, ge=0, description="length of the dropout (0: none), s")

    @field_validator("radar_roll_deg")
    @classmethod
    def _level(cls, v: float) -> float:
        if v not in (0.0, 180.0):
            raise ValueError("the radar model needs a level boresight: roll 0 or 180 degrees")
        return v

    def radar_mount(self) -> Extrinsic:
        """body <- radar: yaw about body z, then the roll about the boresight."""
        rot = Rotation.from_euler("z", self.radar_yaw_deg, degrees=True) * \
            Rotation.from_euler("x", self.radar_roll_deg, degrees=True)
        q = rot.as_quat()
        q = q * (1.0 if q[3] >= 0 else -1.0)
        return Extrinsic(IMU_FRAME, RADAR_FRAME_NAME, self.radar_translation,
                         tuple(float(v) for v in q))  # type: ignore[arg-type]

    def imu_mount(self) -> Extrinsic:
        return Extrinsic(IMU_FRAME, IMU_FRAME, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))


def _ramp(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quintic smoothstep of x (clipped to [0, 1]) and its first two derivatives in x."""
    inside = (x > 0) & (x < 1)
    x = np.clip(x, 0.0, 1.0)
    r = x**3 * (10 - 15 * x + 6 * x**2)
    dr = np.where(inside, 30 * x**2 * (1 - x) ** 2, 0.0)
    ddr = np.where(inside, 60 * x * (1 - x) * (1 - 2 * x), 0.0)
    return r, dr, ddr


class WalkingTrajectory(Trajectory):
    """The world's loop walked once (``laps``) between two standstills, with step dynamics on top."""

    def __init__(self, spec: TrajectorySpec, duration: float, floor: float, rig: HandheldRig) -> None:
        self.rig = rig
        self.v0 = 1.0
        walk = duration - rig.standstill_start_s - rig.standstill_end_s
        if walk < 2 * rig.ramp_s + 1.0:
            raise ValueError(f"duration {duration:g} s leaves too little walking time between the standstills")
        super().__init__(spec, duration, floor=floor)
        # scale the speed so that the walk covers `laps` loops exactly (it ends where it started)
        tg = np.linspace(0.0, duration, int(duration / 1e-3) + 1)
        dist = float(np.trapezoid(self._speed(tg), tg))
        self.v0 = rig.laps * self.path.length / dist
        super().__init__(spec, duration, floor=floor)

    def envelope(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Walking envelope e(t) (0 standing, 1 walking) and its derivatives."""
        rg = self.rig
        a, da, dda = _ramp((t - rg.standstill_start_s) / rg.ramp_s)
        b, db, ddb = _ramp((self.duration - rg.standstill_end_s - t) / rg.ramp_s)
        k = 1.0 / rg.ramp_s
        da, dda, db, ddb = da * k, dda * k * k, -db * k, ddb * k * k
        return a * b, da * b + a * db, dda * b + 2 * da * db + a * ddb

    def _speed(self, t: np.ndarray) -> np.ndarray:
        e, _, _ = self.envelope(t)
        w = 2 * np.pi * self.rig.step_frequency_hz
        return self.v0 * e * (1 + self.rig.surge * np.sin(w * t))

    def _speed_dot(self, t: np.ndarray) -> np.ndarray:
        e, de, _ = self.envelope(t)
        w = 2 * np.pi * self.rig.step_frequency_hz
        return self.v0 * (de * (1 + self.rig.surge * np.sin(w * t)) + e * self.rig.surge * w * np.cos(w * t))

    def state(self, t: np.ndarray) -> TrajectoryState:
        t = np.asarray(t, dtype=np.float64)
        base = super().state(t)
        rg = self.rig
        e, de, dde = self.envelope(t)
        w = 2 * np.pi * rg.step_frequency_hz
        # vertical bob e(t) B sin(w t) and yaw sway e(t) A sin(w t / 2), with exact derivatives
        s1, c1 = np.sin(w * t), np.cos(w * t)
        bz = rg.bob_amplitude_m
        z = bz * e * s1
        zd = bz * (de * s1 + e * w * c1)
        zdd = bz * (dde * s1 + 2 * de * w * c1 - e * w * w * s1)
        wh = w / 2
        s2, c2 = np.sin(wh * t), np.cos(wh * t)
        ay = np.radians(rg.sway_yaw_deg)
        psi = ay * e * s2
        psid = ay * (de * s2 + e * wh * c2)
        psidd = ay * (dde * s2 + 2 * de * wh * c2 - e * wh * wh * s2)
        pos, vel, acc = base.position.copy(), base.velocity.copy(), base.acceleration.copy()
        pos[:, 2] += z
        vel[:, 2] += zd
        acc[:, 2] += zdd
        yaw = base.yaw - YAW_OFFSET + psi  # the handheld body's forward axis is x
        yaw = np.arctan2(np.sin(yaw), np.cos(yaw))
        return TrajectoryState(t=t, position=pos, velocity=vel, acceleration=acc, yaw=yaw,
                               yaw_rate=base.yaw_rate + psid, yaw_acc=base.yaw_acc + psidd)

    def step_times(self) -> np.ndarray:
        """Heel strikes: every step period while the walking envelope is above one half."""
        period = 1.0 / self.rig.step_frequency_hz
        t = np.arange(0.0, self.duration, period)
        return t[self.envelope(t)[0] > 0.5]


def heel_strike(t: np.ndarray, steps: np.ndarray, rig: HandheldRig, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray]:
    """Specific force and angular rate (IMU frame, (n, 3) each) of the heel strikes at ``steps``.

    Each strike is the time derivative of a damped ring ``exp(-u / tau) sin(2 pi f u)`` (u after the
    strike), so it adds no net velocity or rotation; per-strike directions are drawn from ``rng``.
    """
    acc = np.zeros((len(t), 3))
    gyr = np.zeros((len(t), 3))
    if not len(t) or not len(steps):
        return acc, gyr
    tau, om = rig.vibration_decay_s, 2 * np.pi * rig.vibration_hz
    peak = om  # d/du of the ring peaks at about omega (omega tau >> 1)
    for ts in steps:
        lo, hi = np.searchsorted(t, [ts, ts + 6 * tau])
        if hi <= lo:
            continue
        u = t[lo:hi] - ts
        ring = np.exp(-u / tau) * (om * np.cos(om * u) - np.sin(om * u) / tau) / peak
        da = rng.normal(0.0, 1.0, 3) * np.array([0.4, 0.3, 1.0])
        dg = rng.normal(0.0, 1.0, 3) * np.array([1.0, 1.0, 0.3])
        acc[lo:hi] += rig.vibration_accel * ring[:, None] * da[None, :]
        gyr[lo:hi] += rig.vibration_gyro * ring[:, None] * dg[None, :]
    return acc, gyr
