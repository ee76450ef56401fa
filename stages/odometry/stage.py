"""`odometry` stage: radar-inertial odometry (EKF-RIO) at radar scan times."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class OdometryParams(StageParams):
    """Parameters of the `odometry` stage."""


class OdometryStage(Stage):
    name = "odometry"
    description = "radar-inertial odometry (EKF-RIO) at radar scan times"
    inputs = ('ingest', 'filter')
    Params = OdometryParams
    outputs = ('odometry.parquet',)
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'odometry' is not implemented yet")


STAGE = OdometryStage()
