"""The slam stage's adapter on synthetic artifacts: frames, outputs, schemas, Rerun paths, map quality."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from rich.console import Console

from pipeline.errors import UserError
from pipeline.recording import entity_paths_in
from pipeline.sequences import SequenceInfo
from pipeline.stage import StageContext
from schemas.io import read_artifact, write_artifact
from stages.odometry.stage import cov_columns
from stages.slam import hilbert_map as hm
from stages.slam.stage import STAGE, SlamParams
from stages.slam.synthetic import make_run, ray_cast

# the ColoRadar calibration example: radar boresight along base +y, offset from the base origin
T_BASE_RADAR = np.eye(4)
T_BASE_RADAR[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
T_BASE_RADAR[:3, 3] = [-0.145, 0.09, -0.025]


def _write_inputs(root: Path, n: int, seed: int = 0, odometry: str = "odometry") -> dict[str, Any]:
    """ingest/filter/odometry folders from a synthetic corridor run, radar points in the RADAR frame."""
    rng = np.random.default_rng(seed)
    # synthetic beams start at the body origin; here they start at the radar origin, so re-cast them
    run = make_run(n, rng, outlier_fraction=0.0)
    ingest, filt, odo = root / "ingest", root / "filter", root / "odometry"
    for d in (ingest, filt, odo):
        d.mkdir(parents=True)
    (ingest / "calibration.json").write_text(json.dumps({"base_from_radar": T_BASE_RADAR.tolist()}))
    R, t = T_BASE_RADAR[:3, :3], T_BASE_RADAR[:3, 3]
    scans, xs, ys, zs = [], [], [], []
    t_ns = 1_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000
    for i in range(n):
        x, y, yaw = run.groundtruth[i]
        c, s = np.cos(yaw), np.sin(yaw)
        origin_w = np.array([x + c * t[0] - s * t[1], y + s * t[0] + c * t[1]])
        ang = rng.uniform(-1.0, 1.0, 12) + yaw + np.pi / 2  # around the boresight (base +y)
        dirs = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        d = ray_cast(np.tile(origin_w, (12, 1)), dirs, run.walls)
        ok = d < 4.8
        hit_w = origin_w + dirs[ok] * d[ok, None]
        # world -> base -> radar frame
        rel = hit_w - [x, y]
        base = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], np.full(ok.sum(), 0.1)], 1)
        radar = (base - t) @ R  # R^T (p - t)
        scans += [i] * len(radar)
        xs += radar[:, 0].tolist()
        ys += radar[:, 1].tolist()
        zs += radar[:, 2].tolist()
    scans_a = np.asarray(scans, np.int32)
    zero = np.zeros(len(scans_a), np.float32)
    write_artifact({"scan": scans_a, "t_ns": t_ns[scans_a], "x": np.float32(xs), "y": np.float32(ys),
                    "z": np.float32(zs), "intensity": zero, "doppler": zero},
                   filt / "radar_filtered.parquet", "radar_filtered")
    poses = run.groundtruth if odometry == "groundtruth" else run.odometry
    write_artifact({"scan": np.arange(n, dtype=np.int32), "t_ns": t_ns, "x": poses[:, 0], "y": poses[:, 1],
                    "z": np.zeros(n), "roll": np.zeros(n), "pitch": np.zeros(n), "yaw": poses[:, 2], **cov_columns(n)},
                   odo / "odometry.parquet", "odometry")
    return {"run": run, "dirs": {"ingest": ingest, "filter": filt, "odometry": odo}}


def _ctx(out: Path, dirs: dict[str, Path], **params: Any) -> StageContext:
    out.mkdir(parents=True, exist_ok=True)
    info = SequenceInfo(name="synthetic_corridor", kind="source", source=Path("/nonexistent"))
    return StageContext(stage="slam", seq=info, params=SlamParams(**params), out_dir=out, input_dirs=dirs,
                        console=Console(stderr=True, quiet=True))


def _run(ctx: StageContext) -> None:
    try:
        STAGE.run(ctx)
    finally:
        ctx.close()


def test_stage_writes_every_method_and_artifact(tmp_path: Path) -> None:
    inp = _write_inputs(tmp_path / "in", 30)
    ctx = _ctx(tmp_path / "out", inp["dirs"], n_particles=6, n_basis=64, workers=0, n_map_snapshots=2,
               stats_every=4, grid_spacing=1.0)
    _run(ctx)
    out = tmp_path / "out"
    for m in ("odometry", "fastslam_grid", "rich_slam", "rich_slam_no_et", "rich_slam_mean_only", "rich_slam_refined"):
        t = read_artifact(out / f"trajectory_{m}.parquet", "trajectory")
        assert t.num_rows == 30 and np.all(np.isfinite(t["x"].to_numpy()))
    main = read_artifact(out / "trajectory.parquet", "trajectory")
    np.testing.assert_array_equal(main["x"].to_numpy(), pq.read_table(out / "trajectory_rich_slam.parquet")["x"])
    odo = read_artifact(out / "trajectory_odometry.parquet", "trajectory")
    np.testing.assert_array_equal(odo["x"].to_numpy(), pq.read_table(inp["dirs"]["odometry"] / "odometry.parquet")["x"])
    post = read_artifact(out / "map_posterior.parquet", "map_posterior").to_pylist()[0]
    assert post["M"] == 64 and len(post["theta"]) == 64 and len(post["cov"]) == 64 * 64
    assert post["length_unit_m"] == 0.1 and post["lengthscale"] == 20.0 and post["basis_kind"] == "tensor"
    cov = np.asarray(post["cov"]).reshape(64, 64)
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > 0
    grid = read_artifact(out / "map_grid.parquet", "map_grid")
    xs = np.unique(grid["x"].to_numpy())
    np.testing.assert_allclose(np.diff(xs), 1.0)
    occ = grid["occupancy"].to_numpy()
    assert np.all((occ > 0) & (occ < 1)) and np.all(grid["variance"].to_numpy() >= 0)
    stats = pq.read_table(out / "map_stats.parquet")
    assert stats.num_rows == len(range(0, 30, 4)) + 1  # every 4th scan and the last
    u50 = stats["u_p50"].to_numpy()
    assert np.all((u50 > 0) & (u50 <= 1.0 + 1e-9)) and u50[-1] < u50[0]  # uncertainty shrinks as it maps
    paths = entity_paths_in(out / "slam.rrd")
    for p in ("world/slam/trajectory/path", "world/slam/particles", "world/slam/map/occupancy",
              "world/slam/map/uncertainty", "world/slam/methods/fastslam_grid/path"):
        assert "/" + p in paths, paths
    assert ctx.stats["samples_per_scan_mean"] > 5


def test_map_from_true_poses_is_right_and_frames_are_consistent(tmp_path: Path) -> None:
    """Through the whole adapter (radar frame -> base -> world), the map built along ground truth
    separates points on the walls from points on the driven path."""
    inp = _write_inputs(tmp_path / "in", 120, odometry="groundtruth")
    _run(_ctx(tmp_path / "out", inp["dirs"], method="odometry", methods=["odometry"], n_basis=256, workers=0,
              grid_spacing=0.5, domain_padding=5.0))
    post = read_artifact(tmp_path / "out" / "map_posterior.parquet", "map_posterior").to_pylist()[0]
    basis = hm.make_basis((post["L1"], post["L2"]), (post["cx"], post["cy"]), post["M"])
    theta, cov = np.asarray(post["theta"]), np.asarray(post["cov"]).reshape(post["M"], -1)
    run = inp["run"]
    gt = run.groundtruth[:120:3]
    # free: 1.5 m along the radar boresight (base +y) of each pose; occupied: wall points the radar saw
    free = gt[:, :2] + 1.5 * np.stack([-np.sin(gt[:, 2]), np.cos(gt[:, 2])], axis=1)
    walls = np.concatenate([np.linspace(w[0], w[1], 80) for w in run.walls])
    seen = run.groundtruth[:120, :2] + 0.1 * np.stack([-np.sin(run.groundtruth[:120, 2]),
                                                        np.cos(run.groundtruth[:120, 2])], axis=1)
    near = np.min(np.linalg.norm(walls[:, None] - seen[None], axis=2), axis=1) < 4.0
    _, _, occ_wall = hm.query(basis, theta, cov, walls[near])
    _, _, occ_free = hm.query(basis, theta, cov, free)
    auc = np.mean(occ_wall[:, None] > occ_free[None, :])
    # (a 90 degree frame error gives AUC 0.88 and a free median of 0.41)
    assert auc > 0.9 and np.median(occ_wall) > 0.55 and np.median(occ_free) < 0.33, (
        auc, np.median(occ_wall), np.median(occ_free))


def test_zero_motion_noise_reproduces_odometry(tmp_path: Path) -> None:
    inp = _write_inputs(tmp_path / "in", 15)
    _run(_ctx(tmp_path / "out", inp["dirs"], n_particles=4, n_basis=36, motion_std_xy=0.0, motion_std_yaw=0.0,
              motion_rel_trans=0.0, motion_rel_rot=0.0, motion_rot_per_trans=0.0, motion_trans_per_rot=0.0,
              proposal="gmapping", yaw_bias=False, methods=["fastslam_grid", "rich_slam"], workers=0,
              n_map_snapshots=0))
    odo = pq.read_table(inp["dirs"]["odometry"] / "odometry.parquet")
    for m in ("fastslam_grid", "rich_slam"):
        t = pq.read_table(tmp_path / "out" / f"trajectory_{m}.parquet")
        for c in ("x", "y", "yaw"):
            np.testing.assert_allclose(t[c].to_numpy(), odo[c].to_numpy(), atol=1e-9)
        np.testing.assert_allclose(t["n_eff"].to_numpy(), 4.0)


def test_zero_odometry_covariance_without_bias_reproduces_odometry_and_paper_method_runs(tmp_path: Path) -> None:
    inp = _write_inputs(tmp_path / "in", 15)
    odo = pq.read_table(inp["dirs"]["odometry"] / "odometry.parquet").to_pydict()
    for c in ("cov_xx", "cov_xy", "cov_xyaw", "cov_yy", "cov_yyaw", "cov_yawyaw"):
        odo[c] = np.zeros(15)
    write_artifact(odo, inp["dirs"]["odometry"] / "odometry.parquet", "odometry")
    _run(_ctx(tmp_path / "out", inp["dirs"], n_particles=4, n_basis=36, yaw_bias=False, proposal="odometry_covariance",
              methods=["fastslam_grid", "rich_slam", "rich_slam_paper"], workers=0, n_map_snapshots=0))
    for m in ("fastslam_grid", "rich_slam"):  # the odometry's own (zero) covariance: no noise at all
        t = pq.read_table(tmp_path / "out" / f"trajectory_{m}.parquet")
        for c in ("x", "y", "yaw"):
            np.testing.assert_allclose(t[c].to_numpy(), odo[c], atol=1e-9)
    paper = pq.read_table(tmp_path / "out" / "trajectory_rich_slam_paper.parquet")  # the fitted GMapping noise
    assert np.abs(paper["x"].to_numpy() - odo["x"]).max() > 1e-4


def test_bad_inputs_give_one_line_errors(tmp_path: Path) -> None:
    inp = _write_inputs(tmp_path / "in", 5)
    (inp["dirs"]["ingest"] / "calibration.json").write_text(json.dumps({"base_from_lidar": np.eye(4).tolist()}))
    with pytest.raises(UserError, match="base_from_radar"):
        _run(_ctx(tmp_path / "out", inp["dirs"], methods=["odometry"], method="odometry"))
    with pytest.raises(ValueError, match="perfect square"):
        SlamParams(n_basis=250)
    with pytest.raises(ValueError, match=r"rich_slam_refined.*numpy"):
        SlamParams(backend="torch", methods=["odometry", "rich_slam_refined"])
    with pytest.raises(ValueError, match=r"endpoint_noise_variance.*numpy"):
        SlamParams(backend="torch", methods=["rich_slam"], endpoint_noise_variance=0.09)


def test_consistency_sweep_perturbs_the_odometry_and_names_bad_input(tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m stages.slam.consistency_sweep``: the score, its parts and the errors per perturbation."""
    from stages.slam import consistency_sweep

    inp = _write_inputs(tmp_path / "seq_s", 60)
    gt = inp["run"].groundtruth
    t_ns = 1_000_000_000 + np.arange(60, dtype=np.int64) * 100_000_000
    write_artifact({"t_ns": t_ns, "x": gt[:, 0], "y": gt[:, 1], "z": np.zeros(60), "qx": np.zeros(60),
                    "qy": np.zeros(60), "qz": np.sin(gt[:, 2] / 2), "qw": np.cos(gt[:, 2] / 2)},
                   inp["dirs"]["ingest"] / "groundtruth.parquet", "groundtruth")
    out = tmp_path / "sweep.jsonl"
    args = [str(tmp_path / "seq_s"), "--scales", "0.9,1,1.1", "--ramps=-0.1,0,0.1", "--set", "workers=0"]
    assert consistency_sweep.main([*args, "--out", str(out)]) == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["kind"], r["value"]) for r in rows] == [("scale", 0.9), ("scale", 1.0), ("scale", 1.1),
                                                        ("ramp", -0.1), ("ramp", 0.0), ("ramp", 0.1)]
    one, zero = rows[1], rows[4]  # both the odometry itself
    assert one["score_rel"] == 0.0 and zero["score_rel"] == pytest.approx(0.0, abs=1e-15)
    assert one["yaw_rmse_whole_deg"] == pytest.approx(zero["yaw_rmse_whole_deg"], rel=1e-9)
    for r in rows:  # the score is its two parts (0.5 m cap)
        assert 0 < r["matched"] <= 1
        assert r["score"] == pytest.approx(r["matched"] * r["matched_ms"] + (1 - r["matched"]) * 0.25, rel=1e-9)
        assert 0 < r["common_ms"] < 0.25  # the points matched under every perturbation of its kind
    assert rows[0]["yaw_rmse_whole_deg"] == pytest.approx(one["yaw_rmse_whole_deg"], rel=1e-9)  # a scale: no yaw
    assert rows[3]["yaw_rmse_whole_deg"] != rows[5]["yaw_rmse_whole_deg"]
    s = consistency_sweep.summary(rows)
    assert set(s) == {f"{k}_by_{w}" for k in ("scale", "ramp") for w in ("score", "matched", "common", "truth")}
    assert s["ramp_by_score"] == min(rows[3:], key=lambda r: r["score"])["value"]
    assert s["scale_by_common"] == min(rows[:3], key=lambda r: r["common_ms"])["value"]
    text = capsys.readouterr().out
    assert "seq_s: scale by score" in text and "| ramp +0.1 |" in text and not list(tmp_path.glob("*.tmp"))
    # bad input: one line naming it, exit 2, the earlier output left as it was
    assert consistency_sweep.main([args[0], "--scales", "a,b", "--out", str(out)]) == 2
    assert "--scales 'a,b'" in capsys.readouterr().err
    assert consistency_sweep.main([str(tmp_path / "nothing"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("consistency_sweep:") and "\n" not in err
    assert len(out.read_text().splitlines()) == 6
    # --kept: the scales of the fused correction of a kept smoothed trajectory (here the truth itself, so the
    # correction points the odometry's heading towards the truth's)
    from stages.slam.table3 import save_trajectory

    scan_ns = pq.read_table(inp["dirs"]["odometry"] / "odometry.parquet")["t_ns"].to_numpy()
    save_trajectory(tmp_path / "kept", "seq_s", "rich_slam, smoothed", 3, "{}", scan_ns, gt.astype(np.float64),
                    (t_ns, gt[:, :2].astype(np.float64), gt[:, 2].astype(np.float64)), "smoothed")
    prof = tmp_path / "profile.jsonl"
    assert consistency_sweep.main([args[0], "--kept", str(tmp_path / "kept"), "--alphas", "0,0.5,1",
                                   "--set", "workers=0", "--out", str(prof)]) == 0
    steps = [json.loads(line) for line in prof.read_text().splitlines()]
    assert [(r["kind"], r["value"], r["seed"]) for r in steps] == [("alpha", a, 3) for a in (0.0, 0.5, 1.0)]
    assert steps[0]["score_rel"] == 0.0 and steps[0]["yaw_rmse_whole_deg"] == pytest.approx(
        one["yaw_rmse_whole_deg"], rel=1e-9)  # alpha 0: the odometry
    assert steps[2]["yaw_rmse_whole_deg"] < steps[1]["yaw_rmse_whole_deg"] < steps[0]["yaw_rmse_whole_deg"]
    assert 0 < steps[0]["common_share"] <= 1 and all(0 < r["common_ms"] < 0.25 for r in steps)
    assert consistency_sweep.summary(steps)["alpha_by_truth"] == 1.0
    assert re.search(r"seq_s seed 3 \(rich_slam__smoothed_seed3_\w+\.npz\): alpha by score", capsys.readouterr().out)
    # a second file of the same seed (another run's parameters) gets a table of its own, not mixed with the first
    save_trajectory(tmp_path / "kept", "seq_s", "rich_slam, smoothed", 3, '{"n_particles": 7}', scan_ns,
                    gt.astype(np.float64), (t_ns, gt[:, :2].astype(np.float64), gt[:, 2].astype(np.float64)),
                    "smoothed")
    assert consistency_sweep.main([args[0], "--kept", str(tmp_path / "kept"), "--alphas", "0,1",
                                   "--set", "workers=0", "--out", str(prof)]) == 0
    assert len(re.findall(r"seq_s seed 3 \(.+\.npz\): alpha by score", capsys.readouterr().out)) == 2
    assert len(prof.read_text().splitlines()) == 4
    # without --alphas: the grid the fused estimate searches under the given settings
    assert consistency_sweep.main([args[0], "--kept", str(tmp_path / "kept"), "--set", "workers=0", "--set",
                                   "fusion_alpha_max=0.5", "--out", str(prof)]) == 0
    assert sorted({json.loads(r)["value"] for r in prof.read_text().splitlines()}) == [0, 0.125, 0.25, 0.375, 0.5]
    assert consistency_sweep.main([args[0], "--kept", str(tmp_path / "kept"), "--set", "fusion_alpha_max=0",
                                   "--out", str(prof)]) == 2
    assert "fusion_alpha_max is 0" in capsys.readouterr().err
    assert consistency_sweep.main([args[0], "--kept", str(tmp_path / "none"), "--out", str(prof)]) == 2
    assert "no smoothed rich_slam trajectory kept" in capsys.readouterr().err


def test_table3_runner_is_resumable_and_tabulates(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m stages.slam.table3``: one row per (sequence, method, seed), finished rows skipped."""
    from stages.slam import table3

    inp = _write_inputs(tmp_path / "seq_a", 25)
    gt = inp["run"].groundtruth
    t_ns = 1_000_000_000 + np.arange(25, dtype=np.int64) * 100_000_000
    half = gt[:, 2] / 2
    write_artifact({"t_ns": t_ns, "x": gt[:, 0], "y": gt[:, 1], "z": np.zeros(25), "qx": np.zeros(25),
                    "qy": np.zeros(25), "qz": np.sin(half), "qw": np.cos(half)},
                   inp["dirs"]["ingest"] / "groundtruth.parquet", "groundtruth")
    out = tmp_path / "t3.jsonl"
    args = [str(tmp_path / "seq_a"), "--methods", "odometry,fastslam_grid", "--seeds", "0,1", "--out", str(out),
            "--set", "n_particles=4", "--set", "workers=0"]
    assert table3.main(args) == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["method"], r["seed"]) for r in rows] == [("odometry", 0), ("fastslam_grid", 0), ("odometry", 1),
                                                         ("fastslam_grid", 1)]
    odo = [r for r in rows if r["method"] == "odometry"]
    assert odo[0]["pos_rmse_m"] == odo[1]["pos_rmse_m"] > 0  # the odometry's own drift, seed-independent
    assert table3.main(args) == 0  # nothing left to do: no new rows
    assert len(out.read_text().splitlines()) == 4
    md = table3.table(rows)
    assert "| fastslam_grid |" in md and "(2)" in md and md.count("\n") == 3
    cells = table3.by_sequence(rows)["seq_a"]
    assert len(cells["odometry"]) == 1 and len(cells["fastslam_grid"]) == 2  # odometry once, a dot per seed
    assert all("pos_rmse_anchored_m" not in r for r in rows)  # an odometry without a ground-truth anchor
    # anchored at the ground truth (the odometry stage's default): the errors without alignment as well
    odo_xy = inp["run"].odometry
    write_artifact({"scan": np.arange(25, dtype=np.int32), "t_ns": t_ns, "x": odo_xy[:, 0], "y": odo_xy[:, 1],
                    "z": np.zeros(25), "roll": np.zeros(25), "pitch": np.zeros(25), "yaw": odo_xy[:, 2],
                    **cov_columns(25)},
                   inp["dirs"]["odometry"] / "odometry.parquet", "odometry", metadata={"anchor": "groundtruth"})
    out2 = tmp_path / "t3_anchored.jsonl"
    assert table3.main([str(tmp_path / "seq_a"), "--methods", "odometry,fastslam_grid", "--seeds", "0",
                        "--out", str(out2), "--set", "n_particles=4", "--set", "workers=0"]) == 0
    rows2 = [json.loads(line) for line in out2.read_text().splitlines()]
    odo2 = next(r for r in rows2 if r["method"] == "odometry")
    d = odo_xy - gt  # the same times: no interpolation, no alignment
    yaw = np.degrees(np.sqrt(np.mean(np.angle(np.exp(1j * d[:, 2])) ** 2)))
    assert odo2["pos_rmse_anchored_m"] == pytest.approx(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, 1))), rel=1e-9)
    assert odo2["yaw_rmse_anchored_deg"] == pytest.approx(yaw, rel=1e-9)
    assert odo2["pos_rmse_m"] == odo[0]["pos_rmse_m"]  # the protocol's numbers do not change
    md2 = table3.table([*rows, *rows2], anchored=True)
    assert md2.count("\n") == 3 and "(1 seed)" in md2  # only the anchored rows: one seed of the grid
    # --estimates: the other trajectory estimates of the same filter run as rows of their own, resumable too
    out3 = tmp_path / "t3_estimates.jsonl"
    args3 = [str(tmp_path / "seq_a"), "--methods", "odometry,fastslam_grid", "--seeds", "0", "--out", str(out3),
             "--set", "n_particles=4", "--set", "workers=0", "--estimates", "best_per_scan,smoothed"]
    assert table3.main(args3) == 0 and table3.main(args3) == 0
    rows3 = [json.loads(line) for line in out3.read_text().splitlines()]
    others = [e for e in ("best_per_scan", "smoothed") if e != SlamParams().estimate]
    assert [r["method"] for r in rows3] == ["odometry", *(f"fastslam_grid, {e}" for e in others), "fastslam_grid"]
    assert [json.loads(r["config"])["estimate"] for r in rows3[1:-1]] == others
    best = next(r for r in rows2 if r["method"] == "fastslam_grid")
    assert rows3[-1]["pos_rmse_m"] == best["pos_rmse_m"]  # the configured estimate's row is the plain run's
    # --keep saves each row's trajectory; --from-kept computes the fused estimate from the kept smoothed one,
    # equal to the fused row of the filter run itself
    keep, out5, out6 = tmp_path / "kept", tmp_path / "t3_kept.jsonl", tmp_path / "t3_fused.jsonl"
    base5 = [str(tmp_path / "seq_a"), "--methods", "fastslam_grid", "--seeds", "0", "--set", "n_particles=4",
             "--set", "workers=0", "--set", "fusion_filter_sigma=1.5", "--set", "fusion_increment_scale=0.5",
             "--set", 'estimate="smoothed"']
    assert table3.main([*base5, "--out", str(out5), "--keep", str(keep)]) == 0
    kept = list((keep / "seq_a").glob("fastslam_grid_seed0_*.npz"))
    assert len(kept) == 1 and not list(keep.rglob("*.tmp.npz"))
    assert table3.main([*base5, "--out", str(out5), "--from-kept", str(keep)]) == 0
    assert table3.main([*base5, "--out", str(out6), "--estimates", "fused"]) == 0
    from_kept = next(r for r in map(json.loads, out5.read_text().splitlines()) if r["method"] == "fastslam_grid, fused")
    in_run = next(r for r in map(json.loads, out6.read_text().splitlines()) if r["method"] == "fastslam_grid, fused")
    for k in ("pos_rmse_m", "yaw_rmse_deg", "pos_rmse_whole_m", "yaw_rmse_whole_deg"):
        assert from_kept[k] == pytest.approx(in_run[k], rel=1e-9, abs=1e-12)
    assert json.loads(from_kept["config"]) == json.loads(in_run["config"])
    # the fusion's model of the filter's error, widened by the weight's heading information along the odometry
    assert from_kept["heading_information"] > 0
    assert from_kept["fusion_filter_sigma_deg"] == pytest.approx(
        1.5 * max(1.0, (400.0 / from_kept["heading_information"]) ** 0.5), rel=1e-9)
    for k in ("heading_information", "fusion_filter_sigma_deg"):  # the filter run's row says the same
        assert in_run[k] == pytest.approx(from_kept[k], rel=1e-9)
    # the fusion figure of a kept trajectory takes its row's model (configuration and information-scaled std)
    from stages.slam import fusion_figure

    fig = tmp_path / "fusion.png"
    assert fusion_figure.main([str(tmp_path / "seq_a"), str(kept[0]), "--rows", str(out5), "--out", str(fig)]) == 0
    assert fig.stat().st_size > 0 and not list(tmp_path.glob("*.tmp.png"))
    model = fusion_figure.panel_model(from_kept, {})
    assert model.increment_scale == 0.5
    assert np.degrees(model.filter_sigma) == pytest.approx(from_kept["fusion_filter_sigma_deg"], rel=1e-12)
    assert fusion_figure.main([str(tmp_path / "seq_a"), "--out", str(fig)]) == 2  # not a pair
    # the consistency figure: the score and the yaw error over the searched scales, the chosen one marked
    from stages.slam import consistency_figure

    fig2 = tmp_path / "consistency.png"
    panel = consistency_figure.build_panel(tmp_path / "seq_a", kept[0], {}, {})
    assert panel["scores"][0] == 1.0 and len(panel["alphas"]) == len(panel["yaw"]) == 13
    assert panel["alpha"] in panel["alphas"] and panel["scores"][list(panel["alphas"]).index(panel["alpha"])] == \
        panel["scores"].min()
    assert consistency_figure.main([str(tmp_path / "seq_a"), str(kept[0]), "--rows", str(out5), "--out",
                                    str(fig2)]) == 0
    assert fig2.stat().st_size > 0 and not list(tmp_path.glob("*.tmp.png"))
    assert consistency_figure.main([str(tmp_path / "seq_a"), str(kept[0]), "--set", "fusion_alpha_max=0",
                                    "--out", str(fig2)]) == 2  # nothing searched: a one-line error
    # fusion_information_ref = 0: the configured model itself, no information computed nor recorded, both ways
    out7, out8 = tmp_path / "t3_kept_ref0.jsonl", tmp_path / "t3_fused_ref0.jsonl"
    ref0 = [*base5, "--set", "fusion_information_ref=0"]
    assert table3.main([*ref0, "--out", str(out7), "--from-kept", str(keep)]) == 0
    assert table3.main([*ref0, "--out", str(out8), "--estimates", "fused"]) == 0
    kept0 = next(r for r in map(json.loads, out7.read_text().splitlines()) if r["method"] == "fastslam_grid, fused")
    run0 = next(r for r in map(json.loads, out8.read_text().splitlines()) if r["method"] == "fastslam_grid, fused")
    assert json.loads(kept0["config"])["fusion_information_ref"] == 0
    assert "heading_information" not in kept0 and "heading_information" not in run0
    off = [*base5, "--set", "fusion_alpha_max=0", "--out"]  # off: the fusion's correction as it is, no scale recorded
    assert table3.main([*off, str(tmp_path / "t3_off.jsonl"), "--from-kept", str(keep)]) == 0
    assert "fusion_alpha" not in json.loads((tmp_path / "t3_off.jsonl").read_text().splitlines()[0])
    # the guard (stop 55): the same evidence both ways, recorded; nothing matched here, so no evidence for any
    # scale and the odometry stays (alpha 0) where the unguarded search keeps the correction as it is (1)
    guard = [*base5, "--set", "fusion_alpha_guard=2", "--out"]
    assert table3.main([*guard, str(tmp_path / "t3_g_kept.jsonl"), "--from-kept", str(keep)]) == 0
    assert table3.main([*guard, str(tmp_path / "t3_g_run.jsonl"), "--estimates", "fused"]) == 0
    g_kept, g_run = (next(r for r in map(json.loads, (tmp_path / f).read_text().splitlines())
                          if r["method"] == "fastslam_grid, fused") for f in ("t3_g_kept.jsonl", "t3_g_run.jsonl"))
    assert g_kept["fusion_alpha"] == g_run["fusion_alpha"] == 0.0
    assert g_kept["fusion_alpha_evidence"] == g_run["fusion_alpha_evidence"] == 0.0
    assert g_kept["yaw_rmse_whole_deg"] == pytest.approx(odo2["yaw_rmse_whole_deg"], rel=1e-9)
    assert table3.main([*guard, str(tmp_path / "t3_g_off.jsonl"), "--set", "fusion_alpha_max=0", "--from-kept",
                        str(keep)]) == 0  # nothing searched: nothing guarded, no evidence recorded
    assert "fusion_alpha_evidence" not in json.loads((tmp_path / "t3_g_off.jsonl").read_text().splitlines()[0])
    for k in ("yaw_rmse_whole_deg", "pos_rmse_whole_m"):
        assert kept0[k] == pytest.approx(run0[k], rel=1e-9, abs=1e-12)
    # the correction's scale chosen by the scans' consistency (fusion_alpha_max): the same both ways, recorded
    out11, out12 = tmp_path / "t3_kept_alpha.jsonl", tmp_path / "t3_fused_alpha.jsonl"
    alpha = [*base5, "--set", "fusion_alpha_max=1.0"]
    assert table3.main([*alpha, "--out", str(out11), "--from-kept", str(keep)]) == 0
    assert table3.main([*alpha, "--out", str(out12), "--estimates", "fused"]) == 0
    kept_a = next(r for r in map(json.loads, out11.read_text().splitlines()) if r["method"] == "fastslam_grid, fused")
    run_a = next(r for r in map(json.loads, out12.read_text().splitlines()) if r["method"] == "fastslam_grid, fused")
    assert kept_a["fusion_alpha"] == run_a["fusion_alpha"] and 0 <= kept_a["fusion_alpha"] <= 1.0
    assert kept_a["fusion_alpha"] % 0.125 == 0 and from_kept["fusion_alpha"] == in_run["fusion_alpha"]
    assert 0 <= from_kept["fusion_alpha"] <= 1.5  # the default searches up to 1.5
    for k in ("yaw_rmse_whole_deg", "pos_rmse_whole_m"):
        assert kept_a[k] == pytest.approx(run_a[k], rel=1e-9, abs=1e-12)
    # consistency_sweep --kept: every searched scale of the same kept trajectory, its criteria and true errors
    from stages.slam import consistency_sweep

    prof = tmp_path / "profile.jsonl"
    assert consistency_sweep.main([*base5[:1], *base5[5:], "--kept", str(keep), "--method", "fastslam_grid",
                                   "--out", str(prof)]) == 0
    steps = [json.loads(line) for line in prof.read_text().splitlines()]
    assert [r["value"] for r in steps] == [0.125 * i for i in range(13)] and {r["seed"] for r in steps} == {0}
    assert steps[0]["yaw_rmse_whole_deg"] == pytest.approx(odo2["yaw_rmse_whole_deg"], rel=1e-9)  # 0: the odometry
    at = next(r for r in steps if r["value"] == from_kept["fusion_alpha"])  # the scale the fused row chose
    assert at["score"] == min(r["score"] for r in steps)
    for k in ("yaw_rmse_whole_deg", "pos_rmse_whole_m"):
        assert at[k] == pytest.approx(from_kept[k], rel=1e-9, abs=1e-12)
    # a 2.4 s run has no scans 5 s apart: nothing matched, every scale scores the cap, the fused row keeps 1
    assert from_kept["fusion_alpha"] == 1.0 and all(r["matched"] == 0 and r["score"] == 0.25 for r in steps)
    assert steps[0]["common_share"] == 0 and all(np.isnan(r["common_ms"]) for r in steps)
    assert consistency_sweep.main([*base5[:1], "--kept", str(tmp_path), "--out", str(prof)]) == 2  # nothing kept
    assert len(prof.read_text().splitlines()) == 13
    # a Hilbert filter under the informed exponent: --from-kept takes the exponent the filter ran with
    keep9, out9, out10 = tmp_path / "kept9", tmp_path / "t3_kept9.jsonl", tmp_path / "t3_fused9.jsonl"
    base9 = [str(tmp_path / "seq_a"), "--methods", "rich_slam", "--seeds", "0", "--set", "n_particles=4", "--set",
             "workers=0", "--set", "n_basis=16", "--set", "informed_exponent_information=1e-9", "--set",
             'estimate="smoothed"']
    assert table3.main([*base9, "--out", str(out9), "--keep", str(keep9)]) == 0
    assert table3.main([*base9, "--out", str(out9), "--from-kept", str(keep9)]) == 0
    assert table3.main([*base9, "--out", str(out10), "--estimates", "fused"]) == 0
    kept9 = next(r for r in map(json.loads, out9.read_text().splitlines()) if r["method"] == "rich_slam, fused")
    run9 = next(r for r in map(json.loads, out10.read_text().splitlines()) if r["method"] == "rich_slam, fused")
    assert run9["likelihood_exponent"] == 1.0
    for k in ("heading_information", "fusion_filter_sigma_deg", "yaw_rmse_whole_deg"):
        assert kept9[k] == pytest.approx(run9[k], rel=1e-9, abs=1e-12)
    # rich_slam_paper reads its trajectory as Algorithm 1 whatever the configured estimate: that is its own row,
    # and only the other estimate gets a row of its own (no copy of the plain row)
    out4 = tmp_path / "t3_paper.jsonl"
    assert table3.main([str(tmp_path / "seq_a"), "--methods", "rich_slam_paper", "--seeds", "0", "--out", str(out4),
                        "--set", "n_particles=4", "--set", "workers=0", "--set", "n_basis=16",
                        "--estimates", "best_per_scan,weighted_mean"]) == 0
    rows4 = [json.loads(line) for line in out4.read_text().splitlines()]
    assert [r["method"] for r in rows4] == ["rich_slam_paper, weighted_mean", "rich_slam_paper"]
    with pytest.raises(SystemExit):
        table3.main([*args3[:-1], "mean"])
    png = tmp_path / "t3.png"
    assert table3.main(["--table", str(out), "--figure", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not list(tmp_path.glob("*.tmp.png"))
    # --labels keeps only the named rows (the table and the figure); a label no row has is a one-line error
    capsys.readouterr()
    assert table3.main(["--table", str(out), "--labels", "fastslam_grid"]) == 0
    printed = capsys.readouterr().out
    assert "| fastslam_grid |" in printed and "| odometry |" not in printed
    assert table3.main(["--table", str(out), "--labels", "odometry;rich_slam, fused"]) == 2
    assert "no row is labelled 'rich_slam, fused'" in capsys.readouterr().err
