"""The evaluate stage: trajectory errors against evo, SE(2) alignment, the AUC protocol against sklearn,
the SGD baselines against scikit-learn's SGDClassifier, and the stage end to end on synthetic artifacts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.recording import entity_paths_in
from pipeline.store import RunStore
from schemas import read_artifact
from stages.evaluate import baselines
from stages.evaluate.occupancy import (
    LabelledSamples,
    grid_counts_fit,
    grid_counts_predict,
    hilbert_maps_samples,
    roc_auc,
    split_scans_by_block,
)
from stages.evaluate.stage import STAGE, EvaluateParams, Evaluation
from stages.evaluate.trajectory import (
    evaluate_trajectory,
    evaluate_trajectory_whole,
    interpolate_pose2d,
    umeyama_se2,
    wrap_angle,
)
from tests.test_evaluate_fixtures import make_context, room_segments, write_stage, write_synthetic_run


# -- trajectories -----------------------------------------------------------------------------------------------
def test_se2_alignment_recovers_a_known_transform() -> None:
    rng = np.random.default_rng(3)
    src = np.cumsum(rng.normal(0, 0.5, (150, 2)), axis=0)
    th = 2.3
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    t = np.array([4.0, -7.5])
    dst = src @ R.T + t
    R_est, t_est = umeyama_se2(src, dst)
    assert np.allclose(R_est, R, atol=1e-10) and np.allclose(t_est, t, atol=1e-9)
    # an estimate in a rotated and shifted frame, exact otherwise: zero error after alignment
    times = np.arange(150, dtype=np.int64) * 100_000_000
    yaw_gt = rng.uniform(-np.pi, np.pi, 150)
    err = evaluate_trajectory(times, src, wrap_angle(yaw_gt - th), times, dst, yaw_gt, n_align=100)
    assert err.pos_rmse_m < 1e-9 and err.yaw_rmse_deg < 1e-9
    assert err.rotation_deg == pytest.approx(np.degrees(wrap_angle(th)), abs=1e-9)
    assert err.n_aligned == 100 and err.n_matched == 150


def test_alignment_uses_only_the_first_frames() -> None:
    """Drift after the alignment window is not aligned away."""
    times = np.arange(300, dtype=np.int64) * 100_000_000
    gt = np.stack([np.linspace(0, 30, 300), np.zeros(300)], 1)
    est = gt.copy()
    est[200:, 1] += 1.0  # a 1 m lateral jump after frame 200
    err = evaluate_trajectory(times, est, np.zeros(300), times, gt, np.zeros(300), n_align=100)
    assert err.pos_rmse_m == pytest.approx(np.sqrt(100 / 300), rel=1e-9)


def _rot(th: float) -> np.ndarray:
    return np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])


def test_whole_alignment_recovers_the_frame_where_the_first_frames_cannot() -> None:
    """A rotated, shifted, noisy copy of a path whose first 100 frames barely move (coloradar_1_twin's start):
    the whole-trajectory alignment recovers the frame and leaves the noise, the first-100 one fits its rotation
    to the noise and reports metres of error."""
    rng = np.random.default_rng(11)
    n, sigma = 600, 0.02
    s = np.r_[np.linspace(0.0, 0.01, 100), np.linspace(0.01, 60.0, n - 100)]  # 1 cm in the first 100 frames
    gt = np.stack([8.0 * np.sin(s / 8.0), 0.15 * s * np.cos(s / 5.0)], 1)
    yaw_gt = np.unwrap(np.arctan2(*np.gradient(gt, axis=0)[:, ::-1].T))
    th, tr = 1.1, np.array([3.0, -2.0])  # est = R^T (gt - tr): the estimate lives in a rotated, shifted frame
    est = (gt - tr) @ _rot(th) + rng.normal(0.0, sigma, (n, 2))
    yaw_est = wrap_angle(yaw_gt - th + rng.normal(0.0, np.radians(0.5), n))
    times = np.arange(n, dtype=np.int64) * 100_000_000
    whole = evaluate_trajectory_whole(times, est, yaw_est, times, gt, yaw_gt)
    first = evaluate_trajectory(times, est, yaw_est, times, gt, yaw_gt, n_align=100)
    assert whole.n_aligned == n and first.n_aligned == 100
    assert whole.rotation_deg == pytest.approx(np.degrees(th), abs=0.05)
    assert np.allclose(whole.translation, tr, atol=0.02)
    # what is left is the noise: sqrt(2) sigma in position (3 parameters fitted on 600 pairs), 0.5 deg in yaw
    assert whole.pos_rmse_m == pytest.approx(np.sqrt(2) * sigma, rel=0.1)
    assert whole.yaw_rmse_deg == pytest.approx(0.5, rel=0.1)
    assert abs(first.rotation_deg - np.degrees(th)) > 10.0  # fitted to 1 cm of motion under 2 cm of noise
    assert first.pos_rmse_m > 20 * whole.pos_rmse_m and first.yaw_rmse_deg > 2 * whole.yaw_rmse_deg
    # the whole-trajectory alignment minimises the position RMSE: any other rigid transform does worse
    r, t = _rot(np.radians(whole.rotation_deg)), np.asarray(whole.translation)
    for dth, dt in ((0.002, (0.0, 0.0)), (-0.002, (0.0, 0.0)), (0.0, (0.01, 0.0)), (0.0, (0.0, -0.01))):
        moved = est @ (_rot(dth) @ r).T + t + np.asarray(dt)
        assert np.sqrt(np.mean(np.sum((moved - gt) ** 2, 1))) > whole.pos_rmse_m
    same = evaluate_trajectory(times, est, yaw_est, times, gt, yaw_gt, n_align=None)
    assert same.pos_rmse_m == whole.pos_rmse_m
    assert evaluate_trajectory(times, est, yaw_est, times, gt, yaw_gt, n_align=10 * n).pos_rmse_m == whole.pos_rmse_m
    with pytest.raises(ValueError, match="n_align = 1"):
        evaluate_trajectory(times, est, yaw_est, times, gt, yaw_gt, n_align=1)


def test_ground_truth_interpolation_and_gaps() -> None:
    t_ref = np.array([0, 100, 200, 900], np.int64)
    xy = np.array([[0.0, 0.0], [1.0, 2.0], [2.0, 4.0], [9.0, 18.0]])
    yaw = np.array([3.1, -3.1, -3.0, 0.0])  # wraps between the first two samples
    q, qy, ok = interpolate_pose2d(t_ref, xy, yaw, np.array([50, 150, 500, 1000, -1], np.int64), max_gap_ns=150)
    assert ok.tolist() == [True, True, False, False, False]
    assert np.allclose(q[:2], [[0.5, 1.0], [1.5, 3.0]])
    assert abs(wrap_angle(qy[0] - np.pi)) < 0.02  # through +-pi, not through 0


def _evo_numbers(export_dir: Path, method: str) -> tuple[float, float]:
    """Position and yaw RMSE by evo on the exported TUM files, with evo's Umeyama on the first 100 xy pairs."""
    from evo.core import geometry, metrics, sync
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(export_dir / "groundtruth.tum"))
    est = file_interface.read_tum_trajectory_file(str(export_dir / f"{method}.tum"))
    ref, est = sync.associate_trajectories(ref, est, max_diff=1e-3)
    # planar evaluation: zero the altitude, align in SE(2) on the first 100 matched frames
    R2, t2, _ = geometry.umeyama_alignment(est.positions_xyz[:100, :2].T, ref.positions_xyz[:100, :2].T)
    T = np.eye(4)
    T[:2, :2], T[:2, 3] = R2, t2
    planar = np.c_[est.positions_xyz[:, :2], np.zeros(est.num_poses)]
    est = PoseTrajectory3D(planar, est.orientations_quat_wxyz, est.timestamps)
    est.transform(T)
    ref = PoseTrajectory3D(np.c_[ref.positions_xyz[:, :2], np.zeros(ref.num_poses)], ref.orientations_quat_wxyz,
                           ref.timestamps)
    out = []
    for rel in (metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_deg):
        ape = metrics.APE(rel)
        ape.process_data((ref, est))
        out.append(ape.get_statistic(metrics.StatisticsType.rmse))
    return out[0], out[1]


def test_trajectory_metrics_match_evo_on_exported_tum(tmp_path: Path) -> None:
    from pipeline.export import export

    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=20.0, with_maps=False)
    written = export(RunStore(runs, "synth"), "tum", tmp_path / "tum")
    assert {p.name for p in written} >= {"groundtruth.tum", "odometry.tum", "rich_slam.tum"}
    p = EvaluateParams(sections=["trajectory"])
    ctx = make_context(runs, "synth", "evaluate", p, list(STAGE.input_stages(p)), tmp_path / "out")
    STAGE.run(ctx)
    ctx.close()
    m = read_artifact(tmp_path / "out" / "metrics.parquet", "metrics").to_pylist()
    ours = {(r["method"], r["metric"]): r["value"] for r in m}
    for method in ("odometry", "rich_slam", "fastslam_grid"):
        pos, yaw = _evo_numbers(tmp_path / "tum", method)
        assert ours[(method, "ate_pos_rmse_m")] == pytest.approx(pos, rel=1e-5, abs=1e-6), method
        assert ours[(method, "ate_yaw_rmse_deg")] == pytest.approx(yaw, rel=1e-5, abs=1e-5), method
        assert pos > 0.01  # the synthetic estimates do drift: the comparison is not between zeros


# -- the AUC protocol -----------------------------------------------------------------------------------------------
def test_roc_auc_matches_sklearn_with_ties() -> None:
    from sklearn.metrics import roc_auc_score

    rng = np.random.default_rng(0)
    for n in (5, 60, 2000):
        y = np.where(rng.uniform(size=n) < 0.3, 1.0, -1.0)
        y[0], y[1] = 1.0, -1.0
        s = np.round(rng.normal(size=n) + 0.8 * y, 1)  # rounding creates ties
        assert roc_auc(y, s) == pytest.approx(roc_auc_score(y > 0, s), abs=1e-12)
    assert np.isnan(roc_auc(np.ones(4), np.arange(4.0)))


def test_hilbert_maps_samples_follow_the_protocol() -> None:
    rng = np.random.default_rng(1)
    origins = np.zeros((4, 2))
    d = np.array([0.5, 1.99, 2.0, 7.3])
    ends = np.stack([d, np.zeros(4)], 1)
    s = hilbert_maps_samples(origins, ends, np.array([0, 0, 1, 1]), rng)
    assert (s.labels > 0).sum() == 4 and np.allclose(np.sort(s.points[s.labels > 0, 0]), d)
    free = s.points[s.labels < 0]
    assert len(free) == 1 + 1 + 1 + 3  # max(1, floor(d / 2)) per beam
    assert np.allclose(free[:, 1], 0.0) and free[:, 0].min() >= 0 and free[:, 0].max() <= d.max() - 0.1
    assert np.all(np.diff(s.scan) >= 0)


def test_block_split_is_seeded_contiguous_and_sized() -> None:
    scans = np.repeat(np.arange(200), 3)
    a = split_scans_by_block(scans, 0.2, 10, np.random.default_rng(5))
    b = split_scans_by_block(scans, 0.2, 10, np.random.default_rng(5))
    assert np.array_equal(a, b)
    held = np.unique(scans[a])
    assert len(held) == 40
    assert np.all(held.reshape(-1, 10) == held.reshape(-1, 10)[:, :1] + np.arange(10))  # whole blocks


def test_grid_reference_predicts_hit_ratio() -> None:
    pts = np.array([[0.1, 0.1], [0.2, 0.2], [0.3, 0.1], [2.1, 2.1]])
    train = LabelledSamples(pts, np.array([1.0, -1.0, 1.0, -1.0]), np.zeros(4, np.int64))
    model = grid_counts_fit(train, 0.5)
    got = grid_counts_predict(model, np.array([[0.15, 0.15], [2.2, 2.2], [50.0, 50.0], [1.2, 1.2]]), 0.5)
    assert np.allclose(got, [2 / 3, 0.0, 0.5, 0.5])


# -- baselines ------------------------------------------------------------------------------------------------------
def test_sgd_equals_sklearn_sgdclassifier() -> None:
    from sklearn.linear_model import SGDClassifier

    rng = np.random.default_rng(2)
    fmap = baselines.make_rff(32, 1.0, rng)
    batches = []
    for _ in range(15):
        p = rng.uniform(-3, 3, (40, 2))
        batches.append((fmap(p), np.where(np.linalg.norm(p, axis=1) < 1.5, 1.0, -1.0)))
    clf = SGDClassifier(loss="log_loss", penalty="l2", alpha=1e-3, learning_rate="optimal", shuffle=False)
    for phi, y in batches:
        clf.partial_fit(phi, y, classes=[-1.0, 1.0])
    m = baselines.sgd_logistic(batches, 32, 1e-3)
    assert np.allclose(m.w, clf.coef_[0], atol=1e-9) and m.b == pytest.approx(clf.intercept_[0], abs=1e-9)


def test_feature_maps_approximate_their_kernels() -> None:
    rng = np.random.default_rng(4)
    p = rng.uniform(-2, 2, (50, 2))
    d2 = np.sum((p[:, None] - p[None]) ** 2, -1)
    k = np.exp(-0.5 * d2 / 0.8**2)
    rff = baselines.make_rff(20000, 0.8, rng)(p)
    assert np.abs(rff @ rff.T - k).max() < 0.05
    nys = baselines.make_nystrom(50, 0.8, p, rng)(p)  # landmarks = all points: exact on them
    assert np.abs(nys @ nys.T - k).max() < 1e-5
    r = np.linspace(0, 2, 201)
    ks = baselines.sparse_kernel(r, 1.0)
    assert ks[0] == pytest.approx(1.0) and np.all(ks[r >= 1.0] == 0) and np.all(np.diff(ks) <= 1e-12)
    sp = baselines.make_sparse(36, np.array([-2.0, -2.0]), np.array([2.0, 2.0]), 2.0, 0.1)
    assert sp.dim == 36 and np.all(sp(p).sum(1) > 0)  # every point is covered by some feature


# -- the stage --------------------------------------------------------------------------------------------------------
def _point_to_segments(p: np.ndarray, segs: np.ndarray) -> np.ndarray:
    a, b = segs[None, :, :2], segs[None, :, 2:]
    ab = b - a
    t = np.clip(np.sum((p[:, None] - a) * ab, -1) / np.sum(ab * ab, -1), 0, 1)
    return np.linalg.norm(p[:, None] - (a + t[..., None] * ab), axis=-1).min(1)


def test_radar_points_land_on_the_walls_with_ground_truth(tmp_path: Path) -> None:
    """Independent check of calibration + pose interpolation: ray-cast endpoints fall on the world's walls."""

    from stages.evaluate.world import gt_interpolator, radar_beams_world

    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=10.0, with_maps=False)
    ctx = make_context(runs, "synth", "evaluate", EvaluateParams(), ["ingest"], tmp_path / "o")
    gt = Evaluation()._groundtruth(ctx)
    radar = read_artifact(runs / "synth" / "ingest" / "radar.parquet", "radar")
    beams = radar_beams_world(radar, Evaluation._calibration(ctx), gt_interpolator(gt, 10**9), 50.0)
    dist = _point_to_segments(beams.end, room_segments())
    assert len(dist) > 100 and np.percentile(dist, 99) < 0.15


def test_stage_writes_metrics_report_figures_and_rerun(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=20.0)
    p = EvaluateParams(mapping={"feature_counts": [16, 64],  # type: ignore[arg-type]
                                "methods": ["hilbert_gp", "rff", "sparse", "nystrom", "grid"]})
    out = tmp_path / "out"
    ctx = make_context(runs, "synth", "evaluate", p, list(STAGE.input_stages(p)), out)
    STAGE.run(ctx)
    ctx.close()
    m = read_artifact(out / "metrics.parquet", "metrics").to_pylist()
    got = {(r["method"], r["metric"]): r["value"] for r in m}
    for method in ("odometry", "rich_slam", "fastslam_grid"):
        assert (method, "ate_pos_rmse_m") in got and (method, "ate_yaw_rmse_deg") in got
    # the synthetic rich_slam drifts 5x less than the odometry
    assert got[("rich_slam", "ate_pos_rmse_m")] < got[("odometry", "ate_pos_rmse_m")]
    for method in ("hilbert_gp", "rff", "sparse", "nystrom"):
        for n in (16, 64):
            assert 0.5 < got[(f"{method}@{n}", "auc")] <= 1.0
        assert (method, "auc") in got  # at the slam posterior's M = 256
    assert got[("hilbert_gp", "auc")] > 0.9  # a clean ray-cast room; a broken protocol lands near 0.5
    assert ("grid", "auc") in got
    assert got[("hilbert_gp", "uncertainty_p50_final")] < got[("hilbert_gp", "uncertainty_p50_first")]
    for k in ("cd_l1", "cd_l2", "fscore_0.15", "ddist_p50", "ddist_p95", "cd_x", "cd_y", "cd_z", "lr_ratio"):
        assert np.isfinite(got[("radar_map", k)]), k
    assert got[("radar_map", "lr_ratio")] == pytest.approx(4.0, rel=0.01)
    assert {r["seq"] for r in m} == {"synth"}
    report = (out / "report.md").read_text()
    for needle in ("Table III", "| rich_slam |", "AUC", "hilbert_gp", "RMap", "radar_map", "trajectories.png"):
        assert needle in report
    for fig in ("trajectories.png", "auc_vs_features.png", "gt_map.png", "uncertainty.png", "maps_top.png",
                "query_resolutions.png"):
        assert (out / fig).stat().st_size > 1000, fig
        assert f"]({fig})" in report
    assert read_artifact(out / "gt_map_grid.parquet", "map_grid").num_rows > 100
    paths = entity_paths_in(out / "evaluate.rrd")
    assert "/metrics/rich_slam/ate_pos_rmse_m" in paths and "/metrics/uncertainty/p50" in paths


def test_completed_map_is_scored_when_present(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=10.0)
    lid = read_artifact(runs / "synth" / "voxel" / "lidar_map.parquet", "lidar_map")
    write_stage(runs, "synth", "complete", {"completed_map.parquet": (
        {c: lid[c].to_numpy() for c in ("x", "y", "z")}, "completed_map")})
    p = EvaluateParams(sections=["rmap"])
    assert STAGE.input_stages(p) == ("voxel",)  # the map metrics read no log (map sequences have none)
    ctx = make_context(runs, "synth", "evaluate", p, [*STAGE.input_stages(p), "complete"], tmp_path / "out")
    STAGE.run(ctx)
    ctx.close()
    got = {(r["method"], r["metric"]): r["value"]
           for r in read_artifact(tmp_path / "out" / "metrics.parquet", "metrics").to_pylist()}
    assert got[("completed_map", "cd_l1")] == 0.0 and got[("completed_map", "fscore_0.15")] == 1.0
    assert got[("radar_map", "cd_l1")] > 0.0


def test_missing_ground_truth_is_a_user_error(tmp_path: Path) -> None:
    from core.errors import UserError

    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=5.0, with_maps=False)
    gt = read_artifact(runs / "synth" / "ingest" / "groundtruth.parquet", "groundtruth").slice(0, 1)
    write_stage(runs, "synth", "ingest", {"groundtruth.parquet": (gt, "groundtruth")})
    p = EvaluateParams(sections=["trajectory"])
    ctx = make_context(runs, "synth", "evaluate", p, list(STAGE.input_stages(p)), tmp_path / "out")
    with pytest.raises(UserError, match=r"groundtruth\.parquet: 1 ground-truth poses"):
        STAGE.run(ctx)


def test_manifest_fallbacks_read_the_slam_parameters(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=5.0, with_maps=False)
    man = runs / "synth" / "slam" / "manifest.json"
    d = json.loads(man.read_text())
    d["params"] = {"beams": {"max_range": 3.0}}
    man.write_text(json.dumps(d))
    ctx = make_context(runs, "synth", "evaluate", EvaluateParams(), ["slam"], tmp_path / "o")
    assert Evaluation._slam_params(ctx)["beams.max_range"] == 3.0


def test_each_fit_has_its_own_random_stream() -> None:
    """rff@16 is the same number whether or not other fits ran in the same call (sweeps rely on it)."""
    from stages.evaluate.mapping import GPConfig, auc_suite
    from stages.evaluate.params import BaselineParams

    rng = np.random.default_rng(0)
    pts = rng.uniform(-4, 4, (1500, 2))
    lab = np.where(np.abs(np.linalg.norm(pts, axis=1) - 2.5) < 0.4, 1.0, -1.0)
    scan = np.sort(rng.integers(0, 60, 1500))
    s = LabelledSamples(pts, lab, scan)
    train, test = s.select(scan % 5 != 0), s.select(scan % 5 == 0)
    gp = GPConfig((5.0, 5.0), (0.0, 0.0), 1.0, 4.0, 0.36)
    base = BaselineParams(lengthscale_m=1.0)
    alone = auc_suite(train, test, gp, base, [16], ["rff", "nystrom"], seed=3)
    both = auc_suite(train, test, gp, base, [36, 16], ["sparse", "nystrom", "rff"], seed=3)
    pick = {(r.method, r.features): r.auc for r in both}
    for r in alone:
        assert pick[(r.method, r.features)] == r.auc
    other_seed = auc_suite(train, test, gp, base, [16], ["rff"], seed=4)
    assert other_seed[0].auc != pick[("rff", 16)]


@pytest.mark.parametrize("headline, counts, methods", [(False, [16], ["hilbert_gp", "rff", "grid"]),
                                                        (True, [], ["hilbert_gp"])])
def test_sweep_configurations_of_the_mapping_section(tmp_path: Path, headline: bool, counts: list[int],
                                                     methods: list[str]) -> None:
    """The two sweep workflows' settings: per-count rows only (Fig. 6) or the headline map only (Fig. 7)."""
    runs = tmp_path / "runs"
    write_synthetic_run(runs, duration=10.0, with_maps=False)
    p = EvaluateParams(sections=["mapping"], mapping={"headline": headline, "feature_counts": counts,
                                                       "methods": methods})  # type: ignore[arg-type]
    out = tmp_path / "out"
    ctx = make_context(runs, "synth", "evaluate", p, list(STAGE.input_stages(p)), out)
    STAGE.run(ctx)
    ctx.close()
    got = {(r["method"], r["metric"]) for r in read_artifact(out / "metrics.parquet", "metrics").to_pylist()}
    auc = {m for m, k in got if k == "auc"}
    if headline:
        assert auc == {"hilbert_gp"} and (out / "gt_map_grid.parquet").exists()
    else:
        assert auc == {"hilbert_gp@16", "rff@16", "grid"} and not (out / "gt_map_grid.parquet").exists()


def test_the_configured_methods_trajectory_is_scored_once_under_its_own_name(tmp_path: Path) -> None:
    """``trajectory.parquet`` is slam.method's trajectory: with ``trajectory_radar_graph.parquet`` beside it and
    the manifest naming radar_graph it is not scored again (nor under another method's name); alone, it is
    scored under the manifest's method."""
    import json
    from types import SimpleNamespace

    from stages.evaluate.stage import Evaluation

    slam = tmp_path / "slam"
    slam.mkdir()
    for name in ("trajectory.parquet", "trajectory_radar_graph.parquet", "trajectory_odometry.parquet"):
        (slam / name).write_bytes(b"")
    (slam / "manifest.json").write_text(json.dumps({"params": {"method": "radar_graph"}}))
    ctx = SimpleNamespace(input_dirs={"slam": slam})
    names = [m for m, _, _ in Evaluation()._trajectory_files(ctx)]  # type: ignore[arg-type]
    assert sorted(names) == ["odometry", "radar_graph"]
    (slam / "trajectory_radar_graph.parquet").unlink()
    (slam / "trajectory_odometry.parquet").unlink()
    assert [m for m, _, _ in Evaluation()._trajectory_files(ctx)] == ["radar_graph"]  # type: ignore[arg-type]
