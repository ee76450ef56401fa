"""Shared fixtures: isolate caches and run stores in temporary folders."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _isolated_dirs(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Keep tests away from the user's ~/.cache and ./runs unless a test sets them itself."""
    monkeypatch.setenv("RADAR_PIPELINE_RUNS", str(tmp_path_factory.mktemp("runs")))
    monkeypatch.setenv("COLORADAR_ROOT", str(tmp_path_factory.mktemp("coloradar_root")))
