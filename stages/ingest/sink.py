"""Turning the readers' message stream into artifacts: time order, scan numbering, NaN dropping, labels.

Policy for time going backwards (sensor stamps): each streamed sensor (radar, lidar, imu) passes a
small reorder buffer of ``window`` messages, so stamps that jitter out of order are re-sorted; a message
older than one already emitted (a clock jump back) is dropped. Every backwards step between consecutive
arrivals is counted and reported, as is every drop. Small buffered streams (ground truth, odometry) are
sorted; exact duplicate stamps are dropped there.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow.parquet as pq

from core.errors import UserError
from stages.ingest.readers import Message


@dataclass
class ReorderBuffer:
    """Bounded re-sorting of one stream by sensor time."""

    window: int
    backwards: int = 0
    dropped: int = 0
    first_backwards_ns: int | None = None
    _heap: list[tuple[int, int, Message]] = field(default_factory=list)
    _last_in: int | None = None
    _last_out: int | None = None

    def push(self, msg: Message) -> Iterator[Message]:
        if self._last_in is not None and msg.t_ns < self._last_in:
            self.backwards += 1
            if self.first_backwards_ns is None:
                self.first_backwards_ns = msg.t_ns
        self._last_in = msg.t_ns
        heapq.heappush(self._heap, (msg.t_ns, msg.index, msg))
        while len(self._heap) > self.window:
            yield from self._pop()

    def flush(self) -> Iterator[Message]:
        while self._heap:
            yield from self._pop()

    def _pop(self) -> Iterator[Message]:
        t, _, msg = heapq.heappop(self._heap)
        if self._last_out is not None and t < self._last_out:
            self.dropped += 1
            return
        self._last_out = t
        yield msg


def finite_mask(columns: dict[str, npt.NDArray[Any]]) -> npt.NDArray[np.bool_]:
    """Points whose every column is finite."""
    mask: npt.NDArray[np.bool_] | None = None
    for col in columns.values():
        m = np.isfinite(col)
        mask = m if mask is None else mask & m
    assert mask is not None
    return mask


def sort_poses(t_ns: npt.NDArray[np.int64], values: npt.NDArray[np.float64]
               ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], int, int]:
    """Sort a buffered pose stream by time and drop non-finite rows and duplicate stamps.

    Returns times, values, the number of backwards steps in arrival order, and rows dropped.
    """
    backwards = int(np.count_nonzero(np.diff(t_ns) < 0)) if t_ns.size > 1 else 0
    ok = np.isfinite(values).all(axis=1)
    t_ns, values = t_ns[ok], values[ok]
    order = np.argsort(t_ns, kind="stable")
    t_ns, values = t_ns[order], values[order]
    keep = np.r_[True, np.diff(t_ns) > 0] if t_ns.size else np.zeros(0, bool)
    dropped = int((~ok).sum() + (~keep).sum())
    return t_ns[keep], values[keep], backwards, dropped


class LabelSidecar:
    """Simulator ground-truth labels per radar point (``radar_labels.parquet``): 0 true, 1 clutter, 2 ghost.

    Looked up beside the log (``X.sim/`` next to ``X.bag``) or inside it (``X/sim/``). A scan's rows are
    found by its message index on the radar topic (``scan``, the ``.bin`` index in the folder form) and
    accepted when the stamps agree within ``tolerance_ns`` (the folder form keeps microseconds only);
    otherwise by the nearest stamp within that tolerance. Points are matched by their index in the scan.
    """

    FILENAME = "radar_labels.parquet"

    def __init__(self, path: Path, tolerance_ns: int = 1_000_000) -> None:
        self.path = path
        self.tolerance_ns = tolerance_ns
        try:
            table = pq.read_table(path, columns=["scan", "t_ns", "point", "label"])
        except Exception as exc:
            raise UserError(f"{path}: unreadable label sidecar ({exc}); regenerate the simulated sequence") from exc
        scan = table["scan"].to_numpy().astype(np.int64)
        t = table["t_ns"].to_numpy().astype(np.int64)
        point = table["point"].to_numpy().astype(np.int64)
        label = table["label"].to_numpy().astype(np.int8)
        order = np.lexsort((point, scan))
        self.scan, self.t, self.point, self.label = scan[order], t[order], point[order], label[order]
        self.scan_ids, starts = np.unique(self.scan, return_index=True)
        self.starts = np.r_[starts, len(self.scan)]
        self.scan_t = self.t[starts]
        by_time = np.argsort(self.scan_t, kind="stable")
        self._sorted_t, self._sorted_k = self.scan_t[by_time], by_time
        self.unmatched_scans = 0

    @classmethod
    def find(cls, source: Path) -> LabelSidecar | None:
        stem = source.name.removesuffix(".bag").removesuffix(".mcap").removesuffix(".db3")
        for cand in (source.parent / f"{stem}.sim" / cls.FILENAME, source / "sim" / cls.FILENAME):
            if cand.is_file():
                return cls(cand)
        return None

    def _scan_slot(self, index: int, t_ns: int) -> int | None:
        k = int(np.searchsorted(self.scan_ids, index))
        if k < len(self.scan_ids) and self.scan_ids[k] == index:
            if abs(int(self.scan_t[k]) - t_ns) <= self.tolerance_ns:
                return k
        j = int(np.searchsorted(self._sorted_t, t_ns))
        best = [c for c in (j - 1, j) if 0 <= c < len(self._sorted_t)]
        if not best:
            return None
        c = min(best, key=lambda c: abs(int(self._sorted_t[c]) - t_ns))
        return int(self._sorted_k[c]) if abs(int(self._sorted_t[c]) - t_ns) <= self.tolerance_ns else None

    def labels_for(self, index: int, t_ns: int, n_points: int) -> npt.NDArray[np.int8]:
        """Labels of the ``n_points`` points of scan message ``index`` stamped ``t_ns`` (-1 where unknown)."""
        out = np.full(n_points, -1, dtype=np.int8)
        if n_points == 0:  # an empty scan has no label rows to find
            return out
        k = self._scan_slot(index, t_ns)
        if k is None:
            self.unmatched_scans += 1
            return out
        lo, hi = self.starts[k], self.starts[k + 1]
        pts = self.point[lo:hi]
        ok = (pts >= 0) & (pts < n_points)
        out[pts[ok]] = self.label[lo:hi][ok]
        return out


@dataclass
class StreamStats:
    """What happened to one stream (kept in the manifest)."""

    messages: int = 0
    points: int = 0
    nonfinite_dropped: int = 0
    zero_dropped: int = 0
    backwards: int = 0
    out_of_order_dropped: int = 0
    record_time_used: int = 0
    #: point-cloud messages published with no points (width 0), and scans left without points after dropping
    empty_messages: int = 0
    scans_without_points: int = 0
    first_t_ns: int | None = None
    last_t_ns: int | None = None

    def as_dict(self) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if v is not None}
        if self.first_t_ns is not None and self.last_t_ns is not None:
            d["duration_s"] = round((self.last_t_ns - self.first_t_ns) * 1e-9, 3)
        return d
