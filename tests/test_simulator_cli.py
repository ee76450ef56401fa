"""Worlds, trajectories, `pipeline simulate`, and built-in sequences generated once into the cache."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tomllib

from core.errors import UserError
from pipeline.sequences import SequenceInfo, load_registry

ROOT = Path(__file__).resolve().parents[1]
WORLDS = ("demo", "hallway_loop", "outdoor_open", "cluttered_lab")


def _cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, **(env or {}), "COLUMNS": "200"}, timeout=300)


def test_builtin_worlds_and_registered_sequences() -> None:
    from simulator.world import available_worlds, load_world

    assert set(WORLDS) <= set(available_worlds())
    reg = load_registry()
    sims = {s.world for s in reg.values() if s.kind == "simulated"}
    assert set(WORLDS) <= sims
    for name in WORLDS:
        w = load_world(name)
        sc = w.scene
        assert len(sc.seg_a) >= 1 and (len(sc.cyl_r) + len(sc.rect_z)) >= 3, name
        assert (sc.ceiling is None) == (name == "outdoor_open"), name


@pytest.mark.parametrize("name", WORLDS)
def test_trajectories_are_smooth_loops_with_revisits(name: str) -> None:
    from simulator.trajectory import Trajectory
    from simulator.world import load_world

    w = load_world(name)
    seq = next(s for s in load_registry().values() if s.world == name)
    tr = Trajectory(w.spec.trajectory, seq.duration)
    t = np.arange(0, seq.duration, 1 / 300)
    st = tr.state(t)
    speed = np.linalg.norm(st.velocity[:, :2], axis=1)
    moving = t > w.spec.trajectory.start_ramp
    assert speed[0] < 1e-6 and 0.4 < speed[moving].min() and speed[moving].max() < 1.6, name
    assert np.abs(np.diff(st.yaw_rate)).max() < 0.01, name  # yaw rate is continuous at 300 Hz
    assert np.abs(st.yaw_rate).max() < 1.5, name
    assert np.ptp(st.position[:, 2]) < 0.2, name  # 2D motion with small height changes
    travelled = np.sum(np.linalg.norm(np.diff(st.position[:, :2], axis=0), axis=1))
    assert travelled > 1.05 * tr.path.length, name  # the loop is closed and revisited
    # velocity and acceleration are the derivatives of the position
    dt = 1 / 300
    assert np.abs(np.gradient(st.position, dt, axis=0)[2:-2] - st.velocity[2:-2]).max() < 1e-3
    assert np.abs(np.gradient(st.velocity, dt, axis=0)[2:-2] - st.acceleration[2:-2]).max() < 2e-2


def test_bad_world_files_are_user_errors(tmp_path: Path) -> None:
    from simulator.world import load_world

    with pytest.raises(UserError, match="unknown world 'dmeo'; did you mean 'demo'"):
        load_world("dmeo")
    text = (ROOT / "data/worlds/demo.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('material = "drywall"', 'material = "cheese"', 1))
    with pytest.raises(UserError, match=r"bad\.toml: .*unknown material"):
        load_world(bad)
    doc = tomllib.loads(text)
    bad.write_text(text.replace(f"waypoints = {doc['trajectory']['waypoints']}".replace("'", ""), "x = 1"))
    with pytest.raises(UserError, match=r"bad\.toml"):
        load_world(bad)
    bad.write_text(text.replace("[[pillars]]\ncenter = [8.0, 4.0]", "[[pillars]]\ncenter = [6.5, -4.75]"))
    with pytest.raises(UserError, match=r"bad\.toml: the trajectory comes within 0\.\d\d m of an obstacle"):
        load_world(bad)


def test_pipeline_simulate_command(tmp_path: Path) -> None:
    out = tmp_path / "run1"
    r = _cli("simulate", "--world", "outdoor_open", "--out", str(out), "--duration", "1", "--format", "folder",
             "--seed", "5")
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()) == out
    assert (out / "single_chip/pointclouds/timestamps.txt").exists() and (out / "sim/meta.json").exists()
    r = _cli("simulate", "--world", "outdoor_open", "--out", str(out), "--duration", "1", "--format", "folder")
    assert r.returncode == 2 and "already exists" in r.stderr and "Traceback" not in r.stderr
    r = _cli("simulate", "--world", "demo", "--out", str(tmp_path / "x"), "--format", "mcap")
    assert r.returncode == 2 and "--format 'mcap' is not supported" in r.stderr
    r = _cli("simulate", "--world", "atlantis", "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "unknown world 'atlantis'" in r.stderr
    r = _cli("simulate", "--world", "demo", "--out", str(tmp_path / "b"), "--duration", "0.5")
    assert r.returncode == 0 and Path(r.stdout.strip()) == tmp_path / "b.bag"
    assert (tmp_path / "b.sim" / "radar_labels.parquet").exists()
    assert not list(tmp_path.glob(".tmp-*"))


_GEN = """
import sys
from pipeline.sequences import SequenceInfo
from simulator import generate_sequence
seq = SequenceInfo(name="tiny", kind="simulated", world="demo", duration=1.0, seed=2, format=sys.argv[1])
print(generate_sequence(seq))
"""


@pytest.mark.parametrize("fmt", ["bag", "folder"])
def test_generate_sequence_once_under_a_lock(tmp_path: Path, fmt: str) -> None:
    env = {**os.environ, "RADAR_PIPELINE_CACHE": str(tmp_path / "cache")}
    procs = [subprocess.Popen([sys.executable, "-c", _GEN, fmt], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1] for o in outs]
    paths = {Path(o[0].strip().splitlines()[-1]) for o in outs}
    assert len(paths) == 1
    path = paths.pop()
    assert path.exists() and path.parent.parent == tmp_path / "cache" / "sequences"
    side = path.with_suffix(".sim") if fmt == "bag" else path / "sim"
    assert (side / "radar_labels.parquet").exists()
    # exactly one of the two processes simulated (the other found the result after the lock)
    assert sum("simulating sequence 'tiny'" in o[1] for o in outs) == 1
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".tmp-")]


def test_resolve_source_generates_on_first_use(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RADAR_PIPELINE_CACHE", str(tmp_path))
    seq = SequenceInfo(name="tiny2", kind="simulated", world="cluttered_lab", duration=0.6, seed=1, format="bag")
    assert seq.locate() is None
    p = seq.resolve_source()
    assert p == seq.simulated_path() and p.suffix == ".bag" and p.exists()
    mtime = p.stat().st_mtime_ns
    assert seq.resolve_source() == p and p.stat().st_mtime_ns == mtime


def test_cached_sequence_path_follows_simulator_code_and_world_file(monkeypatch: pytest.MonkeyPatch) -> None:
    import simulator

    seq = SequenceInfo(name="demo", kind="simulated", world="demo", duration=60.0, seed=0, format="bag")
    fp = simulator.cache_fingerprint("demo")
    assert set(fp) == {"simulator", "world_file"}
    a = seq.simulated_path()
    assert seq.simulated_path() == a
    monkeypatch.setattr(simulator, "cache_fingerprint", lambda world: {**fp, "world_file": "edited"})
    assert seq.simulated_path() != a and seq.simulated_path().name == "demo.bag"
