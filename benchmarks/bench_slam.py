"""RICH-SLAM filter speed: seconds per scan at N_p = 200, M = 256, against a numpy matrix product.

Scans come from a synthetic corridor (``stages/slam/synthetic.py``) with 6, 30 and 80 beams per
scan fired (about 10, 70 and 170 samples per scan: the filtered simulated sequences range from 15 to
270 depending on the filter's settings; the paper's regime is M > N). One RBPF step = propagate, posterior-aware weights
with the endpoint tolerance (eq. 22-30), Kalman update (eq. 15-19), selection and, when N_eff
drops, resampling. Timed over ``steps`` scans after warm-up, with the stage's defaults (map form
chosen by the cost model, 2 worker processes); s/scan is the mean (the sustained rate, resampling
steps included), the GFLOP/s the median step's.

GFLOP/s counts the dominant operations of the chosen form (``methods.step_flops``) and is compared
with ``a @ b`` on two 2048 x 2048 float64 matrices (all BLAS threads) timed in the same run. The
radar runs at 10 Hz, so real time is 0.1 s per scan. Scaling rows vary N_p and M on the medium scans;
float32 rows report their speed and their log-likelihood difference to float64.

The torch backend (``slam.backend = torch``) on the CPU runs beside numpy at each density (interleaved:
numpy, torch with 1 thread, and at medium density torch with 2 threads, which collapses on a shared
machine), when torch is installed. Its CUDA benchmark is the
separate one-command script ``python -m benchmarks.slam_cuda`` (a GPU, a few minutes).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from benchmarks.common import Result, best_time
from core import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, sample_beams
from stages.slam.methods import NOISE, choose_form, make_hilbert_maps, step_flops, weighting
from stages.slam.parallel import ParallelHilbertMaps
from stages.slam.params import MapParams, SlamParams
from stages.slam.rbpf import RBPF, odometry_increments
from stages.slam.synthetic import make_run

AREA = "slam"
FRAME_S = 0.1  # radar frame period (10 Hz)


def _matmul_rate(n: int) -> float:
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((n, n)), rng.standard_normal((n, n))
    t = best_time(lambda: a @ b, repeat=3)
    return 2 * n**3 / t / 1e9


def _scans(beams: int, steps: int) -> tuple[Any, list[BeamSamples]]:
    run = make_run(steps + 4, np.random.default_rng(1), beams_per_scan=beams, outlier_fraction=0.1)
    return run, [sample_beams(s, [0.0, 0.0], 1.0, 5.0) for s in run.scans]


def _time_filter(cfg: SlamParams, beams: int, steps: int, M: int) -> dict[str, Any]:
    """Seconds per step over ``steps`` scans after 3 warm-up steps (median, and mean with the
    resampling steps' map copies: the sustained rate), and the modelled flops."""
    run, scans = _scans(beams, steps)
    basis = hm.make_basis([20.0, 16.0], [0.0, 0.0], M)
    form = choose_form(cfg, "rich_slam", scans, M)
    maps = make_hilbert_maps(cfg, basis, "rich_slam", cfg.n_particles, form)
    u = odometry_increments(run.odometry)
    times = []
    try:
        f = RBPF(maps, run.odometry[0], cfg.n_particles, NOISE, np.random.default_rng(0))
        for i, s in enumerate(scans):
            t0 = time.perf_counter()
            f.step(u[i], s, first=i == 0)
            if i >= 3:
                times.append(time.perf_counter() - t0)
    finally:
        if isinstance(maps, ParallelHilbertMaps):
            maps.close()
    n = float(np.mean([s.n for s in scans[3:]]))
    b = float(np.mean([len(s.endpoints) for s in scans[3:]]))
    flops = cfg.n_particles * step_flops(form, n, b, M, weighting(cfg, "rich_slam"))
    sec, mean = float(np.median(times)), float(np.mean(times))
    return {"sec": sec, "mean": mean, "gflops": flops / sec / 1e9, "flops": flops, "n": n, "b": b, "form": form}


def _torch_cpu(beams: int, steps: int, threads: tuple[int, ...]) -> dict[int, dict[str, Any]]:
    """The torch backend on the CPU with each number of ``threads`` (empty without torch)."""
    try:
        from benchmarks.slam_torch import time_torch_filter
    except ImportError:
        return {}
    return {n: time_torch_filter(SlamParams(), beams, steps, 256, "cpu", threads=n) for n in threads}


def _float32_accuracy(beams: int, steps: int, form: str = "covariance") -> float:
    """Largest |log-likelihood difference| float32 vs float64 over a short run, relative to the
    spread of the particles' log-likelihoods (what decides the weights)."""
    run, scans = _scans(beams, steps)
    basis = hm.make_basis([20.0, 16.0], [0.0, 0.0], 256)
    u = odometry_increments(run.odometry)
    rng = np.random.default_rng(0)
    poses = [run.odometry[0] + np.zeros((50, 3))]
    for i in range(1, len(scans)):
        poses.append(poses[-1] + u[i] + rng.normal(0, [0.02, 0.02, 0.005], (50, 3)))
    worst = 0.0
    maps = {dt: make_hilbert_maps(SlamParams(map=MapParams(dtype=dt), workers=0), basis, "rich_slam", 50, form)  # type: ignore[arg-type]
            for dt in ("float64", "float32")}
    for p, s in zip(poses, scans, strict=True):
        ll = {dt: m.log_likelihood(p, s) for dt, m in maps.items()}
        spread = float(np.std(ll["float64"])) or 1.0
        worst = max(worst, float(np.max(np.abs(ll["float32"] - ll["float64"]))) / spread)
        for m in maps.values():
            m.update(p, s)
    return worst


def _stage_real_time(quick: bool) -> list[Result]:
    """The slam stage on the demo log: the log's duration over the stage's own seconds (its manifest), for
    ``radar_graph`` alone (target: 5x real time) and, in full mode, the paper's ``rich_slam`` at 200 particles
    (target: real time). The log is simulated and run to the odometry once, in a temporary store."""
    import json
    import os
    import tempfile
    from pathlib import Path

    import pyarrow.parquet as pq

    from benchmarks.common import run_pipeline

    methods = [("radar_graph", 5.0)] + ([] if quick else [("rich_slam", 1.0)])
    out: list[Result] = []
    with tempfile.TemporaryDirectory(prefix="bench_slam_stage_") as tmp:
        env = {**os.environ, "RADAR_PIPELINE_CACHE": str(Path(tmp) / "cache")}

        def cli(*args: str) -> None:
            run_pipeline(list(args), env)

        runs = Path(tmp) / "runs"
        if quick:
            bag = Path(tmp) / "demo15.bag"
            cli("simulate", "--world", "demo", "--out", str(bag), "--duration", "15", "--seed", "0")
            src, seq = ["--source", str(bag), "--seq", "demo15"], "demo15"
        else:
            src, seq = ["--seq", "demo"], "demo"
        cli("run", "odometry", *src, "--runs-dir", str(runs))
        t_ns = pq.read_table(runs / seq / "odometry" / "odometry.parquet", columns=["t_ns"])["t_ns"].to_numpy()
        duration = float(t_ns[-1] - t_ns[0]) * 1e-9
        for method, target in methods:
            cli("run", "slam", *src, "--runs-dir", str(runs), "--set", f"slam.method={method}",
                "--set", f'slam.methods=["{method}"]', "--set", "slam.n_particles=200")
            man = json.loads((runs / seq / "slam" / "manifest.json").read_text())
            seconds = float(man["timings"]["seconds"])
            out.append(Result(AREA, f"slam stage, {method} alone, on the demo log", seconds, "s",
                              f"the log's duration ({duration:.0f} s)", duration / seconds, f">= {target:g}",
                              "log seconds / stage seconds (x real time)"))
    return out


def run(quick: bool = False) -> list[Result]:
    size = 1024 if quick else 2048
    ref0 = _matmul_rate(size)
    steps = 8 if quick else 30
    cfg = SlamParams()
    densities = (("sparse", 6), ("medium", 30), ("dense", 80))
    main, torch_rows = [], []
    for label, beams in densities:  # interleaved, the machine may be shared
        main.append((label, _time_filter(cfg, beams, steps, 256)))
        torch_rows.append((label, _torch_cpu(beams, steps, (1, 2) if label == "medium" else (1,))))
    ref = max(ref0, _matmul_rate(size))  # the better of before and after: the machine may be shared
    out: list[Result] = [Result(AREA, "numpy matmul float64", ref, "GFLOP/s",
                                note=f"{size}^2 @ {size}^2, best before/after, reference")]
    for label, r in main:
        note = (f"N={r['n']:.0f} samples, B={r['b']:.0f} beams, {r['form']} form, 2 workers; median "
                f"{r['sec']:.3f} s; {r['flops'] / 1e9:.2f} GFLOP per scan = {r['flops'] / ref / 1e9:.3f} s "
                "at the matmul rate")
        out.append(Result(AREA, f"step Np=200 M=256 {label}", r["mean"], "s/scan", "10 Hz frame (0.1 s)",
                          FRAME_S / r["mean"], ">= 1 (real time)", note))
        out.append(Result(AREA, f"GFLOP/s Np=200 M=256 {label}", r["gflops"], "GFLOP/s", "numpy matmul",
                          r["gflops"] / ref, ">= 0.5", note + " (modelled dominant flops, median step)"))
    for (label, r), (_, rt) in zip(main, torch_rows, strict=True):
        for threads, t in rt.items():
            out.append(Result(AREA, f"step Np=200 M=256 {label} torch cpu {threads} thread(s)", t["mean"], "s/scan",
                              "10 Hz frame (0.1 s)", FRAME_S / t["mean"], "",
                              f"{t['form']} form; numpy (2 workers) {r['mean']:.3f} s/scan in the same run: torch / "
                              f"numpy = {t['mean'] / r['mean']:.2f}; {t['gflops']:.1f} GFLOP/s"))
    r0 = _time_filter(SlamParams(workers=0), 6, steps, 256)
    out.append(Result(AREA, "step Np=200 M=256 sparse, in process", r0["mean"], "s/scan", "10 Hz frame (0.1 s)",
                      FRAME_S / r0["mean"], "", f"{r0['form']} form, all BLAS threads, no workers"))
    for label, beams in densities:
        r32 = _time_filter(SlamParams(map=MapParams(dtype="float32")), beams, steps, 256)
        err = _float32_accuracy(beams, 12 if quick else 40, r32["form"])
        out.append(Result(AREA, f"step Np=200 M=256 {label} float32", r32["mean"], "s/scan", "10 Hz frame (0.1 s)",
                          FRAME_S / r32["mean"], "", f"{r32['form']} form; max |dlog-lik| / particle spread "
                          f"vs float64: {err:.2g}"))
    for Np in ((50, 400) if quick else (50, 100, 400)):
        r = _time_filter(SlamParams(n_particles=Np), 30, steps, 256)
        out.append(Result(AREA, f"scaling Np={Np} M=256 medium", r["mean"], "s/scan", "10 Hz frame (0.1 s)",
                          FRAME_S / r["mean"], "", f"{r['gflops']:.1f} GFLOP/s, {r['form']}"))
    for M in ((64, 400) if quick else (64, 144, 400, 576)):
        r = _time_filter(cfg, 30, steps, M)
        out.append(Result(AREA, f"scaling Np=200 M={M} medium", r["mean"], "s/scan", "10 Hz frame (0.1 s)",
                          FRAME_S / r["mean"], "", f"{r['gflops']:.1f} GFLOP/s, {r['form']}"))
    return out + _stage_real_time(quick)
