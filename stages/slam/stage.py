"""`slam` stage: RICH-SLAM: RBPF with Hilbert-GP occupancy maps, and baselines."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class SlamParams(StageParams):
    """Parameters of the `slam` stage."""


class SlamStage(Stage):
    name = "slam"
    description = "RICH-SLAM: RBPF with Hilbert-GP occupancy maps, and baselines"
    inputs = ('ingest', 'filter', 'odometry')
    Params = SlamParams
    outputs = ('trajectory.parquet', 'map_posterior.parquet', 'map_grid.parquet')
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'slam' is not implemented yet")


STAGE = SlamStage()
