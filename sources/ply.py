"""Point clouds from PLY files (``plyfile``), float64 kept exactly as stored."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from pipeline.errors import UserError


def read_ply_xyz(path: Path, what: str = "point cloud") -> npt.NDArray[np.float64]:
    """The ``vertex`` x, y, z of a PLY file (ASCII or binary) as an (N, 3) float64 array.

    Double-precision properties are returned bit for bit (the RMap F-score depends on the stored values).
    Raises :class:`UserError` naming the file on an unreadable, truncated or malformed file.
    """
    from plyfile import PlyData, PlyParseError

    try:
        ply = PlyData.read(str(path))
    except FileNotFoundError:
        raise UserError(f"{path}: {what} missing") from None
    except (PlyParseError, ValueError, UnicodeDecodeError, OSError, EOFError) as exc:
        raise UserError(f"{path}: unreadable PLY {what} ({exc}); the file is truncated or not a PLY file: "
                        "download it again") from exc
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise UserError(f"{path}: PLY {what} has no 'vertex' element (has: {', '.join(names) or 'none'})")
    vertex = ply["vertex"]
    props = [p.name for p in vertex.properties]
    missing = [c for c in ("x", "y", "z") if c not in props]
    if missing:
        raise UserError(f"{path}: PLY {what} lacks vertex properties {', '.join(missing)} (has: {', '.join(props)})")
    kinds = {c: vertex[c].dtype for c in ("x", "y", "z")}
    if any(d.kind != "f" for d in kinds.values()):
        raise UserError(f"{path}: PLY vertex x, y, z must be floating point (got {kinds})")
    return np.stack([np.asarray(vertex[c], dtype=np.float64) for c in ("x", "y", "z")], axis=1)
