"""The slam stage's warning when a filter's heading leaves its odometry (stages/slam/divergence.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.slam.divergence import heading_deviation


def test_heading_deviation_in_odometry_sigmas() -> None:
    T = 101
    odo = np.zeros((T, 3))
    odo[:, 0] = np.arange(T) * 0.1
    cov = np.tile(np.diag([1e-4, 1e-4, np.radians(0.1) ** 2]), (T, 1, 1))  # 0.1 deg per scan: 1 deg after 100
    same = heading_deviation(odo, odo, cov)
    assert same.sigmas == 0.0 and same.degrees == 0.0
    est = odo.copy()
    est[:, 2] = np.radians(np.linspace(0.0, 5.0, T))  # leaves it linearly: 5 deg at the end, sigma 1 deg there
    d = heading_deviation(odo, est, cov)
    assert d.index == T - 1 and np.isclose(d.degrees, 5.0) and np.isclose(d.sigma_degrees, 1.0)
    assert np.isclose(d.sigmas, 5.0)
    # the sigma floor keeps the first scans (no accumulated uncertainty yet) from dominating
    est[1, 2] = np.radians(0.2)
    assert heading_deviation(odo, est, cov).index == T - 1
    # headings compare on the circle
    wrapped = odo.copy()
    wrapped[:, 2], est2 = np.pi - 1e-3, odo.copy()
    est2[:, 2] = -np.pi + 1e-3
    assert heading_deviation(wrapped, est2, cov).degrees < 0.2


def test_stage_records_the_deviation_and_warns_past_the_threshold(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from stages.slam import stage as slam_stage
    from tests.test_slam_stage import _ctx, _run, _write_inputs

    inp = _write_inputs(tmp_path / "in", 20)
    quiet = _ctx(tmp_path / "a", inp["dirs"], n_particles=4, map={"n_basis": 36}, workers=0,
                 methods=["odometry", "rich_slam"])
    _run(quiet)
    sig = quiet.stats["methods"]["rich_slam"]["heading_deviation_sigmas"]
    assert 0.0 < sig < 3.0 and not any("heading left" in w for w in quiet.stats.get("warnings", []))
    monkeypatch.setattr(slam_stage, "DEVIATION_WARN_SIGMAS", sig / 2)
    loud = _ctx(tmp_path / "b", inp["dirs"], n_particles=4, map={"n_basis": 36}, workers=0,
                methods=["odometry", "rich_slam"])
    _run(loud)
    assert any(w.startswith("rich_slam's heading left the odometry's by") for w in loud.stats["warnings"])
