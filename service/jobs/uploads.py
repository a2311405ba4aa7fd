"""The upload store: tracked-video datasets uploaded as archives, by id, in a local folder
(``<data_dir>/uploads/``).

An upload is streamed to a temporary file (never held whole in memory, refused once it passes ``max_bytes``),
then, in a worker thread, checked and extracted (:mod:`service.jobs.archive`), validated as the portable format
(``render_core.data.portable.validate_dataset``: every problem listed) and only then published by one rename::

    <root>/<upload_id>/dataset/      the dataset folder (what training reads)
    <root>/<upload_id>/upload.json   id, created_at, size and sha256 of the archive, frames, width, height,
                                     face_model, the original file name, the archive kind

The archive itself is deleted once extracted: face video is biometric data, so the store keeps one copy only, and
:meth:`UploadStore.delete` and :meth:`UploadStore.sweep` (retention) really remove the files. A refused or
abandoned upload leaves nothing behind. Work in progress lives under names starting with ``.`` (never an id):
``.incoming-*`` (the archive being received), ``.staging-*`` (extraction and validation), ``.deleting-*`` (a
deletion in progress); :meth:`UploadStore.clean_stale` removes those a killed process left.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import secrets
import shutil
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import asdict, dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

from render_core.data.portable import MANIFEST, validate_dataset

from .. import intake
from ..errors import InvalidArgument, NotFound
from .archive import ArchiveLimits, detect_kind, extract_archive

__all__ = ["ID_PATTERN", "InvalidDataset", "Upload", "UploadStore", "check_upload_id"]

Spool = Callable[[AsyncIterator[bytes], Path], Awaitable[intake.Spooled]]  # body -> the file it is written to

ID_PATTERN = re.compile(r"^upl_[A-Za-z0-9_-]{16,64}$")
RECORD = "upload.json"
DATASET = "dataset"
_TEMP_PREFIXES = (".incoming-", ".staging-", ".deleting-")
_MAX_PROBLEMS = 50  # problems kept in an InvalidDataset
_MAX_PROBLEM_CHARS = 300  # each
_MAX_MESSAGE_CHARS = 4000
_MAX_FILENAME_CHARS = 255


class InvalidDataset(InvalidArgument):
    """The archive was well formed but the dataset in it is not valid. ``problems`` lists them (``"field or file:
    message"``, as ``blendsplat data validate`` prints them; at most 50, each bounded); the message names them
    all up to a bounded length. ``field`` is ``"file"``."""

    def __init__(self, problems: list[str]):
        self.count = len(problems)
        self.problems = [_clip(p, _MAX_PROBLEM_CHARS) for p in problems[:_MAX_PROBLEMS]]
        text = f"the dataset is not valid ({self.count} problem{'s' if self.count != 1 else ''}): "
        shown = 0
        for p in self.problems:
            if len(text) + len(p) + 2 > _MAX_MESSAGE_CHARS:
                break
            text += ("; " if shown else "") + p
            shown += 1
        if shown < self.count:
            text += f"; ... and {self.count - shown} more"
        super().__init__(text, field="file")


@dataclass(frozen=True)
class Upload:
    """What the store records about a published upload (``upload.json``)."""

    id: str
    created_at: datetime  # UTC
    size: int  # bytes of the archive as received
    sha256: str  # of the archive as received
    frames: int
    width: int
    height: int
    face_model: str
    filename: str | None  # the client's file name (display only: never used as a path)
    archive: str  # "tar", "tar.gz" or "zip"
    tenant: str | None = None  # the owning tenant (service/access/auth.py; None: admin keys only)

    def to_json(self) -> dict:
        """The JSON object of ``upload.json`` (``created_at`` as ISO 8601 UTC)."""
        out = asdict(self)
        out["created_at"] = self.created_at.isoformat().replace("+00:00", "Z")
        return out

    @classmethod
    def from_json(cls, data: dict) -> Upload:
        created = datetime.fromisoformat(data["created_at"].replace("Z", "+00:00"))
        return cls(id=str(data["id"]), created_at=created, size=int(data["size"]), sha256=str(data["sha256"]),
                   frames=int(data["frames"]), width=int(data["width"]), height=int(data["height"]),
                   face_model=str(data["face_model"]), filename=data.get("filename"),
                   archive=str(data.get("archive", "")),
                   tenant=data["tenant"] if isinstance(data.get("tenant"), str) else None)


def check_upload_id(upload_id: str, field: str = "upload_id") -> str:
    """``upload_id`` if it is an upload id (``upl_`` then 16 to 64 of ``A-Z a-z 0-9 _ -``), else InvalidArgument."""
    if not isinstance(upload_id, str) or not ID_PATTERN.match(upload_id):
        raise InvalidArgument(f"{str(upload_id)[:80]!r} is not an upload id ('upl_' followed by 16 to 64 letters, "
                              "digits, '_' or '-')", field=field)
    return upload_id


class UploadStore:
    """Uploaded datasets under ``root``. ``limits`` bound what an archive may hold (default: :class:`ArchiveLimits`
    defaults)."""

    def __init__(self, root: str | os.PathLike, *, limits: ArchiveLimits | None = None):
        self.root = Path(root)
        self.limits = limits or ArchiveLimits()
        self._publish_lock = threading.Lock()

    def ensure(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------------------------------------- receiving
    async def receive(self, chunks: AsyncIterator[bytes], *, max_bytes: int, filename: str | None = None,
                      tenant: str | None = None, spool: Spool | None = None) -> Upload:
        """Receive one archive from ``chunks``, check, extract, validate and publish it; return its record.

        ``spool`` writes the body to the path it is given (default: :func:`service.intake.spool` bounded by
        ``max_bytes``; the HTTP route passes its :class:`~service.intake.UploadIntake`'s, which also checks the
        tenant's quota on the bytes that arrived, before anything is extracted).
        Raises :class:`~service.errors.BodyTooLarge` once more than ``max_bytes`` arrived (the rest is not read),
        :class:`~service.jobs.archive.ArchiveError` for an archive refused, :class:`InvalidDataset` for a dataset that
        is not valid. Whatever happens (also when the caller is cancelled, e.g. the client went away), a refused
        upload leaves nothing in the store."""
        self.ensure()
        token = secrets.token_hex(8)
        incoming = self.root / f".incoming-{token}.tmp"
        cancelled = threading.Event()
        state = {"published": None}
        try:
            if spool is None:
                size, sha256 = await intake.spool(chunks, incoming, max_bytes, "file")
            else:
                spooled = await spool(chunks, incoming)
                size, sha256 = spooled.size, spooled.sha256
            return await asyncio.to_thread(self._ingest, incoming, token, size, sha256, filename, cancelled, state,
                                           tenant)
        except asyncio.CancelledError:
            with self._publish_lock:  # the worker thread either published already or never will
                cancelled.set()
                published = state["published"]
            if published is not None:
                self._remove(published)
            raise
        finally:
            incoming.unlink(missing_ok=True)

    def _ingest(self, archive: Path, token: str, size: int, sha256: str, filename: str | None,
                cancelled: threading.Event, state: dict, tenant: str | None = None) -> Upload:
        """(Worker thread.) Extract, validate and publish; on any failure or cancellation remove the staging
        folder."""
        staging = self.root / f".staging-{token}"
        staging.mkdir(mode=0o700)
        try:
            kind = detect_kind(archive)
            root = extract_archive(archive, staging / "extract", self.limits)
            archive.unlink(missing_ok=True)  # one copy only: the extracted dataset
            problems = validate_dataset(root)
            if problems:
                raise InvalidDataset(problems)
            manifest = json.loads((root / MANIFEST).read_text(encoding="utf-8"))
            os.rename(root, staging / DATASET)
            if (staging / "extract").exists():
                shutil.rmtree(staging / "extract")
            upload_id = "upl_" + secrets.token_urlsafe(16)
            upload = Upload(id=upload_id, created_at=datetime.now(UTC).replace(microsecond=0), size=size,
                            sha256=sha256, frames=int(manifest["frames"]), width=int(manifest["width"]),
                            height=int(manifest["height"]), face_model=str(manifest["face_model"]),
                            filename=_display_name(filename), archive=kind, tenant=tenant)
            _write_record(staging / RECORD, upload)
            os.chmod(staging, 0o755)
            target = self.root / upload_id
            with self._publish_lock:
                if cancelled.is_set():
                    raise _Abandoned(upload_id)
                os.rename(staging, target)
                state["published"] = upload_id
            _fsync_dir(self.root)
            return upload
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise

    # -------------------------------------------------------------------------------------------------- reading
    def get(self, upload_id: str) -> Upload:
        """The record of a published upload; NotFound if there is none."""
        folder = self._folder(upload_id)
        try:
            return Upload.from_json(json.loads((folder / RECORD).read_text(encoding="utf-8")))
        except (OSError, ValueError, KeyError, TypeError):
            raise NotFound(f"no upload {upload_id!r}", field="upload_id") from None

    def path(self, upload_id: str) -> Path:
        """The dataset folder of a published upload (what training reads); NotFound if there is none."""
        self.get(upload_id)
        return self.root / upload_id / DATASET

    def tenant_bytes(self, tenant: str) -> int:
        """Bytes of the archives ``tenant`` uploaded that are still kept (its storage quota counts them)."""
        return sum(u.size for u in self.list() if u.tenant == tenant)

    def list(self) -> list[Upload]:
        """Every published upload, oldest first."""
        out = []
        for name in self._ids():
            try:
                out.append(self.get(name))
            except NotFound:
                continue  # deleted meanwhile
        return sorted(out, key=lambda u: (u.created_at, u.id))

    def _ids(self) -> list[str]:
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if ID_PATTERN.match(p.name) and p.is_dir())

    def _folder(self, upload_id: str) -> Path:
        folder = self.root / check_upload_id(upload_id)
        if not folder.is_dir() or folder.is_symlink():
            raise NotFound(f"no upload {upload_id!r}", field="upload_id")
        return folder

    # ------------------------------------------------------------------------------------------------- deleting
    def delete(self, upload_id: str) -> None:
        """Delete an upload: its folder is renamed out of sight at once, then its files are removed. NotFound if
        there is none."""
        self._folder(upload_id)
        if not self._remove(upload_id):
            raise NotFound(f"no upload {upload_id!r}", field="upload_id")

    def sweep(self, older_than: timedelta, *, now: datetime | None = None) -> list[str]:
        """Retention: delete every upload created more than ``older_than`` before ``now`` (default: the current
        time, UTC); the ids removed. A folder without a readable record counts by its modification time."""
        now = now or datetime.now(UTC)
        cutoff = now - older_than
        removed = []
        for upload_id in self._ids():
            try:
                created = self.get(upload_id).created_at
            except NotFound:
                try:
                    created = datetime.fromtimestamp((self.root / upload_id).stat().st_mtime, UTC)
                except OSError:
                    continue
            if created < cutoff and self._remove(upload_id):
                removed.append(upload_id)
        return removed

    def clean_stale(self, older_than: timedelta = timedelta(0)) -> int:
        """Remove what a killed process left (received archives, staging folders, unfinished deletions) last
        modified more than ``older_than`` ago; how many entries were removed. Call it at start-up; where several
        processes share the folder, pass a grace longer than any upload takes, so that another process's upload in
        progress is spared."""
        if not self.root.is_dir():
            return 0
        cutoff = time.time() - older_than.total_seconds()
        count = 0
        for p in self.root.iterdir():
            if not p.name.startswith(_TEMP_PREFIXES):
                continue
            try:
                if older_than and p.lstat().st_mtime > cutoff:
                    continue
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                else:
                    p.unlink()
                count += 1
            except FileNotFoundError:
                continue
        return count

    def _remove(self, upload_id: str) -> bool:
        """Rename the upload's folder to a ``.deleting-`` name (readers stop seeing it at once), then remove it."""
        doomed = self.root / f".deleting-{upload_id}-{secrets.token_hex(4)}"
        try:
            os.rename(self.root / upload_id, doomed)
        except FileNotFoundError:
            return False
        shutil.rmtree(doomed)
        return True


# --------------------------------------------------------------------------------------------------------- helpers
class _Abandoned(Exception):
    """The receiving task was cancelled before the upload was published: the worker thread cleans up."""


def _clip(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _display_name(filename: str | None) -> str | None:
    """The client's file name for display: its last path component, printable characters only, bounded."""
    if not filename:
        return None
    base = re.split(r"[/\\]", str(filename))[-1]
    base = "".join(c for c in base if c.isprintable())
    return _clip(base, _MAX_FILENAME_CHARS) or None


def _write_record(path: Path, upload: Upload) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(upload.to_json(), f, indent=2)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.chmod(path, 0o644)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
