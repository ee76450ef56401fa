"""FastSLAM-Radar baseline: log-odds grids and the likelihood-field weight."""

from __future__ import annotations

import numpy as np

from stages.slam.beam_sampling import sample_beams
from stages.slam.grid_map import (
    GridModel,
    GridParticleMaps,
    likelihood_field_log_likelihood,
    make_grid_spec,
    nearest_occupied_distance,
    update_grids,
)


def test_inverse_sensor_model_marks_beam_free_and_endpoint_occupied() -> None:
    spec = make_grid_spec([0.0, 0.0], [5.0, 5.0], 0.1)
    grids = np.zeros((2, *spec.shape), np.float32)
    model = GridModel(l_occ=0.9, l_free=-0.4, l_min=-1.0, l_max=2.0)
    origins = np.array([[0.05, 0.05], [0.05, 0.05]])
    ends = np.array([[[2.05, 0.05]], [[0.05, 3.05]]])  # particle 0 along +x, particle 1 along +y
    update_grids(grids, spec, origins, ends, model)
    iy0, ix0 = 50, 50  # cell of (0.05, 0.05)
    assert grids[0, iy0, ix0 + 20] == np.float32(0.9)  # endpoint cell
    np.testing.assert_array_equal(grids[0, iy0, ix0 : ix0 + 20], np.float32(-0.4))  # every cell on the way, once
    assert grids[0, iy0 + 1, ix0 + 5] == 0 and grids[0, iy0, ix0 + 21] == 0
    assert grids[1, iy0 + 30, ix0] == np.float32(0.9) and grids[1, iy0, ix0 + 20] == 0  # particles independent
    for _ in range(5):
        update_grids(grids, spec, origins, ends, model)
    assert grids[0, iy0, ix0 + 20] == np.float32(2.0) and grids[0, iy0, ix0 + 3] == np.float32(-1.0)  # clamped


def test_nearest_occupied_distance_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    spec = make_grid_spec([0.0, 0.0], [3.0, 3.0], 0.1)
    grids = np.zeros((3, *spec.shape), np.float32)
    occ = rng.random(grids.shape) < 0.01
    grids[occ] = 1.0
    model = GridModel(max_dist=0.5)
    pts = rng.uniform(-2.9, 2.9, (3, 40, 2))
    d = nearest_occupied_distance(grids, spec, pts, model)
    xs, ys = spec.centres()
    for k in range(3):
        iy, ix = np.nonzero(occ[k])
        cells = np.stack([xs[ix], ys[iy]], 1)
        # distances are between cells (the query snaps to its cell), capped at max_dist
        q = np.stack([xs[np.floor((pts[k, :, 0] + 3.0) / 0.1).astype(int)],
                      ys[np.floor((pts[k, :, 1] + 3.0) / 0.1).astype(int)]], 1)
        ref = np.minimum(np.min(np.linalg.norm(q[:, None] - cells[None], axis=2), axis=1), 0.5)
        np.testing.assert_allclose(d[k], ref, atol=1e-9)


def test_likelihood_field_prefers_the_pose_that_built_the_map() -> None:
    spec = make_grid_spec([0.0, 0.0], [6.0, 6.0], 0.1)
    maps = GridParticleMaps(spec, 1, GridModel())
    ang = np.linspace(-0.6, 0.6, 15)
    wall = np.stack([np.full_like(ang, 4.0), 4.0 * np.tan(ang)], 1)  # a wall at x = 4 seen from the origin
    s = sample_beams(wall, [0.0, 0.0], 1.0, 6.0)
    maps.update(np.zeros((1, 3)), s)
    cand = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [-0.3, 0.0, 0.0], [0.0, 0.0, 0.08]])
    maps.select(np.zeros(4, dtype=np.int64))
    ll = maps.log_likelihood(cand, s)
    assert np.argmax(ll) == 0 and np.all(ll[1:] < ll[0] - 1.0)
    assert not np.shares_memory(maps.grids[0], maps.grids[1])
    # an empty map scores every pose alike (the prior gives no information)
    empty = likelihood_field_log_likelihood(np.zeros((4, *spec.shape), np.float32), spec,
                                            np.zeros((4, 3, 2)), GridModel())
    assert np.ptp(empty) == 0
