"""``python -m experiments.slam_table3 --table A B``: rows of several results files in one table."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from experiments import slam_table3 as table3


def _row(seq: str, method: str, seed: int, yaw: float, config: dict[str, object]) -> str:
    return json.dumps({"seq": seq, "method": method, "seed": seed, "config": json.dumps(config),
                       "pos_rmse_m": 0.1, "yaw_rmse_deg": yaw, "pos_rmse_whole_m": 0.1, "yaw_rmse_whole_deg": yaw})


def test_config_key_drops_execution_keys_and_defaults() -> None:
    assert table3.config_key('{"n_particles": 200, "workers": 0}') == table3.config_key('{"workers": 2}') == "{}"
    assert table3.config_key('{"n_particles": 50}') == '{"n_particles": 50}'
    assert table3.config_key("") == "{}"


def test_rows_of_two_files_make_one_table_and_a_later_row_replaces_an_earlier_one(tmp_path: Path) -> None:
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    a.write_text("\n".join([_row("demo", "odometry", 0, 0.87, {"workers": 0}),
                            _row("demo", "rich_slam", 0, 0.72, {"workers": 0}),
                            _row("demo", "rich_slam", 1, 0.90, {"workers": 0})]) + "\n")
    b.write_text("\n".join([_row("demo", "rich_slam", 1, 0.63, {"n_particles": 200, "workers": 2}),
                            _row("demo", "rich_slam", 2, 0.80, {})]) + "\n\n")
    rows, notes = table3.read_rows([a, b])
    yaw = sorted(r["yaw_rmse_whole_deg"] for r in rows if r["method"] == "rich_slam")
    assert yaw == [0.63, 0.72, 0.80]  # seed 1 from b.jsonl
    assert notes == [f"demo rich_slam seed 1: the row of {b} replaces an earlier one"]
    md = table3.table(rows, alignment="whole")
    assert "0.72 ± 0.09 (3)" in md  # mean 0.7167, half range (0.80 - 0.63) / 2


def test_a_cell_that_mixes_configurations_in_one_file_is_refused_naming_both(tmp_path: Path) -> None:
    a = tmp_path / "a.jsonl"
    a.write_text(_row("demo", "rich_slam", 0, 0.72, {"workers": 0}) + "\n"
                 + _row("demo", "rich_slam", 1, 0.63, {"endpoint_tolerance": 0.0}) + "\n")
    with pytest.raises(ValueError, match=r"demo rich_slam: rows of different configurations.*a\.jsonl:1.*a\.jsonl:2"):
        table3.read_rows([a])
    assert table3.main(["--table", str(a)]) == 2
    # a calibration grid: each configuration a row of its own, the defaults' under the bare method
    rows, _ = table3.read_rows([a], by_config=True)
    assert sorted(r["method"] for r in rows) == ["rich_slam", 'rich_slam {"endpoint_tolerance": 0.0}']
    assert table3.main(["--table", str(a), "--by-config"]) == 0


def test_a_later_file_with_a_cell_in_another_configuration_supersedes_the_earlier_rows(tmp_path: Path) -> None:
    """A default changed between two files: the later file's cell replaces every seed of the earlier one (not
    only the seeds it repeats), and cells the later file lacks keep their rows."""
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    a.write_text("\n".join([_row("demo", "rich_slam", 0, 0.72, {"fusion_increment_scale": 1.0}),
                            _row("demo", "rich_slam", 1, 0.90, {"fusion_increment_scale": 1.0}),
                            _row("lab", "rich_slam", 0, 0.50, {"fusion_increment_scale": 1.0})]) + "\n")
    b.write_text(_row("demo", "rich_slam", 0, 0.63, {"workers": 0}) + "\n")
    rows, notes = table3.read_rows([a, b])
    assert sorted((r["seq"], r["yaw_rmse_whole_deg"]) for r in rows) == [("demo", 0.63), ("lab", 0.50)]
    assert notes == [f"demo rich_slam: the rows of {a} are dropped: {b} has this cell in another configuration"]
    b.write_text(_row("demo", "rich_slam", 2, 0.66, {"fusion_increment_scale": 1.0}) + "\n")  # the same one
    rows, notes = table3.read_rows([a, b])
    assert sorted(r["yaw_rmse_whole_deg"] for r in rows if r["seq"] == "demo") == [0.66, 0.72, 0.90]
    assert notes == []


def test_a_line_that_is_not_a_row_names_its_file_and_line(tmp_path: Path) -> None:
    a = tmp_path / "a.jsonl"
    a.write_text(_row("demo", "rich_slam", 0, 0.72, {}) + "\n{\"seq\": \"demo\"\n")
    with pytest.raises(ValueError, match=r"a\.jsonl:2: not a table3 row"):
        table3.read_rows([a])
    with pytest.raises(ValueError, match="no such results file"):
        table3.read_rows([tmp_path / "missing.jsonl"])
    with pytest.raises(ValueError, match="no such results file"):
        table3.read_rows([tmp_path])  # a folder
    a.write_text(json.dumps({"seq": "demo", "method": "rich_slam", "seed": 0, "config": "{workers: 0"}) + "\n")
    with pytest.raises(ValueError, match=r"a\.jsonl:1: its config is not JSON"):
        table3.read_rows([a])


def test_set_items_parse_as_json_and_an_item_without_equals_is_named() -> None:
    assert table3.slam_overrides(["n_particles=50", "slam.method=rich_slam", "map=global"]) == {
        "n_particles": 50, "method": "rich_slam", "map": "global"}
    with pytest.raises(ValueError, match=r"--set 'n_particles': expected KEY=VALUE"):
        table3.slam_overrides(["workers=0", "n_particles"])
    with pytest.raises(SystemExit):  # argparse's usage error, exit 2
        table3.main(["RUNS/x", "--set", "n_particles"])


def test_rows_that_ran_on_another_odometry_are_dropped_when_a_later_file_reruns_it(tmp_path: Path) -> None:
    """A later file whose odometry row of a sequence differs (the odometry changed) supersedes every row of that
    sequence in earlier files, including seeds it did not rerun; a sequence whose odometry is unchanged keeps
    its earlier seeds."""
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    a.write_text("\n".join([_row("twin", "odometry", 1, 3.38, {}), _row("twin", "rich_slam", 1, 4.18, {}),
                            _row("twin", "rich_slam", 2, 4.50, {}), _row("demo", "odometry", 0, 0.87, {}),
                            _row("demo", "rich_slam", 0, 0.42, {})]) + "\n")
    b.write_text("\n".join([_row("twin", "odometry", 0, 5.35, {}), _row("twin", "rich_slam", 0, 7.63, {}),
                            _row("demo", "odometry", 1, 0.87, {}), _row("demo", "rich_slam", 1, 0.44, {})]) + "\n")
    rows, notes = table3.read_rows([a, b])
    got = sorted((r["seq"], r["method"], r["seed"], r["yaw_rmse_deg"]) for r in rows)
    assert got == [("demo", "odometry", 0, 0.87), ("demo", "odometry", 1, 0.87), ("demo", "rich_slam", 0, 0.42),
                   ("demo", "rich_slam", 1, 0.44), ("twin", "odometry", 0, 5.35), ("twin", "rich_slam", 0, 7.63)]
    assert notes == [f"twin: the rows of {a} are dropped: its odometry differs from that of {b} (yaw RMSE 3.38 "
                     "against 5.35 deg), so its filters ran on another odometry"]
