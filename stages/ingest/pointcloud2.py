"""sensor_msgs/PointCloud2 to numpy, by the message's own field table (no assumption of packed fields).

The point layout is described by ``fields`` (name, offset, datatype, count), ``point_step``,
``row_step``, ``height``, ``width`` and ``is_bigendian``. A structured dtype with explicit offsets and
``itemsize = point_step`` views the buffer without copying; rows padded beyond ``width * point_step``
(``row_step`` larger) are handled by viewing each row separately.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

#: sensor_msgs/PointField datatype constants -> numpy type codes (without byte order)
DATATYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
DATATYPE_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32", 7: "FLOAT32",
                  8: "FLOAT64"}


class PointCloudError(ValueError):
    """A PointCloud2 message whose layout is inconsistent or lacks a requested field."""


@dataclass(frozen=True)
class Field:
    """One sensor_msgs/PointField."""

    name: str
    offset: int
    datatype: int
    count: int = 1


def fields_of(msg: Any) -> list[Field]:
    """The field table of a deserialized PointCloud2 message (rosbags or any object with ``fields``)."""
    return [Field(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]


def point_dtype(fields: Sequence[Field], point_step: int, big_endian: bool,
                names: Sequence[str] | None = None) -> np.dtype[Any]:
    """Structured dtype for one point: the requested fields (all by default) at their offsets."""
    order = ">" if big_endian else "<"
    wanted = [f for f in fields if names is None or f.name in names]
    formats: list[Any] = []
    for f in wanted:
        if f.datatype not in DATATYPES:
            raise PointCloudError(f"field '{f.name}' has unknown PointField datatype {f.datatype}")
        code = order + DATATYPES[f.datatype]
        formats.append((code, (f.count,)) if f.count > 1 else code)
        size = np.dtype(code).itemsize * max(f.count, 1)
        if f.offset < 0 or f.offset + size > point_step:
            raise PointCloudError(
                f"field '{f.name}' (offset {f.offset}, {size} bytes) does not fit in point_step {point_step}"
            )
    return np.dtype({"names": [f.name for f in wanted], "formats": formats,
                     "offsets": [f.offset for f in wanted], "itemsize": point_step})


@dataclass(frozen=True)
class Layout:
    """A prepared point layout: the structured dtype of the wanted fields and the output mapping."""

    dtype: np.dtype[Any]
    columns: tuple[tuple[str, str], ...]
    point_step: int


def prepare(fields: Sequence[Field], point_step: int, is_bigendian: bool, columns: Mapping[str, str]) -> Layout:
    """Check the wanted fields exist and build their dtype (reusable for every message with this layout)."""
    by_name = {f.name: f for f in fields}
    missing = [src for src in columns.values() if src not in by_name]
    if missing:
        have = ", ".join(f.name for f in fields) or "none"
        raise PointCloudError(f"missing field(s) {', '.join(missing)} (message has: {have})")
    if point_step <= 0:
        raise PointCloudError(f"point_step {point_step} is not positive")
    dt = point_dtype(fields, point_step, is_bigendian, names=sorted(set(columns.values())))
    return Layout(dt, tuple(columns.items()), int(point_step))


def view(layout: Layout, data: bytes | bytearray | memoryview | npt.NDArray[np.uint8], *, row_step: int, width: int,
         height: int, dtype: npt.DTypeLike = np.float32) -> dict[str, npt.NDArray[Any]]:
    """Decode one buffer with a prepared layout into flat, native-order arrays of ``dtype``."""
    point_step = layout.point_step
    n = int(width) * int(height)
    out_dtype = np.dtype(dtype)
    if n == 0:
        return {k: np.zeros(0, out_dtype) for k, _ in layout.columns}
    row_step = int(row_step) if height > 1 or row_step else width * point_step
    if row_step < width * point_step:
        raise PointCloudError(f"row_step {row_step} is smaller than width*point_step {width * point_step}")
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8)
    need = (height - 1) * row_step + width * point_step
    if buf.size < need:
        raise PointCloudError(f"data holds {buf.size} bytes, the layout needs {need}")
    if height == 1 or row_step == width * point_step:
        points = np.ndarray((n,), dtype=layout.dtype, buffer=buf.data if buf.flags.c_contiguous else buf.copy().data)
    else:
        rows = np.lib.stride_tricks.as_strided(buf, shape=(height, width * point_step), strides=(row_step, 1))
        packed = np.ascontiguousarray(rows).reshape(-1)
        points = np.ndarray((n,), dtype=layout.dtype, buffer=packed.data)
    out: dict[str, npt.NDArray[Any]] = {}
    for name, src in layout.columns:
        col = points[src]
        if col.ndim > 1:  # count > 1: keep the first element
            col = col[:, 0]
        out[name] = col.astype(out_dtype)  # copies: native byte order, contiguous
    return out


def decode(
    fields: Sequence[Field],
    data: bytes | bytearray | memoryview | npt.NDArray[np.uint8],
    *,
    point_step: int,
    row_step: int,
    width: int,
    height: int,
    is_bigendian: bool,
    columns: Mapping[str, str],
    dtype: npt.DTypeLike = np.float32,
) -> dict[str, npt.NDArray[Any]]:
    """Decode the fields named in ``columns`` (output name -> field name) into flat arrays of ``dtype``.

    Raises :class:`PointCloudError` when a field is missing or the buffer is shorter than the layout.
    """
    if int(width) * int(height) == 0:
        return {k: np.zeros(0, np.dtype(dtype)) for k in columns}
    layout = prepare(fields, point_step, is_bigendian, columns)
    return view(layout, data, row_step=row_step, width=width, height=height, dtype=dtype)


def decode_message(msg: Any, columns: Mapping[str, str], dtype: npt.DTypeLike = np.float32
                   ) -> dict[str, npt.NDArray[Any]]:
    """:func:`decode` applied to a deserialized sensor_msgs/PointCloud2."""
    return decode(fields_of(msg), msg.data, point_step=int(msg.point_step), row_step=int(msg.row_step),
                  width=int(msg.width), height=int(msg.height), is_bigendian=bool(msg.is_bigendian),
                  columns=columns, dtype=dtype)


def resolve_fields(fields: Sequence[Field], wanted: Mapping[str, Sequence[str]]) -> tuple[dict[str, str], list[str]]:
    """Pick, for each output column, the first candidate field name present in the message.

    Returns the mapping output -> field and the list of outputs for which no candidate exists.
    """
    names = {f.name for f in fields}
    mapping: dict[str, str] = {}
    missing: list[str] = []
    for out, candidates in wanted.items():
        found = next((c for c in candidates if c in names), None)
        if found is None:
            missing.append(out)
        else:
            mapping[out] = found
    return mapping, missing


def encode(columns: Mapping[str, npt.ArrayLike], layout: Sequence[Field], point_step: int,
           big_endian: bool = False) -> bytes:
    """Inverse of :func:`decode` for one row (tests and the benchmark's fixtures): pack columns by offsets."""
    n = len(np.asarray(next(iter(columns.values()))))
    dt = point_dtype(layout, point_step, big_endian)
    arr = np.zeros(n, dtype=dt)
    for f in layout:
        if f.name in columns:
            arr[f.name] = np.asarray(columns[f.name])
    return arr.tobytes()
