"""The RICH-SLAM torch backend on a CUDA GPU: one command, a few minutes, a markdown table for the slam README.

Usage: ``python -m benchmarks.slam_cuda [--out FILE] [--quick] [--form auto|information|covariance]
[--device cuda|cpu]``. Measures, in one run: the GPU's plain (``n x n @ n x n``) and batched
(``bmm`` of ``(B, M, M)`` stacks, the shapes of the particle maps) matrix-product rates in float64
and float32, then s/scan and x real time (10 Hz) of the filter (``benchmarks.slam_torch``) at
N_p = 200 / 1000 / 5000, M = 256 / 1024, sparse / medium / dense corridor scans, float64 and float32,
each with its modelled GFLOP/s as a fraction of both product rates. Configurations that do not fit
in the GPU's memory are reported as such. ``--device cpu --quick`` is a dry run of the script.
The table goes to stdout and to ``--out`` (default ``slam_cuda.md``; ``$OUT/slam_cuda.md`` when
``$OUT`` is set).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import torch

from benchmarks.slam_torch import DENSITIES, time_torch_filter
from stages.slam.params import MapParams, SlamParams

FRAME_S = 0.1
DTYPES = {"float64": torch.float64, "float32": torch.float32}


def _timed(fn: Callable[[], object], device: torch.device, repeat: int = 5) -> float:
    """Best wall time of ``fn()`` with the device synchronised (after one warm-up call)."""
    fn()
    best = float("inf")
    for _ in range(repeat):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        best = min(best, time.perf_counter() - t0)
    return best


def matmul_rates(device: torch.device, dtype: torch.dtype, quick: bool) -> dict[str, float]:
    """GFLOP/s of a plain square product and of batched products of ``M x M`` stacks (per M)."""
    g = torch.Generator(device=device).manual_seed(0)
    n = 2048 if quick else 8192
    a = torch.randn((n, n), generator=g, device=device, dtype=dtype)
    b = torch.randn((n, n), generator=g, device=device, dtype=dtype)
    out = {"plain": 2 * n**3 / _timed(partial(torch.matmul, a, b), device) / 1e9}
    del a, b
    for M, B in ((256, 64 if quick else 2000), (1024, 8 if quick else 200)):
        x = torch.randn((B, M, M), generator=g, device=device, dtype=dtype)
        y = torch.randn((B, M, M), generator=g, device=device, dtype=dtype)
        out[f"bmm{M}"] = 2 * B * M**3 / _timed(partial(torch.bmm, x, y), device) / 1e9
        del x, y
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.slam_cuda", description=__doc__.split("\n")[0])
    default_out = Path(os.environ["OUT"]) / "slam_cuda.md" if os.environ.get("OUT") else Path("slam_cuda.md")
    ap.add_argument("--out", type=Path, default=default_out)
    ap.add_argument("--quick", action="store_true", help="a dry run: small sizes, few steps")
    ap.add_argument("--form", default="auto", choices=("auto", "information", "covariance"))
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    ap.add_argument("--budget", type=float, default=6.0, help="seconds of timed steps per configuration at most")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print(f"slam_cuda: torch {torch.__version__} sees no CUDA device; run it where a GPU is available "
              "(or --device cpu --quick for a dry run)", file=sys.stderr)
        return 2
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    lines = [f"GPU: {name}; torch {torch.__version__}, CUDA {torch.version.cuda}; synthetic corridor, "
             f"form {args.form}, s/scan = mean over the timed steps (resampling included), GFLOP/s = modelled "
             "dominant flops (`step_flops`) over the median step.", ""]
    rates = {dt: matmul_rates(device, t, args.quick) for dt, t in DTYPES.items()}
    for dt, r in rates.items():
        lines.append(f"- {dt}: plain matmul {r['plain']:.0f} GFLOP/s; batched bmm M=256 {r['bmm256']:.0f}, "
                     f"M=1024 {r['bmm1024']:.0f} GFLOP/s")
    lines += ["", "| N_p | M | scans | samples (beams) | form | dtype | s/scan | x real time | GFLOP/s | of bmm | "
              "of matmul | steps |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    particles = (50, 200) if args.quick else (200, 1000, 5000)
    sizes = (64, 256) if args.quick else (256, 1024)
    steps = 4 if args.quick else 10
    for dt in DTYPES:
        for Np in particles:
            for M in sizes:
                for label, beams in DENSITIES:
                    cfg = SlamParams(n_particles=Np, map=MapParams(dtype=dt))
                    try:
                        r = time_torch_filter(cfg, beams, steps, M, args.device, warmup=2, form=args.form,
                                              budget_s=args.budget)
                    except torch.cuda.OutOfMemoryError:
                        row = f"| {Np} | {M} | {label} | | | {dt} | out of memory | | | | | |"
                    except RuntimeError as exc:  # report it and go on with the other configurations
                        msg = str(exc).splitlines()[0][:80] if str(exc) else type(exc).__name__
                        row = f"| {Np} | {M} | {label} | | | {dt} | failed: {msg} | | | | | |"
                    else:
                        bmm = rates[dt]["bmm1024" if M >= 1024 else "bmm256"]
                        row = (f"| {Np} | {M} | {label} | {r['n']:.0f} ({r['b']:.0f}) | {r['form']} | {dt} | "
                               f"{r['mean']:.4f} | {FRAME_S / r['mean']:.2f} | {r['gflops']:.0f} | "
                               f"{r['gflops'] / bmm:.3f} | {r['gflops'] / rates[dt]['plain']:.3f} | {r['steps']} |")
                    if device.type == "cuda":
                        torch.cuda.empty_cache()
                    lines.append(row)
                    print(row, flush=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
