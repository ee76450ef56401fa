"""Table III over seeds (stages/evaluate/seed_table.py): means and spreads of a sweep over ``slam.seed``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stages.evaluate.report import sweep_tables
from stages.evaluate.seed_table import cell, errors_by_seed, plot_seed_spread, seed_tables


def _records() -> list[dict]:
    out = []
    yaw = {("a", "rich_slam"): [2.0, 3.0, 4.0], ("a", "odometry"): [5.0, 5.0, 5.0], ("b", "rich_slam"): [1.0, 1.0]}
    for (seq, method), values in yaw.items():
        for seed, v in enumerate(values):
            params = json.dumps({"slam.seed": seed})
            for metric, value in (("ate_yaw_rmse_whole_deg", v), ("ate_pos_rmse_whole_m", v / 10),
                                  ("ate_yaw_rmse_deg", v + 1), ("ate_pos_rmse_m", v / 5)):
                out.append({"seq": seq, "method": method, "metric": metric, "value": value, "params": params})
    # a point of another sweep (no slam.seed) is not a seed
    out.append({"seq": "a", "method": "rich_slam", "metric": "ate_yaw_rmse_whole_deg", "value": 99.0,
                "params": json.dumps({"slam.n_particles": 5})})
    return out


def test_cells_average_over_the_seeds_and_show_the_spread_only_when_they_differ() -> None:
    by = errors_by_seed(_records(), "ate_yaw_rmse_whole_deg")
    assert by[("a", "rich_slam")] == {0: 2.0, 1: 3.0, 2: 4.0}
    assert cell([0.2, 0.3, 0.4], [2.0, 3.0, 4.0]) == f"0.30 / 3.00 ± {np.std([2.0, 3.0, 4.0]):.2f} (3)"
    assert cell([0.5, 0.5], [5.0, 5.0]) == "0.50 / 5.00 (2)"
    assert cell([], []) == "–"


def test_one_table_per_alignment_with_the_mean_over_sequences() -> None:
    tables = seed_tables(_records())
    assert len(tables) == 2 and "whole-trajectory" in tables[0][0] and "paper's protocol" in tables[1][0]
    _, head, rows = tables[0]
    assert head == ["method", "a", "b", "mean yaw"]
    by = {r[0]: r for r in rows}
    assert by["rich_slam"][1].startswith("0.30 / 3.00 ±") and by["rich_slam"][2] == "0.10 / 1.00 (2)"
    assert by["rich_slam"][3] == "2.00 (2 seq)" and by["odometry"][2] == "–" and by["odometry"][3] == "5.00 (1 seq)"
    assert tables[1][2][0][1].startswith("0.60 / 4.00")  # the paper's protocol: its own metrics
    assert sweep_tables(_records())[:2] == tables  # the evaluate stage's sweep report leads with them
    assert seed_tables([r for r in _records() if "slam.seed" not in r["params"]]) == []


def test_the_seed_figure_is_drawn(tmp_path) -> None:
    pytest.importorskip("matplotlib")
    path = plot_seed_spread(tmp_path / "s.png", _records(), "t")
    assert path.stat().st_size > 1000
