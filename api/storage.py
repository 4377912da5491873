"""Local file storage: content-addressed blobs (``blobs/ab/<sha256>.<ext>``) and per-job result directories.

The layout only uses atomic renames inside one directory tree, so it also works on a volume shared by several
machines (API and workers must see the same ``data_dir``).
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
from pathlib import Path

_REF = re.compile(r"^[0-9a-f]{64}\.(bvh|glb|gltf|fbx)$")


class StorageError(Exception):
    """A path outside the storage, or storage that cannot be written."""


class Storage:
    """Files of the service under one root directory."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        self.blobs_dir = self.root / "blobs"
        self.jobs_dir = self.root / "jobs"
        self.tmp_dir = self.root / "tmp"

    def ensure(self) -> None:
        """Create the directories."""
        for d in (self.blobs_dir, self.jobs_dir, self.tmp_dir):
            d.mkdir(parents=True, exist_ok=True)

    # Blobs -------------------------------------------------------------------------------------------------
    @staticmethod
    def blob_ref(sha256: str, fmt: str) -> str:
        """The name of a blob: its SHA-256 and the extension of its detected format."""
        ref = f"{sha256}.{fmt}"
        if not _REF.match(ref):
            raise StorageError(f"not a blob reference: {ref!r}")
        return ref

    def blob_path(self, ref: str) -> Path:
        """Where the blob ``ref`` (``<sha256>.<ext>``) lives."""
        if not _REF.match(ref):
            raise StorageError(f"not a blob reference: {ref!r}")
        return self.blobs_dir / ref[:2] / ref

    def temp_path(self, suffix: str = ".part") -> Path:
        """A fresh path in the temporary directory (same file system as the blobs, so renames are atomic)."""
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        return self.tmp_dir / f"{secrets.token_hex(16)}{suffix}"

    def commit_blob(self, tmp: Path, ref: str) -> tuple[Path, bool]:
        """Move ``tmp`` into place as blob ``ref``; when that blob exists already, drop ``tmp``.

        Returns the blob path and whether it was newly stored."""
        dest = self.blob_path(ref)
        if dest.exists():
            tmp.unlink(missing_ok=True)
            return dest, False
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp, dest)
        return dest, True

    def delete_blob(self, ref: str) -> None:
        """Remove a blob if present."""
        self.blob_path(ref).unlink(missing_ok=True)

    # Jobs --------------------------------------------------------------------------------------------------
    def job_run_dir(self, job_id: str, attempt: int) -> Path:
        """A clean output directory for one run of a job (earlier partial runs are kept apart)."""
        if not re.fullmatch(r"[A-Za-z0-9_-]+", job_id):
            raise StorageError(f"not a job id: {job_id!r}")
        d = self.jobs_dir / job_id / f"run-{attempt}"
        if d.exists():
            shutil.rmtree(d)
        d.mkdir(parents=True)
        return d

    def relative(self, path: Path) -> str:
        """``path`` relative to the storage root (what the database stores)."""
        return Path(path).resolve().relative_to(self.root).as_posix()

    def resolve(self, rel: str) -> Path:
        """The absolute path of a stored relative path; refuses anything outside the root."""
        p = (self.root / rel).resolve()
        if not p.is_relative_to(self.root):
            raise StorageError(f"path outside storage: {rel!r}")
        return p

    def delete_job(self, job_id: str) -> None:
        """Remove every file of a job."""
        shutil.rmtree(self.jobs_dir / job_id, ignore_errors=True)

    def check_writable(self) -> None:
        """Write, read back and remove a small file; raises StorageError with the reason."""
        try:
            self.ensure()
            p = self.temp_path(".probe")
            p.write_bytes(b"ok")
            ok = p.read_bytes() == b"ok"
            p.unlink()
        except OSError as exc:
            raise StorageError(f"storage at {self.root} is not writable: {exc}") from exc
        if not ok:
            raise StorageError(f"storage at {self.root} returned different bytes")
