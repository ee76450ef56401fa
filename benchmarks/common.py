"""Shared benchmark helpers: timing and the result record."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Result:
    """One measured number; ``ratio`` compares it to ``reference`` measured in the same run."""

    area: str
    name: str
    value: float
    unit: str
    reference: str = ""
    ratio: float | None = None
    target: str = ""
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def run_pipeline(args: list[str], env: Mapping[str, str]) -> float:
    """``pipeline ARGS`` in a subprocess from the project root: its wall seconds; RuntimeError with the tail of its
    stderr when it fails."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=ROOT, env=dict(env), capture_output=True,
                       text=True)
    if r.returncode != 0:
        raise RuntimeError(f"pipeline {' '.join(args)} failed ({r.returncode}): {r.stderr[-2000:]}")
    return time.perf_counter() - t0


def best_time(fn: Callable[[], Any], repeat: int = 3, number: int = 1) -> float:
    """Best wall time of ``number`` calls, over ``repeat`` rounds (seconds per call)."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best
