"""The `slam` stage: RICH-SLAM: RBPF with Hilbert-GP occupancy maps, and baselines."""
