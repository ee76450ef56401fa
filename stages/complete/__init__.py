"""The `complete` stage: point-cloud completion of the radar map (RMap Sec. III-D)."""
