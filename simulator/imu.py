"""IMU measurements from the analytic trajectory: specific force with gravity, angular rate, noise, biases.

``gyro = R_wi^T w + b_g + n_g`` and ``accel = R_wi^T (a_i - g) + b_a + n_a`` with ``g = (0, 0, -9.81)``
(so a level IMU at rest reads +9.81 on z), white noise of std ``density * sqrt(rate)`` and biases that
start at a random offset and drift as random walks. The bias state is carried between blocks so blocks
can be generated one after another with their own seeded generators.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulator.params import ImuParams
from simulator.rig import Extrinsic
from simulator.trajectory import TrajectoryState


@dataclass(frozen=True)
class ImuBlock:
    t: np.ndarray  # (n,) seconds from the start of the run
    accel: np.ndarray  # (n, 3) m/s^2, IMU frame
    gyro: np.ndarray  # (n, 3) rad/s, IMU frame
    bias: np.ndarray  # (n, 6) true gyro bias (3) then accelerometer bias (3)


def initial_bias(p: ImuParams, rng: np.random.Generator) -> np.ndarray:
    return np.concatenate([rng.normal(0, p.gyro_bias_sigma, 3), rng.normal(0, p.accel_bias_sigma, 3)])


def simulate_block(state: TrajectoryState, mount: Extrinsic, p: ImuParams, rate: float, bias0: np.ndarray,
                   rng: np.random.Generator, extra: tuple[np.ndarray, np.ndarray] | None = None,
                   errors: tuple[np.ndarray, np.ndarray] | None = None, bias_extra: np.ndarray | None = None
                   ) -> tuple[ImuBlock, np.ndarray]:
    """Measurements at ``state.t``; returns the block and the bias after its last sample.

    ``extra``: (specific force, angular rate) added in the IMU frame (e.g. heel-strike vibration);
    ``errors``: the gyro and accelerometer matrices of :func:`simulator.sensor_errors.error_matrices`.
    Both are applied to the true signal, before bias and noise. ``bias_extra``: (n, 6) bias added to the
    random walk (the Gauss-Markov bias instability of :func:`simulator.sensor_errors.bias_instability`); the
    returned bias carries the random walk only.
    """
    n = len(state.t)
    dt = 1.0 / rate
    steps = rng.normal(0.0, 1.0, (n, 6)) * np.sqrt(dt) * np.array([p.gyro_bias_walk] * 3 + [p.accel_bias_walk] * 3)
    walk = bias0 + np.cumsum(steps, axis=0)
    bias = walk if bias_extra is None else walk + bias_extra
    r_wi = state.rotation * mount.rotation
    _, _, acc = state.sensor(mount.t)
    g = np.array([0.0, 0.0, -p.gravity])
    gyro = r_wi.inv().apply(state.omega_world)
    accel = r_wi.inv().apply(acc - g)
    if extra is not None:
        accel, gyro = accel + extra[0], gyro + extra[1]
    if errors is not None:
        gyro, accel = gyro @ errors[0].T, accel @ errors[1].T
    gyro += bias[:, :3]
    accel += bias[:, 3:]
    gyro += rng.normal(0.0, p.gyro_noise_density * np.sqrt(rate), (n, 3))
    accel += rng.normal(0.0, p.accel_noise_density * np.sqrt(rate), (n, 3))
    last = walk[-1] if n else bias0
    return ImuBlock(t=state.t, accel=accel, gyro=gyro, bias=bias), last
