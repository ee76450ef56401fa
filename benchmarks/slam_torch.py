"""Timing of the RICH-SLAM filter on the torch backend (CPU or CUDA), shared by ``bench_slam`` and ``slam_cuda``.

Same protocol as ``bench_slam._time_filter``: the synthetic corridor, one RBPF step = propagate,
weights with the endpoint tolerance, Kalman update, N_eff and, when it drops, resampling; timed after
warm-up steps, s/scan the mean over the timed steps (resampling included), GFLOP/s from the modelled
dominant flops (``methods.step_flops``) over the median step. Every step ends with the filter's one
device-to-host read (the scan's statistics), so the times include the device's work.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from core import hilbert_map as hm
from stages.slam.beam_sampling import BeamSamples, sample_beams
from stages.slam.methods import NOISE, TORCH_THREADS, choose_form, map_model, step_flops, weighting
from stages.slam.params import SlamParams
from stages.slam.rbpf import odometry_increments
from stages.slam.synthetic import make_run
from stages.slam.torch_filter import TorchRBPF, cpu_threads
from stages.slam.torch_maps import TorchHilbertMaps

DENSITIES = (("sparse", 6), ("medium", 30), ("dense", 80))  # beams fired per scan (as bench_slam)


def corridor_scans(beams: int, n_scans: int) -> tuple[Any, list[BeamSamples]]:
    """The benchmark's synthetic corridor run and its beam samples (as ``bench_slam._scans``)."""
    run = make_run(n_scans, np.random.default_rng(1), beams_per_scan=beams, outlier_fraction=0.1)
    return run, [sample_beams(s, [0.0, 0.0], 1.0, 5.0) for s in run.scans]


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_torch_filter(cfg: SlamParams, beams: int, steps: int, M: int, device: str, warmup: int = 3,
                      form: str = "auto", budget_s: float | None = None, threads: int = TORCH_THREADS
                      ) -> dict[str, Any]:
    """Seconds per step of the torch filter over ``steps`` scans after ``warmup`` (fewer timed steps when
    ``budget_s`` would be exceeded, at least 3) with ``threads`` CPU threads, with the modelled flops."""
    run, scans = corridor_scans(beams, steps + warmup)
    basis = hm.make_basis([20.0, 16.0], [0.0, 0.0], M)
    chosen = choose_form(cfg, "rich_slam", scans, M) if form == "auto" else form
    maps = TorchHilbertMaps(basis, cfg.n_particles, map_model(cfg, "rich_slam", chosen),  # type: ignore[arg-type]
                            device=device)
    u = odometry_increments(run.odometry)
    dev = torch.device(device)
    times: list[float] = []
    with cpu_threads(threads if dev.type == "cpu" else 0):
        f = TorchRBPF(maps, run.odometry[0], cfg.n_particles, NOISE, np.random.default_rng(0))
        t_start = time.perf_counter()
        for i, s in enumerate(scans):
            sync(dev)
            t0 = time.perf_counter()
            f.step(u[i], s, first=i == 0)
            sync(dev)
            if i >= warmup:
                times.append(time.perf_counter() - t0)
                if budget_s is not None and len(times) >= 3 and time.perf_counter() - t_start > budget_s:
                    break
    used = scans[warmup : warmup + len(times)]
    n = float(np.mean([s.n for s in used]))
    b = float(np.mean([len(s.endpoints) for s in used]))
    flops = cfg.n_particles * step_flops(chosen, n, b, M, weighting(cfg, "rich_slam"))
    sec, mean = float(np.median(times)), float(np.mean(times))
    del f, maps
    return {"sec": sec, "mean": mean, "gflops": flops / sec / 1e9, "flops": flops, "n": n, "b": b, "form": chosen,
            "steps": len(times)}
