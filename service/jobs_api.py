"""The training jobs' REST API (issue 15): dataset uploads, jobs, their artefacts, and real deletion.

Routes (mounted by :func:`service.http_app.create_app`; every answer is a pydantic model, every error the one JSON
error shape of :mod:`service.errors`)::

    POST   /v1/uploads                      multipart/form-data, the archive in the field ``file``: 201 + Location
    GET    /v1/uploads                      every upload, oldest first
    GET    /v1/uploads/{id}
    DELETE /v1/uploads/{id}                 204; 409 while a queued or running job uses it
    POST   /v1/jobs                         JSON JobRequest (+ Idempotency-Key): 201 + Location, 200 on a replay
    GET    /v1/jobs?state=&limit=&cursor=   newest first, keyset pages: {jobs, next_cursor}
    GET    /v1/jobs/{id}
    POST   /v1/jobs/{id}/cancel             202 with the job (200 when it had already finished)
    GET    /v1/jobs/{id}/artefacts/{name}   report | summary | curves | contact-sheet | preview | log
    GET    /v1/jobs/{id}/events             server-sent events: the job's history, then live (service/job_events.py)
    DELETE /v1/jobs/{id}                    204: the row, its events and its work folder

The handlers are thin: :class:`Training` holds the stores (:class:`~service.jobs.JobStore`,
:class:`~service.uploads.UploadStore`) and the few operations that span them (deletion with what is derived,
retention). The job database is the source of truth of a job; its files live in its work folder
``<settings.work_dir>/<job id>/``, written by the worker (``service/worker.py``).

**Uploads are streamed**: the body is parsed as it arrives (python-multipart's streaming parser, not FastAPI's
``UploadFile``, which spools the whole body first) and the file part's bytes go straight to
:meth:`UploadStore.receive`, which writes them to disk, refuses more than ``settings.max_dataset_bytes`` (HTTP
413), checks and extracts the archive and validates the dataset (HTTP 422 with the reason); a refused upload
leaves nothing behind.

**Deletion is real** (face video is biometric data):

- a job: its row and events go at once, then its work folder (checkpoints, previews, log, report, the bundle's
  copy). A worker training it finds the row gone before its next iteration and stops without writing more and
  without committing; a file it was writing at that moment is removed by the next retention sweep (a work folder
  without a job row is an orphan);
- an upload: refused (409, the jobs named) while a queued or running job trains on it: cancel or delete those
  first. Otherwise its dataset goes, and with it the work folders of the finished jobs trained on it (their
  previews and contact sheets show the face); those jobs' rows stay (no image data in them) and their artefacts
  answer 404. Avatars trained from it stay: they are deleted on their own;
- an avatar: its bundle and the store's verification record are removed and every cached copy in this process is
  dropped (other replicas find it gone at their next session; streams already open keep theirs until they end).
  The work folder of the job that trained it is the job's (DELETE the job, or retention);
- retention (:meth:`Training.sweep`, at start and every :data:`RETENTION_INTERVAL_SECONDS`): uploads older than
  ``upload_retention_hours`` (except those a queued or running job still needs) and the work folders of jobs that
  finished more than ``work_retention_hours`` ago (0: never by age); job rows are kept (they hold no image data and
  keep the job's history and result). Orphaned work folders and what killed processes left are removed too.
"""

from __future__ import annotations

import asyncio
import logging
import os
import re
import secrets
import shutil
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_serializer
from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect

from . import job_events
from .archive import ArchiveError
from .auth import TRUSTED, Access, Principal
from .errors import FailedPrecondition, InvalidArgument, NotFound
from .http_auth import Caller
from .jobs import Job, JobState, JobStore
from .jobs.store import CURSOR_PATTERN
from .openapi import ErrorBody
from .settings import Settings
from .store import ID_PATTERN as AVATAR_ID_PATTERN
from .store import Owner
from .uploads import ID_PATTERN as UPLOAD_ID_PATTERN
from .uploads import InvalidDataset, Upload, UploadStore, UploadTooLarge
from .webhooks import MAX_URL_CHARS as MAX_WEBHOOK_URL
from .webhooks import check_url as check_webhook_url

if TYPE_CHECKING:
    from .metrics import Metrics

log = logging.getLogger(__name__)

RETENTION_INTERVAL_SECONDS = 300.0  # how often a service process runs the retention sweep
STALE_GRACE = timedelta(minutes=15)  # upload leftovers younger than this may be another process's upload in progress
ORPHAN_GRACE = timedelta(minutes=1)  # a work folder without a job row, untouched this long, is removed
MAX_PAGE = 500
_MULTIPART_SLACK = 64 << 10  # multipart framing and small form fields allowed beyond max_dataset_bytes
_MAX_PART_HEADERS = 16 << 10  # bytes of part headers, all parts together
_MAX_OTHER_PARTS = 64 << 10  # bytes of form fields other than ``file``
_PAGE = 500  # jobs read per query when scanning

# name in the URL -> (file in the work folder, media type); the worker writes them (service/worker.py)
# http(s)://host[:port][/path...]: no credentials, no whitespace (webhooks.check_url checks the rest)
WEBHOOK_URL_PATTERN = (r"^https?://[A-Za-z0-9][A-Za-z0-9.-]{0,252}(:([1-9][0-9]{0,3}|[1-5][0-9]{4}|6[0-4][0-9]{3}|"
                       r"65[0-4][0-9]{2}|655[0-2][0-9]|6553[0-5]))?(/[!-~]*)?$")
JOB_ID_PATTERN = re.compile(r"^job_[A-Za-z0-9_-]{1,60}$")
ARTEFACTS: dict[str, tuple[str, str]] = {
    "report": ("report.json", "application/json"),
    "summary": ("summary.json", "application/json"),
    "curves": ("curves.png", "image/png"),
    "contact-sheet": ("contact_sheet.png", "image/png"),
    "preview": ("preview.png", "image/png"),
    "truth": ("truth.png", "image/png"),
    "log": ("log.jsonl", "application/x-ndjson"),
}


# ----------------------------------------------------------------------------------------------------- models


class UploadLinks(BaseModel):
    self: str
    jobs: str = Field(description="where to POST a job that trains on this upload")


class UploadOut(BaseModel):
    upload_id: str
    size: int = Field(description="bytes of the archive as received (the archive itself is not kept)")
    sha256: str = Field(description="of the archive as received")
    frames: int
    width: int
    height: int
    face_model: str = Field(description="the face model the video was tracked with")
    filename: str | None = Field(None, description="the client's file name (display only)")
    archive: str = Field(description="tar, tar.gz or zip")
    created_at: datetime
    links: UploadLinks

    @classmethod
    def of(cls, upload: Upload) -> UploadOut:
        return cls(upload_id=upload.id, size=upload.size, sha256=upload.sha256, frames=upload.frames,
                   width=upload.width, height=upload.height, face_model=upload.face_model, filename=upload.filename,
                   archive=upload.archive, created_at=upload.created_at,
                   links=UploadLinks(self=f"/v1/uploads/{upload.id}", jobs="/v1/jobs"))


class UploadList(BaseModel):
    uploads: list[UploadOut]


class JobRequest(BaseModel):
    """A training job: train ``preset`` on an upload and commit the avatar to the bundle store as ``avatar_id``
    (replacing an avatar of that id, as ``PUT /v1/avatars/{id}`` does)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"upload_id": "upl_0123456789abcdefghij", "preset": "tiny", "avatar_id": "ada"}]})

    upload_id: str = Field(pattern=UPLOAD_ID_PATTERN.pattern, description="an upload's id (POST /v1/uploads)")
    preset: Literal["tiny", "paper"] = Field("tiny", description="tiny: minutes on a CPU; paper: the paper's "
                                                                 "40k iterations")
    iterations: int | None = Field(None, ge=1, le=1_000_000, description="default: the preset's")
    avatar_id: str = Field(pattern=AVATAR_ID_PATTERN.pattern, max_length=128,
                           description="the id the trained avatar gets in the bundle store")
    resolution: int | None = Field(None, ge=16, le=8192,
                                   description="longest image side to train at (accepted; today the worker trains at "
                                               "the dataset's own resolution and says so in the job's log)")
    seed: int = Field(0, ge=0, le=2**32 - 1)
    webhook_url: str | None = Field(None, min_length=8, max_length=MAX_WEBHOOK_URL, pattern=WEBHOOK_URL_PATTERN,
                                    description="http(s) URL that gets a signed POST on every state change of the job "
                                                "(service/webhooks.py); left out of the spec when not given")

    @field_validator("avatar_id")
    @classmethod
    def _avatar_id(cls, value: str) -> str:
        if value.endswith(".tmp"):
            raise ValueError("an avatar id may not end in '.tmp'")
        return value

    @field_validator("webhook_url")
    @classmethod
    def _webhook_url(cls, value: str | None) -> str | None:
        return None if value is None else check_webhook_url(value)

    @model_serializer(mode="wrap")
    def _without_unset_webhook(self, handler):
        out = handler(self)
        if out.get("webhook_url") is None:
            out.pop("webhook_url", None)
        return out


class WebhookOut(BaseModel):
    id: str = Field(description="the message id (the webhook-id header), the same on every attempt")
    event: str = Field(description="job.running, job.succeeded, job.failed, job.cancelled or job.queued (requeued)")
    status: Literal["pending", "delivered", "failed"]
    attempts: int
    last_status: int | None = Field(description="the HTTP status of the last answer")
    last_error: str | None
    next_attempt_at: datetime | None
    created_at: datetime
    delivered_at: datetime | None


class Progress(BaseModel):
    fraction: float | None = Field(None, description="0 to 1")
    iteration: int | None = None
    total_iterations: int | None = None
    eta_seconds: float | None = None
    loss: float | None = None
    psnr: float | None = None
    gaussians: int | None = None


class JobLinks(BaseModel):
    self: str
    cancel: str
    upload: str | None = None
    artefacts: dict[str, str] = Field(description="the artefacts written so far, by name")
    avatar: str | None = Field(None, description="the trained avatar (when the job succeeded)")


class JobOut(BaseModel):
    id: str
    state: JobState
    spec: dict[str, Any] = Field(description="the job's request (JobRequest's fields)")
    attempts: int
    max_attempts: int
    cancel_requested: bool
    progress: Progress
    error: str | None
    result: dict[str, Any] | None = Field(description="on success: avatar_id, digest, evaluation, final_psnr, "
                                                      "iterations, seconds")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    links: JobLinks
    webhooks: list[WebhookOut] = Field([], description="the deliveries of the job's webhook_url, oldest first")


class JobList(BaseModel):
    jobs: list[JobOut]
    next_cursor: str | None = Field(description="pass as ?cursor= for the next page; null on the last")


# --------------------------------------------------------------------------------------------------- training
@dataclass
class SweepReport:
    uploads: list[str]
    work_folders: list[str]
    stale: int


class Training:
    """The training side of a service process: its settings, job store and upload store, and the operations that
    span them. Synchronous (the stores are): async callers run it in a thread."""

    def __init__(self, settings: Settings, jobs: JobStore, uploads: UploadStore, metrics: Metrics | None = None):
        self.settings, self.jobs, self.uploads, self.metrics = settings, jobs, uploads, metrics
        self.work_root = Path(settings.work_dir)
        self.access: Access | None = None  # limits and audit (the process sets it: service/server.py)
        self.owner_of_avatar: Callable[[str], Owner | None] | None = None  # an existing avatar's owner

    # ------------------------------------------------------------------------------------------- ownership
    def job_for(self, job_id: str, principal: Principal) -> Job:
        """The job, when ``principal`` may see it (its tenant's; admin: any): NotFound, PermissionDenied."""
        job = self.jobs.get(job_id)
        principal.check_read(f"job {job_id}", job.tenant)
        return job

    def upload_for(self, upload_id: str, principal: Principal) -> Upload:
        upload = self.uploads.get(upload_id)
        principal.check_read(f"upload {upload_id}", upload.tenant)
        return upload

    @classmethod
    def open(cls, settings: Settings, metrics: Metrics | None = None) -> Training:
        """Open the job database (migrated to head) and the upload folder; remove what killed processes left
        there (older than :data:`STALE_GRACE`, so another process's upload in progress is spared)."""
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        jobs = JobStore.open(settings.jobs_database_url)
        uploads = UploadStore(settings.upload_dir)
        uploads.ensure()
        stale = uploads.clean_stale(STALE_GRACE)
        if stale:
            log.info("uploads: removed %d leftovers of interrupted uploads", stale)
        Path(settings.work_dir).mkdir(parents=True, exist_ok=True)
        if metrics is not None:
            metrics.watch_jobs(jobs)
        return cls(settings, jobs, uploads, metrics)

    def close(self) -> None:
        self.jobs.close()

    # ------------------------------------------------------------------------------------------------ jobs
    def submit(self, request: JobRequest, idempotency_key: str | None,
               principal: Principal = TRUSTED) -> tuple[Job, bool]:
        """Queue a job for an existing upload; (the job, whether this call created it). A repeated
        ``idempotency_key`` with the same request returns the first job; with another, IdempotencyConflict.
        The job is the caller's tenant's: it trains on that tenant's upload, into an avatar id that is free or
        the tenant's own (PermissionDenied otherwise; the worker checks the avatar again when it commits)."""
        self.upload_for(request.upload_id, principal)  # NotFound naming upload_id; PermissionDenied
        if self.owner_of_avatar is not None:
            owner = self.owner_of_avatar(request.avatar_id)
            if owner is not None:
                principal.check_write(f"avatar {request.avatar_id!r}", owner.tenant)
        if self.access is not None:
            self.access.count_job(principal)
        before = datetime.now(UTC)
        job = self.jobs.submit(request.model_dump(), tenant=principal.tenant, idempotency_key=idempotency_key,
                               max_attempts=self.settings.job_max_attempts)
        created = idempotency_key is None or job.created_at >= before
        if self.metrics is not None:
            self.metrics.jobs_submitted.labels("created" if created else "replayed").inc()
        return job, created

    def work_folder(self, job_id: str) -> Path:
        return self.work_root / job_id

    def job_out(self, job: Job) -> JobOut:
        base = f"/v1/jobs/{job.id}"
        folder = self.work_folder(job.id)
        artefacts = {name: f"{base}/artefacts/{name}" for name, (file, _) in ARTEFACTS.items()
                     if self._servable(folder, file)}
        upload_id = job.spec.get("upload_id")
        avatar_id = (job.result or {}).get("avatar_id") if job.state is JobState.SUCCEEDED else None
        return JobOut(
            id=job.id, state=job.state, spec=job.spec, attempts=job.attempts, max_attempts=job.max_attempts,
            cancel_requested=job.cancel_requested,
            progress=Progress(fraction=job.fraction, iteration=job.iteration, total_iterations=job.total_iterations,
                              eta_seconds=job.eta_seconds, loss=job.loss, psnr=job.psnr, gaussians=job.gaussians),
            error=job.error, result=job.result, created_at=job.created_at, started_at=job.started_at,
            finished_at=job.finished_at, updated_at=job.updated_at,
            links=JobLinks(self=base, cancel=f"{base}/cancel",
                           upload=f"/v1/uploads/{upload_id}" if isinstance(upload_id, str) else None,
                           artefacts=artefacts, avatar=f"/v1/avatars/{avatar_id}" if avatar_id else None),
            webhooks=[WebhookOut(id=d.id, event=d.event, status=d.status.value, attempts=d.attempts,
                                 last_status=d.last_status, last_error=d.last_error, next_attempt_at=d.next_attempt_at,
                                 created_at=d.created_at, delivered_at=d.delivered_at)
                      for d in (self.jobs.deliveries(job.id) if job.spec.get("webhook_url") else ())])

    def artefact(self, job_id: str, name: str) -> tuple[Path, str]:
        """The file of a job's artefact and its media type; NotFound for an unknown job or name, or a file not
        (yet) written. Only the fixed file names of :data:`ARTEFACTS`, directly in the job's work folder."""
        self.jobs.get(job_id)  # NotFound: an id the database does not know never becomes a path
        if name not in ARTEFACTS:
            raise NotFound(f"no artefact {name!r}; a job's artefacts are {', '.join(ARTEFACTS)}", field="name")
        file, media_type = ARTEFACTS[name]
        folder = self.work_folder(job_id)
        if not self._servable(folder, file):
            when = "as it trains" if name in ("preview", "log") else "when training ends"
            raise NotFound(f"job {job_id} has no {name} yet ({file} is written by the worker {when})", field="name")
        return folder / file, media_type

    def _servable(self, folder: Path, file: str) -> bool:
        """A regular file directly in the job's work folder (no symbolic link on the way is followed)."""
        path = folder / file
        return (not folder.is_symlink() and not path.is_symlink() and path.is_file()
                and path.parent.resolve() == self.work_root.resolve() / folder.name)

    def delete_job(self, job_id: str) -> None:
        """Delete a job whatever its state: its row and events, then its work folder. NotFound if there is none."""
        self.jobs.delete(job_id)
        self._remove_work(job_id)

    def _scan(self, state: JobState | None = None) -> Iterator[Job]:
        cursor = None
        while True:
            page, cursor = self.jobs.list(state=state, limit=_PAGE, cursor=cursor)
            yield from page
            if cursor is None:
                return

    def active_upload_ids(self) -> dict[str, list[str]]:
        """Uploads that queued or running jobs need: upload id -> those jobs' ids."""
        out: dict[str, list[str]] = {}
        for state in (JobState.QUEUED, JobState.RUNNING):
            for job in self._scan(state):
                upload_id = job.spec.get("upload_id")
                if isinstance(upload_id, str):
                    out.setdefault(upload_id, []).append(job.id)
        return out

    # --------------------------------------------------------------------------------------------- uploads
    def delete_upload(self, upload_id: str) -> list[str]:
        """Delete an upload and the work folders of the finished jobs trained on it; the ids of those jobs.
        NotFound if there is no such upload; FailedPrecondition (409) while a queued or running job uses it."""
        self.uploads.get(upload_id)
        users = self.active_upload_ids().get(upload_id)
        if users:
            shown = ", ".join(users[:10]) + (", ..." if len(users) > 10 else "")
            raise FailedPrecondition(f"upload {upload_id} is used by queued or running jobs ({shown}); cancel or "
                                     "delete them first", field="upload_id")
        self.uploads.delete(upload_id)
        removed = []
        for job_id in self._work_folder_ids():
            try:
                job = self.jobs.get(job_id)
            except NotFound:
                continue
            if job.spec.get("upload_id") == upload_id and self._remove_work(job_id):
                removed.append(job_id)
        return removed

    # ------------------------------------------------------------------------------------------- retention
    def sweep(self, now: datetime | None = None) -> SweepReport:
        """Retention: delete uploads older than ``upload_retention_hours`` (not those a queued or running job
        needs) and the work folders of jobs that finished more than ``work_retention_hours`` ago (0: never by
        age); remove orphaned work folders (no job row, untouched for :data:`ORPHAN_GRACE`) and what interrupted
        uploads and deletions left. Job rows are kept."""
        now = now or datetime.now(UTC)
        s = self.settings
        uploads: list[str] = []
        if s.upload_retention_hours > 0:
            cutoff = now - timedelta(hours=s.upload_retention_hours)
            expired = [u.id for u in self.uploads.list() if u.created_at < cutoff]
            if expired:
                needed = self.active_upload_ids()
                for upload_id in expired:
                    if upload_id in needed:
                        log.info("retention: upload %s expired but jobs %s still need it", upload_id,
                                 ", ".join(needed[upload_id]))
                        continue
                    try:
                        self.uploads.delete(upload_id)
                    except NotFound:
                        continue
                    uploads.append(upload_id)
        stale = self.uploads.clean_stale(STALE_GRACE)
        work: list[str] = []
        work_cutoff = now - timedelta(hours=s.work_retention_hours) if s.work_retention_hours > 0 else None
        for job_id in self._work_folder_ids():
            try:
                job = self.jobs.get(job_id)
            except NotFound:
                modified = datetime.fromtimestamp(self._mtime(self.work_folder(job_id)), UTC)
                if now - modified > ORPHAN_GRACE and self._remove_work(job_id):
                    log.info("retention: removed the orphaned work folder of deleted job %s", job_id)
                continue
            if work_cutoff is not None and job.finished and job.finished_at is not None \
                    and job.finished_at < work_cutoff and self._remove_work(job_id):
                work.append(job_id)
        stale += self._clean_work_leftovers()
        if self.metrics is not None:
            self.metrics.retention_deleted.labels("upload").inc(len(uploads))
            self.metrics.retention_deleted.labels("work_folder").inc(len(work))
        if uploads or work:
            log.info("retention: deleted %d uploads and %d work folders", len(uploads), len(work))
        return SweepReport(uploads=uploads, work_folders=work, stale=stale)

    # ----------------------------------------------------------------------------------------- work folders
    def _work_folder_ids(self) -> list[str]:
        if not self.work_root.is_dir():
            return []
        return sorted(p.name for p in self.work_root.iterdir()
                      if p.name.startswith("job_") and p.is_dir() and not p.is_symlink())

    @staticmethod
    def _mtime(path: Path) -> float:
        try:
            return path.stat().st_mtime
        except OSError:
            return time.time()

    def _remove_work(self, job_id: str) -> bool:
        """Rename the job's work folder out of sight (``.deleting-*``), then remove it; False if there was none."""
        doomed = self.work_root / f".deleting-{job_id}-{secrets.token_hex(4)}"
        try:
            os.rename(self.work_folder(job_id), doomed)
        except FileNotFoundError:
            return False
        shutil.rmtree(doomed, ignore_errors=True)
        return True

    def _clean_work_leftovers(self) -> int:
        count = 0
        if self.work_root.is_dir():
            for p in self.work_root.iterdir():
                if p.name.startswith(".deleting-"):
                    shutil.rmtree(p, ignore_errors=True)
                    count += 1
        return count


# -------------------------------------------------------------------------------------------- multipart body
class _FilePart:
    """The ``file`` part of a multipart/form-data request body, parsed as the body arrives (bounded headers and
    other fields; the file's bytes are never held whole)."""

    FIELD = "file"

    def __init__(self, request: Request):
        kind, params = parse_options_header(request.headers.get("content-type", ""))
        boundary = params.get(b"boundary")
        if kind != b"multipart/form-data" or not boundary:
            raise InvalidArgument("expected a multipart/form-data body with the archive in the form field 'file'",
                                  field="file")
        self._body = request.stream().__aiter__()
        self._parser = MultipartParser(boundary, callbacks={
            "on_part_begin": self._part_begin, "on_part_data": self._part_data, "on_part_end": self._part_end,
            "on_header_field": self._header_field, "on_header_value": self._header_value,
            "on_header_end": self._header_end, "on_headers_finished": self._headers_finished,
            "on_end": self._end})
        self._name, self._value = bytearray(), bytearray()
        self._headers: dict[bytes, bytes] = {}
        self._header_bytes = self._other_bytes = 0
        self._in_file = self.found = self.done = self._ended = False
        self.filename: str | None = None
        self._out: list[bytes] = []

    # parser callbacks
    def _part_begin(self) -> None:
        self._headers, self._in_file = {}, False

    def _count_header(self, n: int) -> None:
        self._header_bytes += n
        if self._header_bytes > _MAX_PART_HEADERS:
            raise InvalidArgument("the multipart part headers are too long", field="file")

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._count_header(end - start)
        self._name += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._count_header(end - start)
        self._value += data[start:end]

    def _header_end(self) -> None:
        self._headers[bytes(self._name).lower()] = bytes(self._value)
        self._name, self._value = bytearray(), bytearray()

    def _headers_finished(self) -> None:
        disposition, params = parse_options_header(self._headers.get(b"content-disposition", b""))
        if disposition == b"form-data" and params.get(b"name") == self.FIELD.encode() and not self.found:
            self._in_file = self.found = True
            raw = params.get(b"filename")
            self.filename = raw.decode("utf-8", "replace") if raw else None

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self._in_file:
            self._out.append(data[start:end])
            return
        self._other_bytes += end - start
        if self._other_bytes > _MAX_OTHER_PARTS:
            raise InvalidArgument("form fields other than 'file' are too large", field="body")

    def _part_end(self) -> None:
        if self._in_file:
            self._in_file, self.done = False, True

    def _end(self) -> None:
        self._ended = True

    # reading
    async def _feed(self) -> bool:
        """Parse the next piece of the body; False once the body has ended."""
        try:
            chunk = await self._body.__anext__()
        except StopAsyncIteration:
            return False
        if chunk:
            try:
                self._parser.write(chunk)
            except MultipartParseError as exc:
                raise InvalidArgument(f"not a valid multipart/form-data body ({exc})", field="body") from None
        return True

    async def start(self) -> None:
        """Read up to the start of the file part. InvalidArgument if the body has none."""
        while not self.found:
            if not await self._feed():
                raise InvalidArgument("the body has no form field 'file' (the dataset archive)", field="file")

    async def chunks(self) -> AsyncIterator[bytes]:
        """The file part's bytes as they arrive; the rest of the (bounded) body is read after it."""
        while True:
            if self._out:
                data = b"".join(self._out)
                self._out.clear()
                yield data
            if self.done:
                break
            if not await self._feed():
                raise InvalidArgument("the body ended inside the file part (a truncated upload)", field="file")
        while not self._ended and await self._feed():  # the closing boundary and any small trailing fields
            pass


# ------------------------------------------------------------------------------------------------------ routes
def _training(request: Request) -> Training:
    return request.app.state.training


_ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorBody, "description": "not found"},
    422: {"model": ErrorBody, "description": "invalid request (the field is named)"},
}
_IDEMPOTENCY = Annotated[str | None, Header(alias="Idempotency-Key", min_length=1, max_length=255,
                                            description="the same key and body return the same job (200)")]

JobId = Annotated[str, PathParam(pattern=JOB_ID_PATTERN.pattern, description="a job's id (POST /v1/jobs)")]
UploadId = Annotated[str, PathParam(pattern=UPLOAD_ID_PATTERN.pattern, description="an upload's id")]
ArtefactName = Annotated[Literal[tuple(ARTEFACTS)], PathParam(description="which artefact")]  # type: ignore

uploads = APIRouter(prefix="/v1/uploads", tags=["uploads"])
jobs = APIRouter(prefix="/v1/jobs", tags=["jobs"])


@uploads.post(
    "", status_code=201, response_model=UploadOut, summary="Upload a tracked-video dataset (an archive)",
    description="multipart/form-data with the archive (.tar.gz, .tar or .zip holding a dataset in the portable "
                "format, docs/tracked-video-format.md, at its root or in one top-level folder) in the field `file`. "
                "The body is streamed to disk, the archive checked before anything is extracted and the dataset "
                "validated; a refused upload leaves nothing behind.",
    responses={413: {"model": ErrorBody, "description": "larger than BLENDSPLAT_MAX_DATASET_BYTES"},
               422: {"model": ErrorBody, "description": "a hostile or corrupt archive, or an invalid dataset: the "
                                                        "reason"}},
    openapi_extra={"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
        "type": "object", "required": ["file"],
        "properties": {"file": {"type": "string", "format": "binary"}}}}}}})
async def create_upload(request: Request, response: Response, principal: Caller("jobs")) -> UploadOut:
    training = _training(request)
    limit = training.settings.max_dataset_bytes
    declared = request.headers.get("content-length", "")
    metrics = training.metrics
    try:
        if declared.isascii() and declared.isdigit() and int(declared) > limit + _MULTIPART_SLACK:
            raise UploadTooLarge(f"the upload is larger than {limit} bytes", field="file")
        if training.access is not None:
            incoming = int(declared) if declared.isascii() and declared.isdigit() else 0
            await asyncio.to_thread(training.access.admit_upload, principal, incoming)
        form = _FilePart(request)
        await form.start()
        upload = await training.uploads.receive(form.chunks(), max_bytes=limit, filename=form.filename,
                                                tenant=principal.tenant)
    except (UploadTooLarge, ArchiveError, InvalidDataset) as exc:
        if metrics is not None:
            kind = ("too_large" if isinstance(exc, UploadTooLarge) else
                    "archive" if isinstance(exc, ArchiveError) else "dataset")
            metrics.uploads.labels(kind).inc()
        raise
    except ClientDisconnect:
        log.info("upload: the client went away; nothing was kept")
        return Response(status_code=499)  # nobody reads it
    if metrics is not None:
        metrics.uploads.labels("accepted").inc()
        metrics.upload_bytes.inc(upload.size)
    response.headers["Location"] = f"/v1/uploads/{upload.id}"
    log.info("upload %s: %d frames %dx%d (%s, %d bytes)", upload.id, upload.frames, upload.width, upload.height,
             upload.archive, upload.size)
    return UploadOut.of(upload)


@uploads.get("", response_model=UploadList, summary="Uploaded datasets, oldest first")
def list_uploads(request: Request, principal: Caller("jobs")) -> UploadList:
    return UploadList(uploads=[UploadOut.of(u) for u in _training(request).uploads.list()
                               if principal.may_read(u.tenant)])


@uploads.get("/{upload_id}", response_model=UploadOut, summary="One upload", responses=_ERRORS)
def get_upload(upload_id: UploadId, request: Request, principal: Caller("jobs")) -> UploadOut:
    return UploadOut.of(_training(request).upload_for(upload_id, principal))


@uploads.delete("/{upload_id}", status_code=204, response_class=Response,
                summary="Delete an upload and the work folders of the finished jobs trained on it",
                description="Refused (409) while a queued or running job uses it: cancel or delete those first. "
                            "Finished jobs keep their rows; avatars trained from it stay.",
                responses={**_ERRORS, 409: {"model": ErrorBody, "description": "a queued or running job uses it"}})
def delete_upload(upload_id: UploadId, request: Request, principal: Caller("jobs")) -> Response:
    training = _training(request)
    training.upload_for(upload_id, principal)
    removed = training.delete_upload(upload_id)
    Access.audit(principal, "upload.delete", upload_id)
    log.info("upload %s deleted (and the work folders of jobs %s)", upload_id, removed)
    return Response(status_code=204)


@jobs.post("", status_code=201, response_model=JobOut, summary="Submit a training job",
           description="Queues a job that trains on an upload; a worker (`blendsplat worker`, or the one `blendsplat "
                       "up` runs) claims it. With an `Idempotency-Key` header a repeated request returns the job the "
                       "first one created (200); the same key with a different body is refused (409).",
           responses={200: {"model": JobOut, "description": "the job an earlier request with this key created"},
                      409: {"model": ErrorBody, "description": "the key was used with a different body"},
                      **_ERRORS})
def submit_job(body: JobRequest, request: Request, response: Response, principal: Caller("jobs"),
               idempotency_key: _IDEMPOTENCY = None) -> JobOut:
    training = _training(request)
    job, created = training.submit(body, idempotency_key, principal)
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    if created:
        log.info("job %s submitted: %s", job.id, job.spec)
        Access.audit(principal, "job.submit", job.id, avatar=body.avatar_id, upload=body.upload_id)
    return training.job_out(job)


@jobs.get("", response_model=JobList, summary="Jobs, newest first, optionally of one state (keyset pages)",
          responses={422: _ERRORS[422]})
def list_jobs(request: Request, principal: Caller("jobs"), state: JobState | None = None,
              limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 50,
              cursor: Annotated[str | None, Query(pattern=CURSOR_PATTERN.pattern, max_length=82,
                                                  description="next_cursor of the previous page")] = None) -> JobList:
    training = _training(request)
    page, next_cursor = training.jobs.list(state=state, limit=limit, cursor=cursor,
                                           tenant=None if principal.admin else principal.tenant)
    return JobList(jobs=[training.job_out(j) for j in page], next_cursor=next_cursor)


@jobs.get("/{job_id}", response_model=JobOut, summary="One job: state, progress, error, result, links",
          responses=_ERRORS)
def get_job(job_id: JobId, request: Request, principal: Caller("jobs")) -> JobOut:
    training = _training(request)
    return training.job_out(training.job_for(job_id, principal))


@jobs.post("/{job_id}/cancel", status_code=202, response_model=JobOut, summary="Cancel a job",
           description="A queued job is cancelled at once; a running one stops before its next iteration (its "
                       "worker checkpoints and ends it cancelled: watch its state). A finished job is left as it is "
                       "(200).",
           responses={200: {"model": JobOut, "description": "the job had already finished"}, **_ERRORS})
def cancel_job(job_id: JobId, request: Request, response: Response, principal: Caller("jobs")) -> JobOut:
    training = _training(request)
    job = training.job_for(job_id, principal)
    if job.finished:
        response.status_code = 200
    else:
        job = training.jobs.request_cancel(job_id)
        log.info("job %s: cancel requested (now %s)", job_id, job.state)
        Access.audit(principal, "job.cancel", job_id)
    return training.job_out(job)


@jobs.get("/{job_id}/artefacts/{name}", response_class=FileResponse,
          summary="A job's artefact: report, summary, curves, contact-sheet, preview or log",
          description="report (report.json: the held-out evaluation), summary (summary.json), curves (curves.png), "
                      "contact-sheet (contact_sheet.png), preview (preview.png: the latest, replaced as training "
                      "goes), truth (truth.png: the dataset's image of the preview's frame), log (log.jsonl). "
                      "404 with the reason while one is not written yet.",
          responses={200: {"content": {
              "application/json": {"schema": {"type": "object", "description": "report or summary"}},
              "image/png": {"schema": {"type": "string", "format": "binary"}},
              "application/x-ndjson": {"schema": {"type": "string", "description": "one JSON event per line"}}}},
              404: _ERRORS[404]})
def get_artefact(job_id: JobId, name: ArtefactName, request: Request, principal: Caller("jobs")) -> FileResponse:
    training = _training(request)
    training.job_for(job_id, principal)
    path, media_type = training.artefact(job_id, name)
    return FileResponse(path, media_type=media_type, headers={"Cache-Control": "no-store"})


@jobs.get("/{job_id}/events", response_class=StreamingResponse,
          summary="The job's events as server-sent events: its history, then live, until it ends",
          description="text/event-stream; one event per recorded event: `id` (resume with the `Last-Event-ID` "
                      "header or `?after=`), `event` (progress, state, preview, log) and one line of JSON `data`. "
                      "A finished job's stream sends what is left and `event: end`, then closes. See "
                      "service/job_events.py.",
          responses={200: {"content": {"text/event-stream": {"schema": {
              "type": "string", "description": "id:, event:, data: lines (one JSON object) per event"}}}},
              429: {"model": ErrorBody, "description": "too many streams open"}, **_ERRORS})
def follow_job(job_id: JobId, request: Request, principal: Caller("jobs"),
               after: Annotated[int | None, Query(ge=0)] = None,
               last_event_id: Annotated[str | None, Header(alias="Last-Event-ID", max_length=64)] = None,
               ) -> StreamingResponse:
    training = _training(request)
    training.job_for(job_id, principal)  # NotFound: the one JSON 404, not a stream
    start = job_events.last_event_id(last_event_id, after)
    release = training.access.take_stream(principal) if training.access is not None else None  # a key's streams
    try:
        return job_events.event_stream(request.app, training, job_id, start, on_close=release)
    except BaseException:
        if release is not None:
            release()
        raise


@jobs.delete("/{job_id}", status_code=204, response_class=Response,
             summary="Delete a job: its row, events and work folder (a running one stops before its next iteration)",
             responses=_ERRORS)
def delete_job(job_id: JobId, request: Request, principal: Caller("jobs")) -> Response:
    training = _training(request)
    training.job_for(job_id, principal)
    training.delete_job(job_id)
    log.info("job %s deleted", job_id)
    Access.audit(principal, "job.delete", job_id)
    return Response(status_code=204)


ROUTERS = (uploads, jobs)
