"""Reading and writing artifacts with schema validation.

Every reader goes through :func:`read_artifact`, which checks the schema name, version, required
columns and their types, and fails with one line that names the file and what to do.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from schemas.artifacts import ARTIFACTS, ArtifactSchema

META_NAME = b"radar_pipeline.schema"
META_VERSION = b"radar_pipeline.schema_version"


class SchemaError(ValueError):
    """An artifact does not match its schema (a user-facing error: the message says how to fix it)."""


def _schema(name: str | ArtifactSchema) -> ArtifactSchema:
    if isinstance(name, ArtifactSchema):
        return name
    try:
        return ARTIFACTS[name]
    except KeyError:
        raise KeyError(f"unknown artifact schema {name!r}; known: {', '.join(sorted(ARTIFACTS))}") from None


def _fix_hint(art: ArtifactSchema) -> str:
    return f"rebuild it with `pipeline run {art.stage} --seq <seq> --force`"


def validate_table(table: pa.Table, art: ArtifactSchema, where: str) -> None:
    """Check required columns and types; raise :class:`SchemaError` naming ``where`` on a mismatch."""
    for field in art.schema:
        if field.name not in table.column_names:
            raise SchemaError(
                f"{where}: missing column '{field.name}' required by schema '{art.name}' v{art.version} "
                f"(has: {', '.join(table.column_names) or 'no columns'}); {_fix_hint(art)}"
            )
        got = table.schema.field(field.name).type
        if got != field.type:
            raise SchemaError(
                f"{where}: column '{field.name}' has type {got}, schema '{art.name}' v{art.version} expects "
                f"{field.type}; {_fix_hint(art)}"
            )
        if table.column(field.name).null_count:
            raise SchemaError(f"{where}: column '{field.name}' holds nulls; {_fix_hint(art)}")


def to_table(columns: Mapping[str, Any] | pa.Table, art: ArtifactSchema) -> pa.Table:
    """Build a table from numpy columns, casting required columns to the schema's types."""
    if isinstance(columns, pa.Table):
        table = columns
    else:
        arrays: dict[str, pa.Array] = {}
        for name, values in columns.items():
            if art.schema.get_field_index(name) >= 0:
                typ = art.schema.field(name).type
                arrays[name] = pa.array(values, type=typ) if not isinstance(values, pa.Array) else values
            else:
                arrays[name] = values if isinstance(values, pa.Array) else pa.array(np.asarray(values))
        table = pa.table(arrays)
    ordered = [f.name for f in art.schema if f.name in table.column_names]
    rest = [n for n in table.column_names if n not in ordered]
    return table.select(ordered + rest)


def write_artifact(
    columns: Mapping[str, Any] | pa.Table,
    path: str | Path,
    schema: str | ArtifactSchema,
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Validate and write an artifact atomically (temporary file, then rename)."""
    art = _schema(schema)
    path = Path(path)
    table = to_table(columns, art)
    validate_table(table, art, str(path))
    meta = dict(table.schema.metadata or {})
    meta[META_NAME] = art.name.encode()
    meta[META_VERSION] = str(art.version).encode()
    for k, v in (metadata or {}).items():
        meta[k.encode()] = str(v).encode()
    table = table.replace_schema_metadata(meta)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        float_cols = [f.name for f in table.schema if pa.types.is_floating(f.type)]
        pq.write_table(
            table,
            tmp,
            compression="zstd",
            use_dictionary=[f.name for f in table.schema if not pa.types.is_floating(f.type)],
            column_encoding=dict.fromkeys(float_cols, "BYTE_STREAM_SPLIT") or None,
            row_group_size=1 << 20,
        )
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def read_artifact(
    path: str | Path,
    schema: str | ArtifactSchema,
    columns: Sequence[str] | None = None,
    filters: Any = None,
) -> pa.Table:
    """Read and validate an artifact. Raises :class:`SchemaError` with a one-line fix on any mismatch."""
    art = _schema(schema)
    path = Path(path)
    if not path.exists():
        raise SchemaError(f"{path}: artifact '{art.name}' not found; run `pipeline run {art.stage} --seq <seq>`")
    try:
        file_schema = pq.read_schema(path)
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path}: not a readable Parquet file ({exc}); {_fix_hint(art)}") from exc
    meta = file_schema.metadata or {}
    name = meta.get(META_NAME, b"").decode()
    version = meta.get(META_VERSION, b"").decode()
    if name != art.name:
        raise SchemaError(
            f"{path}: holds schema '{name or 'unknown'}', expected '{art.name}'; {_fix_hint(art)}"
        )
    if version != str(art.version):
        raise SchemaError(
            f"{path}: written with schema '{art.name}' v{version}, this version reads v{art.version}; "
            f"{_fix_hint(art)}"
        )
    try:
        table = pq.read_table(path, columns=list(columns) if columns else None, filters=filters)
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path}: unreadable ({exc}); {_fix_hint(art)}") from exc
    if columns:
        sub = pa.schema([f for f in art.schema if f.name in columns])
        validate_table(table, ArtifactSchema(art.name, art.stage, art.filename, art.version, sub), str(path))
    else:
        validate_table(table, art, str(path))
    return table


class ArtifactWriter:
    """Stream an artifact to Parquet in row-group batches (bounded memory), then rename it into place.

    ``extra`` declares columns beyond the schema's required ones (their types must be fixed up front).
    Rows are buffered until ``batch_rows`` and written as one row group by a background thread (Arrow
    compresses without the GIL, so writing overlaps the caller's work; at most one batch is in flight).
    The schema metadata matches :func:`write_artifact`, so :func:`read_artifact` accepts the file.
    """

    def __init__(
        self,
        path: str | Path,
        schema: str | ArtifactSchema,
        extra: Sequence[pa.Field] = (),
        metadata: Mapping[str, str] | None = None,
        batch_rows: int = 1 << 18,
    ) -> None:
        self.art = _schema(schema)
        self.path = Path(path)
        meta = {META_NAME: self.art.name.encode(), META_VERSION: str(self.art.version).encode()}
        for k, v in (metadata or {}).items():
            meta[k.encode()] = str(v).encode()
        self.schema = pa.schema([*self.art.schema, *extra], metadata=meta)
        self.batch_rows = int(batch_rows)
        self.rows = 0
        self._buf: list[list[Any]] = []
        self._buffered = 0
        self._tmp = self.path.with_name(f".{self.path.name}.{uuid.uuid4().hex[:8]}.tmp")
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"write-{self.art.name}")
        self._pending: Future[None] | None = None
        float_cols = [f.name for f in self.schema if pa.types.is_floating(f.type)]
        self._writer: pq.ParquetWriter | None = pq.ParquetWriter(
            self._tmp,
            self.schema,
            compression="zstd",
            use_dictionary=[f.name for f in self.schema if not pa.types.is_floating(f.type)],
            column_encoding=dict.fromkeys(float_cols, "BYTE_STREAM_SPLIT") or None,
        )

    def write(self, columns: Mapping[str, Any]) -> None:
        """Append rows given as equal-length columns (cast to the declared types when flushed)."""
        arrays = [np.asarray(columns[f.name]) for f in self.schema]
        n = len(arrays[0]) if arrays else 0
        if any(len(a) != n for a in arrays):
            raise ValueError(f"{self.path}: columns of unequal length in one write")
        if n == 0:
            return
        self._buf.append(arrays)
        self._buffered += n
        if self._buffered >= self.batch_rows:
            self.flush()

    def flush(self) -> None:
        """Hand the buffered rows to the writer thread (waiting for the previous batch first)."""
        if not self._buf or self._writer is None:
            return
        cols = [np.concatenate([b[i] for b in self._buf]) for i in range(len(self.schema))]
        self._buf, self._buffered = [], 0
        table = pa.Table.from_arrays([pa.array(c, type=f.type) for c, f in zip(cols, self.schema, strict=True)],
                                     schema=self.schema)
        validate_table(table, self.art, str(self.path))
        self._wait()
        self._pending = self._pool.submit(self._writer.write_table, table,
                                          row_group_size=max(self.batch_rows, table.num_rows))
        self.rows += table.num_rows

    def _wait(self) -> None:
        if self._pending is not None:
            pending, self._pending = self._pending, None
            pending.result()

    def close(self) -> Path:
        """Write the remaining rows and move the file into place."""
        if self._writer is None:
            return self.path
        try:
            self.flush()
            self._wait()
            self._writer.close()
            self._writer = None
            os.replace(self._tmp, self.path)
        finally:
            self._pool.shutdown(wait=True)
            self._tmp.unlink(missing_ok=True)
        return self.path

    def abort(self) -> None:
        """Discard the partial file."""
        try:
            self._wait()
        except Exception:  # the file is discarded anyway
            pass
        self._pool.shutdown(wait=True)
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> ArtifactWriter:
        return self

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
