"""The `ingest` stage: read a ColoRadar-format log (bag, MCAP, extracted folder) into Parquet artifacts."""
