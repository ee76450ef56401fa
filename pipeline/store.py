"""The run store: ``runs/<seq>/<stage>/`` folders, manifests, keys, atomic commits and the per-sequence lock.

A stage writes into ``runs/<seq>/.tmp-<stage>-<id>/``; on success the runner writes the manifest there
and swaps the folder into place with two renames. An interrupted swap is repaired the next time the
lock is taken, so a failed or killed stage always leaves the previous good result.
"""

from __future__ import annotations

import getpass
import hashlib
import json
import os
import shutil
import socket
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from filelock import FileLock, Timeout

from core.errors import LockHeldError

MANIFEST = "manifest.json"


def canonical_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def compute_key(stage: str, params: dict[str, Any], code_version: str, inputs: dict[str, str],
                extra: dict[str, Any]) -> str:
    """A stage's key: sha256 of its effective parameters, code version, input keys and extra material."""
    payload = {"stage": stage, "params": params, "code": code_version, "inputs": inputs, "extra": extra}
    return hashlib.sha256(canonical_json(payload).encode()).hexdigest()[:20]


def file_digest(path: Path) -> str:
    """sha256 of a file, read in 1 MiB blocks."""
    with path.open("rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to a temporary name beside ``path``, then rename it into place (never half a file)."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json_atomic(path: Path, obj: Any) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


@dataclass
class RunStore:
    """Paths and manifests of one sequence's runs."""

    runs_dir: Path
    seq: str

    @property
    def seq_dir(self) -> Path:
        return self.runs_dir / self.seq

    def stage_dir(self, stage: str) -> Path:
        return self.seq_dir / stage

    def manifest_path(self, stage: str) -> Path:
        return self.stage_dir(stage) / MANIFEST

    def damage(self, stage: str, checksums: bool = False, manifest: dict[str, Any] | None = None) -> str | None:
        """What is wrong with the finished result's files (one line), or None: each artifact the manifest lists
        must have its recorded size and, with ``checksums``, its recorded sha256 (``manifest``: the stage's,
        when the caller has read it already)."""
        manifest = manifest if manifest is not None else self.read_manifest(stage)
        if manifest is None:
            return None
        for name, rec in manifest.get("artifacts", {}).items():
            path = self.stage_dir(stage) / name
            size, digest = (rec, None) if isinstance(rec, int) else (rec.get("size"), rec.get("sha256"))
            try:
                actual = path.stat().st_size
            except OSError:
                return f"{path} is missing"
            if size is not None and actual != size:
                return f"{path} is {actual} bytes, the manifest recorded {size}"
            if checksums and digest is not None and file_digest(path) != digest:
                return f"{path} does not match its recorded sha256"
        return None

    def read_manifest(self, stage: str) -> dict[str, Any] | None:
        """The stage's manifest if it is complete and all listed artifacts exist, else None."""
        path = self.manifest_path(stage)
        try:
            manifest: dict[str, Any] = json.loads(path.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None
        if not manifest.get("complete"):
            return None
        for name in manifest.get("artifacts", {}):
            if not (self.stage_dir(stage) / name).exists():
                return None
        return manifest

    # -- atomic commit ---------------------------------------------------------------------------------
    def new_temp_dir(self, stage: str) -> Path:
        self.seq_dir.mkdir(parents=True, exist_ok=True)
        tmp = self.seq_dir / f".tmp-{stage}-{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        return tmp

    def commit(self, stage: str, tmp: Path, manifest: dict[str, Any]) -> Path:
        """Write the manifest into ``tmp`` and swap it into place."""
        manifest["artifacts"] = {
            p.name: {"size": p.stat().st_size, "sha256": file_digest(p)}
            for p in sorted(tmp.iterdir()) if p.is_file() and p.name != MANIFEST
        }
        manifest["complete"] = True
        write_json_atomic(tmp / MANIFEST, manifest)
        return self.swap_in(stage, tmp)

    def swap_in(self, stage: str, tmp: Path) -> Path:
        """Replace ``runs/<seq>/<stage>`` by the finished folder ``tmp`` (two renames)."""
        final = self.stage_dir(stage)
        old = None
        if final.exists():
            old = self.seq_dir / f".old-{stage}-{uuid.uuid4().hex[:8]}"
            os.rename(final, old)
        os.rename(tmp, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return final

    def import_from(self, other: RunStore, stage: str) -> Path:
        """Bring a finished stage folder of another store in with hard links (copies across devices)."""
        tmp = self.new_temp_dir(stage)
        tmp.rmdir()

        def link(src: str, dst: str) -> None:
            try:
                os.link(src, dst)
            except OSError:
                shutil.copy2(src, dst)

        try:
            shutil.copytree(other.stage_dir(stage), tmp, copy_function=link)
            return self.swap_in(stage, tmp)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    def recover(self) -> list[str]:
        """Repair interrupted commits and remove temporary folders. Call with the lock held."""
        notes: list[str] = []
        if not self.seq_dir.exists():
            return notes
        for old in sorted(self.seq_dir.glob(".old-*")):
            stage = old.name[len(".old-"):].rsplit("-", 1)[0]
            final = self.stage_dir(stage)
            if not final.exists():
                os.rename(old, final)
                notes.append(f"restored the previous result of '{stage}' after an interrupted commit")
            else:
                shutil.rmtree(old, ignore_errors=True)
        for tmp in self.seq_dir.glob(".tmp-*"):
            shutil.rmtree(tmp, ignore_errors=True)
            notes.append(f"removed leftover temporary folder {tmp.name}")
        return notes

    # -- lock --------------------------------------------------------------------------------------------
    @contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the per-sequence lock; refuse at once with a clear message when another run holds it."""
        self.seq_dir.mkdir(parents=True, exist_ok=True)
        lock_path = self.seq_dir / ".lock"
        info_path = self.seq_dir / ".lock.info"
        lock = FileLock(str(lock_path), timeout=0)
        try:
            lock.acquire()
        except Timeout:
            holder = ""
            try:
                info = json.loads(info_path.read_text())
                since = time.strftime("%H:%M:%S", time.localtime(info.get("since", 0)))
                holder = f" (pid {info.get('pid')} on {info.get('host')} since {since})"
            except (FileNotFoundError, json.JSONDecodeError):
                pass
            raise LockHeldError(
                f"sequence '{self.seq}' is being run by another process{holder}; wait for it to finish "
                f"(lock: {lock_path})"
            ) from None
        try:
            try:
                write_json_atomic(info_path, {"pid": os.getpid(), "host": socket.gethostname(),
                                              "user": getpass.getuser(), "since": time.time()})
            except OSError:
                pass  # who holds the lock is a courtesy (a full disk must not stop the run from reporting it)
            yield
        finally:
            info_path.unlink(missing_ok=True)
            lock.release()
