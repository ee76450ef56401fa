"""`filter` stage: Doppler ego-velocity and multi-frame radar point filtering (RICH-SLAM Sec. IV-B)."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class FilterParams(StageParams):
    """Parameters of the `filter` stage."""


class FilterStage(Stage):
    name = "filter"
    description = "Doppler ego-velocity and multi-frame radar point filtering (RICH-SLAM Sec. IV-B)"
    inputs = ('ingest',)
    Params = FilterParams
    outputs = ('radar_filtered.parquet', 'ego_velocity.parquet')
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'filter' is not implemented yet")


STAGE = FilterStage()
