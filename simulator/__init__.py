"""ColoRadar-format log simulator: built-in worlds -> ROS1 bag or extracted folder, plus a ground-truth sidecar.

Entry points:
- :func:`generate_sequence` writes a registered simulated sequence into the data cache on first use
  (atomically, under a file lock, with a progress bar);
- :func:`simulate_to` backs ``pipeline simulate --world NAME --out PATH``.

The formats written are documented, with the evidence, in ``data/datasets/coloradar.md``.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from core.errors import UserError

if TYPE_CHECKING:
    from rich.console import Console

    from simulator.world import World


class SimulatedSpec(Protocol):
    """What :func:`generate_sequence` reads of a registered simulated sequence (``sources.sequence.SequenceInfo``
    satisfies it; the simulator does not import the registry, so the two layers stay acyclic)."""

    @property
    def name(self) -> str: ...
    @property
    def world(self) -> str | None: ...
    @property
    def duration(self) -> float: ...
    @property
    def seed(self) -> int: ...
    @property
    def format(self) -> str: ...

    def simulated_path(self) -> Path: ...

FORMATS = ("bag", "folder")
MAX_DURATION_S = 3600.0
#: ``pipeline simulate``'s length for a world file when ``--duration`` is not given, seconds
DEFAULT_DURATION_S = 60.0


def cache_fingerprint(world: str) -> dict[str, str]:
    """Hashes of the simulator's code and of the world file: a cached simulated sequence made by other code
    or from another version of the world is not reused (``SequenceInfo.simulated_path`` includes them)."""
    from simulator.world import worlds_dir

    code = hashlib.sha256()
    for f in sorted(Path(__file__).parent.glob("*.py")):
        code.update(f.name.encode())
        code.update(f.read_bytes())
    out = {"simulator": code.hexdigest()[:12]}
    wf = worlds_dir() / f"{world}.toml"
    if wf.is_file():
        out["world_file"] = hashlib.sha256(wf.read_bytes()).hexdigest()[:12]
    return out


def sidecar_path(log: Path) -> Path:
    """Where the ground-truth sidecar of a log lives: ``X.bag`` -> ``X.sim/``, folder ``X/`` -> ``X/sim/``."""
    log = Path(log)
    if log.suffix == ".bag":
        return log.with_suffix(".sim")
    return log / "sim"


def write_run(world: World, out: Path, duration: float, seed: int, fmt: str, console: Console | None = None,
              workers: int = 2, label: str | None = None) -> dict[str, Any]:
    """Simulate ``duration`` seconds in ``world`` and write the log and its sidecar to ``out`` (not atomic)."""
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

    from simulator.sidecar import SidecarWriter
    from simulator.simulate import Simulation

    sim = Simulation(world, duration, seed, workers=workers)
    writer: Any
    if sim.handheld is not None:
        if fmt != "bag":
            raise UserError(f"{world.path}: the handheld rig writes ROS1 bags only; use --format bag")
        from simulator.handheld_bag import HandheldBagWriter

        writer = HandheldBagWriter(out, sim)
    elif fmt == "bag":
        from simulator.bagwriter import BagWriter

        writer = BagWriter(out, seed, sim.imu_p)
    else:
        from simulator.folderwriter import FolderWriter

        writer = FolderWriter(out)
    side = SidecarWriter(sidecar_path(out), sim)
    t0 = time.perf_counter()
    progress = Progress(TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(), TimeElapsedColumn(),
                        console=console, transient=False, disable=console is None)
    with progress:
        task = progress.add_task(label or f"simulating {world.spec.name} ({fmt}, {duration:g} s)", total=sim.n_windows)
        for w in sim.windows():
            writer.add(w)
            side.add(w)
            progress.advance(task)
        writer.close()
    return side.close({"format": fmt})["stats"] | {"generation_s": time.perf_counter() - t0}


def _write_atomic(world: World, final: Path, duration: float, seed: int, fmt: str, console: Console | None,
                  label: str | None = None) -> dict[str, Any]:
    """Write into a temporary folder beside ``final``, then rename into place (the sidecar first)."""
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.parent / f".tmp-{final.name}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        target = tmp / final.name
        stats = write_run(world, target, duration, seed, fmt, console, label=label)
        if fmt == "bag":
            side = sidecar_path(final)
            if side.exists():
                shutil.rmtree(side)
            os.replace(sidecar_path(target), side)
        os.replace(target, final)
        return stats
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _check(fmt: str, duration: float) -> None:
    if fmt not in FORMATS:
        raise UserError(f"--format '{fmt}' is not supported; use one of: {', '.join(FORMATS)}")
    if not (0 < duration <= MAX_DURATION_S):
        raise UserError(f"--duration {duration:g}: must be in (0, {MAX_DURATION_S:g}] seconds")


def generate_sequence(seq: SimulatedSpec, world: World | None = None) -> Path:
    """Write the registered simulated sequence ``seq`` to ``seq.simulated_path()`` unless it is there already.

    ``world``: a world built by the caller (a ColoRadar twin, :func:`simulator.twin.twin_world`) instead of
    the world file ``seq.world``."""
    from filelock import FileLock
    from rich.console import Console

    from simulator.world import load_world

    path = seq.simulated_path()
    if path.exists():
        return path
    _check(seq.format, seq.duration)
    if world is None:
        world = load_world(seq.world or seq.name)
    path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(str(path.parent / f"{path.name}.lock")):
        if path.exists():  # another process made it while we waited
            return path
        _write_atomic(world, path, seq.duration, seq.seed, seq.format, Console(stderr=True),
                      label=f"simulating sequence '{seq.name}' ({seq.format}, {seq.duration:g} s)")
    return path


def simulate_to(world: str | World, out: Path, duration: float | None = None, seed: int = 0, fmt: str = "bag",
                console: Console | None = None) -> Path:
    """Write a simulated ColoRadar-format log (``fmt`` 'bag' or 'folder') to ``out``; returns the log's path.

    ``world``: a world file's name or path, or a built world (a ColoRadar twin, :func:`simulator.twin.twin_world`).
    ``duration``: seconds, by default 60 for a world file and the whole recorded path for a twin (which cannot
    run past the end of its path)."""
    from simulator.world import load_world

    built = None if isinstance(world, str | Path) else world
    limit = getattr(built, "duration", None)  # a twin's recorded path ends
    if duration is None:
        duration = float(limit) if limit is not None else DEFAULT_DURATION_S
    if built is not None and limit is not None and duration > limit + 1e-9:
        raise UserError(f"--duration {duration:g}: the twin '{built.spec.name}' follows a recorded path of "
                        f"{limit:g} s; ask for {limit:g} s or less")
    _check(fmt, duration)
    out = Path(out)
    if fmt == "bag" and out.suffix != ".bag":
        out = out.with_name(out.name + ".bag")
    if out.exists() or (fmt == "bag" and sidecar_path(out).exists()):
        raise UserError(f"--out {out} already exists; remove it or choose another path")
    w = load_world(world) if isinstance(world, str | Path) else world
    _write_atomic(w, out, duration, seed, fmt, console)
    return out
