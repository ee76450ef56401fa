"""`evaluate` stage: the papers' tables and figures."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class EvaluateParams(StageParams):
    """Parameters of the `evaluate` stage."""


class EvaluateStage(Stage):
    name = "evaluate"
    description = "the papers' tables and figures"
    inputs = ('ingest', 'slam', 'voxel')
    Params = EvaluateParams
    outputs = ('metrics.parquet', 'report.md')
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'evaluate' is not implemented yet")


STAGE = EvaluateStage()
