"""The upload store: tracked-video datasets uploaded as archives, and ordinary videos, by id, in a local folder
(``<data_dir>/uploads/``).

An upload is streamed to a temporary file (never held whole in memory, refused once it passes ``max_bytes``),
then, in a worker thread, checked and extracted (:mod:`service.jobs.archive`), validated as the portable format
(``render_core.data.portable.validate_dataset``: every problem listed) and only then published by one rename::

    <root>/<upload_id>/dataset/      the dataset folder (what training reads)
    <root>/<upload_id>/upload.json   id, created_at, size and sha256 of the archive, frames, width, height,
                                     face_model, the original file name, the archive kind, and what the upload
                                     takes on disk (stored_bytes) in how many entries (files)

A **video** (recognised by its first bytes, whatever its name: :func:`service.jobs.video.sniff_video`) is kept as
the file itself, probed for the limits without decoding it (:func:`service.jobs.video.probe_upload`: refused with a
:class:`~service.jobs.video.VideoError` over ``max_video_seconds``, ``max_video_side``, ``max_video_frames``, too
short, or not decodable); the job that trains on it tracks it first (:mod:`service.jobs.track`)::

    <root>/<upload_id>/video.<mp4|mov|webm|mkv>   the video as received
    <root>/<upload_id>/upload.json                kind "video", its container, frames, width, height (as
                                                  displayed), fps, duration; face_model: the tracker's (open head)

The archive itself is deleted once extracted: face video is biometric data, so the store keeps one copy only, and
:meth:`UploadStore.delete` and :meth:`UploadStore.sweep` (retention) really remove the files. A refused or
abandoned upload leaves nothing behind. Work in progress lives under names starting with ``.`` (never an id):
``.incoming-*`` (the archive being received, and its lock), ``.staging-*`` (extraction and validation),
``.deleting-*`` (the trash: a deletion's files being removed in the background); :meth:`UploadStore.clean_stale`
removes what a killed process left, :meth:`UploadStore.empty_trash` what it was deleting
(:mod:`service.jobs.leftovers`).

**What an upload stores** is measured once, at ingest (:func:`service.usage.tree_usage`), and recorded: the tenant's
storage quota counts those bytes (:meth:`UploadStore.tenant_bytes`), not the archive's, and its entries count
against the tenant's file bound (:meth:`UploadStore.tenant_files`). An extraction that takes more than
``limits.max_extraction_ratio`` times the archive's bytes on disk is refused (:class:`ArchiveError`, reason
``bomb``); ``admit``, given by the caller, is asked with the measure before the upload is published (the HTTP
route's refuses past the tenant's quota or file bound), and a refusal keeps nothing.
"""

from __future__ import annotations

import asyncio
import json
import os
import secrets
import shutil
import threading
from collections.abc import AsyncIterator, Awaitable, Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path

from render_core.data.portable import MANIFEST, validate_dataset

from .. import intake
from ..errors import NotFound
from ..usage import BLOCK, Usage, tree_usage
from .archive import ArchiveError, ArchiveLimits, detect_kind, extract_archive
from .leftovers import Trash, UploadLock, clean_stale
from .records import (
    DATASET,
    ID_PATTERN,
    RECORD,
    VIDEO,
    InvalidDataset,
    Upload,
    check_upload_id,
    display_name,
    write_record,
)
from .video import CONTAINERS, probe_upload, sniff_video, tracker_limits

__all__ = ["ID_PATTERN", "InvalidDataset", "Upload", "UploadStore", "check_upload_id"]

Spool = Callable[[AsyncIterator[bytes], Path], Awaitable[intake.Spooled]]  # body -> the file it is written to
Admit = Callable[[Usage], None]  # what an upload stores, before it is published: raises to refuse it



class UploadStore:
    """Uploaded datasets and videos under ``root``. ``limits`` bound what an archive may hold (default:
    :class:`ArchiveLimits` defaults); ``video_limits`` what a video may be (a
    :class:`~render_core.tracking.video.VideoLimits`; default: the tracker's, which the settings' defaults are)."""

    def __init__(self, root: str | os.PathLike, *, limits: ArchiveLimits | None = None, video_limits=None):
        self.root = Path(root)
        self.limits = limits or ArchiveLimits()
        self.video_limits = video_limits if video_limits is not None else tracker_limits()
        self._publish_lock = threading.Lock()
        self.trash = Trash(self.root)  # deletions: renamed out of sight, removed in the background

    def ensure(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------------------------------------- receiving
    async def receive(self, chunks: AsyncIterator[bytes], *, max_bytes: int, filename: str | None = None,
                      tenant: str | None = None, spool: Spool | None = None, admit: Admit | None = None) -> Upload:
        """Receive one archive or video from ``chunks``, check (an archive: extract and validate; a video: probe)
        and publish it; return its record.

        ``spool`` writes the body to the path it is given (default: :func:`service.intake.spool` bounded by
        ``max_bytes``; the HTTP route passes its :class:`~service.intake.UploadIntake`'s, which also checks the
        tenant's quota on the bytes that arrived, before anything is extracted); ``admit`` is asked with what the
        upload takes on disk, extracted, before it is published (module docstring).
        Raises :class:`~service.errors.BodyTooLarge` once more than ``max_bytes`` arrived (the rest is not read),
        :class:`~service.jobs.archive.ArchiveError` for an archive refused (or bytes that are neither an archive nor
        a video), :class:`InvalidDataset` for a dataset that is not valid, :class:`~service.jobs.video.VideoError`
        for a video refused. Whatever happens (also when the caller is cancelled, e.g. the client went away), a refused
        upload leaves nothing in the store."""
        self.ensure()
        lock = UploadLock(self.root)  # held until the end: service/jobs/leftovers.py
        token = lock.acquire()
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
                                           tenant, admit)
        except asyncio.CancelledError:
            with self._publish_lock:  # the worker thread either published already or never will
                cancelled.set()
                published = state["published"]
            if published is not None:
                self._remove(published)
            raise
        finally:
            incoming.unlink(missing_ok=True)
            lock.release()

    def _ingest(self, archive: Path, token: str, size: int, sha256: str, filename: str | None,
                cancelled: threading.Event, state: dict, tenant: str | None = None, admit: Admit | None = None,
                ) -> Upload:
        """(Worker thread.) Extract and validate (a video: probe), and publish; on any failure or cancellation
        remove the staging folder."""
        staging = self.root / f".staging-{token}"
        staging.mkdir(mode=0o700)
        try:
            container = sniff_video(archive)
            fields = (self._stage_video(archive, staging, container) if container is not None
                      else self._stage_dataset(archive, staging, size))
            used = tree_usage(staging) + Usage(BLOCK, 1)  # and the record, written next
            if admit is not None:
                admit(used)
            upload_id = "upl_" + secrets.token_urlsafe(16)
            upload = Upload(id=upload_id, created_at=datetime.now(UTC).replace(microsecond=0), size=size,
                            sha256=sha256, filename=display_name(filename), tenant=tenant,
                            stored_bytes=used.bytes, files=used.files, **fields)
            write_record(staging / RECORD, upload)
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

    def _stage_dataset(self, archive: Path, staging: Path, size: int) -> dict:
        """Extract and validate the archive (``size`` bytes) into ``staging/dataset``; the record's fields."""
        kind = detect_kind(archive)
        root = extract_archive(archive, staging / "extract", self.limits)
        archive.unlink(missing_ok=True)  # one copy only: the extracted dataset
        self._check_ratio(tree_usage(staging).bytes, size)
        problems = validate_dataset(root)
        if problems:
            raise InvalidDataset(problems)
        manifest = json.loads((root / MANIFEST).read_text(encoding="utf-8"))
        os.rename(root, staging / DATASET)
        if (staging / "extract").exists():
            shutil.rmtree(staging / "extract")
        return {"frames": int(manifest["frames"]), "width": int(manifest["width"]),
                "height": int(manifest["height"]), "face_model": str(manifest["face_model"]), "archive": kind}

    def _check_ratio(self, stored: int, size: int) -> None:
        """The extraction as measured on disk against ``max_extraction_ratio`` (the archive's checks estimated it
        before writing; a file system with larger blocks is caught here)."""
        limits = self.limits
        if stored > max(limits.ratio_grace_bytes, limits.max_extraction_ratio * size):
            raise ArchiveError(f"a decompression bomb: the extraction takes {stored} bytes on disk, more than "
                               f"{limits.max_extraction_ratio:g} times the archive's {size} (max_extraction_ratio)",
                               reason="bomb")

    def _stage_video(self, received: Path, staging: Path, container: str) -> dict:
        """Move the video into ``staging/video.<container>`` (one copy: the file itself) and probe it against the
        limits (:class:`~service.jobs.video.VideoError`); the record's fields."""
        from render_core.facemodel.open_head import NAME as OPEN_HEAD

        video = staging / f"{VIDEO}.{container}"
        os.rename(received, video)
        meta = probe_upload(video, container, self.video_limits)
        os.chmod(video, 0o644)
        return {"kind": "video", "frames": meta.frames, "width": meta.width, "height": meta.height,
                "face_model": OPEN_HEAD, "archive": None, "container": container, "duration": meta.duration,
                "fps": meta.fps}

    # -------------------------------------------------------------------------------------------------- reading
    def get(self, upload_id: str) -> Upload:
        """The record of a published upload; NotFound if there is none."""
        folder = self._folder(upload_id)
        try:
            return Upload.from_json(json.loads((folder / RECORD).read_text(encoding="utf-8")))
        except (OSError, ValueError, KeyError, TypeError):
            raise NotFound(f"no upload {upload_id!r}", field="upload_id") from None

    def path(self, upload_id: str) -> Path:
        """The dataset folder of a published dataset upload (what training reads); NotFound if there is none. (A
        video upload has none: :meth:`video_path`.)"""
        self.get(upload_id)
        return self.root / upload_id / DATASET

    def video_path(self, upload_id: str) -> Path:
        """The file of a published video upload (what its job tracks); NotFound if there is none, or the upload is
        a dataset."""
        upload = self.get(upload_id)
        if upload.kind != "video" or upload.container not in CONTAINERS:
            raise NotFound(f"upload {upload_id!r} is a dataset, not a video", field="upload_id")
        return self.root / upload_id / f"{VIDEO}.{upload.container}"

    def tenant_bytes(self, tenant: str) -> int:
        """Bytes on disk of ``tenant``'s uploads, as extracted (its storage quota counts them): their records'."""
        return sum(u.usage.bytes for u in self.list() if u.tenant == tenant)

    def tenant_files(self, tenant: str) -> int:
        """Entries on disk (files and folders) of ``tenant``'s uploads (its file bound counts them)."""
        return sum(u.usage.files for u in self.list() if u.tenant == tenant)

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
        """Delete an upload: its folder is renamed into the trash at once (readers stop seeing it), then its files
        are removed in the background (:class:`~service.jobs.leftovers.Trash`). NotFound if there is none."""
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
        """Remove what killed processes left (received archives, staging folders): at once when the process that
        received the upload is gone, else (an older version's names) when last modified more than ``older_than``
        ago; how many entries were removed. Call it at start-up and now and then; an upload another process is
        receiving is never taken (:func:`service.jobs.leftovers.clean_stale`)."""
        return clean_stale(self.root, older_than)

    def empty_trash(self) -> int:
        """Have the trash emptied in the background (deletions a killed process did not finish); how many trees."""
        return self.trash.empty()

    def _remove(self, upload_id: str) -> bool:
        """Move the upload's folder into the trash (readers stop seeing it at once); its files go in the
        background. False when it was not there."""
        return self.trash.discard(self.root / upload_id)


# --------------------------------------------------------------------------------------------------------- helpers
class _Abandoned(Exception):
    """The receiving task was cancelled before the upload was published: the worker thread cleans up."""


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
