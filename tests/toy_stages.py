"""A toy two-stage workflow used to test the runner: `make_numbers` -> `square`."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
from pydantic import Field

from core.stage import Stage, StageContext, StageParams
from pipeline.config import Workflow
from schemas import write_artifact
from schemas.artifacts import ArtifactSchema

NUMBERS = ArtifactSchema("toy_numbers", "make_numbers", "numbers.parquet", 1,
                         pa.schema([pa.field("i", pa.int32(), nullable=False),
                                    pa.field("v", pa.float64(), nullable=False)]))


class NumbersParams(StageParams):
    count: int = Field(5, ge=1, description="how many numbers")
    scale: float = Field(1.0, description="multiplier")
    sleep_s: float = Field(0.0, ge=0, description="pause before writing (to overlap concurrent runs in tests)")


class MakeNumbers(Stage):
    name = "make_numbers"
    Params = NumbersParams
    outputs = ("numbers.parquet",)
    calls = 0

    def run(self, ctx: StageContext) -> None:
        type(self).calls += 1
        from threadpoolctl import threadpool_info

        ctx.stats["blas_threads"] = max((p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"),
                                        default=0)
        time.sleep(ctx.params.sleep_s)
        i = np.arange(ctx.params.count, dtype=np.int32)
        write_artifact({"i": i, "v": i * ctx.params.scale}, ctx.output("numbers.parquet"), NUMBERS)
        rec = ctx.recording
        rec.points_over_time("world/radar/raw", scans=i, t_ns=i.astype(np.int64) * 100_000_000,
                             positions=np.column_stack([i, i, i]).astype(np.float32), lengths=np.ones(len(i)))
        rec.scalars("metrics/value", i, None, i * ctx.params.scale)


class SquareParams(StageParams):
    offset: float = Field(0.0, description="added after squaring")
    fail_midway: bool = Field(False, description="raise after writing a partial file (for tests)")
    kill_midway: bool = Field(False, description="SIGKILL the process after writing a partial file (for tests)")


class Square(Stage):
    name = "square"
    inputs = ("make_numbers",)
    Params = SquareParams
    outputs = ("squares.parquet",)
    calls = 0

    def run(self, ctx: StageContext) -> None:
        from schemas import read_artifact

        type(self).calls += 1
        t = read_artifact(ctx.input("make_numbers", "numbers.parquet"), NUMBERS)
        v = t["v"].to_numpy() ** 2 + ctx.params.offset
        out = ctx.output("squares.parquet")
        if ctx.params.kill_midway:
            out.write_bytes(b"partial")
            os.kill(os.getpid(), signal.SIGKILL)
        if ctx.params.fail_midway:
            out.write_bytes(b"partial")
            raise RuntimeError("boom midway")
        write_artifact({"i": t["i"].to_numpy(), "v": v}, out, NUMBERS)
        ctx.stats["n"] = len(v)


def registry() -> dict[str, Stage]:
    MakeNumbers.calls = 0
    Square.calls = 0
    return {"make_numbers": MakeNumbers(), "square": Square()}


def workflow(**params: dict[str, object]) -> Workflow:
    return Workflow("toy", ["make_numbers", "square"], {k: dict(v) for k, v in params.items()})


TOY_WORKFLOW = """
[workflow]
stages = ["make_numbers", "square"]
"""


def workflow_file(folder: Path) -> Path:
    path = folder / "toy.toml"
    path.write_text(TOY_WORKFLOW)
    return path
