"""The slam stage's adapter on synthetic artifacts: frames, outputs, schemas, Rerun paths, map quality."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from rich.console import Console

from core import hilbert_map as hm
from core.errors import UserError
from core.recording import entity_paths_in
from core.stage import StageContext
from pipeline.sequences import SequenceInfo
from schemas.io import read_artifact, write_artifact
from stages.odometry.stage import cov_columns
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


def test_stage_writes_every_method_and_artifact(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    inp = _write_inputs(tmp_path / "in", 30)
    from stages.slam import stage as slam_stage

    for name, value in (("MAP_SNAPSHOTS", 2), ("STATS_EVERY", 4), ("GRID_SPACING", 1.0)):
        monkeypatch.setattr(slam_stage, name, value)
    ctx = _ctx(tmp_path / "out", inp["dirs"], method="rich_slam", n_particles=6, map={"n_basis": 64}, workers=0,
               methods=["odometry", "fastslam_grid", "rich_slam", "rich_slam_no_et", "rich_slam_mean_only"])
    _run(ctx)
    out = tmp_path / "out"
    for m in ("odometry", "fastslam_grid", "rich_slam", "rich_slam_no_et", "rich_slam_mean_only"):
        t = read_artifact(out / f"trajectory_{m}.parquet", "trajectory")
        assert t.num_rows == 30 and np.all(np.isfinite(t["x"].to_numpy()))
    main = read_artifact(out / "trajectory.parquet", "trajectory")
    np.testing.assert_array_equal(main["x"].to_numpy(), pq.read_table(out / "trajectory_rich_slam.parquet")["x"])
    odo = read_artifact(out / "trajectory_odometry.parquet", "trajectory")
    np.testing.assert_array_equal(odo["x"].to_numpy(), pq.read_table(inp["dirs"]["odometry"] / "odometry.parquet")["x"])
    post = read_artifact(out / "map_posterior.parquet", "map_posterior").to_pylist()[0]
    assert post["M"] == 64 and len(post["theta"]) == 64 and len(post["cov"]) == 64 * 64
    assert post["lengthscale_m"] == 2.0 and post["basis_kind"] == "tensor"
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
    _run(_ctx(tmp_path / "out", inp["dirs"], method="odometry", methods=["odometry"], workers=0))
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


def test_zero_motion_noise_reproduces_odometry(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from stages.slam import methods
    from stages.slam.rbpf import MotionNoise

    monkeypatch.setattr(methods, "NOISE", MotionNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    inp = _write_inputs(tmp_path / "in", 15)
    _run(_ctx(tmp_path / "out", inp["dirs"], n_particles=4, map={"n_basis": 36},
              method="rich_slam", methods=["fastslam_grid", "rich_slam"], workers=0))
    odo = pq.read_table(inp["dirs"]["odometry"] / "odometry.parquet")
    for m in ("fastslam_grid", "rich_slam"):
        t = pq.read_table(tmp_path / "out" / f"trajectory_{m}.parquet")
        for c in ("x", "y", "yaw"):
            np.testing.assert_allclose(t[c].to_numpy(), odo[c].to_numpy(), atol=1e-9)
        np.testing.assert_allclose(t["n_eff"].to_numpy(), 4.0)


def test_bad_inputs_give_one_line_errors(tmp_path: Path) -> None:
    inp = _write_inputs(tmp_path / "in", 5)
    (inp["dirs"]["ingest"] / "calibration.json").write_text(json.dumps({"base_from_lidar": np.eye(4).tolist()}))
    with pytest.raises(UserError, match="base_from_radar"):
        _run(_ctx(tmp_path / "out", inp["dirs"], methods=["odometry"], method="odometry"))
    with pytest.raises(ValueError, match="perfect square"):
        SlamParams(map={"n_basis": 250})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"needs backend = torch"):
        SlamParams(backend="numpy", device="cuda")


def test_table3_runner_is_resumable_and_tabulates(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m experiments.slam_table3``: one row per (sequence, method, seed), finished rows skipped."""
    from experiments import slam_table3 as table3

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
    # --keep saves each row's trajectory (written to a temporary name, then renamed)
    keep = tmp_path / "kept"
    assert table3.main([str(tmp_path / "seq_a"), "--methods", "fastslam_grid,radar_graph", "--seeds", "0",
                        "--set", "n_particles=4", "--set", "workers=0", "--out", str(tmp_path / "t3_kept.jsonl"),
                        "--keep", str(keep)]) == 0
    kept = list((keep / "seq_a").glob("*_seed0_*.npz"))
    assert len(kept) == 2 and not list(keep.rglob("*.tmp.npz"))
    graph = next(json.loads(r) for r in (tmp_path / "t3_kept.jsonl").read_text().splitlines()
                 if json.loads(r)["method"] == "radar_graph")
    assert graph["keyframes"] >= 2 and graph["loops_proposed"] >= graph["loops_accepted"]
    with pytest.raises(SystemExit) as info:  # argparse's usage error: exit 2
        table3.main([str(tmp_path / "seq_a"), "--methods", "rich_slam_refined", "--out", str(out)])
    assert info.value.code == 2
