"""Rerun conventions: one recording id per sequence, one ``.rrd`` per stage, bulk logging by columns.

Timelines are ``scan`` (sequence index) and ``sensor_time`` (timestamp). Entity paths follow
the artifact contract (``world/radar/raw``, ``world/slam/trajectory``, ``metrics/<name>``, ...).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

APPLICATION_ID = "radar-pipeline"

ENTITY_PATHS = (
    "world/groundtruth",
    "world/radar/raw",
    "world/radar/filtered",
    "world/odometry",
    "world/slam/trajectory",
    "world/slam/particles",
    "world/slam/map/occupancy",
    "world/slam/map/uncertainty",
    "world/voxel/radar",
    "world/voxel/lidar",
    "world/patches",
    "world/complete",
    "world/plan",
    "metrics",
)


def recording_id(seq: str) -> str:
    """All stage files of a sequence share this id so the viewer merges them into one recording."""
    return f"{APPLICATION_ID}/{seq}"


def time_columns(scans: npt.ArrayLike | None, t_ns: npt.ArrayLike | None) -> list[rr.TimeColumn]:
    """The ``scan`` and ``sensor_time`` index columns for ``send_columns``."""
    cols: list[rr.TimeColumn] = []
    if scans is not None:
        cols.append(rr.TimeColumn("scan", sequence=np.asarray(scans, dtype=np.int64)))
    if t_ns is not None:
        cols.append(rr.TimeColumn("sensor_time", timestamp=np.asarray(t_ns, dtype=np.int64).astype("datetime64[ns]")))
    return cols


def scan_lengths(scan_ids: npt.NDArray[Any]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """For points sorted by scan: the distinct scan ids and the number of points in each."""
    scan_ids = np.asarray(scan_ids)
    if scan_ids.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.flatnonzero(np.r_[True, scan_ids[1:] != scan_ids[:-1]])
    lengths = np.diff(np.r_[starts, scan_ids.size])
    return scan_ids[starts].astype(np.int64), lengths.astype(np.int64)


class StageRecording:
    """A Rerun recording saved to one ``.rrd`` file.

    The encoded stream is kept by Rerun in memory (a stage's recording is megabytes) and written by Python's file
    I/O when the stage closes it, not by Rerun's file sink, whose background writer blocks for good on a full
    disk: a write error is raised here, where the runner turns it into a one-line message.
    """

    def __init__(self, seq: str, path: str | Path) -> None:
        self.path = Path(path)
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(seq), make_default=False)
        self._stream: rr.BinaryStream | None = rr.binary_stream(recording=self.rec)

    # -- bulk helpers ---------------------------------------------------------------------------------
    def points_over_time(
        self,
        entity: str,
        scans: npt.ArrayLike,
        t_ns: npt.ArrayLike | None,
        positions: npt.ArrayLike,
        lengths: Sequence[int] | npt.ArrayLike,
        colors: npt.ArrayLike | None = None,
        radii: float | None = None,
    ) -> None:
        """One point cloud per time step (ragged), logged in a single ``send_columns`` call."""
        positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        lengths = np.asarray(lengths, dtype=np.int64)
        if lengths.size == 0:
            return
        kwargs: dict[str, Any] = {"positions": positions}
        if colors is not None:
            kwargs["colors"] = np.asarray(colors)
        if radii is not None:
            kwargs["radii"] = np.full(len(positions), radii, dtype=np.float32)
        self.rec.send_columns(
            entity,
            indexes=time_columns(scans, t_ns),
            columns=rr.Points3D.columns(**kwargs).partition(lengths=lengths),
        )

    def points_by_scan(
        self,
        entity: str,
        scan_ids: npt.ArrayLike,
        t_ns: npt.ArrayLike | None,
        positions: npt.ArrayLike,
        colors: npt.ArrayLike | None = None,
        radii: float | None = None,
    ) -> None:
        """Points in a long table sorted by scan: one cloud per scan on the ``scan`` timeline."""
        scan_ids = np.asarray(scan_ids)
        scans, lengths = scan_lengths(scan_ids)
        times = None
        if t_ns is not None:
            t = np.asarray(t_ns)
            starts = np.r_[0, np.cumsum(lengths)[:-1]]
            times = t[starts] if len(t) else None
        self.points_over_time(entity, scans, times, positions, lengths, colors=colors, radii=radii)

    def trajectory(
        self,
        entity: str,
        scans: npt.ArrayLike,
        t_ns: npt.ArrayLike | None,
        xyz: npt.ArrayLike,
        color: tuple[int, int, int] = (255, 255, 255),
    ) -> None:
        """The full path as a static line strip plus the current position over time."""
        xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
        if len(xyz) == 0:
            return
        self.rec.log(entity + "/path", rr.LineStrips3D([xyz], colors=[color]), static=True)
        self.points_over_time(entity + "/pose", scans, t_ns, xyz, np.ones(len(xyz), np.int64),
                              colors=np.tile(np.asarray(color, np.uint8), (len(xyz), 1)), radii=0.08)

    def scalars(self, entity: str, scans: npt.ArrayLike | None, t_ns: npt.ArrayLike | None,
                values: npt.ArrayLike) -> None:
        """A scalar time series in one call."""
        values = np.asarray(values, dtype=np.float64)
        if values.size == 0:
            return
        self.rec.send_columns(entity, indexes=time_columns(scans, t_ns), columns=rr.Scalars.columns(scalars=values))

    def static_points(self, entity: str, positions: npt.ArrayLike, colors: npt.ArrayLike | None = None,
                      radii: float | None = None) -> None:
        positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        self.rec.log(entity, rr.Points3D(positions, colors=colors, radii=radii), static=True)

    def log(self, entity: str, archetype: Any, scan: int | None = None, t_ns: int | None = None,
            static: bool = False) -> None:
        """Log one archetype, optionally at a scan / time."""
        if scan is not None:
            self.rec.set_time("scan", sequence=int(scan))
        if t_ns is not None:
            self.rec.set_time("sensor_time", timestamp=np.datetime64(int(t_ns), "ns"))
        self.rec.log(entity, archetype, static=static)

    def close(self) -> None:
        """Write the recording to its file and release it; a write error (a full disk) is raised."""
        if self._stream is None:
            return
        try:
            data = self._stream.read(flush=True) or b""
            self.path.write_bytes(data)
        finally:
            self.abort()

    def abort(self) -> None:
        """Release the recording without writing it (the stage failed)."""
        if self._stream is not None:
            self._stream = None
            self.rec.disconnect()


def entity_paths_in(path: str | Path) -> set[str]:
    """Entity paths present in an ``.rrd`` file (used by tests and ``pipeline status``)."""
    from rerun.chunk import RrdReader

    return {str(ch.entity_path) for ch in RrdReader(str(path)).stream().to_chunks()}
