"""Damaged copies of a ROS1 bag, for fault tests: streams dropped, clocks that jump or pause, radar scans
emptied or filled with NaN. Each function reads ``src`` and writes a new bag ``dst`` (rosbags)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Reader, Writer

from simulator import rig
from simulator.bagwriter import coloradar_typestore

NS = 1_000_000_000

#: (topic, record time ns, message or None to drop) -> (record time ns, message or None)
Edit = Callable[[str, int, Any], tuple[int, Any]]


def rewrite(src: Path, dst: Path, edit: Edit, topics: Iterable[str] | None = None) -> Path:
    """Copy ``src`` to ``dst`` passing every message of ``topics`` (default: all) through ``edit``."""
    ts = coloradar_typestore()
    keep = None if topics is None else set(topics)
    with Reader(src) as r:
        conns = [c for c in r.connections if keep is None or c.topic in keep]
        t_first = r.start_time
        items: list[tuple[int, int, bytes]] = []
        for c, t, raw in r.messages(connections=conns):
            msg = ts.deserialize_ros1(raw, c.msgtype)
            t_new, msg = edit(c.topic, t - t_first, msg)
            if msg is None:
                continue
            items.append((t_first + t_new, c.id, bytes(ts.serialize_ros1(msg, c.msgtype))))
    items.sort(key=lambda x: x[0])
    with Writer(dst) as w:
        out = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest) for c in conns}
        for t, cid, raw in items:
            w.write(out[cid], t, raw)
    return dst


def _shift_stamp(msg: Any, shift_ns: int) -> Any:
    header = getattr(msg, "header", None)
    if header is None:
        return msg
    ns = header.stamp.sec * NS + header.stamp.nanosec + shift_ns
    stamp = replace(header.stamp, sec=ns // NS, nanosec=ns % NS)
    return replace(msg, header=replace(header, stamp=stamp))


def clock_jump(src: Path, dst: Path, after_s: float, jump_s: float, topics: Iterable[str]) -> Path:
    """Messages of ``topics`` later than ``after_s`` into the log are stamped (and recorded) ``jump_s`` later."""
    chosen = set(topics)

    def edit(topic: str, t: int, msg: Any) -> tuple[int, Any]:
        if topic in chosen and t > after_s * NS:
            shift = int(jump_s * NS)
            return t + shift, _shift_stamp(msg, shift)
        return t, msg

    return rewrite(src, dst, edit)


def pause_all(src: Path, dst: Path, after_s: float, pause_s: float) -> Path:
    """Every stream stops at ``after_s`` and resumes ``pause_s`` later (a recorder paused)."""
    return clock_jump(src, dst, after_s, pause_s, _all_topics(src))


def radar_points(src: Path, dst: Path, fill: str) -> Path:
    """Every radar scan emptied (``fill="empty"``) or its coordinates set to NaN (``fill="nan"``)."""

    def edit(topic: str, t: int, msg: Any) -> tuple[int, Any]:
        if topic != rig.RADAR_TOPIC:
            return t, msg
        if fill == "empty":
            return t, replace(msg, width=0, row_step=0, data=np.zeros(0, np.uint8))
        data = np.array(msg.data, dtype=np.uint8, copy=True)
        step = msg.point_step
        offsets = [f.offset for f in msg.fields if f.name in ("x", "y", "z")]
        n = len(data) // step
        nan = np.frombuffer(np.float32(np.nan).tobytes(), np.uint8)
        for off in offsets:
            for k in range(4):
                data[np.arange(n) * step + off + k] = nan[k]
        return t, replace(msg, data=data)

    return rewrite(src, dst, edit)


def drop_topics(src: Path, dst: Path, keep: Iterable[str]) -> Path:
    """A copy holding only ``keep`` (e.g. radar and IMU without lidar or ground truth)."""
    return rewrite(src, dst, lambda topic, t, msg: (t, msg), topics=keep)


def _all_topics(src: Path) -> list[str]:
    with Reader(src) as r:
        return sorted({c.topic for c in r.connections})
