"""The sensor error model of the drifting twins (simulator.sensor_errors).

Each error term is checked for its intended statistical effect on a synthetic IMU stream or a radar scan,
deterministic from the seed; all-zero errors leave the measurements untouched; the `_drift` worlds are
their base worlds plus the error tables only.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import tomllib

from simulator import imu as imu_model
from simulator import radar as radar_model
from simulator.params import ImuParams
from simulator.rig import BASE_TO_IMU
from simulator.sensor_errors import (
    SensorErrors,
    bias_instability,
    error_matrices,
    gauss_markov,
    mount_error,
    rotate_points,
)
from simulator.simulate import STREAM_RADAR, Simulation
from simulator.trajectory import TrajectoryState
from simulator.world import load_world, worlds_dir

QUIET = ImuParams(gyro_noise_density=0.0, accel_noise_density=0.0, gyro_bias_sigma=0.0, accel_bias_sigma=0.0,
                  gyro_bias_walk=0.0, accel_bias_walk=0.0)


def _spin(n: int, rate: float, yaw_rate: float) -> TrajectoryState:
    """A base at rest at the origin turning about z at a constant rate."""
    t = np.arange(n) / rate
    z = np.zeros(n)
    return TrajectoryState(t=t, position=np.zeros((n, 3)), velocity=np.zeros((n, 3)), acceleration=np.zeros((n, 3)),
                           yaw=yaw_rate * t, yaw_rate=np.full(n, yaw_rate), yaw_acc=z)


def test_gauss_markov_bias_has_the_set_std_and_correlation_time() -> None:
    sigma, tau, dt = 2e-4, 1.0, 0.01
    x = gauss_markov(400_000, dt, sigma, tau, np.random.default_rng(0))
    assert x.shape == (400_000, 3)
    assert np.allclose(x.std(axis=0), sigma, rtol=0.08)
    lag = round(tau / dt)  # autocorrelation exp(-1) one correlation time apart
    rho = [np.corrcoef(x[:-lag, i], x[lag:, i])[0, 1] for i in range(3)]
    assert np.allclose(rho, np.exp(-1.0), atol=0.06)
    assert np.array_equal(x, gauss_markov(400_000, dt, sigma, tau, np.random.default_rng(0)))
    assert not np.array_equal(x, gauss_markov(400_000, dt, sigma, tau, np.random.default_rng(1)))


def test_bias_random_walk_grows_with_the_square_root_of_time() -> None:
    walk, rate, n = 1e-3, 100.0, 400
    p = ImuParams(**{**QUIET.model_dump(), "gyro_bias_walk": walk})
    ends = []
    for seed in range(300):
        block, _ = imu_model.simulate_block(_spin(n, rate, 0.0), BASE_TO_IMU, p, rate, np.zeros(6),
                                            np.random.default_rng(seed))
        ends.append(block.bias[[n // 4 - 1, n - 1], :3])
    e = np.asarray(ends)  # (seeds, 2, 3): bias after 1 s and 4 s
    std_1s, std_4s = e[:, 0].std(), e[:, 1].std()
    assert std_1s == pytest.approx(walk * np.sqrt(1.0), rel=0.1)
    assert std_4s == pytest.approx(walk * np.sqrt(4.0), rel=0.1)


def test_gyro_scale_error_scales_the_integrated_rotation() -> None:
    rate, n, w = 300.0, 3000, 0.5  # 10 s at 0.5 rad/s: 5 rad about z
    e = SensorErrors(gyro_scale=(0.0, 0.0, 0.02))
    mats = error_matrices(e, np.random.default_rng(0))
    block, _ = imu_model.simulate_block(_spin(n, rate, w), BASE_TO_IMU, QUIET, rate, np.zeros(6),
                                        np.random.default_rng(0), errors=mats)
    angle = block.gyro[:, 2].sum() / rate
    assert angle == pytest.approx(1.02 * w * n / rate, rel=1e-9)
    assert np.abs(block.gyro[:, :2]).max() == 0.0  # no misalignment: no leak into x and y


def test_misalignment_leaks_a_rotation_into_the_other_axes_with_the_set_std() -> None:
    sigma = 2e-3
    e = SensorErrors(misalignment_sigma_rad=sigma)
    leak = []
    for seed in range(400):
        g, _ = error_matrices(e, np.random.default_rng(seed))
        gyro = np.array([[0.0, 0.0, 1.0]]) @ g.T  # 1 rad/s about z
        leak.append(gyro[0, :2])
        assert gyro[0, 2] == 1.0
    assert np.std(leak) == pytest.approx(sigma, rel=0.1)


def test_bias_instability_enters_the_measured_rate_but_not_the_carried_walk() -> None:
    e = SensorErrors(gyro_bias_instability=1e-3, gyro_bias_tau_s=50.0)
    rate, n = 100.0, 500
    gm = bias_instability(e, n, rate, np.random.default_rng(3))
    assert np.abs(gm[:, 3:]).max() == 0.0  # accelerometer part off
    block, last = imu_model.simulate_block(_spin(n, rate, 0.0), BASE_TO_IMU, QUIET, rate, np.zeros(6),
                                           np.random.default_rng(0), bias_extra=gm)
    assert np.array_equal(block.gyro, gm[:, :3])
    assert np.array_equal(block.bias, gm)
    assert np.array_equal(last, np.zeros(6))
    assert np.array_equal(gm, bias_instability(e, n, rate, np.random.default_rng(3)))


def test_mount_error_draws_have_the_set_spread_and_rotate_the_points() -> None:
    e = SensorErrors(radar_mount_sigma_deg=1.0, radar_mount_offset_sigma_m=0.02)
    draws = [mount_error(e, np.random.default_rng(s)) for s in range(500)]
    rpy = np.array([d.rotation.as_euler("xyz", degrees=True) for d in draws])
    off = np.array([d.offset for d in draws])
    assert np.allclose(rpy.std(axis=0), 1.0, rtol=0.12)
    assert np.allclose(off.std(axis=0), 0.02, rtol=0.12)
    yaw = mount_error(SensorErrors(radar_mount_rpy_deg=(0.0, 0.0, 2.0)), np.random.default_rng(0))
    pts = np.zeros(2, dtype=radar_model.RADAR_DTYPE)
    pts["x"], pts["doppler"] = 5.0, (0.3, -0.2)
    xyz = np.array([[5.0, 0.0, 0.0], [0.0, 5.0, 0.0]], np.float32)
    p2, x2 = rotate_points(pts, xyz, yaw)
    # the true boresight is 2 deg left of the stated one: a point straight ahead (stated) lies 2 deg right
    assert np.degrees(np.arctan2(p2["y"][0], p2["x"][0])) == pytest.approx(-2.0, abs=1e-4)
    assert np.array_equal(p2["doppler"], pts["doppler"])
    assert np.hypot(x2[1, 0], x2[1, 1]) == pytest.approx(5.0, rel=1e-6)


def _sim(errors: dict[str, object] | None, duration: float = 1.0) -> Simulation:
    w = load_world("demo")
    if errors is not None:
        w = replace(w, spec=w.spec.model_copy(update={"errors": errors}))
    return Simulation(w, duration, seed=4, workers=1)


ALL_ZERO = {"gyro_bias": [0.0, 0.0, 0.0], "gyro_scale": [0.0, 0.0, 0.0], "accel_scale": [0.0, 0.0, 0.0],
            "gyro_scale_sigma": 0.0, "accel_scale_sigma": 0.0, "misalignment_sigma_rad": 0.0,
            "gyro_bias_instability": 0.0,
            "accel_bias_instability": 0.0, "radar_time_offset_s": 0.0, "radar_mount_rpy_deg": [0.0, 0.0, 0.0],
            "radar_mount_sigma_deg": 0.0, "radar_mount_offset_m": [0.0, 0.0, 0.0], "radar_mount_offset_sigma_m": 0.0}


def test_all_zero_errors_leave_the_measurements_untouched() -> None:
    a, b = next(_sim(None).windows()), next(_sim(ALL_ZERO).windows())
    assert set(ALL_ZERO) | {"gyro_bias_tau_s", "accel_bias_tau_s"} == set(SensorErrors.model_fields)
    assert np.array_equal(a.imu.gyro, b.imu.gyro) and np.array_equal(a.imu.accel, b.imu.accel)
    assert len(a.radar) == len(b.radar) > 0
    for sa, sb in zip(a.radar, b.radar, strict=True):
        assert sa.t == sb.t and sa.points.tobytes() == sb.points.tobytes()
    assert _sim(ALL_ZERO).drift_errors() is None  # and the sidecar gets no errors entry


def test_radar_time_offset_measures_the_scene_before_the_stamp() -> None:
    off = 0.03
    sim, ref = _sim({"radar_time_offset_s": off}), _sim(None)
    assert np.array_equal(sim.radar_ns, ref.radar_ns)  # the stamps stay on the radar's clock grid
    scan = sim.radar_scans(0)[2]
    t = sim.radar_ns[scan.index] / 1e9
    st = ref.traj.state(np.array([t - off]))
    pos, vel, _ = st.sensor(ref.radar_mount.t)
    expect = radar_model.simulate_scan(ref.world.scene, ref.scatterers, ref.radar_p, scan.index, t, pos[0],
                                       float(st.yaw[0] + ref.radar_yaw), vel[0],
                                       np.random.default_rng([ref.seed, STREAM_RADAR, scan.index]))
    assert scan.t == t
    assert scan.points.tobytes() == expect.points.tobytes()
    assert scan.points.tobytes() != ref.radar_scans(0)[2].points.tobytes()


@pytest.mark.parametrize("base", ["demo", "hallway_loop", "outdoor_open", "cluttered_lab", "handheld_loop"])
def test_drift_world_is_its_base_world_plus_sensor_errors(base: str) -> None:
    d = worlds_dir()
    twin = tomllib.loads((d / f"{base}_drift.toml").read_text())
    orig = tomllib.loads((d / f"{base}.toml").read_text())
    assert twin.pop("name") == f"{base}_drift"
    assert twin.pop("description").startswith(orig.pop("description"))
    orig.pop("name")
    errors, imu = SensorErrors(**twin.pop("errors")), twin.pop("imu")
    orig.pop("errors", None)
    orig_imu = orig.pop("imu", None)
    assert twin == orig
    assert orig_imu in (None, imu)
    assert errors.bias_instability_active and errors.mount_active and errors.active
    load_world(d / f"{base}_drift.toml")


def test_drift_sequences_are_registered_beside_their_twins() -> None:
    reg = tomllib.loads((Path(__file__).resolve().parents[1] / "data" / "sequences.toml").read_text())
    for name in ("demo", "sim_hallway_loop", "sim_outdoor_open", "sim_cluttered_lab", "sim_handheld_loop"):
        a, b = reg[name], reg[f"{name}_drift"]
        assert b["world"] == f"{a['world']}_drift"
        for key in ("kind", "duration", "seed", "format"):
            assert a[key] == b[key]
