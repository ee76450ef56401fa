"""Versioned pyarrow schemas of every artifact and the one validator that readers use."""

from schemas.artifacts import ARTIFACTS, ArtifactSchema, artifact_for_file
from schemas.io import SchemaError, read_artifact, validate_table, write_artifact

__all__ = [
    "ARTIFACTS",
    "ArtifactSchema",
    "SchemaError",
    "artifact_for_file",
    "read_artifact",
    "validate_table",
    "write_artifact",
]
