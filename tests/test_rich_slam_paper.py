"""RICH-SLAM's Table III as data: transcribed values checked against the paper's text, and the
table3 runner's side-by-side table of the ColoRadar twins."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from experiments import slam_table3 as table3
from stages.evaluate.rich_slam_paper import PAPER_METHODS, PAPER_SEQUENCES, TABLE_III, paper_sequence

PAPER = Path(__file__).resolve().parents[1].parent / "shared" / "papers" / "rich-slam.md"


def test_table_iii_matches_the_papers_text() -> None:
    if not PAPER.is_file():
        pytest.skip(f"{PAPER} not found: the shared folder beside the clone (../shared) holds the paper")
    lines = PAPER.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("TABLE III"))
    parsed: dict[str, list[tuple[float, float]]] = {}
    for line in lines[start + 1 : start + 12]:
        name, *cells = line.split("\t")
        if name in PAPER_METHODS:
            pairs = [re.findall(r"\d+\.\d+", c) for c in cells]  # underlines (<u>..</u>) are markup only
            parsed[name] = [(float(p), float(y)) for p, y in pairs]
    assert set(parsed) == set(PAPER_METHODS)
    for m in PAPER_METHODS:
        assert parsed[m] == [TABLE_III[s][m] for s in PAPER_SEQUENCES], m


def test_paper_sequence_maps_twins_and_logs_to_their_column() -> None:
    assert paper_sequence("coloradar_3_twin") == "CR 3"
    assert paper_sequence("coloradar_6") == "CR 6"
    assert paper_sequence("coloradar_7_twin") is None  # Table III has six ColoRadar columns
    assert paper_sequence("demo_drift") is None and paper_sequence("coloradar_x_twin") is None


def test_twins_table_puts_the_papers_rows_beside_ours(tmp_path: Path) -> None:
    def row(seq: str, method: str, seed: int, pos: float, yaw: float) -> dict[str, object]:
        return {"seq": seq, "method": method, "seed": seed, "config": "{}", "pos_rmse_m": pos, "yaw_rmse_deg": yaw}

    rows = [row("coloradar_2_twin", "rich_slam", 0, 1.0, 10.0), row("coloradar_2_twin", "rich_slam", 1, 3.0, 14.0),
            row("demo_drift", "rich_slam", 0, 0.5, 5.0), row("coloradar_1_twin", "fastslam_grid", 0, 2.0, 7.0)]
    md = table3.paper_table(rows).splitlines()
    assert len(md) == 4 and "demo_drift" not in "\n".join(md)  # header, rule, CR 1, CR 2 (paper order)
    assert md[0].startswith("| sequence | fastslam_grid | rich_slam | paper EKF-RIO |")  # our methods' order
    assert md[2].startswith("| CR 1 (coloradar_1_twin) | 2.00 / 7.00 (1 seed) | – |")
    assert md[3].startswith("| CR 2 (coloradar_2_twin) | – | 2.00 ± 1.00 / 12.00 ± 2.00 (2) |")
    assert md[3].endswith("| 1.60 / 91.98 | 2.78 / 25.41 | 2.41 / 24.69 | 3.06 / 24.43 | 2.68 / 22.88 |")
    assert table3.paper_marks(rows) == {"coloradar_2_twin": {"rich_slam": (2.68, 22.88)},
                                        "coloradar_1_twin": {"fastslam_grid": (0.96, 13.51)}}
    assert table3.paper_table(rows[2:3]) == ""
    # the full table's columns: the other sequences first, then the twins in the paper's order (as the figure)
    assert table3.table(rows).splitlines()[0] == "| method | demo_drift | coloradar_1_twin | coloradar_2_twin |"
    out = tmp_path / "t3.jsonl"
    out.write_text("".join(json.dumps(r) + "\n" for r in rows))
    png = tmp_path / "t3.png"
    assert table3.main(["--table", str(out), "--paper", "--figure", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_report_table_iii_adds_the_papers_rows_for_the_twins() -> None:
    from stages.evaluate.tables import trajectory_table

    recs = [{"seq": s, "method": "rich_slam", "metric": k, "value": v} for s in ("demo", "coloradar_4_twin")
            for k, v in (("ate_pos_rmse_m", 1.0), ("ate_yaw_rmse_deg", 5.0))]
    headers, rows = trajectory_table(recs)
    assert headers == ["method", "demo", "coloradar_4_twin"]
    paper = {r[0]: r[1:] for r in rows if r[0].startswith("paper ")}
    assert list(paper) == [f"paper {m}" for m in PAPER_METHODS]
    assert paper["paper RICH-SLAM"] == ["–", "3.59 / 12.61"]
    _, rows = trajectory_table(recs[:2])  # no twin: no paper rows
    assert not any(r[0].startswith("paper ") for r in rows)


def test_tables_put_the_whole_trajectory_alignment_first_and_the_papers_protocol_beside_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from stages.evaluate.tables import trajectory_table

    recs = [{"seq": s, "method": "rich_slam", "metric": k, "value": v} for s in ("demo", "coloradar_1_twin")
            for k, v in (("ate_pos_rmse_whole_m", 0.4), ("ate_yaw_rmse_whole_deg", 1.2), ("ate_pos_rmse_m", 6.4),
                         ("ate_yaw_rmse_deg", 119.9), ("aligned_frames", 100.0))]
    recs += [{"seq": "demo", "method": "groundtruth", "metric": k, "value": v}
             for k, v in (("length_m", 40.0), ("duration_s", 60.0))]
    headers, rows = trajectory_table(recs)
    assert headers == ["method", "demo: whole", "demo: paper, first 100", "coloradar_1_twin: whole",
                       "coloradar_1_twin: paper, first 100"]
    by = {r[0]: r[1:] for r in rows}
    assert by["rich_slam"] == ["0.40 / 1.20", "6.40 / 119.90"] * 2
    assert by["length / duration"] == ["40.0 m, 60 s", "–", "–", "–"]
    assert by["paper RICH-SLAM"] == ["–", "–", "–", "0.86 / 6.18"]  # the paper's numbers: under its protocol only

    def row(seq: str, seed: int, whole: float, paper: float) -> dict[str, object]:
        return {"seq": seq, "method": "rich_slam", "seed": seed, "config": "{}", "pos_rmse_m": paper,
                "yaw_rmse_deg": 10 * paper, "pos_rmse_whole_m": whole, "yaw_rmse_whole_deg": 10 * whole}

    jrows = [row("coloradar_1_twin", 0, 0.3, 6.3), row("coloradar_1_twin", 1, 0.5, 6.5)]
    assert "| 0.40 ± 0.10 / 4.00 ± 1.00 (2) |" in table3.table(jrows, alignment="whole")
    assert "| 6.40 ± 0.10 / 64.00 ± 1.00 (2) |" in table3.table(jrows)  # the protocol's, as before
    md = table3.paper_table(jrows).splitlines()
    assert md[0].startswith("| sequence | rich_slam, whole | rich_slam, paper | paper EKF-RIO |")
    assert md[2].startswith("| CR 1 (coloradar_1_twin) | 0.40 ± 0.10 / 4.00 ± 1.00 (2) "
                            "| 6.40 ± 0.10 / 64.00 ± 1.00 (2) | 3.26 / 79.53 |")
    out = tmp_path / "t3.jsonl"
    out.write_text("".join(json.dumps(r) + "\n" for r in jrows))
    png = tmp_path / "t3.png"
    assert table3.main(["--table", str(out), "--figure", str(png)]) == 0
    printed = capsys.readouterr().out
    assert printed.index("Whole-trajectory SE(2)") < printed.index("The paper's protocol") and png.exists()
    rows_old = [{k: v for k, v in r.items() if "whole" not in k} for r in jrows]  # rows written before: protocol only
    assert table3.table(rows_old, alignment="whole").count("\n") == 1  # no row has them: the header alone
    out.write_text("".join(json.dumps(r) + "\n" for r in rows_old))
    assert table3.main(["--table", str(out), "--figure", str(png)]) == 0
    printed = capsys.readouterr().out
    assert "Whole-trajectory" not in printed and "draws the paper's protocol" in printed
