"""Beam sampling (Fig. 3a), radar-to-base projection and the tolerance stencil (Fig. 3b)."""

from __future__ import annotations

import numpy as np

from stages.slam.beam_sampling import radar_to_body_2d, sample_beams, stencil_offsets, to_world


def test_free_samples_every_step_and_endpoint_last() -> None:
    s = sample_beams([[3.5, 0.0], [0.0, 2.0], [6.0, 0.0], [0.05, 0.0]], [0.0, 0.0], 1.0, 5.0, min_range=0.1)
    # 3.5 m: free at 1, 2, 3; 2.0 m: free at 1 (2.0 is the endpoint); 6 m and 0.05 m beams dropped
    free = s.points[s.labels < 0]
    np.testing.assert_allclose(free, [[1, 0], [2, 0], [3, 0], [0, 1]])
    np.testing.assert_allclose(s.endpoints, [[3.5, 0.0], [0.0, 2.0]])
    np.testing.assert_array_equal(s.beam, [0, 0, 0, 1, 0, 1])
    c = sample_beams([[3.5, 0.0]], [0.0, 0.0], 1.0, 5.0, clearance=0.6)
    np.testing.assert_allclose(c.points[c.labels < 0], [[1, 0], [2, 0]])  # 3 m is within 0.6 m of the hit
    o = sample_beams([[1.0, 3.0]], [1.0, 1.0], 0.5, 5.0)  # beams start at the radar origin
    np.testing.assert_allclose(o.points[:, 0], 1.0)
    np.testing.assert_allclose(o.points[:, 1], [1.5, 2.0, 2.5, 3.0])


def test_radar_to_body_projection_and_height_gate() -> None:
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # boresight (radar x) along base +y
    T[:3, 3] = [0.5, 0.2, 0.3]
    pts, origin = radar_to_body_2d([[2.0, 0.0, 0.0], [1.0, 1.0, 1.0]], T, z_max=1.0)
    np.testing.assert_allclose(origin, [0.5, 0.2])
    np.testing.assert_allclose(pts, [[0.5, 2.2]])  # the second point (z = 1.3 in base) is gated


def test_to_world_and_stencil() -> None:
    w = to_world(np.array([[1.0, 2.0, np.pi / 2]]), np.array([[1.0, 0.0], [0.0, 1.0]]))
    np.testing.assert_allclose(w[0], [[1.0, 3.0], [0.0, 2.0]], atol=1e-12)
    offs = stencil_offsets(0.25, 8, 2)
    assert offs.shape == (17, 2) and np.all(offs[0] == 0)
    r = np.linalg.norm(offs[1:], axis=1)
    np.testing.assert_allclose(np.sort(np.unique(r.round(12))), [0.125, 0.25])
