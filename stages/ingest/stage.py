"""`ingest` stage: read a ColoRadar-format log (bag, MCAP, extracted folder) into Parquet artifacts."""

from __future__ import annotations

from pipeline.errors import UserError
from pipeline.stage import Stage, StageContext, StageParams


class IngestParams(StageParams):
    """Parameters of the `ingest` stage."""


class IngestStage(Stage):
    name = "ingest"
    description = "read a ColoRadar-format log (bag, MCAP, extracted folder) into Parquet artifacts"
    inputs = ()
    Params = IngestParams
    outputs = ('radar.parquet', 'imu.parquet', 'lidar.parquet', 'groundtruth.parquet', 'calibration.json')
    implemented = False

    def run(self, ctx: StageContext) -> None:
        raise UserError("stage 'ingest' is not implemented yet")


STAGE = IngestStage()
