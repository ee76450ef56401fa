"""Point clouds from and to PLY files with ``meshio`` (MIT), float64 kept exactly as stored.

Reading: our own header check (x, y, z must be the vertex element's first three properties, floating
point, as meshio's PLY reader assumes), then meshio for the data. meshio parses ASCII vertices with
``numpy.genfromtxt``, which converts every double token with Python's ``float`` (correctly rounded), so the
authors' ASCII files (``property double``, written by Open3D) come back bit for bit as the same float64
values as before (``tests/test_map_sequences.py`` compares them with the shared Parquet copies and
``tests/test_ply.py`` with ``float(token)``); binary files are read with ``numpy.frombuffer``, exact by
construction. ``property float`` coordinates are float32 values widened to float64.

Writing: meshio's writer, with its time-stamped ``comment Created by meshio ...`` header line replaced by a
fixed one, so that the same map gives the same bytes.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import BinaryIO

import numpy as np
import numpy.typing as npt

from core.errors import UserError

F64 = npt.NDArray[np.float64]
#: the header comment our files carry instead of meshio's time-stamped one
COMMENT = b"comment Created by radar-pipeline (meshio)"
_FLOAT_TYPES = {"float", "float32", "double", "float64"}
_FORMATS = {"ascii", "binary_little_endian", "binary_big_endian"}


def _header(f: BinaryIO, path: Path, what: str) -> tuple[str, int, list[tuple[str, str]]]:
    """(format, vertex count, vertex properties as (type, name)) of a PLY header; UserError when malformed."""
    def bad(why: str) -> UserError:
        return UserError(f"{path}: unreadable PLY {what} ({why}); the file is truncated or not a PLY file: "
                         "download it again")

    lines: list[str] = []
    while True:
        raw = f.readline()
        if not raw:
            raise bad("no end_header")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise bad("the header is not ASCII") from None
        if not lines and line != "ply":
            raise bad("it does not start with 'ply'")
        lines.append(line)
        if line == "end_header":
            break
        if len(lines) > 10_000:
            raise bad("no end_header in the first 10,000 lines")
    fmt, n_vertex, props, elements = "", -1, [], []
    current = ""
    for line in lines[1:-1]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            current = words[1]
            elements.append(current)
            if current == "vertex":
                if not words[2].isdigit():
                    raise bad(f"vertex count {words[2]!r}")
                n_vertex = int(words[2])
        elif words[0] == "property" and current == "vertex":
            if len(words) != 3:
                raise bad(f"vertex property {line!r} (lists are not supported for vertices)")
            props.append((words[1], words[2]))
        elif words[0] != "property":
            raise bad(f"header line {line!r}")
    if fmt not in _FORMATS:
        raise bad(f"format {fmt or 'missing'!r}")
    if n_vertex < 0:
        raise UserError(f"{path}: PLY {what} has no 'vertex' element (has: {', '.join(elements) or 'none'})")
    others = [e for e in elements if e not in ("vertex", "face")]
    if others:
        raise bad(f"elements {', '.join(others)}: only vertex and face are read")
    names = [n for _, n in props]
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise UserError(f"{path}: PLY {what} lacks vertex properties {', '.join(missing)} (has: {', '.join(names)})")
    if names[:3] != ["x", "y", "z"]:
        raise UserError(f"{path}: PLY {what}: x, y, z must be the first vertex properties (has: {', '.join(names)})")
    types = [t for t, _ in props[:3]]
    if any(t not in _FLOAT_TYPES for t in types):
        raise UserError(f"{path}: PLY vertex x, y, z must be floating point (got {', '.join(types)})")
    return fmt, n_vertex, props


def read_ply_xyz(path: Path, what: str = "point cloud") -> F64:
    """The ``vertex`` x, y, z of a PLY file (ASCII or binary) as an (N, 3) float64 array.

    Double-precision properties are returned bit for bit (the RMap F-score depends on the stored values).
    Raises :class:`UserError` naming the file on an unreadable, truncated or malformed file.
    """
    import meshio

    path = Path(path)
    try:
        with path.open("rb") as f:
            fmt, n, _props = _header(f, path, what)
        if n == 0:  # nothing to parse (meshio's ASCII reader rejects a zero vertex count)
            return np.zeros((0, 3))
        mesh = meshio.read(path, file_format="ply")
    except FileNotFoundError:
        raise UserError(f"{path}: {what} missing") from None
    except UserError:
        raise
    except (meshio.ReadError, ValueError, IndexError, KeyError, UnicodeDecodeError, OSError, EOFError) as exc:
        why = " ".join(str(exc).split()) or type(exc).__name__  # numpy's messages span lines
        raise UserError(f"{path}: unreadable PLY {what} ({why}); the file is truncated or not a PLY file: "
                        "download it again") from exc
    pts = np.asarray(mesh.points)
    if pts.ndim != 2 or pts.shape != (n, 3):
        raise UserError(f"{path}: PLY {what} holds {len(pts)} of the {n} vertices its header announces; the file "
                        "is truncated: download it again")
    if fmt == "ascii" and not np.isfinite(pts).all():
        raise UserError(f"{path}: PLY {what} has non-numeric or non-finite vertex coordinates; download it again")
    return pts.astype(np.float64, copy=False)


def ply_bytes(xyz: npt.ArrayLike, scalars: dict[str, npt.ArrayLike] | None = None, binary: bool = True) -> bytes:
    """A vertex-only PLY file (meshio's writer) of ``xyz`` (N, 3) and per-vertex ``scalars``, as bytes.

    The coordinates and scalars keep their dtypes (float32 -> ``float``, float64 -> ``double``); binary
    files are in the machine's byte order (the header says which); ASCII writes ``repr`` of each value,
    which reads back bit for bit.
    """
    import meshio

    pts = np.ascontiguousarray(xyz)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"xyz must be an (N, 3) array, got shape {pts.shape}")
    point_data = {k: np.ascontiguousarray(v) for k, v in (scalars or {}).items()}
    for k, v in point_data.items():
        if v.shape != (len(pts),):
            raise ValueError(f"scalar {k!r} must have shape ({len(pts)},), got {v.shape}")
    buf = io.BytesIO()
    # meshio's ASCII writer fails on zero vertices; a header-only file is the same in both formats
    as_binary = binary or len(pts) == 0
    meshio.write_points_cells(buf, pts, [], point_data=point_data, file_format="ply", binary=as_binary)
    header, sep, body = buf.getvalue().partition(b"end_header\n")
    lines = [COMMENT if ln.startswith(b"comment Created by meshio") else ln for ln in header.split(b"\n")]
    if not binary:
        lines = [b"format ascii 1.0" if ln.startswith(b"format ") else ln for ln in lines]
    return b"\n".join(lines) + sep + body


def write_ply(path: Path, xyz: npt.ArrayLike, scalars: dict[str, npt.ArrayLike] | None = None,
              binary: bool = True) -> Path:
    """Write :func:`ply_bytes` to ``path`` (not atomic: callers that need that write to a temporary name)."""
    path = Path(path)
    path.write_bytes(ply_bytes(xyz, scalars, binary))
    return path
