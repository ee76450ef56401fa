"""radar_graph: the correlative matcher, covariance propagation, the robust optimiser and the whole graph."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from stages.slam.params import GraphParams
from stages.slam.pose_graph import (
    Edge,
    between,
    compose,
    keyframe_clouds,
    largest_consistent_set,
    local_cloud,
    loop_closures,
    matcher_of,
    optimise,
    optimise_graph,
    pairwise_consistent,
    propagate,
    select_keyframes,
    transform,
)
from stages.slam.registration import MatcherModel, match
from stages.slam.se2 import wrap_angle
from stages.slam.synthetic import box_walls, corridor_world, make_run, ray_cast

gtsam = pytest.importorskip("gtsam")


def _wall_points(walls: np.ndarray, step: float = 0.05) -> np.ndarray:
    out = []
    for a, b in walls:
        n = max(2, int(np.linalg.norm(b - a) / step))
        out.append(a + np.linspace(0, 1, n)[:, None] * (b - a))
    return np.concatenate(out)


def test_propagate_matches_monte_carlo_composition() -> None:
    rng = np.random.default_rng(0)
    inc = rng.normal(size=(6, 3)) * [0.3, 0.1, 0.1]
    cov = np.stack([np.diag(rng.uniform(0.001, 0.01, 3)) for _ in range(6)])
    total, sigma = propagate(inc, cov)
    n = 20000
    poses = np.zeros((n, 3))
    for d, c in zip(inc, cov, strict=True):
        poses = compose(poses, compose(np.broadcast_to(d, (n, 3)), rng.multivariate_normal(np.zeros(3), c, n)))
    err = np.array([gtsam.Pose2.Logmap(gtsam.Pose2(*total).between(gtsam.Pose2(*p))) for p in poses[:8000]])
    np.testing.assert_allclose(np.cov(err.T), sigma, rtol=0.1, atol=2e-4)


def test_matcher_recovers_a_known_offset_against_brute_force_truth() -> None:
    rng = np.random.default_rng(1)
    ref = _wall_points(corridor_world())
    truth = np.array([0.32, -0.21, np.radians(3.5)])
    q_world = ref[rng.choice(len(ref), 300, replace=False)] + rng.normal(0, 0.02, (300, 2))
    query = transform(between(truth, np.zeros(3)), q_world)  # the query in its own (truth) frame
    m = match(ref, query, np.zeros(3), MatcherModel(), search_xy=0.6, search_yaw_deg=6.0)
    assert abs(m.pose[0] - truth[0]) <= 0.1 and abs(m.pose[1] - truth[1]) <= 0.1
    assert abs(np.degrees(m.pose[2] - truth[2])) <= 0.75
    assert m.inliers > 0.95


def test_matcher_covariance_is_long_along_a_featureless_corridor() -> None:
    """Two parallel walls constrain y and yaw, not x: the search's covariance says so."""
    walls = np.concatenate([box_walls(-30, -1, 30, -1.0001), box_walls(-30, 1, 30, 1.0001)])
    ref = _wall_points(walls)
    query = ref[np.abs(ref[:, 0]) < 4]
    m = match(ref, query, np.zeros(3), MatcherModel(temperature=5.0), search_xy=0.8, search_yaw_deg=4.0)
    assert m.cov[0, 0] > 20 * m.cov[1, 1]
    with pytest.raises(ValueError, match="no points"):
        match(ref, np.zeros((0, 2)), np.zeros(3), MatcherModel(), 0.5, 5.0)


def _square_graph(wrong: bool) -> tuple[np.ndarray, np.ndarray, list[Edge]]:
    """A 4 x 4 m square driven twice with an odometry whose yaw drifts, exact loop closures at the revisits and,
    with ``wrong``, one closure 2 m and 30 deg off."""
    side = [np.array([1.0, 0.0, 0.0])] * 3 + [np.array([1.0, 0.0, np.pi / 2])]
    inc = np.array(side * 8)
    truth = np.zeros((len(inc) + 1, 3))
    for k, d in enumerate(inc):
        truth[k + 1] = compose(truth[k], d)
    drift = inc + np.array([0.0, 0.0, 0.02])
    cov = np.diag([1e-4, 1e-4, 4e-4])
    edges = [Edge("odometry", k, k + 1, d, cov) for k, d in enumerate(drift)]
    odo = np.zeros_like(truth)
    for k, d in enumerate(drift):
        odo[k + 1] = compose(odo[k], d)
    lcov = np.diag([1e-3, 1e-3, 1e-4])
    for j in range(16, len(truth)):
        edges.append(Edge("loop", j - 16, j, between(truth[j - 16], truth[j]), lcov))
    if wrong:
        edges.append(Edge("loop", 2, 20, between(truth[2], compose(truth[20], np.array([2.0, 0.0, 0.5]))), lcov))
    return truth, odo, edges


def test_the_odometry_prior_picks_the_match_it_allows_over_an_aliased_one() -> None:
    """A corridor with doors every 4 m: a query shifted by one door period matches the reference as well as the
    true pose does. Without a prior the search may take either; with the odometry's prior (0.3 m) around the true
    pose, the aliased peak 4 m away loses, and the reported covariance is still the likelihood's."""
    walls = []
    for x0 in np.arange(-20.0, 20.0, 4.0):  # door gaps of 1 m in both walls, every 4 m
        walls += [box_walls(x0, -1.0, x0 + 3.0, -1.0001), box_walls(x0, 1.0, x0 + 3.0, 1.0001)]
    ref = _wall_points(np.concatenate(walls))
    query = ref[np.abs(ref[:, 0] - 4.0) < 6.0] - np.array([4.0, 0.0])  # the pose (4, 0, 0) in its own frame
    at_true = match(ref, query, np.array([4.0, 0.0, 0.0]), MatcherModel(), 0.3, 1.0)
    at_alias = match(ref, query, np.array([0.0, 0.0, 0.0]), MatcherModel(), 0.3, 1.0)
    assert abs(at_true.score - at_alias.score) < 0.05 and min(at_true.inliers, at_alias.inliers) > 0.9  # a tie
    prior = np.diag([0.3**2, 0.3**2, np.radians(2.0) ** 2])
    near = match(ref, query, np.array([3.8, 0.0, 0.0]), MatcherModel(), 3.0, 5.0, prior_cov=prior)
    assert abs(near.pose[0] - 4.0) < 0.15 and near.inliers > 0.9
    far = match(ref, query, np.array([0.2, 0.0, 0.0]), MatcherModel(), 3.0, 5.0, prior_cov=prior)
    assert abs(far.pose[0] - 0.0) < 0.15  # the prior decides which period, not the likelihood
    assert np.all(np.linalg.eigvalsh(near.cov) > 0)


def test_pairwise_consistency_keeps_the_consistent_closures_and_drops_the_odd_one() -> None:
    """PCM on a square loop driven twice: closures at the revisits agree with each other through the odometry;
    one planted 1.5 m and 20 deg off agrees with none, and the largest consistent set leaves it out."""
    side = [np.array([1.0, 0.0, 0.0])] * 3 + [np.array([1.0, 0.0, np.pi / 2])]
    inc = np.array(side * 2)
    truth = np.zeros((len(inc) + 1, 3))
    for k, d in enumerate(inc):
        truth[k + 1] = compose(truth[k], d)
    cov = np.diag([1e-4, 1e-4, 1e-6])
    odo_edges = [Edge("odometry", k, k + 1, between(truth[k], truth[k + 1]), cov, dt=1.0) for k in range(len(inc))]
    lcov = np.diag([4e-3, 4e-3, 1e-4])
    loops = [Edge("loop", j - 4, j, between(truth[j - 4], truth[j]), lcov) for j in range(5, 9)]
    wrong = between(truth[2], truth[7]) + np.array([1.5, 0.0, np.radians(20.0)])
    loops.append(Edge("loop", 2, 7, wrong, lcov))
    consistent = pairwise_consistent(loops, odo_edges, truth, bias_sigma0=0.001)
    assert consistent[:4, :4].all() and not consistent[4, :4].any()
    assert largest_consistent_set(consistent) == [0, 1, 2, 3]
    assert largest_consistent_set(np.zeros((0, 0), bool)) == []


def test_gnc_drops_a_deliberately_wrong_loop_closure() -> None:
    truth, odo, edges = _square_graph(wrong=True)
    poses, cov, kept, _ = optimise(odo, edges, "gnc")
    assert kept[-1] is False  # the wrong closure
    assert all(kept[:-1])
    err = np.abs(between(truth, poses))
    assert err[:, :2].max() < 0.05 and err[:, 2].max() < 0.01
    assert np.all(np.isfinite(cov)) and np.all(cov[:, 2, 2] > 0)
    plain, _, _, _ = optimise(odo, edges, "none")  # least squares bends the whole loop toward it
    assert np.abs(between(truth, plain))[:, :2].max() > 0.1


def test_the_bias_state_recovers_a_constant_gyro_bias_from_loop_closures() -> None:
    """A square driven four times by an odometry whose yaw drifts at a constant 0.01 rad/s, exact closures at
    the revisits: the keyframes' yaw-rate bias converges to the drift and the loop closes; without the bias
    state's time intervals (dt = 0: plain factors) the same closures leave a larger heading error."""
    side = [np.array([1.0, 0.0, 0.0])] * 3 + [np.array([1.0, 0.0, np.pi / 2])]
    inc = np.array(side * 4)
    truth = np.zeros((len(inc) + 1, 3))
    for k, d in enumerate(inc):
        truth[k + 1] = compose(truth[k], d)
    dt, rate = 2.0, 0.01
    cov = np.diag([1e-4, 1e-4, 1e-6])
    odo = np.zeros_like(truth)
    for k, d in enumerate(inc):
        odo[k + 1] = compose(odo[k], d + np.array([0.0, 0.0, rate * dt]))
    lcov = np.diag([1e-3, 1e-3, 1e-4])
    loops = [Edge("loop", j - 4, j, between(truth[j - 4], truth[j]), lcov) for j in range(16, len(truth), 4)]
    odo_edges = [Edge("odometry", k, k + 1, between(odo[k], odo[k + 1]), cov, dt=dt) for k in range(len(inc))]
    poses, _, kept, bias = optimise(odo, [*odo_edges, *loops], "gnc", bias_sigma0=0.05, bias_walk=1e-4)
    assert all(kept)
    np.testing.assert_allclose(bias[:-1], rate, atol=2e-3)  # the last keyframe's bias acts on no interval
    yaw = lambda p: np.degrees(np.sqrt(np.mean(between(truth, p)[:, 2] ** 2)))  # noqa: E731
    assert yaw(poses) < 0.5 and yaw(poses) < 0.1 * yaw(odo)
    plain = [Edge(e.kind, e.i, e.j, e.z, e.cov) for e in odo_edges]
    flat, _, _, _ = optimise(odo, [*plain, *loops], "gnc")
    assert yaw(poses) < yaw(flat)


def test_graph_on_a_drifting_synthetic_loop_beats_its_odometry() -> None:
    run = make_run(700, np.random.default_rng(3), beams_per_scan=60, odo_yaw_bias=0.0003, odo_yaw_noise=0.001,
                   outlier_fraction=0.05)
    t = np.arange(700) * 0.1
    cov = np.broadcast_to(np.diag([1e-4, 1e-4, 1e-6]), (700, 3, 3)).copy()
    res = optimise_graph(run.odometry, cov, t, run.scans, GraphParams(loop_min_travel=10.0))
    yaw = lambda p: np.degrees(np.sqrt(np.mean(between(run.groundtruth, p)[:, 2] ** 2)))  # noqa: E731
    assert res.count("loop", True) >= 3
    assert yaw(res.poses) < 0.5 * yaw(run.odometry)
    assert len(res.poses) == 700 and res.keyframes[0] == 0


def test_later_rounds_close_the_loops_a_large_drift_put_out_of_reach() -> None:
    """A yaw drift of 0.001 rad/s (34 deg RMSE) puts most revisits beyond the loop search around the odometry's
    poses: one round closes few; proposing again from the optimised poses closes more and the yaw error falls."""
    n = 1000
    run = make_run(n, np.random.default_rng(3), beams_per_scan=60, odo_yaw_bias=0.001, odo_yaw_noise=0.001,
                   outlier_fraction=0.05)
    t = np.arange(n) * 0.1
    cov = np.broadcast_to(np.diag([1e-4, 1e-4, 1e-6]), (n, 3, 3)).copy()
    yaw = lambda p: np.degrees(np.sqrt(np.mean(between(run.groundtruth, p)[:, 2] ** 2)))  # noqa: E731
    one = optimise_graph(run.odometry, cov, t, run.scans, GraphParams(loop_min_travel=10.0, loop_rounds=1))
    three = optimise_graph(run.odometry, cov, t, run.scans, GraphParams(loop_min_travel=10.0, loop_rounds=3))
    assert three.count("loop", True) > one.count("loop", True)
    assert yaw(three.poses) < 0.5 * yaw(one.poses) < 0.5 * yaw(run.odometry)


def _out_and_back() -> tuple[np.ndarray, list[np.ndarray]]:
    """Walked out along one side of a 2.5 m corridor with irregular pillars and back along the other side; a
    forward-looking sensor (120 deg, 10 m): scans at the true poses."""
    walls = [box_walls(-4.0, -1.25, 44.0, 1.25)]
    for x, side in ((3.0, 1), (7.5, -1), (11.0, 1), (17.5, -1), (21.0, 1), (26.5, 1), (29.0, -1), (34.0, -1),
                    (38.5, 1)):
        y = 1.05 * side
        walls.append(box_walls(x - 0.2, y - 0.2, x + 0.2, y + 0.2))
    w = np.concatenate(walls)
    out = np.column_stack([np.arange(0.0, 40.0, 0.1), np.full(400, 0.45), np.zeros(400)])
    th = np.linspace(0.0, np.pi, 30)[1:-1]
    turn = np.column_stack([40.0 + 0.45 * np.sin(th), 0.45 * np.cos(th), th])
    back = np.column_stack([np.arange(40.0, 0.0, -0.1), np.full(400, -0.45), np.full(400, np.pi)])
    poses = np.concatenate([out, turn, back])
    rng = np.random.default_rng(5)
    scans = []
    for p in poses:
        ang = rng.uniform(-np.pi / 3, np.pi / 3, 60)
        d = ray_cast(np.repeat(p[None, :2], 60, 0), np.stack([np.cos(ang + p[2]), np.sin(ang + p[2])], 1), w)
        ok = d <= 10.0
        d = d[ok] + rng.normal(0.0, 0.03, ok.sum())
        scans.append(np.stack([d * np.cos(ang[ok]), d * np.sin(ang[ok])], 1))
    return poses, scans


def test_opposite_direction_revisits_match_against_the_earlier_pass() -> None:
    """Coming back the other way, a forward-looking sensor's window of keyframes sees mostly what lies ahead:
    two windows share a few metres of wall, and the likelihood field pays the query for sliding along the
    corridor onto the other window's walls (every window-to-window match lands 3 m off here). Matched against
    the earlier pass within reach (:func:`pass_segment`), the closures along the corridor's middle land at the
    true pose. Near the start, which the outward pass never looked back at, the query still slides."""
    poses, scans = _out_and_back()
    model = GraphParams(loop_min_travel=10.0)
    kf = select_keyframes(poses, model.keyframe_distance, model.keyframe_angle)
    clouds = keyframe_clouds(poses, scans, kf, 0.1)
    P = poses[kf]
    loops = [e for e in loop_closures(P, clouds, model) if abs(wrap_angle(P[e.j, 2] - P[e.i, 2])) > np.radians(150)]
    middle = [e for e in loops if 14.0 <= P[e.i, 0] <= 36.0]
    assert len(middle) >= 8
    half = model.local_keyframes // 2
    err_pass, err_window = [], []
    for e in middle:
        truth = between(P[e.i], P[e.j])
        err_pass.append(np.hypot(*(e.z[:2] - truth[:2])))
        assert abs(np.degrees(wrap_angle(e.z[2] - truth[2]))) < 1.0
        ref = local_cloud(P, clouds, e.i, range(max(0, e.i - half), e.i + half + 1))
        q = local_cloud(P, clouds, e.j, range(e.j - half, min(len(P), e.j + half + 1)))
        m = match(ref, q, truth, matcher_of(model), model.loop_radius, model.loop_search_yaw)
        err_window.append(np.hypot(*(m.pose[:2] - truth[:2])))
    assert np.median(err_pass) < 0.3 and np.mean(np.array(err_pass) < 0.5) >= 0.75
    assert np.median(err_window) > 2.0


def test_bad_inputs_are_stated() -> None:
    odo = np.zeros((5, 3))
    cov = np.broadcast_to(np.eye(3) * 1e-4, (5, 3, 3)).copy()
    with pytest.raises(ValueError, match="one keyframe"):
        optimise_graph(odo, cov, np.arange(5.0), [np.zeros((0, 2))] * 5, GraphParams())
    with pytest.raises(ValueError, match="must agree"):
        optimise_graph(odo, cov, np.arange(5.0), [np.zeros((0, 2))] * 4, GraphParams())
    path = np.array([[0, 0, 0], [0.5, 0, 0], [1.0, 0, 0], [1.1, 0, 0.3]])
    assert list(select_keyframes(path, 1.0, 15.0)) == [0, 2, 3]


def test_missing_gtsam_names_the_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "gtsam", None)
    odo = np.column_stack([np.arange(30) * 0.2, np.zeros(30), np.zeros(30)])
    cov = np.broadcast_to(np.eye(3) * 1e-4, (30, 3, 3)).copy()
    with pytest.raises(ImportError, match="pip install gtsam"):
        optimise_graph(odo, cov, np.arange(30.0), [np.zeros((0, 2))] * 30, GraphParams())
