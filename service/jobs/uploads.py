"""The upload store: tracked-video datasets uploaded as archives, and ordinary videos, by id, in a local folder
(``<data_dir>/uploads/``).

An upload is streamed to a temporary file (never held whole in memory, refused once it passes ``max_bytes``),
then, in a worker thread, checked and extracted (:mod:`service.jobs.archive`), validated as the portable format
(``render_core.data.portable.validate_dataset``: every problem listed) and only then published by one rename::

    <root>/<upload_id>/dataset/      the dataset folder (what training reads)
    <root>/<upload_id>/upload.json   id, created_at, size and sha256 of the archive, frames, width, height,
                                     face_model, the original file name, the archive kind

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
from .video import CONTAINERS, probe_upload, sniff_video, tracker_limits

__all__ = ["ID_PATTERN", "InvalidDataset", "Upload", "UploadStore", "check_upload_id"]

Spool = Callable[[AsyncIterator[bytes], Path], Awaitable[intake.Spooled]]  # body -> the file it is written to

ID_PATTERN = re.compile(r"^upl_[A-Za-z0-9_-]{16,64}$")
RECORD = "upload.json"
DATASET = "dataset"
VIDEO = "video"  # a video upload's file: video.<container>
KINDS = ("dataset", "video")
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
    archive: str | None  # "tar", "tar.gz" or "zip"; None for a video
    tenant: str | None = None  # the owning tenant (service/access/auth.py; None: admin keys only)
    kind: str = "dataset"  # "dataset" (an archive, extracted) or "video" (kept as the file, tracked by its job)
    container: str | None = None  # a video's: "mp4", "mov", "webm" or "mkv"
    duration: float | None = None  # a video's seconds
    fps: float | None = None  # a video's frame rate

    def to_json(self) -> dict:
        """The JSON object of ``upload.json`` (``created_at`` as ISO 8601 UTC; a dataset's record as before videos:
        without ``kind`` and the video fields)."""
        out = asdict(self)
        out["created_at"] = self.created_at.isoformat().replace("+00:00", "Z")
        if self.kind == "dataset":
            for key in ("kind", "container", "duration", "fps"):
                out.pop(key)
        return out

    @classmethod
    def from_json(cls, data: dict) -> Upload:
        created = datetime.fromisoformat(data["created_at"].replace("Z", "+00:00"))
        return cls(id=str(data["id"]), created_at=created, size=int(data["size"]), sha256=str(data["sha256"]),
                   frames=int(data["frames"]), width=int(data["width"]), height=int(data["height"]),
                   face_model=str(data["face_model"]), filename=data.get("filename"),
                   archive=data["archive"] if isinstance(data.get("archive"), str) else None,
                   tenant=data["tenant"] if isinstance(data.get("tenant"), str) else None,
                   kind=str(data.get("kind") or "dataset"), container=data.get("container"),
                   duration=_number(data.get("duration")), fps=_number(data.get("fps")))


def check_upload_id(upload_id: str, field: str = "upload_id") -> str:
    """``upload_id`` if it is an upload id (``upl_`` then 16 to 64 of ``A-Z a-z 0-9 _ -``), else InvalidArgument."""
    if not isinstance(upload_id, str) or not ID_PATTERN.match(upload_id):
        raise InvalidArgument(f"{str(upload_id)[:80]!r} is not an upload id ('upl_' followed by 16 to 64 letters, "
                              "digits, '_' or '-')", field=field)
    return upload_id


class UploadStore:
    """Uploaded datasets and videos under ``root``. ``limits`` bound what an archive may hold (default:
    :class:`ArchiveLimits` defaults); ``video_limits`` what a video may be (a
    :class:`~render_core.tracking.video.VideoLimits`; default: the tracker's, which the settings' defaults are)."""

    def __init__(self, root: str | os.PathLike, *, limits: ArchiveLimits | None = None, video_limits=None):
        self.root = Path(root)
        self.limits = limits or ArchiveLimits()
        self.video_limits = video_limits if video_limits is not None else tracker_limits()
        self._publish_lock = threading.Lock()

    def ensure(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------------------------------------- receiving
    async def receive(self, chunks: AsyncIterator[bytes], *, max_bytes: int, filename: str | None = None,
                      tenant: str | None = None, spool: Spool | None = None) -> Upload:
        """Receive one archive or video from ``chunks``, check (an archive: extract and validate; a video: probe)
        and publish it; return its record.

        ``spool`` writes the body to the path it is given (default: :func:`service.intake.spool` bounded by
        ``max_bytes``; the HTTP route passes its :class:`~service.intake.UploadIntake`'s, which also checks the
        tenant's quota on the bytes that arrived, before anything is extracted).
        Raises :class:`~service.errors.BodyTooLarge` once more than ``max_bytes`` arrived (the rest is not read),
        :class:`~service.jobs.archive.ArchiveError` for an archive refused (or bytes that are neither an archive nor
        a video), :class:`InvalidDataset` for a dataset that is not valid, :class:`~service.jobs.video.VideoError`
        for a video refused. Whatever happens (also when the caller is cancelled, e.g. the client went away), a refused
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
        """(Worker thread.) Extract and validate (a video: probe), and publish; on any failure or cancellation
        remove the staging folder."""
        staging = self.root / f".staging-{token}"
        staging.mkdir(mode=0o700)
        try:
            container = sniff_video(archive)
            fields = (self._stage_video(archive, staging, container) if container is not None
                      else self._stage_dataset(archive, staging))
            upload_id = "upl_" + secrets.token_urlsafe(16)
            upload = Upload(id=upload_id, created_at=datetime.now(UTC).replace(microsecond=0), size=size,
                            sha256=sha256, filename=_display_name(filename), tenant=tenant, **fields)
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

    def _stage_dataset(self, archive: Path, staging: Path) -> dict:
        """Extract and validate the archive into ``staging/dataset``; the record's fields."""
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
        return {"frames": int(manifest["frames"]), "width": int(manifest["width"]),
                "height": int(manifest["height"]), "face_model": str(manifest["face_model"]), "archive": kind}

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
        """Bytes of the archives and videos ``tenant`` uploaded that are still kept (its storage quota counts them)."""
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


def _number(value) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


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
