"""Fault probes: 50 kinds of bad input against the installed ``pipeline`` command, one verdict line each.

Usage: ``python -m benchmarks.fault_probe [--keep DIR] [-k SUBSTRING]``. Each probe runs the command line a user
would type on a damaged log, parameter, run folder, map file or machine state, and checks what a user needs:
the exit code (0 for what should run, 2 for a user error, 130 for Ctrl-C), a one-line message without a
traceback, and that nothing was lost (the previous result intact, no temporary folders, the lock released).
Prints ``OK`` or ``FAIL <why>`` per probe and exits 1 when any failed. The full-disk probe needs root (a tmpfs).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: the slam settings of the prepared runs (small, so the probes stay fast)
FEW = ("--set", "slam.n_particles=20", "--set", 'slam.methods=["rich_slam"]')


@dataclass
class Ran:
    code: int
    out: str
    err: str
    seconds: float

    @property
    def last(self) -> str:
        lines = [ln for ln in self.err.strip().splitlines() if ln.strip()]
        return lines[-1] if lines else ""


class Failed(Exception):
    pass


class Lab:
    """The probes' shared material: a short simulated log, a finished run of it, helpers."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.env = {**os.environ, "COLUMNS": "250", "RADAR_PIPELINE_RUNS": str(root / "default_runs")}
        self.runs = root / "runs"
        self.bag = root / "short.bag"  # a 5 s simulated ColoRadar log (sequence "short")
        self.radar_imu = root / "radar_imu.bag"  # the same without lidar, ground truth and tf
        self.seq = "radar_imu"

    def cli(self, *args: str, timeout: float = 180) -> Ran:
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                           env=self.env, timeout=timeout)
        return Ran(r.returncode, r.stdout, r.stderr, time.perf_counter() - t0)

    def expect(self, r: Ran, code: int, *needles: str) -> None:
        if "Traceback" in r.err:
            raise Failed(f"traceback: {r.err.strip().splitlines()[-1][:160]}")
        if r.code != code:
            raise Failed(f"exit {r.code}, expected {code}: {r.last[:200]}")
        if code == 2 and not r.last.startswith("error:"):
            raise Failed(f"last line is not a one-line error: {r.last[:200]}")
        text = r.err + r.out
        for n in needles:
            if n not in text:
                raise Failed(f"'{n}' not in the output: {r.last[:200]}")

    def bad_log(self, name: str, make: Callable[[Path, Path], object]) -> Path:
        path = self.root / name
        if not path.exists():
            make(self.bag, path)
        return path

    def intact(self, runs: Path, seq: str, stage: str, manifest_before: str) -> None:
        from pipeline.store import RunStore

        store = RunStore(runs, seq)
        if store.manifest_path(stage).read_text() != manifest_before:
            raise Failed(f"the previous '{stage}' result was replaced")
        damage = store.damage(stage, checksums=True)
        if damage:
            raise Failed(f"the previous '{stage}' result is damaged: {damage}")
        if list(store.seq_dir.glob(".tmp-*")):
            raise Failed("a temporary folder was left behind")
        with store.lock():
            pass


# -- the probes ---------------------------------------------------------------------------------------------------
PROBES: list[tuple[str, Callable[[Lab], None]]] = []


def probe(name: str) -> Callable[[Callable[[Lab], None]], Callable[[Lab], None]]:
    def register(fn: Callable[[Lab], None]) -> Callable[[Lab], None]:
        PROBES.append((name, fn))
        return fn

    return register


def _src(lab: Lab, path: Path, *more: str, stage: str = "ingest") -> Ran:
    return lab.cli("run", stage, "--source", str(path), "--runs-dir", str(lab.root / "probe_runs"), *more)


@probe("log: truncated bag")
def _truncated(lab: Lab) -> None:
    p = lab.root / "truncated.bag"
    p.write_bytes(lab.bag.read_bytes()[: lab.bag.stat().st_size // 2])
    lab.expect(_src(lab, p), 2, "truncated.bag")


@probe("log: random bytes named .bag")
def _random(lab: Lab) -> None:
    p = lab.root / "random.bag"
    p.write_bytes(np.random.default_rng(0).integers(0, 256, 100_000, dtype=np.uint8).tobytes())
    lab.expect(_src(lab, p), 2, "random.bag")


@probe("log: empty file")
def _empty_file(lab: Lab) -> None:
    p = lab.root / "empty.bag"
    p.write_bytes(b"")
    lab.expect(_src(lab, p), 2, "empty.bag")


@probe("log: unknown file type")
def _unknown_type(lab: Lab) -> None:
    p = lab.root / "log.txt"
    p.write_text("not a log\n")
    lab.expect(_src(lab, p), 2)


@probe("log: path does not exist")
def _no_path(lab: Lab) -> None:
    lab.expect(_src(lab, lab.root / "nowhere.bag"), 2, "nowhere.bag")


@probe("log: empty folder as source")
def _empty_folder(lab: Lab) -> None:
    d = lab.root / "empty_folder"
    d.mkdir(exist_ok=True)
    lab.expect(_src(lab, d), 2)


@probe("log: no radar topic")
def _no_radar(lab: Lab) -> None:
    from simulator import log_faults, rig

    p = lab.bad_log("imu_only.bag", lambda s, d: log_faults.drop_topics(s, d, [rig.TF_STATIC_TOPIC, rig.IMU_TOPIC]))
    lab.expect(_src(lab, p), 2, "radar")


@probe("log: no IMU topic (coloradar profile needs it)")
def _no_imu(lab: Lab) -> None:
    from simulator import log_faults, rig

    p = lab.bad_log("radar_only.bag",
                    lambda s, d: log_faults.drop_topics(s, d, [rig.TF_STATIC_TOPIC, rig.RADAR_TOPIC]))
    lab.expect(_src(lab, p), 2, "imu")


@probe("log: radar + IMU only, default profile, runs to odometry")
def _radar_imu(lab: Lab) -> None:
    lab.expect(_src(lab, lab.radar_imu, stage="odometry"), 0, "no lidar topic")


@probe("log: every radar scan NaN")
def _nan(lab: Lab) -> None:
    from simulator import log_faults

    p = lab.bad_log("nan.bag", lambda s, d: log_faults.radar_points(s, d, "nan"))
    lab.expect(_src(lab, p), 2, "empty or hold only NaN")


@probe("log: every radar scan empty")
def _empty_scans(lab: Lab) -> None:
    from simulator import log_faults

    p = lab.bad_log("empty_scans.bag", lambda s, d: log_faults.radar_points(s, d, "empty"))
    lab.expect(_src(lab, p), 2, "empty or hold only NaN")


@probe("clock: radar jumps +2 h, IMU does not")
def _radar_jump(lab: Lab) -> None:
    from simulator import log_faults, rig

    p = lab.bad_log("radar_jump.bag", lambda s, d: log_faults.clock_jump(s, d, 2.0, 7200.0, [rig.RADAR_TOPIC]))
    lab.expect(_src(lab, p, stage="odometry"), 2, "no radar points for 7200", "ingest.clock.max_gap_s")


@probe("clock: every stream pauses 2 h")
def _pause(lab: Lab) -> None:
    from simulator import log_faults

    p = lab.bad_log("pause.bag", lambda s, d: log_faults.pause_all(s, d, 2.0, 7200.0))
    lab.expect(_src(lab, p, stage="odometry"), 2, "7200", "ingest.clock.max_gap_s")


@probe("clock: IMU jumps +2 h, radar does not")
def _imu_jump(lab: Lab) -> None:
    from simulator import log_faults, rig

    p = lab.bad_log("imu_jump.bag", lambda s, d: log_faults.clock_jump(s, d, 2.0, 7200.0, [rig.IMU_TOPIC]))
    lab.expect(_src(lab, p, stage="odometry"), 2, "IMU samples")


@probe("log: a radar topic that is not in the log")
def _wrong_topic(lab: Lab) -> None:
    lab.expect(_src(lab, lab.bag, "--set", "ingest.topics.radar=/nope"), 2, "/nope")


@probe("profile: unknown dataset profile")
def _unknown_profile(lab: Lab) -> None:
    lab.expect(_src(lab, lab.bag, "--dataset", "no_such_profile"), 2, "no_such_profile")


@probe("profile: malformed profile file")
def _bad_profile(lab: Lab) -> None:
    p = lab.root / "bad_profile.toml"
    p.write_text("required = [radar\n")
    lab.expect(_src(lab, lab.bag, "--dataset", str(p)), 2, "bad_profile.toml")


@probe("params: slam.n_particles=10000000 (above its bound)")
def _too_many(lab: Lab) -> None:
    lab.expect(_src(lab, lab.radar_imu, "--set", "slam.n_particles=10000000", stage="slam"), 2, "less than or equal")


@probe("params: slam.n_particles=true (a bool for a number)")
def _bool(lab: Lab) -> None:
    lab.expect(_src(lab, lab.radar_imu, "--set", "slam.n_particles=true", stage="slam"), 2,
               "a bool where a number is expected")


@probe("params: a run that cannot fit in memory is refused before it starts")
def _memory(lab: Lab) -> None:
    r = _src(lab, lab.radar_imu, "--set", "slam.n_particles=100000", "--set", "slam.map.n_basis=4096", stage="slam")
    lab.expect(r, 2, "of memory", "slam.n_particles=100000")


#: command-line mistakes on a registered sequence: (name, --set or other arguments, words the error must hold)
STATUS_MISTAKES: list[tuple[str, tuple[str, ...], str]] = [
    ("params: slam.n_particles=abc", ("--set", "slam.n_particles=abc"), "slam.n_particles"),
    ("params: unknown parameter", ("--set", "slam.n_particle=5"), "did you mean"),
    ("params: unknown stage in --set", ("--set", "slma.n_particles=5"), "unknown stage"),
    ("params: --set without '='", ("--set", "slam.n_particles"), "STAGE.PARAM=VALUE"),
    ("params: voxel.resolution=0", ("--set", "voxel.resolution=0"), "voxel.resolution"),
    ("workflow: unknown name", ("--workflow", "no_such_flow"), "no_such_flow"),
]


def _status_mistake(args: tuple[str, ...], needle: str) -> Callable[[Lab], None]:
    def check(lab: Lab) -> None:
        lab.expect(lab.cli("status", "--seq", "demo", *args), 2, needle)

    return check


for _name, _args, _needle in STATUS_MISTAKES:
    probe(_name)(_status_mistake(_args, _needle))


@probe("sequence: unknown name")
def _unknown_seq(lab: Lab) -> None:
    lab.expect(lab.cli("status", "--seq", "demoo"), 2, "demoo")


@probe("workflow: malformed TOML file")
def _bad_workflow(lab: Lab) -> None:
    p = lab.root / "bad_flow.toml"
    p.write_text("[workflow\nstages = 3\n")
    lab.expect(lab.cli("status", "--seq", "demo", "--workflow", str(p)), 2, "bad_flow.toml")


@probe("stage: unknown name")
def _unknown_stage(lab: Lab) -> None:
    lab.expect(lab.cli("run", "slma", "--seq", "demo", "--runs-dir", str(lab.runs)), 2, "did you mean")


@probe("run store: --runs-dir is a file")
def _runs_is_file(lab: Lab) -> None:
    p = lab.root / "a_file"
    p.write_text("")
    lab.expect(lab.cli("run", "ingest", "--seq", "demo", "--runs-dir", str(p)), 2, "is a file")


@probe("run store: --runs-dir under a file")
def _runs_under_file(lab: Lab) -> None:
    p = lab.root / "a_file"
    p.write_text("")
    lab.expect(lab.cli("run", "ingest", "--seq", "demo", "--runs-dir", str(p / "runs")), 2, "cannot write there")


@probe("run store: the sequence lock is held by another process")
def _lock(lab: Lab) -> None:
    from pipeline.store import RunStore

    with RunStore(lab.runs, lab.seq).lock():
        r = lab.cli("run", "odometry", "--source", str(lab.radar_imu), "--runs-dir", str(lab.runs))
    lab.expect(r, 2, "being run by another process")


def _damaged(lab: Lab, how: Callable[[Path], object]) -> None:
    from pipeline.store import RunStore

    store = RunStore(lab.runs, lab.seq)
    how(store.stage_dir("odometry") / "odometry.parquet")
    r = lab.cli("run", "odometry", "--source", str(lab.radar_imu), "--runs-dir", str(lab.runs))
    lab.expect(r, 0, "odometry  running")
    if store.damage("odometry", checksums=True) is not None:
        raise Failed("the rerun result is damaged too")


@probe("artifact: truncated inside the run folder")
def _truncated_artifact(lab: Lab) -> None:
    def cut(p: Path) -> None:
        os.truncate(p, p.stat().st_size // 2)

    _damaged(lab, cut)


@probe("artifact: one byte changed (same size)")
def _flipped_artifact(lab: Lab) -> None:
    def flip(p: Path) -> None:
        b = bytearray(p.read_bytes())
        b[len(b) // 2] ^= 0xFF
        p.write_bytes(bytes(b))

    _damaged(lab, flip)


@probe("artifact: manifest.json garbage")
def _bad_manifest(lab: Lab) -> None:
    _damaged(lab, lambda p: (p.parent / "manifest.json").write_text("{not json"))


@probe("artifact: an artifact file deleted")
def _deleted_artifact(lab: Lab) -> None:
    _damaged(lab, lambda p: p.unlink())


@probe("run store: leftovers of an interrupted commit (.tmp-, .old-)")
def _leftovers(lab: Lab) -> None:
    from pipeline.store import RunStore

    store = RunStore(lab.runs, lab.seq)
    (store.seq_dir / ".tmp-odometry-deadbeef").mkdir()
    os.rename(store.stage_dir("odometry"), store.seq_dir / ".old-odometry-cafecafe")
    r = lab.cli("run", "odometry", "--source", str(lab.radar_imu), "--runs-dir", str(lab.runs))
    lab.expect(r, 0, "restored the previous result", "odometry  cached")


def _interrupt(lab: Lab, sig: int, code: int) -> None:
    from pipeline.store import RunStore

    store = RunStore(lab.runs, lab.seq)
    before = store.manifest_path("slam").read_text()
    cmd = [sys.executable, "-m", "pipeline", "run", "slam", "--force", "--source", str(lab.radar_imu), "--runs-dir",
           str(lab.runs), "--set", "slam.n_particles=40", "--set", 'slam.methods=["rich_slam"]']
    with subprocess.Popen(cmd, cwd=ROOT, env=lab.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as p:
        assert p.stderr is not None
        for line in p.stderr:
            if line.startswith("slam") and "running" in line:
                break
        time.sleep(1.0)
        p.send_signal(sig)
        p.wait(timeout=60)
        err = p.stderr.read()
    if p.returncode not in (code, -sig):
        raise Failed(f"exit {p.returncode}, expected {code}: {err.strip()[-200:]}")
    if "Traceback" in err:
        raise Failed(f"traceback: {err[err.index('Traceback'):][:300]}")
    if sig == signal.SIGKILL:  # no chance to clean up: the next run repairs the folder and keeps the old result
        r = lab.cli("run", "slam", "--source", str(lab.radar_imu), "--runs-dir", str(lab.runs), *FEW)
        lab.expect(r, 0, "removed leftover temporary folder", "slam      cached")
    lab.intact(lab.runs, lab.seq, "slam", before)


@probe("Ctrl-C while a stage runs")
def _ctrl_c(lab: Lab) -> None:
    _interrupt(lab, signal.SIGINT, 130)


@probe("kill -9 while a stage runs")
def _kill(lab: Lab) -> None:
    _interrupt(lab, signal.SIGKILL, -9)


@probe("disk: full while a stage writes (a 2 MB tmpfs)")
def _full_disk(lab: Lab) -> None:
    mnt = lab.root / "tiny"
    mnt.mkdir(exist_ok=True)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True).returncode:
        raise Failed("SKIP: mounting a tmpfs needs root")
    try:
        runs = mnt / "runs"
        r = lab.cli("run", "odometry", "--source", str(lab.radar_imu), "--runs-dir", str(runs), timeout=120)
        lab.expect(r, 0)
        before = (runs / lab.seq / "odometry" / "manifest.json").read_text()
        r = lab.cli("run", "all", "--source", str(lab.bag), "--runs-dir", str(runs), timeout=120)
        lab.expect(r, 2, "the disk is full", "nothing was lost")
        lab.intact(runs, lab.seq, "odometry", before)
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@probe("report: --out cannot be written")
def _report_out(lab: Lab) -> None:
    p = lab.root / "a_file"
    p.write_text("")
    lab.expect(lab.cli("report", "--seqs", "short", "--runs-dir", str(lab.runs), "--out", str(p / "r.md")), 2,
               "cannot write there")


@probe("report: sequences never evaluated")
def _report_none(lab: Lab) -> None:
    lab.expect(lab.cli("report", "--seqs", lab.seq, "--runs-dir", str(lab.runs)), 2, "no evaluation results")


@probe("report: rows computed from replaced results are called stale")
def _report_stale(lab: Lab) -> None:
    r = lab.cli("run", "odometry", "--source", str(lab.bag), "--runs-dir", str(lab.runs), "--set",
                "odometry.velocity.sigma_mps=0.12")
    lab.expect(r, 0)
    lab.expect(lab.cli("report", "--seqs", "short", "--runs-dir", str(lab.runs)), 0, "stale", "rerun since")


@probe("status --source")
def _status_source(lab: Lab) -> None:
    lab.expect(lab.cli("status", "--source", str(lab.radar_imu), "--runs-dir", str(lab.runs)), 0, "odometry")


@probe("view --source (headless)")
def _view_source(lab: Lab) -> None:
    env = {k: v for k, v in lab.env.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    r = subprocess.run([sys.executable, "-m", "pipeline", "view", "--source", str(lab.radar_imu), "--runs-dir",
                        str(lab.runs)], capture_output=True, text=True, cwd=ROOT, env=env, timeout=60)
    lab.expect(Ran(r.returncode, r.stdout, r.stderr, 0), 0, "odometry.rrd")


@probe("export --source --format tum")
def _export_source(lab: Lab) -> None:
    lab.expect(lab.cli("export", "--source", str(lab.radar_imu), "--runs-dir", str(lab.runs), "--format", "tum",
                       "--out", str(lab.root / "tum")), 0, "odometry.tum")


@probe("export: unknown format")
def _export_format(lab: Lab) -> None:
    lab.expect(lab.cli("export", "--source", str(lab.radar_imu), "--runs-dir", str(lab.runs), "--format", "xyz"), 2,
               "xyz")


def _map_scene(lab: Lab, name: str, damage: Callable[[Path], None]) -> Ran:
    """A synthetic one-scene map set (folders layout), damaged, run through the voxel stage."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    d = lab.root / "maps" / name / "scene0"
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for f, n in (("radar", 2000), ("lidar_filtered", 8000), ("poses", 20), ("trajectory", 200)):
        xyz = rng.uniform(-5, 5, (n, 3))
        pq.write_table(pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}), d / f"{f}.parquet")
    damage(d)
    return lab.cli("run", "voxel", "--source", str(d.parent), "--runs-dir", str(lab.root / "map_runs"))


@probe("map: radar.parquet truncated")
def _map_truncated(lab: Lab) -> None:
    r = _map_scene(lab, "truncated", lambda d: os.truncate(d / "radar.parquet", 100))
    lab.expect(r, 2, "radar.parquet")


@probe("map: lidar_filtered.parquet without a z column")
def _map_no_z(lab: Lab) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    r = _map_scene(lab, "no_z", lambda d: pq.write_table(pa.table({"x": [0.0], "y": [0.0]}),
                                                         d / "lidar_filtered.parquet"))
    lab.expect(r, 2, "lidar_filtered.parquet")


@probe("map: poses.parquet missing")
def _map_no_poses(lab: Lab) -> None:
    lab.expect(_map_scene(lab, "no_poses", lambda d: (d / "poses.parquet").unlink()), 2, "poses")


@probe("map: radar map with NaN coordinates")
def _map_nan(lab: Lab) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    r = _map_scene(lab, "nan", lambda d: pq.write_table(pa.table({"x": [np.nan] * 5, "y": [0.0] * 5, "z": [0.0] * 5}),
                                                        d / "radar.parquet"))
    lab.expect(r, 2, "radar.parquet")


# -- driver ----------------------------------------------------------------------------------------------------------
def prepare(lab: Lab) -> None:
    from simulator import log_faults, rig, simulate_to

    simulate_to("demo", lab.bag, duration=5.0, seed=3)
    log_faults.drop_topics(lab.bag, lab.radar_imu, [rig.TF_STATIC_TOPIC, rig.IMU_TOPIC, rig.RADAR_TOPIC])
    for args in (("run", "slam", "--source", str(lab.radar_imu), *FEW),
                 ("run", "evaluate", "--source", str(lab.bag), *FEW)):
        r = lab.cli(*args, "--runs-dir", str(lab.runs), timeout=600)
        if r.code != 0:
            raise SystemExit(f"preparing the probes failed: {' '.join(args)}: {r.last}")


def main(argv: list[str]) -> int:
    keep = argv[argv.index("--keep") + 1] if "--keep" in argv else None
    only = argv[argv.index("-k") + 1] if "-k" in argv else ""
    root = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="fault_probe_"))
    root.mkdir(parents=True, exist_ok=True)
    lab = Lab(root)
    t0 = time.perf_counter()
    prepare(lab)
    print(f"prepared in {time.perf_counter() - t0:.0f} s ({root})", flush=True)
    failed = 0
    chosen = [(n, f) for n, f in PROBES if only in n]
    for i, (name, fn) in enumerate(chosen, 1):
        t = time.perf_counter()
        try:
            fn(lab)
            verdict = "OK"
        except Failed as exc:
            verdict = f"FAIL {exc}" if not str(exc).startswith("SKIP") else str(exc)
            failed += not str(exc).startswith("SKIP")
        except Exception as exc:  # a probe that breaks is a failure too
            verdict = f"FAIL {type(exc).__name__}: {exc}"
            failed += 1
        print(f"{i:2d} {name:<66} {verdict} ({time.perf_counter() - t:.1f} s)", flush=True)
    print(f"{len(chosen) - failed}/{len(chosen)} OK in {time.perf_counter() - t0:.0f} s", flush=True)
    if not keep:
        shutil.rmtree(root, ignore_errors=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
