"""Where the project's data, workflows and caches live."""

from __future__ import annotations

import os
from pathlib import Path

#: Root of the source tree (holds ``data/`` and ``workflows/``). Overridable for relocated installs.
PROJECT_ROOT = Path(os.environ.get("RADAR_PIPELINE_HOME", Path(__file__).resolve().parents[1]))


def data_dir() -> Path:
    """The ``data/`` folder: sequences.toml, dataset profiles, worlds, fixtures."""
    return PROJECT_ROOT / "data"


def workflows_dir() -> Path:
    """The ``workflows/`` folder with declarative pipelines and parameter sets."""
    return PROJECT_ROOT / "workflows"


def cache_dir() -> Path:
    """Cache for generated simulated sequences (``$RADAR_PIPELINE_CACHE`` or ``~/.cache/radar-pipeline``)."""
    env = os.environ.get("RADAR_PIPELINE_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".cache"
    return base / "radar-pipeline"


def default_runs_dir() -> Path:
    """Default run store: ``$RADAR_PIPELINE_RUNS`` or ``./runs``."""
    return Path(os.environ.get("RADAR_PIPELINE_RUNS", "runs"))
