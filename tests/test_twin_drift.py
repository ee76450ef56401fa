"""The drifting ColoRadar twins: the registry entries, the variant file, the fixed gyro
offset and the real-radar effects (multipath ghosts, Doppler outliers, elevation spread) of simulator/radar.py.

The effects are measured on a tiny voxel world (one wall, a box) with a standing radar: every true Doppler
is then 0, so a Doppler outlier is any point off the zero bin; ghosts carry their own label.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.errors import UserError
from pipeline.sequences import load_registry
from simulator import twin as twin_mod
from simulator.params import RadarParams, radar_dump
from simulator.radar import LABEL_CLUTTER, LABEL_GHOST, LABEL_SURFACE, Detections, multipath_ghosts, simulate_scan
from simulator.twin import COLORADAR_ERRORS, TWIN_RADAR, TwinParams, twin_world, variant_params

EFFECTS = {"multipath_ghost_share": 0.3, "doppler_outlier_share": 0.3, "elevation_noise_deg": 8.0}


def _world() -> Any:
    """A wall at y = 2 m (x -1..6 m) and a box at x 3..4 m, y 0.8..1.2 m; the path runs along x at y = 0."""
    path = np.column_stack([np.linspace(0, 5, 50), np.zeros(50), np.full(50, 0.5)])
    r = np.arange(0, 1.5, 0.15)
    wall = [[x, 2.0, z] for x in np.arange(-1, 6, 0.15) for z in r]
    box = [[x, y, z] for x in np.arange(3.0, 4.0, 0.15) for y in np.arange(0.8, 1.2, 0.15) for z in r]
    return twin_world("x_run0", np.array(wall + box), path, duration=10.0)


def _scans(effects: dict[str, float], n: int = 12) -> list[Any]:
    """``n`` scans of a radar standing at (1, 0, 0.5) m facing +y (the wall), no clutter, no cap."""
    w = _world()
    p = RadarParams(clutter_rate=0.0, max_points=2000, **effects)
    scat = w.scatterers(p, np.random.default_rng(0))
    return [simulate_scan(w.scene, scat, p, i, 0.1 * i, np.array([1.0, 0.0, 0.5]), np.pi / 2, np.zeros(3),
                          np.random.default_rng([7, i])) for i in range(n)]


def _pooled(scans: list[Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts = np.concatenate([s.points for s in scans])
    return pts, np.concatenate([s.labels for s in scans]), np.concatenate([s.xyz_true for s in scans])


def test_drift_twins_are_the_twins_with_the_drift_variant() -> None:
    reg = load_registry()
    for i in range(1, 7):
        a, b = reg[f"coloradar_{i}_twin"], reg[f"coloradar_{i}_twin_drift"]
        assert (b.kind, b.scene, b.duration, b.seed, b.format, b.params) == (a.kind, a.scene, a.duration, a.seed,
                                                                              a.format, a.params)
        assert a.twin is None and b.twin == "drift"
        assert a.simulated_path() != b.simulated_path()


def test_drift_variant_sets_the_imu_errors_and_radar_effects() -> None:
    p = variant_params("drift")
    assert variant_params(None) == TwinParams()
    assert TwinParams().imu == {} and TwinParams().errors == COLORADAR_ERRORS  # the plain twins are unchanged
    assert {k: p.radar[k] for k in TWIN_RADAR} == TWIN_RADAR
    radar = RadarParams(**p.radar)
    assert radar.multipath_ghost_share > 0 and radar.doppler_outlier_share > 0 and radar.elevation_noise_deg > 0
    assert p.errors["gyro_bias"][2] != 0 and p.imu["gyro_noise_density"] > 1.5e-4  # a lower grade than the GX5's
    assert "multipath_ghost_share" in radar_dump(radar)
    assert "multipath_ghost_share" not in radar_dump(RadarParams())  # sidecars of the other worlds: as before


def test_bad_variant_is_a_one_line_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(twin_mod, "twins_dir", lambda: tmp_path)
    (tmp_path / "ok.toml").write_text("[radar]\nelevation_noise_deg = 2.0\n")
    with pytest.raises(UserError, match=r"twin variant 'nope'.*known: ok"):
        variant_params("nope")
    (tmp_path / "bad.toml").write_text("[radar]\nghost_share_typo = 1.0\n")
    with pytest.raises(UserError, match=r"bad.toml \[radar\]: ghost_share_typo"):
        variant_params("bad")
    (tmp_path / "tables.toml").write_text("[lidar]\nbeams = 8\n")
    with pytest.raises(UserError, match="unknown table"):
        variant_params("tables")
    assert RadarParams(**variant_params("ok").radar).elevation_noise_deg == 2.0


def test_fixed_gyro_offset_is_in_every_imu_sample() -> None:
    from simulator.simulate import Simulation

    still = {"gyro_bias_sigma": 0.0, "gyro_bias_walk": 0.0}
    sim = Simulation(_world(), 2.0, 0, workers=1)
    assert "gyro_bias" not in (sim.drift_errors() or {}).get("settings", {})  # plain twins: sidecar as before
    w = twin_world("x_run0", _world().grid.centres(np.argwhere(_world().grid.occupied)),
                   np.column_stack([np.linspace(0, 5, 50), np.zeros(50), np.full(50, 0.5)]), duration=10.0,
                   params=TwinParams(imu=still, errors={"gyro_bias": (0.0, 0.0, 0.01)}))
    sim = Simulation(w, 2.0, 0, workers=1)
    bias = np.concatenate([win.imu.bias for win in sim.windows()])
    np.testing.assert_allclose(bias[:, :3], np.tile([0.0, 0.0, 0.01], (len(bias), 1)))


def test_no_ghosts_in_a_voxel_world_unless_turned_on() -> None:
    """A voxel world has no mirror faces: the physical ghost model gives none; the statistical one does."""
    _, lab_off, _ = _pooled(_scans({}))
    _, lab, xyz_true = _pooled(_scans(EFFECTS))
    scene = lab != LABEL_CLUTTER
    assert (lab_off == LABEL_GHOST).sum() == 0 and (lab_off == LABEL_SURFACE).sum() > 200
    share = (lab == LABEL_GHOST).sum() / scene.sum()
    assert 0.04 < share < 0.3, share  # 0.3 candidates per point, about half on the radar's side of a wall
    # ghosts lie behind the surfaces the radar sees: farther than every real return in their direction
    g = lab == LABEL_GHOST
    r_g = np.linalg.norm(xyz_true[g], axis=1)
    assert np.median(r_g) > np.median(np.linalg.norm(xyz_true[lab == LABEL_SURFACE], axis=1))


def test_multipath_ghost_is_the_mirror_image_behind_a_seen_wall() -> None:
    """One source in front of one wall point: the ghost is its reflection in the wall, with the image's Doppler."""
    xyz = np.array([[2.0, 0.5, 0.0], [4.0, 0.0, 0.0]])  # source at 2 m, wall point straight ahead at 4 m
    det = Detections(xyz=xyz, r=np.linalg.norm(xyz, axis=1), dop=np.zeros(2), snr=np.array([30.0, 20.0]),
                     label=np.array([LABEL_SURFACE, LABEL_SURFACE], np.int8), xyz_true=xyz,
                     n_cell=np.zeros(2, np.int16))
    p = RadarParams(multipath_ghost_share=2.0, range_resolution=0.001, doppler_resolution=0.001)
    found = [multipath_ghosts(det, np.array([1.0, 0.0, 0.0]), p, 10_000, np.random.default_rng(s)) for s in range(8)]
    g = Detections(*(np.concatenate([getattr(f, k) for f in found]) for k in Detections.__dataclass_fields__))
    assert len(g.r) > 0  # only source 0 in front of wall point 1 makes a ghost
    np.testing.assert_allclose(g.xyz_true, np.tile([6.0, 0.5, 0.0], (len(g.r), 1)))  # 2 m in front -> 2 m behind
    u = g.xyz_true / np.linalg.norm(g.xyz_true, axis=1)[:, None]
    np.testing.assert_allclose(g.dop, -u[:, 0], atol=1e-3)  # a static virtual target seen while moving at 1 m/s
    np.testing.assert_allclose(g.snr, 30.0 - p.multipath_ghost_loss_db)
    assert (g.label == LABEL_GHOST).all()


def test_doppler_outliers_have_the_set_share() -> None:
    """Standing radar: true Doppler 0, so points off the zero bin are outliers (1 of 128 bins is 0)."""
    pts_off, lab_off, _ = _pooled(_scans({}))
    pts, lab, _ = _pooled(_scans(EFFECTS))
    off_share = np.mean(np.abs(pts_off["doppler"][lab_off == LABEL_SURFACE]) > 0.05)
    scene = lab != LABEL_CLUTTER
    share = np.mean(np.abs(pts["doppler"][scene]) > 0.05)
    assert off_share < 0.02
    assert 0.3 * 0.85 < share < 0.3 * 1.15, share  # 0.3 x 127/128 expected


def test_elevation_spread_of_the_returns() -> None:
    def el_err(pts: np.ndarray, lab: np.ndarray, xyz_true: np.ndarray) -> np.ndarray:
        s = lab == LABEL_SURFACE
        xyz = np.column_stack([pts["x"], pts["y"], pts["z"]])[s].astype(np.float64)
        t = xyz_true[s].astype(np.float64)
        return np.degrees(np.arcsin(xyz[:, 2] / np.linalg.norm(xyz, axis=1))
                          - np.arcsin(t[:, 2] / np.linalg.norm(t, axis=1)))

    off = el_err(*_pooled(_scans({})))
    on = el_err(*_pooled(_scans({"elevation_noise_deg": 8.0})))
    s_off, s_on = np.std(off), np.std(on)
    assert s_on > s_off + 2.0, (s_off, s_on)
    assert np.sqrt(s_off**2 + 8.0**2) * 0.75 < s_on < np.sqrt(s_off**2 + 8.0**2) * 1.25, (s_off, s_on)


SHARED_MAPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "coloradar_maps"


@pytest.mark.skipif(not (SHARED_MAPS / "aspen_run0" / "lidar.parquet").is_file(), reason="shared maps absent")
def test_a_registered_drift_twin_gets_the_variant(monkeypatch: pytest.MonkeyPatch) -> None:
    """The registry's ``twin`` reaches the world the runner and ``pipeline simulate`` simulate."""
    from sources.simulated import twin_world_of

    monkeypatch.setenv("RMAP_ROOT", str(SHARED_MAPS))
    reg = load_registry()
    drift, plain = twin_world_of(reg["coloradar_1_twin_drift"]), twin_world_of(reg["coloradar_1_twin"])
    assert drift.params == variant_params("drift") and plain.params == TwinParams()
    assert drift.spec.imu == variant_params("drift").imu and plain.spec.imu == {}
    assert np.array_equal(drift.grid.occupied, plain.grid.occupied)  # same scene, same path
