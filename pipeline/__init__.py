"""radar-pipeline: orchestration of the radar SLAM and mapping stages.

This package holds orchestration only (CLI, configuration, sequence registry, run store, executors and
Rerun helpers). The algorithms live beside each stage in ``stages/``.
"""

__version__ = "0.1.0"
