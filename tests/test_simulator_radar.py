"""Pieces of the radar model against independent references: the window kernel, CFAR, the AoA chain, scatterers."""

from __future__ import annotations

import numpy as np
import pytest

from simulator.params import RadarParams
from simulator.radar import angle_of_arrival, cfar_detect, hann_kernel, steering
from simulator.scatterers import KIND_CORNER, KIND_PILLAR, build_scatterers
from simulator.world import WorldSpec, load_world


def test_hann_kernel_matches_a_windowed_fft() -> None:
    # reference: a Hann-windowed tone, zero-padded FFT, read at integer offsets from the tone's frequency
    n, pad = 256, 64
    w = np.hanning(n + 1)[:-1]  # periodic Hann
    for frac in (0.0, 0.25, 0.5):
        k0 = 40 + frac
        spec = np.abs(np.fft.fft(w * np.exp(2j * np.pi * k0 * np.arange(n) / n), n * pad))
        spec /= np.abs(np.fft.fft(w * np.exp(2j * np.pi * 40 * np.arange(n) / n), n * pad)).max()
        for o in range(-2, 3):
            ref = spec[(40 + o) * pad]
            assert abs(abs(hann_kernel(np.array([o - frac]))[0]) - ref) < 0.01
    assert hann_kernel(np.array([0.0, 1.0, -1.0, 2.0]))[[0, 1, 2]].tolist() == [1.0, 0.5, 0.5]
    assert abs(hann_kernel(np.array([2.0]))[0]) < 1e-12


def _grid(rng: np.random.Generator, nr: int = 96, nd: int = 64) -> np.ndarray:
    return rng.gamma(12, 1 / 12, (nr, nd))


def _add(power: np.ndarray, r: float, d: float, snr_db: float) -> None:
    off = np.arange(-2, 3)
    ir, idp = round(r), round(d)
    wr, wd = hann_kernel(off - (r - ir)), hann_kernel(off - (d - idp))
    for i, a in zip(off, wr, strict=True):
        for j, b in zip(off, wd, strict=True):
            power[ir + i, (idp + j) % power.shape[1]] += 10 ** (snr_db / 10) * (a * b) ** 2


def test_cfar_detects_isolated_returns_once_and_noise_never() -> None:
    rng = np.random.default_rng(0)
    p = RadarParams(peak_grouping=True)  # the out-of-box chain
    power = _grid(rng)
    assert not cfar_detect(10 * np.log10(power), p).any()  # 15 dB over 12-channel averaged noise: no false alarms
    _add(power, 30.3, 10.2, 40.0)
    _add(power, 60.0, 40.4, 25.0)
    _add(power, 80.0, 20.0, 12.0)  # below the threshold
    det = cfar_detect(10 * np.log10(power), p)
    assert sorted(zip(*np.nonzero(det), strict=True)) == [(30, 10), (60, 40)]  # one cell each, at the peak
    # without grouping (the default, as the TI ROS driver's 3D configuration) the main lobe's neighbours of
    # the strong returns are reported too, all within +-2 bins of the peaks
    loose = np.nonzero(cfar_detect(10 * np.log10(power), RadarParams()))
    cells = np.column_stack(loose)
    assert len(cells) > 2 and {(30, 10), (60, 40)} <= set(map(tuple, cells.tolist()))
    near = np.minimum(np.abs(cells - [30, 10]).max(1), np.abs(cells - [60, 40]).max(1))
    assert np.all(near <= 2)


def test_cfar_masks_a_weak_return_beside_a_strong_one_and_in_dense_clutter() -> None:
    rng = np.random.default_rng(1)
    p = RadarParams(peak_grouping=True)
    power = _grid(rng)
    _add(power, 30.0, 10.0, 45.0)
    _add(power, 31.0, 11.0, 30.0)  # a neighbouring cell: peak grouping keeps only the strong one
    det = cfar_detect(10 * np.log10(power), p)
    assert sorted(zip(*np.nonzero(det), strict=True)) == [(30, 10)]
    assert cfar_detect(10 * np.log10(power), p.model_copy(update={"peak_grouping": False})).sum() > 1
    # a wall-like ridge of equal returns along range (bins 40..69): smallest-of averaging detects only near its
    # ends, where one noise window still lies outside it, never inside where both windows are in the ridge
    power = _grid(rng)
    for r in range(40, 70):
        _add(power, float(r), 20.0, 30.0)
    det = cfar_detect(10 * np.log10(power), p)
    rows = np.nonzero(det[:, 20])[0]
    reach = p.cfar_range_guard + p.cfar_range_window
    assert 0 < len(rows) <= 8 and np.all((rows < 40 + reach) | (rows > 69 - reach))


def test_angle_of_arrival_quantises_azimuth_and_keeps_elevation() -> None:
    rng = np.random.default_rng(2)
    az = np.radians(rng.uniform(-55, 55, 200))
    el = np.radians(rng.uniform(-20, 20, 200))
    u = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    snap = 1000.0 * steering(u)  # 60 dB per channel, no noise
    pc, _, wx, wz = angle_of_arrival(snap, 64, multi_peak_ratio=0.5)
    assert np.array_equal(pc, np.arange(200))  # one lone target: no second peak
    assert np.all(np.abs(wx - np.round(u[:, 1] * 32) / 32) < 1e-12)  # nearest bin of the 64-point FFT
    assert np.abs(wz - u[:, 2]).max() < 1e-9  # the phase comparison is exact for a lone target
    # noise: azimuth off by at most a bin at 20 dB, elevation error grows as the SNR falls
    noise = (rng.standard_normal((200, 12)) + 1j * rng.standard_normal((200, 12))) / np.sqrt(2)
    errs = []
    for snr_db in (30.0, 15.0):
        _, _, wx2, wz2 = angle_of_arrival(10 ** (snr_db / 20) * steering(u) + noise, 64, 0.0)
        errs.append(np.median(np.abs(wz2 - u[:, 2])))
        assert np.abs(wx2 - u[:, 1]).max() < 2.0 / 32
    assert errs[1] > 2 * errs[0]


def test_angle_of_arrival_reports_a_second_azimuth_peak() -> None:
    u = np.array([[np.cos(0.5), np.sin(0.5), 0.0], [np.cos(-0.4), np.sin(-0.4), 0.0]])
    snap = steering(u[:1]) + 0.9 * steering(u[1:]) * np.exp(1j)
    pc, _, wx, _ = angle_of_arrival(snap, 64, 0.5)
    assert list(pc) == [0, 0] and sorted(np.round(wx * 32).tolist()) == sorted(np.round(u[:, 1] * 32).tolist())
    pc, _, _, _ = angle_of_arrival(snap, 64, 0.0)
    assert list(pc) == [0]


def _room() -> WorldSpec:
    return WorldSpec(name="room", ceiling=3.0,
                     walls=[{"points": [[0, 0], [6, 0], [6, 4], [0, 4]], "closed": True}],
                     pillars=[{"center": [3.0, 2.0], "radius": 0.2}],
                     trajectory={"waypoints": [[1, 1], [5, 1], [5, 3]]})


def test_scatterers_are_deterministic_and_view_dependent() -> None:
    spec, p = _room(), RadarParams()
    a = build_scatterers(spec, p, np.random.default_rng(5))
    b = build_scatterers(spec, p, np.random.default_rng(5))
    c = build_scatterers(spec, p, np.random.default_rng(6))
    assert np.array_equal(a.pt_pos, b.pt_pos) and np.array_equal(a.pt_rcs_db, b.pt_rcs_db)
    assert not np.array_equal(a.pt_pos, c.pt_pos)
    # density: 4 per m^2 over 4 walls (20 m x 3 m) and floor + ceiling (24 m^2 each), Poisson
    n_surf = int((a.pt_kind == 0).sum())
    expected = p.scatterer_density * (20 * 3 + 2 * 24 + np.pi * 0.0)
    assert abs(n_surf - expected) < 5 * np.sqrt(expected)
    # 4 concave room corners, each a trihedral at floor and ceiling, all seen from inside the room
    origin = np.array([2.0, 1.5, 1.1])
    assert a.inside_wedge(origin).all()
    corner00 = int(np.nonzero(np.all(np.abs(a.wedge_v) < 1e-9, axis=1))[0][0])
    assert not a.inside_wedge(np.array([-1.0, -1.0, 1.1]))[corner00]  # behind that corner: its convex side
    ret = a.returns(origin, 20.0)
    assert (ret.kind == KIND_CORNER).sum() == 8
    # the vertical corner edges return at the radar's height; the pillar from its surface facing the radar
    pil = ret.pos[ret.kind == KIND_PILLAR][0]
    assert abs(pil[2] - 1.1) < 1e-9
    assert abs(np.linalg.norm(pil[:2] - [3.0, 2.0]) - 0.2) < 1e-9
    assert abs(np.linalg.norm(pil[:2] - origin[:2]) - (np.linalg.norm(origin[:2] - [3.0, 2.0]) - 0.2)) < 1e-9
    # from outside, behind a corner, that corner is a convex edge (weaker) and its trihedrals are not active
    out = a.returns(np.array([-1.0, -1.0, 1.1]), 20.0)
    assert (out.kind == KIND_CORNER).sum() == 2  # only the far corner (6, 4) has (-1, -1) in its quadrant
    def vertical_edge_at_origin(r):  # the (0, 0) corner's vertical edge returns at the radar's height, 1.1 m
        m = (r.kind == 1) & (np.abs(r.pos - [0.0, 0.0, 1.1]).max(axis=1) < 1e-9)
        return r.pos[m], r.rcs_db[m]

    v_in, rcs_in = vertical_edge_at_origin(ret)
    v_out, rcs_out = vertical_edge_at_origin(out)
    assert len(v_in) == len(v_out) == 1 and rcs_in[0] - rcs_out[0] == pytest.approx(p.dihedral_rcs_db - p.edge_rcs_db)


@pytest.mark.parametrize("name", ["demo", "hallway_loop", "outdoor_open", "cluttered_lab"])
def test_every_world_has_scatterers(name: str) -> None:
    w = load_world(name)
    s = build_scatterers(w.spec, RadarParams(), np.random.default_rng(0))
    assert len(s.line_a) > 0 and len(s.pt_pos) > 100
