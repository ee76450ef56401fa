"""The command line on a real (simulated) run: Ctrl-C during a stage, and exports that evo reads as printed."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from filelock import FileLock

simulator = pytest.importorskip("simulator")
ROOT = Path(__file__).resolve().parents[1]
SEQ = "clirun"
#: a short run: 6 s of the demo world, slam with few particles, the default method (the README compares it) and
#: one filter (long enough at 400 particles to be interrupted)
SLAM = ["--set", "slam.n_particles=5", "--set", "slam.map.n_basis=64",
        "--set", 'slam.methods=["odometry","radar_graph","rich_slam"]']


def cli(*args: str, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "COLUMNS": "120"}, timeout=300, **kw)  # type: ignore[call-overload]


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(runs folder, bag) with ingest .. slam finished."""
    root = tmp_path_factory.mktemp("clirun")
    bag = simulator.simulate_to(world="demo", out=root / "demo.bag", duration=6.0, seed=2, fmt="bag")
    r = cli("run", "slam", "--source", str(bag), "--seq", SEQ, "--runs-dir", str(root / "runs"), *SLAM)
    assert r.returncode == 0, r.stderr
    return root / "runs", bag


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_ctrl_c_during_a_stage_exits_130_and_keeps_the_previous_result(run: tuple[Path, Path],
                                                                        tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    shutil.copytree(run[0], runs)
    seq_dir = runs / SEQ
    before = _snapshot(seq_dir / "slam")
    # a slam run long enough to be interrupted: 400 particles (a parameter change, so slam is stale and reruns)
    proc = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "run", "slam", "--source", str(run[1]), "--seq", SEQ, "--runs-dir",
         str(runs), *SLAM, "--set", "slam.n_particles=400"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "COLUMNS": "120"},
        # the signal disposition a terminal gives (a non-interactive shell starts jobs with SIGINT ignored)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.monotonic() + 120
        while not list(seq_dir.glob(".tmp-slam-*")):  # the stage is running: it writes into its temporary folder
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert "slam      done" not in err  # it really was interrupted while running
    assert _snapshot(seq_dir / "slam") == before  # the previous result, untouched
    assert not [p.name for p in seq_dir.iterdir() if p.name.startswith((".tmp-", ".old-"))]
    assert json.loads((seq_dir / "slam" / "manifest.json").read_text())["params"]["n_particles"] == 5
    lock = FileLock(str(seq_dir / ".lock"), timeout=0)  # released: the next run can take it
    lock.acquire()
    lock.release()


def test_readme_evo_command_works_on_the_tum_export(run: tuple[Path, Path], tmp_path: Path) -> None:
    out = tmp_path / "tum"
    r = cli("export", "--seq", SEQ, "--runs-dir", str(run[0]), "--format", "tum", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert sorted(Path(p).name for p in r.stdout.split()) == ["groundtruth.tum", "odometry.tum", "radar_graph.tum",
                                                              "rich_slam.tum"]
    assert "planar estimates without z" not in r.stderr  # 3D poses: the odometry's z, roll and pitch
    odo, slam = (np.loadtxt(out / f"{n}.tum") for n in ("odometry", "radar_graph"))
    np.testing.assert_array_equal(slam[:, 3], odo[:, 3])  # the graph's height is its odometry's
    evo_ape = Path(sys.executable).with_name("evo_ape")
    if not evo_ape.exists():
        pytest.skip(f"no evo_ape beside {sys.executable} (install the dev extra)")
    # 3D, without alignment (checked against evo's Python API below)
    res = subprocess.run([str(evo_ape), "tum", "groundtruth.tum", "radar_graph.tum", "-v"], cwd=out,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    found = re.search(r"Found (\d+) of max\. (\d+) possible matching timestamps", res.stdout)
    assert found, res.stdout
    n_est = len(np.loadtxt(out / "radar_graph.tum"))
    n_gt = len(np.loadtxt(out / "groundtruth.tum"))
    # every ground-truth row is at an estimate stamp, and ground truth covers nearly all of the run
    assert int(found.group(1)) == int(found.group(2)) == n_gt and n_gt >= n_est - 2
    rmse = float(re.search(r"rmse\s+([0-9.eE+-]+)", res.stdout).group(1))  # type: ignore[union-attr]
    assert math.isfinite(rmse) and rmse > 0
    # in the plane, against evo's Python API on the same files
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(out / "groundtruth.tum"))
    est = file_interface.read_tum_trajectory_file(str(out / "radar_graph.tum"))
    ref, est = sync.associate_trajectories(ref, est)
    assert np.array_equal(ref.timestamps, est.timestamps)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    # the CLI prints 6 decimals: equal to half a unit in the last printed digit
    assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(rmse, rel=0, abs=5.0000001e-7)
    planar = subprocess.run([str(evo_ape), "tum", "groundtruth.tum", "radar_graph.tum", "--project_to_plane", "xy"],
                            cwd=out, capture_output=True, text=True, timeout=120)
    assert planar.returncode == 0, planar.stdout + planar.stderr
    planar_rmse = float(re.search(r"rmse\s+([0-9.eE+-]+)", planar.stdout).group(1))  # type: ignore[union-attr]
    assert math.isfinite(planar_rmse) and planar_rmse < rmse  # the 3D error adds the height error
    # exactly as the README prints it: aligned in the plane, at most the unaligned planar error
    readme = subprocess.run([str(evo_ape), "tum", "groundtruth.tum", "radar_graph.tum", "--align", "--project_to_plane",
                             "xy"], cwd=out, capture_output=True, text=True, timeout=120)
    assert readme.returncode == 0, readme.stdout + readme.stderr
    aligned = float(re.search(r"rmse\s+([0-9.eE+-]+)", readme.stdout).group(1))  # type: ignore[union-attr]
    assert math.isfinite(aligned) and aligned <= planar_rmse + 1e-9


def test_mcap_export_of_the_run_has_each_stamp_once(run: tuple[Path, Path], tmp_path: Path) -> None:
    from mcap.reader import make_reader

    r = cli("export", "--seq", SEQ, "--runs-dir", str(run[0]), "--format", "mcap", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    stamps: dict[str, list[int]] = {}
    with open(r.stdout.strip(), "rb") as f:
        for _schema, channel, msg in make_reader(f).iter_messages(log_time_order=False):
            stamps.setdefault(channel.topic, []).append(msg.log_time)
    odo = stamps["/trajectory/odometry"]
    assert len(odo) == len(set(odo)) and odo == sorted(odo)
    assert set(stamps) >= {"/trajectory/groundtruth", "/trajectory/odometry", "/trajectory/rich_slam"}
    assert "/trajectory/slam" not in stamps  # trajectory.parquet is rich_slam's copy: not a second channel


def _tum_stamps(path: Path) -> np.ndarray:
    """The stamps of a TUM file in integer nanoseconds, as written (``sec.nanoseconds``)."""
    return np.array([int(sec) * 1_000_000_000 + int(ns.ljust(9, "0"))
                     for sec, ns in (line.split()[0].split(".") for line in path.read_text().splitlines())], np.int64)


def _evo_ape_rmse(folder: Path, est: str, *args: str) -> float:
    res = subprocess.run([str(Path(sys.executable).with_name("evo_ape")), "tum", "groundtruth.tum", est, *args],
                         cwd=folder, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    return float(re.search(r"rmse\s+([0-9.eE+-]+)", res.stdout).group(1))  # type: ignore[union-attr]


def test_both_alignments_equal_evo_on_the_tum_export(run: tuple[Path, Path], tmp_path: Path) -> None:
    """The evaluate stage's errors under both SE(2) alignments against evo on the exported TUM files.

    Exact by construction: the export writes the ground truth at the estimates' stamps, so evo pairs every pose
    with its reference and our function, given the files' own poses (ground-truth times = estimate times),
    interpolates nothing. evo's Python API with the poses projected to the plane before its Umeyama alignment is
    an SE(2) alignment on xy: equal to ours to 1e-6 (the files' 9 decimals). ``evo_ape --align
    --project_to_plane xy`` aligns in SE(3) on x, y, z first and projects after (evo's ``main_ape.ape``): on
    planar copies of the files (z = 0, yaw only) it equals ours to its 6 printed digits; on the files as
    exported the height errors tilt its fit, a difference bounded below."""
    import copy

    pytest.importorskip("evo")
    if not Path(sys.executable).with_name("evo_ape").exists():
        pytest.skip(f"no evo_ape beside {sys.executable} (install the dev extra)")
    from evo.core import metrics, sync
    from evo.core.trajectory import Plane
    from evo.main_ape import ape
    from evo.tools import file_interface

    from schemas import read_artifact
    from stages.evaluate.stage import STAGE, EvaluateParams
    from stages.evaluate.trajectory import evaluate_trajectory, quat_to_yaw
    from tests.test_evaluate_fixtures import make_context

    out = tmp_path / "tum"
    r = cli("export", "--seq", SEQ, "--runs-dir", str(run[0]), "--format", "tum", "--out", str(out))
    assert r.returncode == 0, r.stderr
    n_align = 20  # the paper's protocol on the first 20 of the 6 s run's ~59 frames: the two alignments differ
    p = EvaluateParams(sections=["trajectory"], trajectory={"n_align": n_align})  # type: ignore[arg-type]
    ctx = make_context(run[0], SEQ, "evaluate", p, list(STAGE.input_stages(p)), tmp_path / "evaluate")
    STAGE.run(ctx)
    ctx.close()
    stage = {(m["method"], m["metric"]): m["value"]
             for m in read_artifact(tmp_path / "evaluate" / "metrics.parquet", "metrics").to_pylist()}
    gt = np.loadtxt(out / "groundtruth.tum")
    t_gt = _tum_stamps(out / "groundtruth.tum")
    planar = tmp_path / "planar"
    planar.mkdir()

    def flatten(src: Path) -> None:  # z = 0 and the yaw alone: what --project_to_plane xy makes of a pose
        a = np.loadtxt(src)
        yaw = quat_to_yaw(*a[:, 4:8].T)
        a[:, 3], a[:, 4], a[:, 5], a[:, 6], a[:, 7] = 0.0, 0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)
        lines = src.read_text().splitlines()
        (planar / src.name).write_text("".join(f"{line.split()[0]} " + " ".join(f"{v:.9f}" for v in row[1:]) + "\n"
                                               for line, row in zip(lines, a, strict=True)))

    flatten(out / "groundtruth.tum")
    for method in ("odometry", "rich_slam"):
        est = np.loadtxt(out / f"{method}.tum")
        t_est = _tum_stamps(out / f"{method}.tum")
        ref0 = file_interface.read_tum_trajectory_file(str(out / "groundtruth.tum"))
        est0 = file_interface.read_tum_trajectory_file(str(out / f"{method}.tum"))
        ref0, est0 = sync.associate_trajectories(ref0, est0, max_diff=1e-6)
        assert est0.num_poses == len(gt) >= 50  # every ground-truth row paired with the estimate at its stamp
        args = (t_est, est[:, 1:3], quat_to_yaw(*est[:, 4:8].T), t_gt, gt[:, 1:3], quat_to_yaw(*gt[:, 4:8].T))
        for n, pos_key, yaw_key in ((None, "ate_pos_rmse_whole_m", "ate_yaw_rmse_whole_deg"),
                                    (n_align, "ate_pos_rmse_m", "ate_yaw_rmse_deg")):
            ours = evaluate_trajectory(*args, n_align=n)
            assert ours.n_matched == len(gt)
            evo = []
            for rel in (metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_deg):
                ref, e = copy.deepcopy(ref0), copy.deepcopy(est0)
                ref.project(Plane.XY)
                e.project(Plane.XY)
                evo.append(ape(ref, e, rel, align=True, n_to_align=-1 if n is None else n).stats["rmse"])
            assert ours.pos_rmse_m == pytest.approx(evo[0], rel=1e-6), (method, n)
            assert ours.yaw_rmse_deg == pytest.approx(evo[1], rel=1e-6), (method, n)
            # the stage, on the ingested ground truth (interpolated at the estimates' stamps as the export does)
            assert stage[(method, pos_key)] == pytest.approx(evo[0], rel=1e-6), (method, n)
            assert stage[(method, yaw_key)] == pytest.approx(evo[1], rel=1e-6), (method, n)
        whole = evaluate_trajectory(*args, n_align=None)
        first = evaluate_trajectory(*args, n_align=n_align)
        assert abs(whole.pos_rmse_m - first.pos_rmse_m) > 1e-3  # not one number twice
        assert whole.pos_rmse_m <= first.pos_rmse_m  # the whole-trajectory fit minimises the position RMSE
        # the command line on planar copies: exactly the whole-trajectory SE(2) alignment
        flatten(out / f"{method}.tum")
        cmd = ("--align", "--project_to_plane", "xy")
        assert _evo_ape_rmse(planar, f"{method}.tum", *cmd) == pytest.approx(whole.pos_rmse_m, rel=1e-5, abs=1e-6)
        assert _evo_ape_rmse(planar, f"{method}.tum", *cmd, "--pose_relation", "angle_deg") == pytest.approx(
            whole.yaw_rmse_deg, rel=1e-5, abs=1e-6)
        # on the files as exported: SE(3) on x, y, z, then projected; the height errors tilt the fit a little
        assert _evo_ape_rmse(out, f"{method}.tum", *cmd) == pytest.approx(whole.pos_rmse_m, abs=0.01)
        assert _evo_ape_rmse(out, f"{method}.tum", *cmd, "--pose_relation", "angle_deg") == pytest.approx(
            whole.yaw_rmse_deg, abs=0.1)
