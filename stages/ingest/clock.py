"""Which clock each stream's times come from: header stamps, the log's record time, or shifted header stamps.

Pure functions on a sample of each stream's first messages (header stamp and record time, ns). A
stream's header stamps are *unusable* when they are all zero, constant while the record time moves, or
go backwards in most steps; otherwise its offset ``d = median(record - header)`` tells which clock they
are on. ``time_source``:

- ``header``: header stamps as they are (zero stamps fall back to the record time, as before);
- ``record``: the record time for every stream (latency jitter included);
- ``auto``: the reference clock is the radar's header clock when its stamps are usable, else the record
  clock (offset 0). A stream with unusable stamps takes its record time moved onto the reference
  (``record - d_ref``); a stream whose offset differs from the reference by more than ``tolerance_s``
  keeps its header stamps shifted by the difference (``header + d - d_ref``: the stamps' precision is kept,
  the constant clock offset removed); every other stream keeps its header stamps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

TimeSource = Literal["auto", "header", "record"]
NS = 1_000_000_000


@dataclass(frozen=True)
class StreamClock:
    """What was found for one stream and what its times will be."""

    stream: str
    #: 'header', 'record' or 'shifted' (header + shift_ns)
    use: str
    shift_ns: int = 0
    #: median(record - header) over the sample, ns (None when the header stamps are unusable)
    offset_ns: int | None = None
    #: why the header stamps are unusable ('' when usable)
    problem: str = ""

    def time(self, header_ns: int, record_ns: int) -> int:
        if self.use == "record" or (self.use == "header" and header_ns == 0):
            return record_ns + self.shift_ns
        return header_ns + self.shift_ns


@dataclass
class ClockPlan:
    """Per-stream clocks for one log."""

    source: str
    streams: dict[str, StreamClock] = field(default_factory=dict)

    def time(self, stream: str, header_ns: int, record_ns: int) -> int:
        c = self.streams.get(stream)
        if c is None:
            return header_ns if header_ns else record_ns
        return c.time(header_ns, record_ns)

    @property
    def changed(self) -> bool:
        """Whether any stream does not simply use its own header stamps."""
        return any(c.use != "header" or c.problem for c in self.streams.values())

    def describe(self) -> str:
        """One line: offsets found and what each stream uses."""
        parts = []
        for c in self.streams.values():
            found = c.problem or (f"header - record {-(c.offset_ns or 0) / NS:+.3f} s" if c.offset_ns is not None
                                  else "header")
            if c.use == "record":
                used = "record time" + (f" {c.shift_ns / NS:+.3f} s" if c.shift_ns else "")
            elif c.use == "shifted":
                used = f"header stamps {c.shift_ns / NS:+.3f} s"
            else:
                used = "header stamps"
            parts.append(f"{c.stream}: {found} -> {used}")
        return "; ".join(parts)

    def as_dict(self) -> dict[str, dict[str, object]]:
        return {s: {"use": c.use, "shift_s": c.shift_ns / NS, "offset_s": None if c.offset_ns is None
                    else c.offset_ns / NS, "problem": c.problem} for s, c in self.streams.items()}


def header_problem(header: npt.NDArray[np.int64], record: npt.NDArray[np.int64]) -> str:
    """Why a stream's header stamps cannot be used ('' when they can)."""
    if header.size == 0:
        return ""
    if np.all(header == 0):
        return "header stamps are all zero"
    if header.size > 2 and np.all(header == header[0]) and np.ptp(record) > 0:
        return f"header stamps are constant ({header[0] / NS:.3f} s)"
    if header.size > 4 and np.count_nonzero(np.diff(header) < 0) > header.size // 2:
        return "header stamps go backwards in most steps"
    return ""


def plan_clocks(samples: dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]], source: TimeSource,
                tolerance_s: float = 1.0, reference: str = "radar") -> ClockPlan:
    """Decide each stream's clock from ``samples[stream] = (header_ns, record_ns)`` of its first messages."""
    plan = ClockPlan(source)
    found: dict[str, tuple[str, int | None]] = {}
    for stream, (h, r) in samples.items():
        h = np.asarray(h, dtype=np.int64)
        r = np.asarray(r, dtype=np.int64)
        problem = header_problem(h, r)
        ok = h != 0
        offset = int(np.median(r[ok] - h[ok])) if not problem and ok.any() else None
        found[stream] = (problem, offset)
    if source == "record":
        for stream, (problem, offset) in found.items():
            plan.streams[stream] = StreamClock(stream, "record", 0, offset, problem)
        return plan
    if source == "header":
        for stream, (problem, offset) in found.items():
            plan.streams[stream] = StreamClock(stream, "header", 0, offset, problem)
        return plan
    tol = round(tolerance_s * NS)
    ref_problem, ref_offset = found.get(reference, ("", None))
    d_ref = ref_offset if (not ref_problem and ref_offset is not None) else 0
    for stream, (problem, offset) in found.items():
        if problem or offset is None:
            plan.streams[stream] = StreamClock(stream, "record", -d_ref, offset, problem or "no header stamps")
        elif abs(offset - d_ref) > tol:
            plan.streams[stream] = StreamClock(stream, "shifted", offset - d_ref, offset)
        else:
            plan.streams[stream] = StreamClock(stream, "header", 0, offset)
    return plan


def spans_overlap(a: tuple[int, int], b: tuple[int, int]) -> bool:
    return a[0] <= b[1] and b[0] <= a[1]
