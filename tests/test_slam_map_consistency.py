"""The radar map's self-consistency along a trajectory (stages/slam/map_consistency.py)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from stages.slam.heading_fusion import recompose
from stages.slam.map_consistency import (
    MapConsistency,
    block_sums,
    common_support_scores,
    consistency_parts,
    consistent_scale,
    difference_evidence,
    heading_ramp,
    map_consistency,
    scaled_positions,
    world_points,
)


def _room_run(seed: int = 0, n: int = 400, dt: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 12 x 9 m room with two pillars, a path looping twice around it, and each scan's endpoints (body
    frame) of the walls within 6 m and +-60 deg, with 3 cm noise and 10 % clutter."""
    rng = np.random.default_rng(seed)
    s = np.arange(0.0, 1.0, 0.004)
    walls = np.concatenate([np.c_[12 * s, 0 * s], np.c_[12 * s, 0 * s + 9], np.c_[0 * s, 9 * s],
                            np.c_[0 * s + 12, 9 * s], np.c_[4 + s, 3 + 0 * s], np.c_[8 + 0 * s, 5 + s]])
    t = np.arange(n) * dt
    ang = 2 * np.pi * 2 * t / t[-1]
    truth = np.c_[6 + 3.5 * np.cos(ang), 4.5 + 2.5 * np.sin(ang), ang + np.pi / 2]
    pts, scan = [], []
    for k, (x, y, yaw) in enumerate(truth):
        rel = walls - [x, y]
        c, sn = np.cos(yaw), np.sin(yaw)
        body = np.c_[c * rel[:, 0] + sn * rel[:, 1], -sn * rel[:, 0] + c * rel[:, 1]]
        r, bearing = np.hypot(*body.T), np.arctan2(body[:, 1], body[:, 0])
        seen = body[(r < 6) & (np.abs(bearing) < np.radians(60))]
        seen = seen[rng.random(len(seen)) < 0.3]
        seen = seen + rng.normal(0, 0.03, seen.shape)
        clutter = rng.uniform([-1, -4], [6, 4], (max(1, len(seen) // 10), 2))
        both = np.concatenate([seen, clutter])
        pts.append(both)
        scan.append(np.full(len(both), k))
    return t, truth, np.concatenate(pts), np.concatenate(scan)


def _drifted(truth: np.ndarray, t: np.ndarray, rate: float) -> np.ndarray:
    """The truth's body-frame increments composed along a heading that drifts by ``rate`` rad/s."""
    return recompose(truth, rate * t)


def test_world_points_puts_body_points_along_the_poses() -> None:
    poses = np.array([[1.0, 2.0, np.pi / 2], [0.0, 0.0, 0.0]])
    w = world_points(poses, [[1.0, 0.0], [1.0, 0.0]], [0, 1])
    np.testing.assert_allclose(w, [[1.0, 3.0], [1.0, 0.0]], atol=1e-12)


def _brute_force(seed: int, poses: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Random poses (or ``poses``), 5 points per scan, and each point's distance to the nearest point of a scan 5 s
    away or more, by a pairwise search over all points: ``t, poses, points, scan, nearest``."""
    rng = np.random.default_rng(seed)
    t = np.arange(60) * 0.5
    drawn = np.c_[rng.normal(0, 0.3, (60, 2)), rng.normal(0, 0.05, 60)]
    poses = drawn if poses is None else poses
    scan = np.repeat(np.arange(60), 5)
    pts = rng.uniform(-2, 2, (300, 2))
    w = world_points(poses, pts, scan)
    d = np.hypot(*(w[:, None] - w[None]).transpose(2, 0, 1))
    far = np.abs(t[scan][:, None] - t[scan][None]) >= 5.0
    return t, poses, pts, scan, np.where(far, d, np.inf).min(axis=1)


def test_score_equals_a_brute_force_pairwise_search() -> None:
    t, poses, pts, scan, nearest = _brute_force(3)
    p = MapConsistency(cell=0, neighbours=300, separation=5.0, truncation=0.4)
    want = float(np.mean(np.minimum(nearest, 0.4) ** 2))
    assert map_consistency(poses, pts, scan, t, p) == pytest.approx(want, rel=1e-12)


def test_the_parts_split_the_score_as_a_brute_force_search_does() -> None:
    t, poses, pts, scan, nearest = _brute_force(5)
    p = MapConsistency(cell=0, neighbours=300, separation=5.0, truncation=0.1)
    matched = nearest < 0.1
    assert 0.1 < matched.mean() < 0.9  # both kinds of point are there
    parts = consistency_parts(poses, pts, scan, t, p)
    assert parts.matched == pytest.approx(float(matched.mean()), rel=1e-12)
    assert parts.matched_ms == pytest.approx(float(np.mean(nearest[matched] ** 2)), rel=1e-12)
    assert parts.score == pytest.approx(parts.matched * parts.matched_ms + (1 - parts.matched) * 0.01, rel=1e-12)
    assert parts.score == map_consistency(poses, pts, scan, t, p)
    none = consistency_parts(poses, pts, scan, t, MapConsistency(cell=0, separation=100.0))
    assert none.matched == 0.0 and np.isnan(none.matched_ms) and none.score == pytest.approx(0.25)


def test_the_common_support_scores_equal_a_brute_force_search_on_one_set_of_points() -> None:
    t, poses, pts, scan, nearest = _brute_force(5)
    rng = np.random.default_rng(7)
    moved = poses + np.c_[rng.normal(0, 0.05, (len(poses), 2)), rng.normal(0, 0.02, len(poses))]
    *_, nearest_moved = _brute_force(5, moved)
    p = MapConsistency(cell=0, neighbours=300, separation=5.0, truncation=0.1)
    common = (nearest < 0.1) & (nearest_moved < 0.1)
    assert 0.05 < common.mean() < (nearest < 0.1).mean()  # the moved poses lose some matches
    scores, share = common_support_scores([poses, moved], pts, scan, t, p)
    assert share == pytest.approx(float(common.mean()), rel=1e-12)
    np.testing.assert_allclose(scores, [np.mean(nearest[common] ** 2), np.mean(nearest_moved[common] ** 2)],
                               rtol=1e-12)
    # the per-trajectory matched mean square averages other points: it is not what the common set scores
    assert consistency_parts(moved, pts, scan, t, p).matched_ms != pytest.approx(scores[1], rel=1e-6)
    nothing, none = common_support_scores([poses, moved], pts, scan, t, MapConsistency(cell=0, separation=100.0))
    assert none == 0.0 and np.all(np.isnan(nothing))
    assert common_support_scores([], pts, scan, t, p)[0].size == 0


def test_the_perturbations_of_the_sweep() -> None:
    t, truth, _, _ = _room_run(3, n=60)
    np.testing.assert_allclose(scaled_positions(truth, 1.0), truth, rtol=0, atol=1e-12)
    half = scaled_positions(truth, 0.5)
    np.testing.assert_allclose(half[:, :2] - truth[0, :2], 0.5 * (truth[:, :2] - truth[0, :2]), atol=1e-12)
    np.testing.assert_array_equal(half[:, 2], truth[:, 2])
    np.testing.assert_allclose(heading_ramp(truth, t, 0.0), recompose(truth, np.zeros(len(t))), atol=1e-12)
    ramp = heading_ramp(truth, t, 0.1)
    d = np.angle(np.exp(1j * (ramp[:, 2] - truth[:, 2])))
    np.testing.assert_allclose(d, 0.1 * t / t[-1], atol=1e-12)


def test_the_criterion_chooses_by_the_matched_points_or_by_the_whole_score() -> None:
    t, truth, pts, scan = _room_run(1)
    odometry = _drifted(truth, t, 4e-3)
    exact = -4e-3 * t
    for criterion in ("matched", "capped", "common"):
        p = MapConsistency(alpha_max=1.5, criterion=criterion)
        choice = consistent_scale(odometry, 2 * exact, pts, scan, t, p)
        trajectories = [recompose(odometry, a * 2 * exact) for a in choice.alphas]
        parts = [consistency_parts(traj, pts, scan, t, p) for traj in trajectories]
        want = {"matched": [q.matched_ms for q in parts], "capped": [q.score for q in parts],
                "common": common_support_scores(trajectories, pts, scan, t, p)[0]}[criterion]
        np.testing.assert_allclose(choice.scores, want, rtol=1e-12)
        assert choice.alpha == 0.5


def test_a_drifting_heading_scores_worse_than_the_truth_and_worse_the_more_it_drifts() -> None:
    t, truth, pts, scan = _room_run()
    scores = [map_consistency(_drifted(truth, t, rate), pts, scan, t) for rate in (0.0, 1e-3, 3e-3, 1e-2)]
    assert scores == sorted(scores) and scores[0] < 0.8 * scores[-1]


def test_the_scale_that_undoes_a_drift_is_chosen() -> None:
    t, truth, pts, scan = _room_run(1)
    odometry = _drifted(truth, t, 4e-3)  # 9 deg off at the end
    exact = -4e-3 * t  # the correction that undoes it
    assert consistent_scale(odometry, exact, pts, scan, t).alpha == 1.0
    choice = consistent_scale(odometry, 2 * exact, pts, scan, t, MapConsistency(alpha_max=1.5))
    assert choice.alpha == 0.5 and choice.scores.argmin() == 4
    assert np.array_equal(choice.alphas, MapConsistency(alpha_max=1.5).scales())  # one grid for every caller
    assert np.allclose(MapConsistency(alpha_max=1.0, alpha_step=0.25).scales(), [0, 0.25, 0.5, 0.75, 1.0])
    # a correction that makes it worse is dropped: the odometry stays
    assert consistent_scale(odometry, -exact, pts, scan, t).alpha == 0.0


def test_off_and_empty() -> None:
    t, truth, pts, scan = _room_run(2, n=50)
    off = consistent_scale(truth, np.ones(len(t)), pts, scan, t, MapConsistency(alpha_max=0))
    assert off.alpha == 1.0 and off.scores.size == 1 and MapConsistency(alpha_max=0).scales().size == 0
    assert map_consistency(truth, np.zeros((0, 2)), np.zeros(0, np.int64), t) == 0.0
    # no endpoints: every scale scores the same, and the correction stays as the fusion gives it
    for criterion in ("matched", "capped", "common"):
        blind = consistent_scale(truth, np.ones(len(t)), np.zeros((0, 2)), np.zeros(0, np.int64), t,
                                 MapConsistency(criterion=criterion))
        assert blind.alpha == 1.0
        assert np.all(np.isnan(blind.scores)) if criterion != "capped" else np.all(blind.scores == 0)
    with pytest.raises(ValueError, match="poses for"):
        map_consistency(truth[:-1], pts, scan, t)


def test_the_fused_estimate_keeps_the_odometry_where_the_filter_smears_the_map() -> None:
    """fused_estimate with the consistency search: a filter heading that wanders away from a right odometry is
    dropped (alpha 0: the odometry itself); one that undoes the odometry's drift is kept (alpha 1)."""
    from stages.slam.beam_sampling import BeamSamples
    from stages.slam.heading_fusion import HeadingFusion
    from stages.slam.methods import OdometryMotion, fused_estimate

    t, truth, pts, scan = _room_run(4)
    scans = [BeamSamples(pts[scan == k], np.ones(int(np.sum(scan == k))), np.arange(int(np.sum(scan == k))),
                         pts[scan == k], np.zeros(2)) for k in range(len(t))]
    motion = OdometryMotion(np.tile(np.diag([1e-4, 1e-4, 1e-6]), (len(t), 1, 1)), np.r_[0.0, np.diff(t)])
    model = HeadingFusion(bias_sigma0=0.01, information_ref=0)
    on = MapConsistency(alpha_max=1.0)
    wander = recompose(truth, np.radians(6) * np.sin(2 * np.pi * t / t[-1]))  # the filter, off by up to 6 deg
    fused, _, alpha, evidence = fused_estimate(truth, wander, motion, model, scans, on)
    assert alpha == 0.0 and np.isnan(evidence)  # no guard: no evidence computed
    np.testing.assert_allclose(fused, recompose(truth, np.zeros(len(t))), atol=1e-12)
    odometry = _drifted(truth, t, 4e-3)
    fused, _, alpha, _ = fused_estimate(odometry, truth, motion, model, scans, on)
    assert alpha == 1.0
    guarded = fused_estimate(odometry, truth, motion, model, scans, MapConsistency(alpha_max=1.0, guard=2.0))
    assert guarded.alpha == 1.0 and guarded.evidence > 2.0 and np.array_equal(guarded.poses, fused)
    plain, _, one, _ = fused_estimate(odometry, truth, motion, model)
    assert one == 1.0 and np.array_equal(fused, plain)


def test_the_slam_parameters_carry_the_criterion() -> None:
    from pydantic import ValidationError

    from stages.slam.stage import SlamParams

    assert SlamParams().config().consistency.criterion == "capped"  # the default of stop 51 (README, stop 52)
    matched = SlamParams(fusion_alpha_criterion="matched", fusion_alpha_max=1.0).config().consistency
    assert matched.criterion == "matched" and matched.alpha_max == 1.0
    with pytest.raises(ValidationError, match="fusion_alpha_criterion"):
        SlamParams(fusion_alpha_criterion="kernel")
    assert SlamParams(fusion_alpha_criterion="common").config().consistency.criterion == "common"


def test_the_block_sums_add_up_to_the_score_and_its_matched_part() -> None:
    t, truth, pts, scan = _room_run(3)
    odometry = _drifted(truth, t, 2e-3)
    p = MapConsistency(guard_block=4.0)
    parts = consistency_parts(odometry, pts, scan, t, p)
    s, n = block_sums(odometry, pts, scan, t, p)
    assert len(s) == int(np.floor((t[-1] - t[0]) / 4.0)) + 1 and np.all(n > 0)
    assert s.sum() / n.sum() == pytest.approx(parts.score, rel=1e-12)
    sm, nm = block_sums(odometry, pts, scan, t, p, matched_only=True)
    assert sm.sum() / nm.sum() == pytest.approx(parts.matched_ms, rel=1e-12)
    assert nm.sum() / n.sum() == pytest.approx(parts.matched, rel=1e-12) and np.all(nm <= n)


def test_the_difference_evidence_matches_a_jackknife_over_blocks() -> None:
    """The linearised standard error of a difference of two ratio scores against the delete-one-block jackknife
    (an independent estimate of the same variance; they agree to first order)."""
    rng = np.random.default_rng(5)
    n0, n1 = rng.integers(20, 60, 40).astype(float), rng.integers(20, 60, 40).astype(float)
    s0 = n0 * 0.05 * (1 + 0.3 * rng.standard_normal(40))
    s1 = s0 * n1 / n0 * 0.93 * (1 + 0.1 * rng.standard_normal(40))
    ev = difference_evidence((s0, n0), (s1, n1))
    gain = s0.sum() / n0.sum() - s1.sum() / n1.sum()
    keep = ~np.eye(40, dtype=bool)
    jack = np.array([(s0[k].sum() / n0[k].sum()) - (s1[k].sum() / n1[k].sum()) for k in keep])
    se_jack = np.sqrt(39 / 40 * np.sum((jack - jack.mean()) ** 2))
    assert gain > 0 and ev == pytest.approx(gain / se_jack, rel=0.05)
    assert difference_evidence((s1, n1), (s0, n0)) == 0.0  # a loss is no evidence
    assert np.isnan(difference_evidence((s0, 0 * n0), (s1, n1)))


def test_the_guard_keeps_a_clear_correction_and_drops_one_the_noise_chose() -> None:
    t, truth, pts, scan = _room_run(1)
    odometry = _drifted(truth, t, 4e-3)  # 9 deg off at the end: the correction is plain
    clear = consistent_scale(odometry, -4e-3 * t, pts, scan, t, MapConsistency(guard=2.0))
    assert clear.alpha == 1.0 and clear.evidence > 2.0
    # the odometry right and a correction of noise: the unguarded search takes a scale by chance, the guard not
    noise = np.cumsum(np.random.default_rng(0).normal(0, 2e-4, len(t)))
    free = consistent_scale(truth, noise, pts, scan, t, MapConsistency())
    guarded = consistent_scale(truth, noise, pts, scan, t, MapConsistency(guard=2.0))
    assert free.alpha > 0 and np.isnan(free.evidence)
    assert guarded.alpha == 0.0 and guarded.evidence <= 2.0
    assert np.array_equal(free.scores, guarded.scores)
    with pytest.raises(ValueError, match="criterion 'common'"):
        MapConsistency(guard=2.0, criterion="common")
    from stages.slam.stage import SlamParams  # the stage's parameters name theirs

    with pytest.raises(ValueError, match=re.escape("slam.fusion_alpha_guard = 2 with slam.fusion_alpha_criterion "
                                                   "= common: the guard compares")):
        SlamParams(fusion_alpha_guard=2, fusion_alpha_criterion="common")


def test_the_guard_under_the_matched_criterion_weighs_the_matched_points_only() -> None:
    """With ``criterion = 'matched'`` the guard's evidence is the difference of the matched points' mean squares:
    recomputed here from :func:`block_sums` with ``matched_only`` on the two trajectories it compares, it must
    equal what :func:`consistent_scale` records, and differ from the capped score's evidence."""
    t, truth, pts, scan = _room_run(1)
    odometry = _drifted(truth, t, 4e-3)
    correction = -4e-3 * t
    p = MapConsistency(guard=2.0, criterion="matched")
    choice = consistent_scale(odometry, correction, pts, scan, t, p)
    assert choice.alpha > 0 and choice.evidence > 2.0
    chosen = recompose(odometry, choice.alpha * correction)
    expected = difference_evidence(block_sums(odometry, pts, scan, t, p, matched_only=True),
                                   block_sums(chosen, pts, scan, t, p, matched_only=True))
    assert choice.evidence == pytest.approx(expected, rel=1e-12)
    capped = difference_evidence(block_sums(odometry, pts, scan, t, p), block_sums(chosen, pts, scan, t, p))
    assert capped != pytest.approx(expected, rel=1e-3)
    # above the evidence the odometry stays, whatever the search chose
    strict = consistent_scale(odometry, correction, pts, scan, t, p.model_copy(update={"guard": expected * 1.01}))
    assert strict.alpha == 0.0 and strict.evidence == pytest.approx(expected, rel=1e-12)
