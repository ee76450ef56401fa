"""RMap Table III as published, in the row form of the Table III script (``map_table``).

A view of :data:`core.rmap_paper.TABLE_III` (the one transcription of the paper's tables, with
its errata: outdoors_run4's input F-score printed "0.0123" is 0.123): per scene (input row, RMap row) of
(CD-l1, CD-l2, F-score, D-Dist 50, 75, 90, 95), in metres.
"""

from __future__ import annotations

from core.rmap_paper import MAP_KEYS, TABLE_III, TABLE_III_OVERALL, Scores

Row = tuple[float, float, float, float, float, float, float]

KEYS = MAP_KEYS


def _row(s: Scores) -> Row:
    m = s.metrics()
    return tuple(m[k] for k in KEYS)  # type: ignore[return-value]


#: scene -> (input row, RMap row)
TABLE3: dict[str, tuple[Row, Row]] = {scene: (_row(r.input), _row(r.rmap)) for scene, r in TABLE_III.items()}

#: the paper's printed Overall row (mean over all 21 scenes)
OVERALL: tuple[Row, Row] = (_row(TABLE_III_OVERALL.input), _row(TABLE_III_OVERALL.rmap))


def as_dict(row: Row) -> dict[str, float]:
    return dict(zip(KEYS, row, strict=True))
