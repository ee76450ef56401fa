"""``table3 --targets``: the default method's targets per sequence from the rows (whole-trajectory alignment)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from experiments import slam_table3 as table3


def _row(seq: str, method: str, seed: int, pos: float, yaw: float) -> dict[str, object]:
    return {"seq": seq, "method": method, "seed": seed, "config": "{}", "pos_rmse_m": pos, "yaw_rmse_deg": yaw,
            "pos_rmse_whole_m": pos, "yaw_rmse_whole_deg": yaw}


def test_targets_count_no_worse_within_the_spread_and_the_drifting_clauses(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m, g = "radar_graph", "rich_slam"
    rows = [
        _row("a", "odometry", 0, 0.2, 1.0),  # good odometry: seeds 0.9 and 1.2 -> mean 1.05, half range 0.15: within
        _row("a", m, 0, 0.2, 0.9), _row("a", m, 1, 0.2, 1.2),
        _row("b", "odometry", 0, 0.2, 1.0),  # 1.1 and 1.12: mean 1.11 - 0.01 > 1.0: worse
        _row("b", m, 0, 0.2, 1.1), _row("b", m, 1, 0.2, 1.12),
        _row("c_drift", "odometry", 0, 1.0, 10.0),  # drifting, odometry above 5 deg: no "no worse" clause
        _row("c_drift", m, 0, 0.5, 6.9), _row("c_drift", g, 0, 0.5, 7.5),  # -31 % and below the grid
        _row("d_drift", "odometry", 0, 0.3, 4.0),  # drifting and good: all three clauses
        _row("d_drift", m, 0, 0.2, 3.0),  # -25 %: not 30 % below; no grid row: not below it
        _row("e", "odometry", 0, 0.1, 1.0),  # no row of the method: left out
    ]
    text, counts = table3.targets(rows, m, g)
    assert counts == {"no worse": (2, 3), "30 % below": (1, 2), f"below {g}": (1, 2), "both drifting": (1, 2)}
    lines = {line.split(" | ")[0].lstrip("| "): line for line in text.splitlines() if line.startswith("| ")}
    assert "| ✓ |" in lines["a"] and "| ✗ |" in lines["b"] and "e" not in lines
    assert "✓ (-31 %)" in lines["c_drift"] and "no row" in lines["d_drift"] and "✗ (-25 %)" in lines["d_drift"]
    # through the command line, and a one-line error for a method without rows
    out = tmp_path / "rows.jsonl"
    out.write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert table3.main(["--table", str(out), "--targets"]) == 0
    assert "no worse: 2 of 3; 30 % below: 1 of 2" in capsys.readouterr().out
    assert table3.main(["--table", str(out), "--targets", "rich_slam_no_et"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --targets") and "\n" not in err
