"""Choosing each stream's clock (stages/ingest/clock.py): one test per case of ``ingest.clock.time_source``."""

from __future__ import annotations

import numpy as np
import pytest

from stages.ingest.clock import NS, plan_clocks

T0 = 1_609_459_200 * NS  # record clock (the bag's)
DAYS = round(337_000.25 * NS)


def _sample(rate: float, latency_s: float, header_offset_ns: int | None, n: int = 50, seed: int = 0
            ) -> tuple[np.ndarray, np.ndarray]:
    """(header, record) of ``n`` messages at ``rate``: record = sensor time + latency; header = sensor time +
    ``header_offset_ns`` (None: zero stamps)."""
    rng = np.random.default_rng(seed)
    t = T0 + np.round(np.arange(n) / rate * NS).astype(np.int64)
    rec = t + np.round(rng.uniform(0.5, 1.5, n) * latency_s * NS).astype(np.int64)
    head = np.zeros(n, np.int64) if header_offset_ns is None else t + header_offset_ns
    return head, rec


def test_consistent_header_stamps_are_kept() -> None:
    plan = plan_clocks({"radar": _sample(10, 0.01, 0), "imu": _sample(400, 0.001, 0)}, "auto")
    assert {c.use for c in plan.streams.values()} == {"header"} and not plan.changed
    assert plan.time("radar", 123, 456) == 123


def test_zero_radar_stamps_use_the_record_time_and_imu_header_stays() -> None:
    plan = plan_clocks({"radar": _sample(10, 0.01, None), "imu": _sample(400, 0.001, 0)}, "auto")
    r, i = plan.streams["radar"], plan.streams["imu"]
    assert (r.use, r.problem) == ("record", "header stamps are all zero")
    assert i.use == "header" and plan.changed
    assert plan.time("radar", 0, T0 + 5) == T0 + 5
    assert "radar: header stamps are all zero -> record time" in plan.describe()


def test_imu_on_another_clock_is_shifted_onto_the_record_clock() -> None:
    head, rec = _sample(400, 0.001, -DAYS)
    plan = plan_clocks({"radar": _sample(10, 0.01, None), "imu": (head, rec)}, "auto")
    imu = plan.streams["imu"]
    assert imu.use == "shifted"
    assert imu.shift_ns == pytest.approx(DAYS + 0.001 * NS, abs=0.0006 * NS)  # the offset and the median latency
    aligned = np.array([plan.time("imu", int(h), int(r)) for h, r in zip(head, rec, strict=True)])
    assert np.abs(aligned - rec).max() < 0.001 * NS  # on the record clock, header precision kept
    assert np.all(np.diff(aligned) == np.diff(head))
    assert "header - record -337000.25" in plan.describe()


def test_imu_far_from_a_valid_radar_clock_is_shifted_onto_the_radar_clock() -> None:
    radar = _sample(10, 0.02, -5 * NS)  # a radar clock 5 s behind the record time
    plan = plan_clocks({"radar": radar, "imu": _sample(400, 0.001, +DAYS)}, "auto")
    assert plan.streams["radar"].use == "header"
    imu = plan.streams["imu"]
    assert imu.use == "shifted" and imu.shift_ns == pytest.approx(-DAYS - 5 * NS, abs=0.03 * NS)


def test_small_offsets_within_the_tolerance_are_left_alone() -> None:
    plan = plan_clocks({"radar": _sample(10, 0.01, 0), "imu": _sample(400, 0.001, -round(0.4 * NS))}, "auto",
                       tolerance_s=1.0)
    assert plan.streams["imu"].use == "header" and not plan.changed


def test_constant_header_stamps_are_unusable() -> None:
    head, rec = _sample(10, 0.01, 0)
    head[:] = head[0]
    plan = plan_clocks({"radar": (head, rec), "imu": _sample(400, 0.001, 0)}, "auto")
    assert plan.streams["radar"].use == "record" and "constant" in plan.streams["radar"].problem


def test_time_source_record_uses_the_record_time_for_every_stream() -> None:
    plan = plan_clocks({"radar": _sample(10, 0.01, 0), "imu": _sample(400, 0.001, -DAYS)}, "record")
    assert {c.use for c in plan.streams.values()} == {"record"}
    assert plan.time("imu", 5, 7) == 7


def test_time_source_header_keeps_the_stamps_and_reports_problems() -> None:
    plan = plan_clocks({"radar": _sample(10, 0.01, None), "imu": _sample(400, 0.001, -DAYS)}, "header")
    assert plan.streams["imu"].use == "header" and plan.time("imu", 5, 7) == 5
    assert plan.streams["radar"].problem == "header stamps are all zero"
    assert plan.time("radar", 0, 7) == 7  # a zero stamp still falls back to the record time
