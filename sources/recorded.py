"""Recorded logs: ColoRadar runs under ``$COLORADAR_ROOT`` and ad-hoc paths (``--source``)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

from core.errors import UserError

ROOT_VAR = "COLORADAR_ROOT"


def coloradar_locations(run: str | None) -> list[Path]:
    """Where a ColoRadar run is looked for under ``$COLORADAR_ROOT``, in order (bag, folder, short names)."""
    root = os.environ.get(ROOT_VAR)
    if not root or run is None:
        return []
    short = run.split("_", 3)[-1] if run[:1].isdigit() else run
    base = Path(root)
    out: list[Path] = []
    for n in dict.fromkeys([run, short]):
        out += [base / f"{n}.bag", base / n, base / "bags" / f"{n}.bag", base / f"{n}.mcap"]
    return out


def missing_log_error(name: str, run: str | None, tried: list[Path]) -> UserError:
    if not os.environ.get(ROOT_VAR):
        return UserError(f"sequence '{name}' ({run}): {ROOT_VAR} is not set; point it at the folder holding the "
                         "ColoRadar bags or extracted runs, or use --source PATH")
    where = ", ".join(str(p) for p in tried[:2])
    return UserError(f"sequence '{name}': no data found (looked for {where}, ...); download {run} or use "
                     "--source PATH")


def log_stem(path: Path) -> str:
    """A sequence name for an unregistered log path."""
    return path.name.removesuffix(".bag").removesuffix(".mcap").removesuffix(".db3") or "source"


def fingerprint(path: Path) -> dict[str, Any]:
    """Cheap identity of a data source for cache keys: path, sizes and mtimes (not a content hash)."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    h = hashlib.sha256()
    total = 0
    for f in files:
        st = f.stat()
        total += st.st_size
        h.update(f"{f.relative_to(path) if path.is_dir() else f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    return {"path": str(path), "bytes": total, "files": len(files), "digest": h.hexdigest()[:16]}
